"""A lens region's projection (docs/dataset-format.md: fisheye, the default, or rectilinear) decides where the
linearity stage looks for the optical axis; a fisheye region without an image circle stops the stage."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.stages.linearity import axis_masks, fisheye_circle

DARK_DN = 800.0
READ_DN = 2.0


def _noise(shape, seed):
    return READ_DN * np.random.default_rng(seed).standard_normal(shape)


def _rectilinear_frame(shape=(64, 96), signal_dn=3000.0, focal_px=60.0, seed=0):
    """A uniformly lit ordinary camera, vignetted by the natural cos^4 law of a pinhole (written here,
    not in the package): lit to its corners (cos^4 at the corner of 64 x 96 with f = 60 px is 0.5)."""
    h, w = shape
    y, x = np.indices(shape, dtype=float)
    cos_theta = focal_px / np.sqrt(focal_px**2 + (x - (w - 1) / 2) ** 2 + (y - (h - 1) / 2) ** 2)
    return DARK_DN + signal_dn * cos_theta**4 + _noise(shape, seed)


def test_fisheye_region_without_image_circle_stops_naming_it(config):
    """One line, naming the lens region and the dataset.yaml key that fixes it."""
    with pytest.raises(InputError) as info:
        axis_masks(_rectilinear_frame(), None, config, lens="phone", projection="fisheye", dark_level_dn=DARK_DN)
    message = str(info.value)
    assert "\n" not in message
    assert "lens region 'phone'" in message and "no image circle" in message
    assert "projection: rectilinear" in message


def test_dark_fisheye_region_stops_too(config):
    """A region with nothing lit (lens capped) has no circle either: the same line, not a fit to noise."""
    frame = DARK_DN + _noise((64, 64), 3)
    with pytest.raises(InputError, match="lens region 'far' is declared fisheye"):
        fisheye_circle(frame, DARK_DN, config, "far")


def test_fisheye_circle_is_found_and_passes(config):
    """Positive control: a lit disc of radius 26 band px (unlit outside, as docs/dataset-format.md says of a fisheye)
    passes the check, its radius within 0.5 px (the edge is located to sub-pixel on 360 profiles at
    SNR ~ 1000 per pixel)."""
    y, x = np.indices((64, 64), dtype=float)
    disc = np.hypot(x - 31.5, y - 30.0) <= 26.0
    frame = DARK_DN + 4000.0 * disc + _noise((64, 64), 1)
    circle = fisheye_circle(frame, DARK_DN, config, "far")
    assert circle.radius == pytest.approx(26.0, abs=0.5)


def test_rectilinear_mask_on_region_centre(config):
    """A rectilinear region: no circle is looked for; the mask is centred on the region and its radius is
    f tan(mask angle) with f putting the nominal half field of view at the half diagonal."""
    frame = _rectilinear_frame()
    (cx, cy, radius, r_mask), mask, ptc, source = axis_masks(frame, None, config, lens="phone",
                                                             projection="rectilinear", dark_level_dn=DARK_DN)
    cfg = config["linearity"]
    half_diagonal = np.hypot(64, 96) / 2
    f = half_diagonal / np.tan(np.radians(cfg["rectilinear_nominal_half_fov_deg"]))
    assert (cx, cy) == (47.5, 31.5) and radius == pytest.approx(half_diagonal)
    assert r_mask == pytest.approx(f * np.tan(np.radians(cfg["mask_half_angle_deg"])))
    yy, xx = np.nonzero(mask)
    assert xx.mean() == pytest.approx(47.5) and yy.mean() == pytest.approx(31.5)
    # pixel count of a digitised disc: pi r^2 within its perimeter
    assert abs(mask.sum() - np.pi * r_mask**2) < 2 * np.pi * r_mask
    assert ptc.sum() > mask.sum() and "rectilinear" in source
