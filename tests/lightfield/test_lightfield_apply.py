"""The light field of raw frames (python -m pipeline lightfield --calibration) against the scene's analytic truth.

The tiny camera that the session fixture ``calibrated`` calibrated with the
pipeline's own stages (seed 5, no effects) photographs, through the
simulator's renderer with the same seed, a sky of L_b = A_b + B_b cos z over
both lenses (z the zenith angle in apply's sphere convention: the close lens
looks at the zenith), defined here; ``lightfield --calibration`` turns the
frame into the light field. Its E_d, E_u, E_0d, E_0u, E_0, mu_d, mu_u, mu, L_d,
L_u and Q have closed forms (mu = cos z: int_0^1 (A + B mu) mu dmu = A/2 +
B/3, ...). Each is within 3 of its stated total standard uncertainty
(random, the calibration's systematic R^-1 and roll-off, the fill of the band
between the lenses, the quadrature); 3 sigma is the Bonferroni bound at 95 %
for the 33 values (11 quantities, 3 bands), whatever their correlation.

Run time: a few seconds beyond the session fixture (about two minutes when
this file runs alone, shared with the apply tests in the whole suite).
"""

from __future__ import annotations

from datetime import datetime

import numpy as np
import xarray as xr

from pipeline.io.bands import BANDS
from pipeline.cli import main
from pipeline.io.rawio import write_dng
from pipeline.simulate.camera import Camera
from pipeline.simulate.dataset import SCALES
from pipeline.simulate.plan import FrameSpec
from pipeline.simulate.render import Renderer

SEED = 5                                   # the calibrated fixture's
A = {"R": 1.2e-3, "G": 1.6e-3, "B": 2.2e-3}
B = {"R": 0.9e-3, "G": 1.1e-3, "B": 1.4e-3}
CONE_DEG = 5.0                             # lightfield.radiance_cone_half_angle_deg
GRID_DEG = 9.0                             # cells of several band pixels of the tiny camera
ISO, EXPOSURE_S = 100.0, 1 / 30


def cosine_sky(lens, geo, band_index):
    th = np.radians(geo.theta_deg)
    zen = th if lens == "close" else np.pi - th
    a = np.array([A[b] for b in BANDS])[band_index]
    b = np.array([B[b] for b in BANDS])[band_index]
    return a + b * np.cos(zen)


def truth(a, b):
    c = np.cos(np.radians(CONE_DEG))
    t = {"E_d": 2 * np.pi * (a / 2 + b / 3), "E_u": 2 * np.pi * (a / 2 - b / 3), "E_0d": 2 * np.pi * (a + b / 2),
         "E_0u": 2 * np.pi * (a - b / 2), "L_d": a + b * (1 + c) / 2, "L_u": a - b * (1 + c) / 2}
    t["E_0"] = t["E_0d"] + t["E_0u"]
    t["mu_d"], t["mu_u"] = t["E_d"] / t["E_0d"], t["E_u"] / t["E_0u"]
    t["mu"] = (t["E_d"] - t["E_u"]) / t["E_0"]
    t["Q"] = t["E_u"] / t["L_u"]
    return t


def test_raw_frame_light_field_within_its_stated_uncertainty(calibrated, tmp_path):
    _, _, _, _, bundle_path, _ = calibrated
    camera = Camera()
    renderer = Renderer(camera, SCALES["tiny"].lens_px, SEED, [])
    frame = renderer.render(0, 43, FrameSpec("both", "signal", ISO, EXPOSURE_S, radiance=cosine_sky, medium="air"))
    raw = tmp_path / "sky.dng"
    write_dng(raw, frame, exposure_s=EXPOSURE_S, iso=ISO, time=datetime(2021, 3, 18, 16, 0, 0),
              black_level=round(camera.sensor.bias_dn), white_level=camera.sensor.adc_max_dn, cfa_pattern="RGGB",
              make=camera.make, model=camera.model, serial=camera.serial)
    out = tmp_path / "lf.nc"
    assert main(["lightfield", "--calibration", str(bundle_path), "--grid-deg", str(GRID_DEG), str(raw),
                 "-o", str(out)]) == 0
    with xr.open_dataset(out) as ds:
        flag = ds["sphere_cell_flag"][0, 0].values
        assert (flag == 1).any() and not (flag == 2).any()        # the band between the lenses filled
        for band in BANDS:
            expected = truth(A[band], B[band])
            for q, value in expected.items():
                got, sigma = float(ds[q].sel(band=band)[0]), float(ds[f"{q}_sigma"].sel(band=band)[0])
                assert abs(got - value) <= 3 * sigma, (band, q, got, value, sigma)
                # the stated uncertainty says something: under 20 % of the value
                assert sigma < 0.2 * abs(value), (band, q, sigma, value)
        # the band-common R^-1 term is in E_d's systematic sigma and cancels in mu_d's
        e_sys = ds["E_d_systematic_sigma"][0] / ds["E_d"][0]
        mu_sys = ds["mu_d_systematic_sigma"][0] / ds["mu_d"][0]
        assert (e_sys > 0.01).all() and (mu_sys < 0.5 * e_sys).all()
