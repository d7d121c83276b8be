"""The real Insta360 ONE's measured calibration data, the simulator's default camera.

Package data in ``pipeline/simulate/data/`` (see its ``README.md``): the measured relative spectral
responses of both lenses and the authors' roll-off fits, from the public repository
RaphaelLarouche/radiance_camera_insta360 (MIT licence, (c) 2021 Raphael Larouche; licence text
``LICENSE-insta360.txt`` beside the data), written unchanged by ``scripts/insta360_calibration_data.py``.
"""

from __future__ import annotations

import io
from functools import lru_cache
from importlib.resources import files

import numpy as np
import pandas as pd

#: the lenses with measured data
LENSES = ("close", "far")
_BANDS = ("R", "G", "B")


def _read_csv(name: str) -> pd.DataFrame:
    text = files("pipeline.simulate").joinpath("data", name).read_text()
    return pd.read_csv(io.StringIO(text), comment="#")


@lru_cache(maxsize=None)
def _rsr_table(lens: str) -> pd.DataFrame:
    return _read_csv(f"insta360_rsr_{lens}.csv")


def measured_response(lens: str) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The measured relative spectral response of one lens, as stored.

    Parameters
    ----------
    lens : str
        ``"close"`` or ``"far"``.

    Returns
    -------
    wavelength_nm : ndarray
        The monochromator's wavelengths (nm), increasing.
    response : dict
        Band (``"R"``, ``"G"``, ``"B"``) -> peak-normalised response at ``wavelength_nm``.
    relative_unc : dict
        Band -> relative standard uncertainty of the response (fraction).
    """
    if lens not in LENSES:
        raise ValueError(f"lens must be one of {LENSES}, got {lens!r}")
    t = _rsr_table(lens)
    wl = t["wavelength_nm"].to_numpy(float)
    return (wl.copy(), {b: t[b].to_numpy(float) for b in _BANDS},
            {b: t[f"{b}_relative_unc"].to_numpy(float) for b in _BANDS})


@lru_cache(maxsize=None)
def _rolloff_table() -> pd.DataFrame:
    return _read_csv("insta360_rolloff.csv")


def authors_rolloff(lens: str, medium: str, band: str) -> np.ndarray:
    """The authors' roll-off fit (a0, a2, a4, a6, a8; field angle in degrees) as stored, not normalised.

    Parameters
    ----------
    lens : str
        ``"close"`` or ``"far"``.
    medium : str
        ``"air"`` or ``"water"``.
    band : str
        ``"R"``, ``"G"`` or ``"B"``.

    Returns
    -------
    ndarray
        The five coefficients (a new array).
    """
    t = _rolloff_table()
    row = t[(t["lens"] == lens) & (t["medium"] == medium) & (t["band"] == band)]
    if len(row) != 1:
        raise ValueError(f"no roll-off fit for lens {lens!r}, medium {medium!r}, band {band!r}")
    return row[["a0", "a2", "a4", "a6", "a8"]].to_numpy(float)[0]
