"""Plausibility of the fitted physics (pipeline.diagnostics.plausibility): values outside their physical range are found.

Real case: the immersion factors of the Insta360 ONE in the files of Larouche et al. (2024), public repository
RaphaelLarouche/radiance_camera_insta360, ``calibrations/immersion-factor/calibrationfiles/immersion_factor.h5``
(MIT licence, (c) 2021 Raphael Larouche; copied unchanged to ``shared/realdata/insta360-larouche``, see its
SOURCES.md). Its far lens's factors, 1.7774, 1.7762, 1.7939 (R, G, B; not in the paper), imply an outer-window
index of 1.12 to 1.17 through Eq. (10), which no lens material has; its close lens's, 1.6932, 1.6929, 1.7051 (the
paper's Table 2), 1.60 to 1.64 (the paper's Section 3.6: 1.58 to 1.63). The numbers are typed below for a
checkout without the shared folder. The water's index is Quan and Fry's at the bands' effective wavelengths of
the authors' measured spectral responses (``rsr_20200610.h5`` close, ``rsr_20200710.h5`` far, same repository)
or, without them, at 600, 540, 480 nm, at 25 C in fresh water (the immersion stage's default water).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from pipeline.io.artefact import read_artefact, write_artefact
from pipeline.config import defaults
from pipeline.diagnostics.findings import diagnosis_lines
from pipeline.diagnostics.missing_effects import write_plausibility
from pipeline.diagnostics.plausibility import (check_artefacts, conversion_gain_checks, dark_current_checks, finding_sentence,
                                   findings, quantum_efficiency_checks, rolloff_checks, window_index_checks)
from pipeline.radiometry.water import refractive_index_water
from pipeline.runner.run_summary import plausibility_summary

from conftest import SHARED

REAL = SHARED / "realdata" / "insta360-larouche"
#: the authors' immersion factors (R, G, B), typed from immersion_factor.h5 for a checkout without it
TYPED_FACTORS = {"close": (1.69318473, 1.69291801, 1.70506351), "far": (1.77744089, 1.7761491, 1.79386097)}
RSR_FILES = {"close": "rsr_20200610.h5", "far": "rsr_20200710.h5"}
NOMINAL_WAVELENGTH_NM = (600.0, 540.0, 480.0)
WATER_TEMPERATURE_C, WATER_SALINITY_PSU = 25.0, 0.0
BANDS = ("R", "G", "B")


@pytest.fixture(scope="module")
def settings():
    return defaults()["plausibility"]


def authors_factors(lens: str) -> np.ndarray:
    path = REAL / "immersion_factor.h5"
    if not path.exists():
        return np.array(TYPED_FACTORS[lens])
    h5py = pytest.importorskip("h5py")
    with h5py.File(path, "r") as f:
        group = f[f"lens-{lens}"]
        (date,) = list(group)
        return np.asarray(group[date]["immersion"][()], dtype=float).ravel()


def authors_water_index(lens: str) -> np.ndarray:
    """n_w at the effective wavelengths (Eq. 8, trapezoidal) of the lens's measured spectral response."""
    path = REAL / RSR_FILES[lens]
    wavelength = np.array(NOMINAL_WAVELENGTH_NM)
    if path.exists():
        h5py = pytest.importorskip("h5py")
        with h5py.File(path, "r") as f:
            g = f[f"lens-{lens}"]
            lam, s = np.asarray(g["wavelength"][()], float), np.asarray(g["rsr_peak_norm"][()], float)
        wavelength = np.trapezoid(lam[:, None] * s, lam, axis=0) / np.trapezoid(s, lam, axis=0)
    return refractive_index_water(wavelength, WATER_TEMPERATURE_C, WATER_SALINITY_PSU)


def eq10(n_w, n_g):
    """Larouche et al. (2024), Section 2.7, Eq. (10), written here: I = n_w (n_w + n_g)^2 / (1 + n_g)^2."""
    return n_w * (n_w + n_g) ** 2 / (1.0 + n_g) ** 2


@pytest.mark.parametrize("lens, status, low, high", [("far", "implausible", 1.10, 1.19),
                                                     ("close", "plausible", 1.59, 1.66)])
def test_authors_immersion_factors_implied_window_index(settings, lens, status, low, high):
    """Far lens: every band's implied index below the 1.3 of the lowest window material (measured 1.12-1.17);
    close lens: within 1.3-2.0 (measured 1.60-1.64). Each index, put back into Eq. (10) as written here,
    gives the authors' factor to 1e-9."""
    factors, n_w = authors_factors(lens), authors_water_index(lens)
    checks = window_index_checks(factors, n_w, settings=settings, lens=lens, bands=BANDS)
    assert [c.status for c in checks] == [status] * 3
    values = np.array([c.value for c in checks])
    assert np.all((values > low) & (values < high)), values
    np.testing.assert_allclose(eq10(n_w, values), factors, rtol=0, atol=1e-9)
    if status == "implausible":
        assert np.all(values < settings["window_index_range"][0])
        table = pd.DataFrame([c.__dict__ for c in checks])
        for (_, row), value in zip(findings(table).iterrows(), values):
            sentence = finding_sentence(row)
            assert f"{value:.4g}" in sentence and "1.3 to 2" in sentence and "implausible" in sentence


def test_immersion_factor_no_index_solves_is_impossible(settings):
    """I below n_w (or above n_w^3) has no index in Eq. (10): impossible, the value NaN and said so."""
    (check,) = window_index_checks([1.30], [1.3322], [0.002], settings=settings, lens="close", bands=["R"])
    assert check.status == "impossible" and np.isnan(check.value)
    assert "no index solves Eq. (10)" in check.derivation


def _dark(value, sigma, measured=1) -> xr.Dataset:
    ds = xr.Dataset({"dark_current_dn_per_s": ((), value, {"units": "DN s-1", "measured": measured}),
                     "dark_current_dn_per_s_sigma": ((), sigma, {"units": "DN s-1"})})
    return ds


def _written(ds: xr.Dataset, stage: str, path) -> xr.Dataset:
    write_artefact(ds, path, stage=stage, inputs={}, config_subset={}, effects=[])
    return read_artefact(path, stage)


def test_negative_dark_current_beyond_its_sigma(settings, tmp_path):
    """-0.05 +- 0.01 DN/s is 5 sigma below 0: impossible; -0.02 +- 0.01 is within 3 sigma; not measured: not
    checked. Through an artefact written and read back (the ``measured`` attribute survives)."""
    beyond = _written(_dark(-0.05, 0.01), "dark", tmp_path / "beyond.nc")
    (check,) = dark_current_checks(beyond, settings=settings, lens="far")
    assert check.status == "impossible"
    assert check.departure_sigma == pytest.approx(5.0, rel=1e-9)
    assert dark_current_checks(_dark(-0.02, 0.01), settings=settings)[0].status == "plausible"
    assert dark_current_checks(_written(_dark(-0.5, 0.01, measured=0), "dark", tmp_path / "not.nc"),
                               settings=settings) == []


def test_rolloff_above_its_on_axis_value(settings):
    """g = 1 + 2e-5 theta^2 (sigma of a2 1e-6) measured to 40 degree: furthest beyond its margin at 40 degree,
    g = 1.032 by hand, (0.032) / (1e-6 x 1600) = 20 sigma above 1; a cos^4 fall-off fitted to it is not."""
    cov = np.zeros((5, 5))
    cov[1, 1] = 1e-6 ** 2
    (check,) = rolloff_checks([1.0, 2e-5, 0, 0, 0], cov, 40.0, settings=settings, lens="close", band="G",
                              medium="air")
    assert check.status == "implausible" and check.at == "air, theta 40 degree"
    assert check.value == pytest.approx(1.032, abs=1e-12)
    assert check.departure_sigma == pytest.approx(20.0, rel=1e-9)
    theta = np.linspace(0.0, 80.0, 81)
    falling = np.polynomial.polynomial.polyfit(theta ** 2, np.cos(np.deg2rad(theta)) ** 4, 4)
    (fine,) = rolloff_checks(falling / falling[0], None, 80.0, settings=settings)
    assert fine.status == "plausible" and fine.value <= 1.0


def test_authors_far_lens_water_rolloff_rises_above_its_on_axis_value(settings):
    """The authors' in-water roll-off polynomials (rolloff_w.h5, not normalised for the far lens) divided by
    their on-axis value: the far lens's rise to 1.011, 1.025, 1.034 (R, G, B) near 20-26 degrees, above 1 with
    no stated uncertainty; the close lens's fall from the axis."""
    path = REAL / "rolloff_w.h5"
    if not path.exists():
        pytest.skip("shared/realdata/insta360-larouche/rolloff_w.h5 not present")
    h5py = pytest.importorskip("h5py")
    with h5py.File(path, "r") as f:
        coef = {lens: np.asarray(f[f"lens-{lens}"][list(f[f"lens-{lens}"])[0]]["fit-coefficients"][()], float)
                for lens in ("close", "far")}
    water_max_deg = 70.0    # the in-water measurements reach 70 degrees (Section 2.4)
    for lens, status in (("far", "implausible"), ("close", "plausible")):
        checks = [rolloff_checks(c, None, water_max_deg, settings=settings, lens=lens, band=b, medium="water")[0]
                  for c, b in zip(coef[lens], BANDS)]
        assert [c.status for c in checks] == [status] * 3
    theta = np.arange(0.0, water_max_deg + 0.25, 0.5)
    by_hand = [max(sum(a * theta ** (2 * k) for k, a in enumerate(c))) / c[0] for c in coef["far"]]
    far = [rolloff_checks(c, None, water_max_deg, settings=settings)[0].value for c in coef["far"]]
    np.testing.assert_allclose(far, by_hand, rtol=1e-12)
    assert 1.01 < min(far) and max(far) < 1.04


def test_zero_or_negative_conversion_gain(settings, tmp_path):
    """A photon-transfer gain of 0 or below is impossible whatever its uncertainty, and so is one ISO's of
    the gain sweep; a gain that was not measured is not checked."""
    def linearity(gain, sweep, measured=1):
        return xr.Dataset({"conversion_gain_dn_per_e": ((), gain, {"measured": measured}),
                           "conversion_gain_dn_per_e_sigma": ((), 0.05),
                           "ptc_gain_sweep_conversion_gain_dn_per_e": ("ptc_iso", np.array(sweep, float))},
                          coords={"ptc_iso": [100.0, 200.0]})

    zero = _written(linearity(0.0, [0.8, 1.6]), "linearity", tmp_path / "zero.nc")
    statuses = [c.status for c in conversion_gain_checks(zero, settings=settings)]
    assert statuses == ["impossible", "plausible", "plausible"]
    negative = conversion_gain_checks(linearity(0.8, [0.8, -1.6]), settings=settings)
    assert [(c.at, c.status) for c in negative] == [("", "plausible"), ("ISO 100", "plausible"),
                                                    ("ISO 200", "impossible")]
    assert [c.at for c in conversion_gain_checks(linearity(-0.4, [0.8, 1.6], measured=0), settings=settings)] == \
        ["ISO 100", "ISO 200"]


def test_quantum_efficiency_outside_zero_one(settings):
    """QE 0.45 +- 0.02 fine, 1.2 +- 0.05 is 4 sigma above 1, -0.1 +- 0.01 10 sigma below 0: impossible."""
    ds = xr.Dataset({"quantum_efficiency": ("band", [0.45, 1.2, -0.1]),
                     "quantum_efficiency_sigma": ("band", [0.02, 0.05, 0.01])}, coords={"band": list(BANDS)})
    checks = quantum_efficiency_checks(ds, settings=settings, lens="close", stage="absolute")
    assert [(c.band, c.status) for c in checks] == [("R", "plausible"), ("G", "impossible"), ("B", "impossible")]
    np.testing.assert_allclose([c.departure_sigma for c in checks[1:]], [4.0, 10.0], rtol=1e-9)


def test_diagnose_and_run_summary_say_the_findings(tmp_path, settings):
    """The diagnostics' table, read back as ``diagnose`` reads it, gives one finding per value outside its
    range, with the value and the range, and the run summary one line each."""
    far = xr.Dataset({"immersion_factor": ("band", authors_factors("far")),
                      "immersion_factor_sigma": ("band", np.full(3, np.nan)),
                      "n_w": ("band", authors_water_index("far"))}, coords={"band": list(BANDS)})
    table = check_artefacts({"immersion": {"far": far}, "dark": {"close": _dark(-0.05, 0.01)}})
    path = tmp_path / "diagnostics" / "plausibility.csv"
    path.parent.mkdir()
    table.to_csv(path, index=False)
    empty = pd.DataFrame()
    found = {"model_effects": [], "n_measurements": 0, "run_errors": empty, "residual_tests": empty,
             "missing_effects": empty, "unexplained": empty, "lens_tests": empty, "error_history": empty,
             "plausibility": pd.read_csv(path)}
    lines = diagnosis_lines(found, tmp_path)
    numbered = [line for line in lines if line.startswith("  1.") or line.startswith("  2.") or
                line.startswith("  3.") or line.startswith("  4.")]
    assert len(numbered) == 4
    assert "dark current -0.05 ± 0.01 DN s-1, outside at least 0" in numbered[0]
    assert all("outer-window index" in line and "1.3 to 2" in line for line in numbered[1:])
    assert any(line.startswith("  outer-window index") and "3 outside" in line for line in lines)
    summary = plausibility_summary(path.parent / "plausibility.csv")
    assert [line.split(":")[0].strip() for line in summary] == ["impossible"] + ["implausible"] * 3


def test_clean_calibration_has_no_finding(calibrated, config, tmp_path):
    """The simulated camera calibrated by the pipeline (seed 5, no effects): the checks run on every stage that
    has a quantity with a range, and none is outside it."""
    _, _, _, artefacts, _, _ = calibrated
    paths = {stage: [str(p) for p in by_lens.values()] for stage, by_lens in artefacts.items()}
    loaded = {stage: [read_artefact(p, stage) for p in ps] for stage, ps in paths.items()}
    table = write_plausibility(paths, loaded, config, tmp_path / "plausibility.csv")
    assert set(table["quantity"]) >= {"window_index", "conversion_gain_dn_per_e", "rolloff", "dark_current_dn_per_s"}
    assert findings(table).empty, findings(table).apply(finding_sentence, axis=1).tolist()
    assert len(pd.read_csv(tmp_path / "plausibility.csv")) == len(table)


def test_report_summary_states_each_finding_with_value_and_range(settings):
    """The report's summary: a callout and a marked row per value outside its range, with the value, the range
    and its config key; one 'ok' line when every value is within."""
    from pipeline.report.content import Table, Text
    from pipeline.report.inputs import ReportInputs
    from pipeline.report.sections.summary import summary_section

    far = xr.Dataset({"immersion_factor": ("band", authors_factors("far")), "n_w": ("band", authors_water_index("far"))},
                     coords={"band": list(BANDS)})
    empty = pd.DataFrame()

    def summary(table):
        inputs = ReportInputs(artefacts={}, paths={}, missing_effects=empty, unexplained=empty, run_errors=empty,
                              error_history=empty, plausibility=table, settings={"rolloff_summary_angles_deg": []})
        return summary_section(inputs)

    blocks = summary(check_artefacts({"immersion": {"far": far}}))
    callouts = [b for b in blocks if isinstance(b, Text) and "outside their physical range" in str(b.text)]
    assert len(callouts) == 1 and callouts[0].kind == "callout"
    (table,) = [b for b in blocks if isinstance(b, Table) and "outer-window index" in " ".join(map(str, b.rows[0]))]
    assert len(table.rows) == 3 and all(table.marked)
    for row, value in zip(table.rows, window_index_checks(authors_factors("far"), authors_water_index("far"),
                                                          settings=settings)):
        assert row[3] == "implausible" and row[4] == f"{value.value:.4g}"
        assert row[5] == "1.3 to 2 (plausibility.window_index_range)"
    fine = summary(check_artefacts({"dark": {"close": _dark(0.7, 0.001)}}))
    assert any(isinstance(b, Text) and b.kind == "ok" and "within it" in str(b.text) for b in fine)
