"""Tests for pipeline.io.bands: region cutting and Bayer band splitting."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.io.bands import BANDS, cut_region, split_bands, split_saturation

SITE_VALUES = {"R": 100, "G1": 200, "G2": 300, "B": 400}


def _mosaic(pattern: str, rows=6, cols=8) -> np.ndarray:
    """Mosaic where R, the first G, the second G and B each hold a distinct value."""
    cell = np.zeros((2, 2), np.uint16)
    greens = iter(("G1", "G2"))
    for index, letter in enumerate(pattern):
        key = next(greens) if letter == "G" else letter
        cell[divmod(index, 2)] = SITE_VALUES[key]
    return np.tile(cell, (rows // 2, cols // 2))


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_split_bands_all_patterns(pattern):
    cfa = _mosaic(pattern)
    bands = split_bands(cfa, pattern)
    assert tuple(bands) == BANDS == ("R", "G", "B")
    for name in BANDS:
        assert bands[name].dtype == np.float32
        assert bands[name].shape == (3, 4)
    assert np.all(bands["R"] == 100)
    assert np.all(bands["G"] == 250)  # mean of the two green sites
    assert np.all(bands["B"] == 400)


def test_split_bands_follows_the_given_pattern():
    cfa = _mosaic("RGGB")
    swapped = split_bands(cfa, "BGGR")  # the same pixels read with another pattern
    assert np.all(swapped["R"] == 400) and np.all(swapped["B"] == 100)


def test_split_bands_keeps_positions_and_drops_odd_edge():
    cfa = np.arange(5 * 7, dtype=np.uint16).reshape(5, 7)
    bands = split_bands(cfa, "RGGB")
    assert bands["R"].shape == (2, 3)
    np.testing.assert_array_equal(bands["R"], cfa[0:4:2, 0:6:2])
    np.testing.assert_array_equal(bands["B"], cfa[1:4:2, 1:6:2])
    np.testing.assert_allclose(bands["G"], (cfa[0:4:2, 1:6:2] + cfa[1:4:2, 0:6:2].astype(float)) / 2)


def test_split_bands_rejects_bad_input():
    with pytest.raises(ValueError):
        split_bands(np.zeros((4, 4)), "RGBX")
    with pytest.raises(ValueError):
        split_bands(np.zeros((4, 4)), "RRGB")
    with pytest.raises(ValueError):
        split_bands(np.zeros((4, 4, 3)), "RGGB")
    with pytest.raises(ValueError):
        split_bands(np.zeros((1, 4)), "RGGB")


def test_cut_region():
    cfa = np.arange(12 * 16).reshape(12, 16)
    part = cut_region(cfa, (2, 8), (4, 16))
    np.testing.assert_array_equal(part, cfa[2:8, 4:16])
    # the Bayer phase is kept: a region cut on even starts splits like the original
    bands = split_bands(part, "RGGB")
    np.testing.assert_array_equal(bands["R"], split_bands(cfa, "RGGB")["R"][1:4, 2:8])


@pytest.mark.parametrize("rows, cols", [
    ((1, 8), (0, 4)),     # odd start row
    ((0, 8), (3, 9)),     # odd start column
    ((0, 14), (0, 4)),    # beyond the last row
    ((0, 8), (0, 17)),    # beyond the last column
    ((-2, 4), (0, 4)),    # negative
    ((6, 6), (0, 4)),     # empty
])
def test_cut_region_rejects(rows, cols):
    with pytest.raises(ValueError):
        cut_region(np.zeros((12, 16)), rows, cols)


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_split_saturation_marks_a_band_pixel_when_any_of_its_sites_reaches_the_threshold(pattern):
    """Hand cells: one site at the threshold marks its band pixel only (both greens count for G)."""
    cfa = np.full((4, 6), 100, np.uint16)
    letters = {(dy, dx): pattern[2 * dy + dx] for dy in range(2) for dx in range(2)}
    cells = {(0, 0): (0, 0), (0, 1): (0, 1), (1, 0): (1, 0), (1, 2): (1, 1)}   # cell (row, col) -> site (dy, dx)
    for (r, c), (dy, dx) in cells.items():
        cfa[2 * r + dy, 2 * c + dx] = 1000
    cfa[0, 4] = 999   # below the threshold: nothing
    sat = split_saturation(cfa, pattern, 1000.0)
    want = {b: np.zeros((2, 3), bool) for b in BANDS}
    for (r, c), site in cells.items():
        want[letters[site]][r, c] = True
    for band in BANDS:
        np.testing.assert_array_equal(sat[band], want[band], err_msg=band)


@pytest.mark.parametrize("pattern", ["RGGB", "GBRG"])
@pytest.mark.parametrize("threshold", [4094.0, 4093.5, 0.0, 70000.0])
def test_split_saturation_flags_a_band_pixel_when_any_site_reaches_the_threshold(pattern, threshold):
    """Against the definition written out with the 2x2 cells: a band pixel is saturated when any of its
    sites (both sites for G) is at or above the threshold."""
    rng = np.random.default_rng(3)
    cfa = rng.integers(4090, 4096, size=(6, 8), dtype=np.uint16)
    sat = split_saturation(cfa, pattern, threshold)
    cells = cfa.reshape(3, 2, 4, 2).transpose(0, 2, 1, 3).reshape(3, 4, 4) >= threshold   # row-major 2x2 cell
    for band in BANDS:
        where = [k for k, letter in enumerate(pattern) if letter == band]
        assert sat[band].dtype == bool
        assert np.array_equal(sat[band], cells[:, :, where].any(axis=2)), band
