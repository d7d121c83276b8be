"""The simulator's default-camera data files from the Insta360 ONE calibration files of Larouche et al.

    PYTHONPATH=src python scripts/insta360_calibration_data.py [REALDATA]

REALDATA holds ``insta360-larouche/`` (default: ``$PIPELINE_REALDATA``), unchanged copies of the public
repository RaphaelLarouche/radiance_camera_insta360 (MIT licence, (c) 2021 Raphael Larouche). Writes, in
``src/pipeline/simulate/data/``:

* ``insta360_rsr_close.csv``, ``insta360_rsr_far.csv``: the measured relative spectral response of each
  lens (``calibrations/relative-spectral-response/calibrationfiles/rsr_20200610.h5`` and
  ``rsr_20200710.h5``: ``lens-*/wavelength``, ``rsr_peak_norm``, ``rsr_relative_unc``), values as stored;
* ``insta360_rolloff.csv``: the roll-off fits a0 + a2 t^2 + ... + a8 t^8 (t in degrees) per lens, medium
  and band (``calibrations/roll-off/calibrationfiles/rolloff_a.h5``, ``rolloff_w.h5``), as stored;
* ``LICENSE-insta360.txt``: the repository's licence text, which the MIT licence asks to keep beside
  the copied data.

Each CSV file starts with ``#`` lines that state its source. Rerun after a change of the source files;
the files are package data, read by :mod:`pipeline.simulate.camera_data`.
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import h5py
import numpy as np

REPOSITORY = "RaphaelLarouche/radiance_camera_insta360 (branch master)"
LICENCE = "MIT licence, Copyright (c) 2021 Raphael Larouche (LICENSE-insta360.txt beside this file)"
RSR_FILES = {"close": "rsr_20200610.h5", "far": "rsr_20200710.h5"}
RSR_PATH = "calibrations/relative-spectral-response/calibrationfiles/"
ROLLOFF_FILES = {"air": "rolloff_a.h5", "water": "rolloff_w.h5"}
ROLLOFF_PATH = "calibrations/roll-off/calibrationfiles/"
#: row order of the files' (3, ...) arrays
BANDS = ("R", "G", "B")
OUT = Path(__file__).resolve().parents[1] / "src" / "pipeline" / "simulate" / "data"


def _header(lines: list[str]) -> str:
    return "".join(f"# {line}\n" for line in lines)


def write_rsr(folder: Path, lens: str) -> Path:
    """Write one lens's measured relative spectral response as CSV.

    Parameters
    ----------
    folder : Path
        The ``insta360-larouche`` folder.
    lens : str
        ``"close"`` or ``"far"``.

    Returns
    -------
    Path
        The written file.
    """
    name = RSR_FILES[lens]
    with h5py.File(folder / name, "r") as h5:
        g = h5[f"lens-{lens}"]
        wl, rsr, unc = g["wavelength"][()], g["rsr_peak_norm"][()], g["rsr_relative_unc"][()]
    text = _header([
        f"Measured relative spectral response of the Insta360 ONE's {lens} lens (peak-normalised per band),",
        "and its relative standard uncertainty (fraction of the value).",
        f"Source: {REPOSITORY}, file {RSR_PATH}{name}",
        f"(lens-{lens}/wavelength, rsr_peak_norm, rsr_relative_unc; values as stored). {LICENCE}.",
        "Written by scripts/insta360_calibration_data.py.",
    ])
    text += "wavelength_nm,R,G,B,R_relative_unc,G_relative_unc,B_relative_unc\n"
    for w, r, u in zip(wl, rsr, unc):
        text += f"{w:.1f}," + ",".join(f"{v:.10g}" for v in (*r, *u)) + "\n"
    path = OUT / f"insta360_rsr_{lens}.csv"
    path.write_text(text)
    return path


def write_rolloff(folder: Path) -> Path:
    """Write the authors' roll-off fits of both lenses in both media as CSV.

    Parameters
    ----------
    folder : Path
        The ``insta360-larouche`` folder.

    Returns
    -------
    Path
        The written file.
    """
    rows = []
    sources = []
    for medium, name in ROLLOFF_FILES.items():
        with h5py.File(folder / name, "r") as h5:
            for lens in ("close", "far"):
                (date,) = list(h5[f"lens-{lens}"])
                coef = np.asarray(h5[f"lens-{lens}/{date}/fit-coefficients"][()], float)
                sources.append(f"{ROLLOFF_PATH}{name} lens-{lens}/{date}/fit-coefficients")
                for band, c in zip(BANDS, coef):
                    rows.append(f"{lens},{medium},{band},{date}," + ",".join(f"{v:.10g}" for v in c))
    text = _header([
        "Roll-off fits g(t) = a0 + a2 t^2 + a4 t^4 + a6 t^6 + a8 t^8 (t: field angle in degrees) of the",
        "Insta360 ONE's lenses, per lens, medium and band (rows R, G, B of the stored arrays), as stored.",
        f"Source: {REPOSITORY}, files:",
        *[f"  {s}" for s in sources],
        f"{LICENCE}.",
        "The far lens's water fit is not normalised (a0 about 0.90) and goes negative beyond 76 degrees;",
        "the simulator uses the air fits only and derives the water roll-off from them by the immersion",
        "physics (pipeline.simulate.lens.water_rolloff_from_air).",
        "Written by scripts/insta360_calibration_data.py.",
    ])
    text += "lens,medium,band,date,a0,a2,a4,a6,a8\n" + "\n".join(rows) + "\n"
    path = OUT / "insta360_rolloff.csv"
    path.write_text(text)
    return path


def main(argv: list[str]) -> None:
    root = Path(argv[1]) if len(argv) > 1 else Path(os.environ["PIPELINE_REALDATA"])
    folder = root / "insta360-larouche"
    for lens in RSR_FILES:
        print(write_rsr(folder, lens))
    print(write_rolloff(folder))
    shutil.copyfile(folder / "LICENSE.txt", OUT / "LICENSE-insta360.txt")
    print(OUT / "LICENSE-insta360.txt")


if __name__ == "__main__":
    main(sys.argv)
