"""A co-located reference radiometer over a profile of depths: an OCR-504-like pair of sensors beside the camera.

Two sensors of narrow channels (one per camera band, at the band's nominal
wavelength: the scene is defined per band, and a channel reads the band's
true quantity): a plane irradiance sensor looking up (E_d, cosine collector)
and a radiance sensor looking down (L_u, the nadir radiance over the cone of
``cone_half_angle_deg``). At each depth of the profile each reading is the
truth of :func:`pipeline.simulate.underwater.light_field_truth` for the scene
at that depth, times (1 + c) with c the sensor's calibration error (one draw
per profile and channel, normal of sigma ``calibration_sigma``), times
(1 + e) with e the reading's noise (normal of sigma ``noise_sigma``, per
reading). The file states both sigmas per reading: the calibration's and the
noise's (relative), and their root sum of squares times the value.
"""

from __future__ import annotations

from dataclasses import replace
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.io.bands import BANDS
from pipeline.simulate.immersion import BAND_WAVELENGTH_NM
from pipeline.simulate.underwater import UnderwaterScene, light_field_truth

__all__ = ["REFERENCE_CALIBRATION_SIGMA", "REFERENCE_NOISE_SIGMA", "write_reference_profile", "profile_truth",
           "profile_times"]

#: relative calibration uncertainty of each channel (one draw per profile), E_d and L_u sensors
REFERENCE_CALIBRATION_SIGMA = {"E_d": 0.03, "L_u": 0.03}
#: relative noise of one reading
REFERENCE_NOISE_SIGMA = {"E_d": 0.01, "L_u": 0.02}


def profile_truth(scene: UnderwaterScene, depths_m, cone_half_angle_deg: float = 5.0) -> dict:
    """The true E_d and L_u per depth and band of the scene moved to each depth.

    Parameters
    ----------
    scene : UnderwaterScene
        The scene (its ``depth_m`` replaced by each depth).
    depths_m : sequence of float
        The depths, m.
    cone_half_angle_deg : float, optional
        The L_u cone half-angle, degree; default 5.

    Returns
    -------
    dict
        ``E_d`` and ``L_u``: numpy.ndarray (depth, band), W m-2 nm-1 and W m-2 sr-1 nm-1.
    """
    out = {"E_d": [], "L_u": []}
    for z in depths_m:
        t = light_field_truth(replace(scene, depth_m=float(z), attitude_deg=(0.0, 0.0, 0.0)), cone_half_angle_deg,
                              azimuth_step_deg=1.0)
        out["E_d"].append(t["E_d"])
        out["L_u"].append(t["L_u"])
    return {k: np.array(v) for k, v in out.items()}


def write_reference_profile(path, scene: UnderwaterScene, depths_m, times, *, seed: int,
                            calibration_error=None, cone_half_angle_deg: float = 5.0) -> pd.DataFrame:
    """Write the reference's readings over the profile (CSV) and return them.

    Parameters
    ----------
    path : str or pathlib.Path
        The CSV to write: columns ``time_utc``, ``depth_m``, ``channel`` (``E_d_<nm>`` or ``L_u_<nm>``),
        ``band``, ``quantity``, ``wavelength_nm``, ``value``, ``sigma`` (absolute, the root sum of squares of the
        two below times the value), ``calibration_relative_sigma`` and ``noise_relative_sigma``.
    scene : UnderwaterScene
        The scene (moved to each depth).
    depths_m : sequence of float
        The depths, m.
    times : sequence of datetime.datetime
        The time of each depth's reading (UTC, naive).
    seed : int
        Seed of the calibration errors and the noise (stream 504).
    calibration_error : dict, optional
        ``{quantity: relative error}``: an error added to every channel of that sensor on top of the drawn one,
        not stated (an injected miscalibration); default none.
    cone_half_angle_deg : float, optional
        The L_u sensor's cone half-angle, degree; default 5.

    Returns
    -------
    pandas.DataFrame
        The rows written.
    """
    rng = np.random.default_rng([seed, 504])
    truth = profile_truth(scene, depths_m, cone_half_angle_deg)
    rows = []
    for q in ("E_d", "L_u"):
        cal = rng.normal(0.0, REFERENCE_CALIBRATION_SIGMA[q], len(BANDS)) + (calibration_error or {}).get(q, 0.0)
        noise = rng.normal(0.0, REFERENCE_NOISE_SIGMA[q], (len(depths_m), len(BANDS)))
        rel = float(np.hypot(REFERENCE_CALIBRATION_SIGMA[q], REFERENCE_NOISE_SIGMA[q]))
        for i, (z, t) in enumerate(zip(depths_m, times)):
            for b, band in enumerate(BANDS):
                value = truth[q][i, b] * (1.0 + cal[b]) * (1.0 + noise[i, b])
                nm = int(BAND_WAVELENGTH_NM[band])
                rows.append({"time_utc": pd.Timestamp(t, tz="UTC").isoformat(), "depth_m": float(z),
                             "channel": f"{q}_{nm}", "band": band, "quantity": q, "wavelength_nm": nm,
                             "value": value, "sigma": rel * value,
                             "calibration_relative_sigma": REFERENCE_CALIBRATION_SIGMA[q],
                             "noise_relative_sigma": REFERENCE_NOISE_SIGMA[q]})
    table = pd.DataFrame(rows)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    table.to_csv(path, index=False)
    return table


def profile_times(start: datetime, n: int, step_s: float = 60.0) -> list:
    """``n`` times ``step_s`` apart from ``start`` (one depth a minute by default).

    Parameters
    ----------
    start : datetime.datetime
        The first time.
    n : int
        The number of times.
    step_s : float, optional
        The step, s; default 60.

    Returns
    -------
    list of datetime.datetime
        The times.
    """
    return [start + timedelta(seconds=k * step_s) for k in range(n)]
