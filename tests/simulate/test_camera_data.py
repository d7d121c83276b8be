"""The simulator's default camera's data (package data in pipeline/simulate/data) are the real Insta360 ONE's
calibration files, unchanged, and the simulator uses them as its truth.

The source files are the authors' processed calibration results (Larouche et al. 2024; public repository
RaphaelLarouche/radiance_camera_insta360, MIT licence, (c) 2021 Raphael Larouche), read from
``../shared/realdata/insta360-larouche/`` beside the repository or from the folder the environment variable
``PIPELINE_REALDATA`` names; the comparison with them skips with one line when they are absent. The other
tests need only the package's copy.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from pipeline.radiometry.rolloff import evaluate_rolloff
from pipeline.simulate.camera_data import authors_rolloff, measured_response
from pipeline.simulate.lens import default_rolloff
from pipeline.simulate.spectral import default_spectral_response

_ENV = os.environ.get("PIPELINE_REALDATA")
REALDATA = (Path(_ENV) if _ENV else Path(__file__).resolve().parents[2].parent / "shared" / "realdata")
FOLDER = REALDATA / "insta360-larouche"
RSR_FILES = {"close": "rsr_20200610.h5", "far": "rsr_20200710.h5"}
ROLLOFF_FILES = {"air": "rolloff_a.h5", "water": "rolloff_w.h5"}
#: the CSV files keep 10 significant digits of the stored doubles
RELATIVE_DIGITS = 1e-9


@pytest.mark.parametrize("lens", ["close", "far"])
def test_package_data_are_the_authors_files(lens):
    if not FOLDER.is_dir():
        pytest.skip(f"the authors' calibration files are not in {FOLDER}")
    h5py = pytest.importorskip("h5py")
    wl, response, unc = measured_response(lens)
    with h5py.File(FOLDER / RSR_FILES[lens], "r") as h5:
        g = h5[f"lens-{lens}"]
        np.testing.assert_array_equal(wl, g["wavelength"][()])
        np.testing.assert_allclose(np.stack([response[b] for b in "RGB"], axis=1), g["rsr_peak_norm"][()],
                                   rtol=RELATIVE_DIGITS)
        np.testing.assert_allclose(np.stack([unc[b] for b in "RGB"], axis=1), g["rsr_relative_unc"][()],
                                   rtol=RELATIVE_DIGITS)
    for medium, name in ROLLOFF_FILES.items():
        with h5py.File(FOLDER / name, "r") as h5:
            (date,) = list(h5[f"lens-{lens}"])
            stored = h5[f"lens-{lens}/{date}/fit-coefficients"][()]
        for i, band in enumerate("RGB"):
            np.testing.assert_allclose(authors_rolloff(lens, medium, band), stored[i], rtol=RELATIVE_DIGITS)


@pytest.mark.parametrize("lens", ["close", "far"])
def test_true_response_passes_through_the_measured_points(lens):
    """On the measured wavelengths the interpolated truth is the measurement (to rounding); between them it
    stays within the neighbouring points (monotone cubics do not overshoot)."""
    wl, response, _ = measured_response(lens)
    at = default_spectral_response(wl, lens)
    fine = np.linspace(wl[0], wl[-1], int(round((wl[-1] - wl[0]) / 0.1)) + 1)
    dense = default_spectral_response(fine, lens)
    for band in "RGB":
        np.testing.assert_allclose(at[band], response[band], rtol=1e-12, atol=1e-15)
        k = np.clip(np.searchsorted(wl, fine, side="right") - 1, 0, wl.size - 2)
        lo = np.minimum(response[band][k], response[band][k + 1])
        hi = np.maximum(response[band][k], response[band][k + 1])
        assert np.all((dense[band] >= lo - 1e-12) & (dense[band] <= hi + 1e-12)), band


def test_water_truth_ignores_the_authors_far_lens_water_fit():
    """The far lens's stored in-water fit is not normalised and goes negative beyond 76 degrees (the water
    field's edge); the simulator's in-water truth is positive and 1 on the axis."""
    stored = authors_rolloff("far", "water", "R")
    assert stored[0] < 0.95 and evaluate_rolloff(stored, 85.0) < 0.0
    truth = default_rolloff("R", "water", "far")
    assert evaluate_rolloff(truth, 0.0) == 1.0 and evaluate_rolloff(truth, 76.0) > 0.4
