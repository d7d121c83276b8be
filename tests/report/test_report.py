"""The HTML report: self-contained, built from a tiny simulated run's artefacts and diagnostics."""

from __future__ import annotations

import re

import pandas as pd
import pytest

from pipeline.io.artefact import read_artefact
from pipeline.report import build_report, fmt_uncertain, fmt_value

LENSES = ("far", "close")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from pipeline.config import load_config
    from pipeline.simulate import simulate_dataset
    from pipeline.diagnostics.missing_effects import diagnose_artefacts
    from pipeline.runner.workflow import run_stage

    tmp = tmp_path_factory.mktemp("report")
    cfg = load_config()
    simulate_dataset(tmp / "data", "tiny", seed=2,
                     effects=[("dark_current", {}), ("hot_pixels", {}), ("shutter_offset", {})],
                     experiments=("dark", "linearity"), progress=False)
    dark = {lens: tmp / "dark" / f"{lens}.nc" for lens in LENSES}
    lin = {lens: tmp / "lin" / f"{lens}.nc" for lens in LENSES}
    # checked=True: the frames' tag checks (what validate makes, which every run_stage call on a folder repeats) are
    # not what these tests assert; the simulator's datasets pass them (tests/io/test_validation.py, test_consistency.py),
    # as helpers.calibrate runs its stages
    run_stage("dark", tmp / "data", cfg, dark, checked=True)
    run_stage("linearity", tmp / "data", cfg, lin, {"dark": dark}, checked=True)
    diag = {name: tmp / "diag" / f"{name}.csv"
            for name in ("missing_effects", "unexplained", "run_errors", "error_history")}
    diagnose_artefacts({"dark": list(dark.values()), "linearity": list(lin.values())}, cfg,
                       diag["missing_effects"], diag["unexplained"], diag["run_errors"], tmp / "diag" / "ledger",
                       diag["error_history"])
    out = tmp / "report" / "report.html"
    skipped = {"geometry": "dataset has no geometry/ folder"}
    path = build_report(dark=dark, linearity=lin, out_html=out, skipped=skipped,
                        figures_dir=tmp / "figures", **diag)
    return {"tmp": tmp, "dark": dark, "lin": lin, "diag": diag, "path": path, "out": out,
            "html": out.read_text(encoding="utf-8")}


def test_report_written_atomically_at_requested_path(run):
    assert run["path"] == run["out"]
    assert run["out"].exists()
    assert not list(run["out"].parent.glob(".*.tmp"))
    assert run["html"].lstrip().startswith("<!DOCTYPE html>")
    assert run["html"].rstrip().endswith("</html>")


def test_report_is_self_contained(run):
    html = run["html"]
    assert not re.search(r"""(src|href)\s*=\s*["']?\s*(https?:)?//""", html, re.I)
    assert "http://" not in html and "https://" not in html
    assert "<script" not in html.lower()
    assert '<link ' not in html.lower()


def test_report_embeds_figures_and_saves_pngs(run):
    imgs = re.findall(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"', run["html"])
    assert len(imgs) >= 6
    pngs = sorted((run["tmp"] / "figures").glob("*.png"))
    assert len(pngs) == len(imgs)
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)


def test_report_names_top_ranked_missing_effect(run):
    missing = pd.read_csv(run["diag"]["missing_effects"]).sort_values("rank")
    assert len(missing)
    top = missing.iloc[0]
    assert str(top["effect"]) in run["html"]
    if bool(top["significant"]):
        assert "The residuals point to a missing effect" in run["html"]
        assert "model.effects" in run["html"]


def test_report_shows_dark_current_from_artefact(run):
    html = run["html"]
    for path in run["dark"].values():
        ds = read_artefact(path, "dark")
        text = fmt_uncertain(float(ds["dark_current_dn_per_s"]), float(ds["dark_current_dn_per_s_sigma"]))
        assert "±" in text
        assert text in html


def test_report_lists_skipped_stage_and_sections(run):
    html = run["html"]
    section = _section(html, "skipped")
    assert "geometry" in section and "dataset has no geometry/ folder" in section
    for title in ("Summary", "Dark frames", "Linearity", "Diagnostics", "Stages not run", "Provenance"):
        assert title in html


def test_fmt_uncertain_rounds_to_the_uncertainty():
    assert fmt_uncertain(0.71960019, 0.00265484) == "0.7196 ± 0.0027"
    assert fmt_uncertain(30560.48, 28.07) == "30560 ± 28"
    assert fmt_uncertain(1.5, float("nan")) == "1.500"
    assert "×10^-4" in fmt_uncertain(4.108e-4, 5.7e-6)


# ---------------------------------------------------------------- later stages: geometry ... immersion

LATER = ("geometry", "rolloff", "spectral", "absolute", "immersion")


def _geometry_with_curves(lens: str):
    """True maps plus the stage's curve variables (projection, references, band differences, errors).

    The real geometry stage needs the small scale (minutes); this gives the
    report's full geometry branch the same variable layout in a second.
    """
    import numpy as np

    from helpers import true_geometry_dataset

    from pipeline.simulate.lens import default_model
    from pipeline.stages.geometry import _projection_curves

    ds = true_geometry_dataset(lens, 64)
    media, bands = list(ds["medium"].values), list(ds["band"].values)
    rho = np.linspace(0.0, 40.0, 50)
    theta = np.zeros((len(media), len(bands), rho.size))
    refs = {k: np.zeros_like(theta) for k in ("equidistant", "stereographic", "orthographic")}
    for i, m in enumerate(media):
        th, ref = _projection_curves(default_model(lens, m, (64, 64)), rho)
        for j in range(len(bands)):
            theta[i, j] = th + 0.01 * (j - 1) * rho / 40.0
            for k in refs:
                refs[k][i, j] = ref[k]
    ds = ds.assign_coords(rho_px=("rho", rho, {"units": "pixel"}))
    dims3 = ("medium", "band", "rho")
    ds["projection_theta_deg"] = (dims3, theta, {"units": "degree"})
    for k, v in refs.items():
        ds[f"reference_{k}_theta_deg"] = (dims3, v, {"units": "degree"})
    g = bands.index("G")
    ds["theta_difference_vs_green_deg"] = (dims3, theta - theta[:, g:g + 1], {"units": "degree"})
    shape2 = (len(media), len(bands))
    ds["mean_error_px"] = (("medium", "band"), np.full(shape2, 0.3123), {"units": "pixel"})
    bins = np.linspace(2.0, 38.0, 8)
    ds["error_vs_radius_px"] = (("medium", "band", "radius_bin"), np.broadcast_to(0.2 + bins / 100, shape2 + bins.shape).copy(),
                                {"units": "pixel"})
    ds["error_vs_radius_rho_px"] = (("medium", "band", "radius_bin"), np.broadcast_to(bins, shape2 + bins.shape).copy(),
                                    {"units": "pixel"})
    return ds


@pytest.fixture(scope="module")
def later(run, calibrated):
    """Tiny artefacts of the later stages and a report that includes them (plus dark and linearity): the
    roll-off, spectral, absolute and immersion artefacts of the session's calibrated camera (the stages run on
    a tiny simulated dataset, as this fixture ran them before on datasets of its own), a geometry of its own."""
    from pipeline.io.artefact import write_artefact
    from helpers import true_geometry_dataset

    _, _, _, artefacts, _, _ = calibrated
    tmp = run["tmp"] / "later"
    # geometry: "far" with the stage's curve variables, "close" maps only (degrades gracefully)
    geo_ds = {"far": _geometry_with_curves("far"), "close": true_geometry_dataset("close", 64)}
    geo = {lens: write_artefact(geo_ds[lens], tmp / "geometry" / f"{lens}.nc", stage="geometry", inputs={},
                                config_subset={}, effects=[]) for lens in LENSES}
    paths = {st: dict(artefacts[st]) for st in LATER if st != "geometry"}
    paths["geometry"] = geo
    out = tmp / "report" / "report.html"
    build_report(dark=run["dark"], linearity=run["lin"], out_html=out, skipped={}, figures_dir=tmp / "figures",
                 **run["diag"], **paths)
    html = out.read_text(encoding="utf-8")
    return {"paths": paths, "html": html, "tmp": tmp}


def _section(html: str, anchor: str) -> str:
    return html.split(f'<section id="{anchor}">', 1)[1].split("</section>", 1)[0]


def _n_imgs(html: str) -> int:
    return len(re.findall(r'<img src="data:image/png;base64,', html))


def test_later_sections_present_with_figures(run, later):
    html = later["html"]
    for anchor, title in (("geometry", "Geometry"), ("rolloff", "Roll-off"), ("spectral", "Relative spectral response"),
                          ("absolute", "Absolute spectral radiance"), ("immersion", "Immersion factor")):
        sec = _section(html, anchor)
        assert title in sec and "not run" not in sec
        for lens in LENSES:
            assert f"Lens “{lens}”" in sec
            assert _n_imgs(sec) >= len(LENSES), anchor
    # at least one figure per lens and stage more than the dark/linearity-only report
    assert _n_imgs(html) >= _n_imgs(run["html"]) + len(LATER) * len(LENSES)
    assert len(list((later["tmp"] / "figures").glob("*.png"))) == _n_imgs(html)
    # the existing sections are still there
    for title in ("Summary", "Dark frames", "Linearity", "Diagnostics", "Stages not run", "Provenance"):
        assert title in html
    assert not re.search(r"https?://", html)


def test_later_numbers_come_from_the_artefacts(later):
    html = later["html"]
    p = later["paths"]
    a = read_artefact(p["absolute"]["far"], "absolute").sel(band="G")
    r_inv = fmt_uncertain(float(a["inverse_responsivity"]), float(a["inverse_responsivity_sigma"]))
    assert "±" in r_inv
    assert r_inv in _section(html, "absolute") and r_inv in _section(html, "summary")
    assert "W sr⁻¹ m⁻² nm⁻¹ s DN⁻¹" in _section(html, "absolute")
    lrad = fmt_uncertain(float(a["effective_radiance"]), float(a["effective_radiance_sigma"]))
    assert lrad in _section(html, "absolute")
    im = read_artefact(p["immersion"]["close"], "immersion").sel(band="R")
    i_r = fmt_uncertain(float(im["immersion_factor"]), float(im["immersion_factor_sigma"]))
    assert i_r in _section(html, "immersion") and i_r in _section(html, "summary")
    sp = read_artefact(p["spectral"]["far"], "spectral").sel(band="B")
    lam = fmt_uncertain(float(sp["effective_wavelength_nm"]), float(sp["effective_wavelength_nm_sigma"]))
    assert f"{lam} nm" in _section(html, "spectral")
    ro = read_artefact(p["rolloff"]["far"], "rolloff")
    c = fmt_uncertain(float(ro["water_closure_scale"].sel(band="G")), float(ro["water_closure_scale_sigma"].sel(band="G")))
    assert c in _section(html, "rolloff")


def test_geometry_section_with_and_without_curves(later):
    sec = _section(later["html"], "geometry")
    far, close = sec.split("Lens “close”", 1)
    assert "0.3123 pixel" in far                       # mean reprojection error from the curve artefact
    assert "reprojection error of the used corners" in far
    assert "no stored projection curves" in close      # maps-only artefact: theta map against radius
    assert "holds no reprojection errors" in close
    half = read_artefact(later["paths"]["geometry"]["close"], "geometry")["half_fov_deg"].sel(medium="water", band="G")
    assert f"{fmt_value(float(half))} °" in close


def test_stage_passed_as_none_says_not_run(run):
    html = run["html"]
    geo = _section(html, "geometry")
    assert "not run" in geo and "dataset has no geometry/ folder" in geo and 'href="#skipped"' in geo
    for anchor in ("rolloff", "spectral", "absolute", "immersion"):
        assert "not run" in _section(html, anchor)
    assert "Calibration per lens" not in _section(html, "summary")


def test_missing_experiment_folder_is_said_at_the_top_and_the_rest_is_shown(run):
    """The run fixture's dataset has no geometry/ folder: the summary opens with that (before any table),
    and the dark and linearity sections still show their figures."""
    summary = _section(run["html"], "summary")
    top = summary.split("<h2>", 1)[1].split("</h2>", 1)[1]
    first = top.lstrip().split("</div>", 1)[0]
    assert first.startswith('<div class="callout">') and "dataset has no geometry/ folder" in first
    assert summary.index("dataset has no geometry/ folder") < summary.index("<table>")
    for anchor in ("dark", "linearity"):
        assert _n_imgs(_section(run["html"], anchor)) >= len(LENSES)


def test_every_section_has_a_heading_and_every_figure_alt_text(run):
    """The page's structure the browser test relies on: sections with an <h2>, images with alt text,
    wide tables in a scrolling box, images no wider than their column."""
    html = run["html"]
    ids = re.findall(r'<section id="([^"]+)">\s*<h2>', html)
    assert {"summary", "dark", "linearity", "diagnostics", "skipped", "provenance"} <= set(ids)
    assert len(ids) == html.count("<section ")
    alts = re.findall(r'<img src="data:image/png;base64,[^"]+" alt="([^"]*)"', html)
    assert len(alts) == _n_imgs(html) and all(a.strip() for a in alts)
    assert html.count("<table>") == html.count('<div class="wide"><table>')
    assert "max-width:100%" in html


def test_error_history_labels_each_run_by_the_effects_it_added_or_removed():
    """Three runs of two experiments: the first labelled by its effects, the next by the change."""
    from pipeline.report.sections.diagnostics import history_figure, run_labels

    rows = []
    for t, effects, rms in (("t1", "dark_current hot_pixels", (1.0, 4.0)),
                            ("t2", "dark_current hot_pixels shutter_offset", (1.0, 1.1)),
                            ("t3", "dark_current shutter_offset", (1.3, 1.1)),
                            ("t4", "dark_current shutter_offset", (1.3, 1.1))):
        rows += [{"run_time": t, "experiment": exp, "model_effects": effects, "rms_z": z}
                 for exp, z in zip(("dark", "linearity"), rms)]
    history = pd.DataFrame(rows)
    assert run_labels(history) == ["run 1\ndark_current\nhot_pixels", "run 2\n+shutter_offset", "run 3\n−hot_pixels",
                                   "run 4\n(same effects)"]
    fig = history_figure(history)
    assert fig.png[:8] == b"\x89PNG\r\n\x1a\n" and "added" in fig.caption
    assert history_figure(pd.DataFrame()) is None


def _contrast_on_white(colour) -> float:
    """WCAG contrast ratio of a colour against white (1 = invisible, 21 = black)."""
    from matplotlib.colors import to_rgb

    def linear(c):
        return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4

    r, g, b = (linear(c) for c in to_rgb(colour))
    return 1.05 / (0.2126 * r + 0.7152 * g + 0.0722 * b + 0.05)


def test_palette_stays_legible_on_white():
    """Every categorical and sequential colour of the report keeps a contrast of at least 1.7 against white;
    the colours the palette leaves out, Okabe-Ito's yellow (#F0E442, 1.3) and viridis's yellow end (1.2),
    would fail the same bound."""
    from matplotlib import colormaps

    from pipeline.report.palette import BAND_COLOURS, OKABE_ITO, category, sequence

    colours = list(OKABE_ITO) + list(BAND_COLOURS.values()) + [category(i) for i in range(10)] + sequence(12)
    assert min(_contrast_on_white(c) for c in colours) >= 1.7
    assert _contrast_on_white("#F0E442") < 1.7 and _contrast_on_white(colormaps["viridis"](1.0)) < 1.7


def test_a_section_module_registers_itself_in_page_order():
    """A section registered with @section appears at its place on the page, without any other change;
    the same id from a second module is refused."""
    from pipeline.report import build_sections
    from pipeline.report.content import Text
    from pipeline.report.inputs import ReportInputs
    from pipeline.report.registry import _REGISTRY, section
    from pipeline.report.sections import registered_sections

    registered_sections()
    try:
        @section("closure-test", "A new stage", order=95)
        def build(inputs):
            return [Text(f"{len(inputs.stage('dark'))} dark artefacts")]

        empty = pd.DataFrame()
        # no artefacts: every section says what did not run, no figure is drawn (the test stays cheap)
        inputs = ReportInputs(artefacts={}, paths={}, missing_effects=empty, unexplained=empty, run_errors=empty,
                              error_history=empty, skipped={"dark": "the dataset has no dark/ folder"},
                              settings={"rolloff_summary_angles_deg": [70.0]})
        ids = [s.id for s in registered_sections()]
        assert ids.index("field") < ids.index("closure-test") < ids.index("diagnostics")
        new = [s for s in build_sections(inputs) if s.id == "closure-test"]
        assert new and new[0].blocks[0].text == "0 dark artefacts"
        with pytest.raises(ValueError, match="registered twice"):
            section("dark", "Dark again", order=1)(lambda inputs: [])
    finally:
        _REGISTRY.pop("closure-test", None)


def _residual_tests_and_closure(tmp_path):
    """A residual_tests.csv with one structured table (the roll-off's, following spot_x_px, in the far
    lens's right cell) and one at the noise floor, and the closure table of both as the closure artefact."""
    import numpy as np
    import xarray as xr

    from pipeline.io.artefact import write_artefact

    rng = np.random.default_rng(3)
    n_dark, n_roll = 60, 180
    x = rng.uniform(0, 900, n_roll)
    y = rng.uniform(0, 600, n_roll)
    z_roll = rng.normal(size=n_roll) + np.where(x > 600, 3.0, 0.0)
    z = np.concatenate([rng.normal(size=n_dark), z_roll])
    nan_dark = np.full(n_dark, np.nan)
    n = n_dark + n_roll
    text = {"experiment": ["dark"] * n_dark + ["rolloff"] * n_roll, "level": ["frame"] * n_dark + ["spot"] * n_roll,
            "lens": ["far"] * n, "band": [""] * n}
    numeric = {"z": (z, "1"), "value": (z, "DN"), "prediction": (np.zeros(n), "DN"), "residual": (z, "DN"),
               "sigma": (np.ones(n), "DN"),
               "exposure_s": (np.concatenate([rng.choice([0.01, 0.1, 1.0], n_dark), np.full(n_roll, np.nan)]), "s"),
               "spot_x_px": (np.concatenate([nan_dark, x]), "pixel"),
               "spot_y_px": (np.concatenate([nan_dark, y]), "pixel")}
    ds = xr.Dataset({k: ("measurement", np.asarray(v, dtype=str)) for k, v in text.items()}
                    | {k: ("measurement", v, {"units": u}) for k, (v, u) in numeric.items()})
    closure = write_artefact(ds, tmp_path / "residuals.nc", stage="closure", inputs={}, config_subset={}, effects=[])
    tests = pd.DataFrame([
        {"experiment": "dark", "level": "frame", "n_obs": n_dark, "chi2": 58.0, "dof": 57, "rms_z": 1.0,
         "p_chi2": 0.44, "p_block": 0.5, "significant": False, "covariate": "exposure_s",
         "covariate_p_value": 0.6, "image_plane": ""},
        {"experiment": "rolloff", "level": "spot", "n_obs": n_roll, "chi2": 700.0, "dof": 170, "rms_z": 2.0,
         "p_chi2": 1e-60, "p_block": 1e-9, "significant": True, "covariate": "spot_x_px",
         "covariate_p_value": 1e-30, "image_plane": "far lens, x 600 to 900 px, y 0 to 600 px"}])
    tests_csv = tmp_path / "residual_tests.csv"
    tests.to_csv(tests_csv, index=False)
    return tests_csv, closure


def test_residual_tests_and_closure_views_mark_the_structured_table(run, tmp_path):
    """Given residual_tests.csv and the closure table, the diagnostics section lists every table with the
    structured one highlighted, and draws per experiment z against the covariate its test names and, for the
    measurements with pixel positions, the image-plane map (measured: 1.5 s CPU)."""
    import json

    tests_csv, closure = _residual_tests_and_closure(tmp_path)
    out = build_report(dark={}, linearity={}, out_html=tmp_path / "r.html", figures_dir=tmp_path / "figures",
                       residual_tests=tests_csv, closure=closure, **run["diag"])
    sec = _section(out.read_text(encoding="utf-8"), "diagnostics")
    rows = re.findall(r"<tr( class=\"flag\")?>(.*?)</tr>", sec.split('id="residual-tests"', 1)[1], re.S)
    flagged = [cells for mark, cells in rows if mark]
    assert len(flagged) == 1 and ">rolloff<" in flagged[0] and "spot_x_px" in flagged[0] and ">yes<" in flagged[0]
    assert any(">dark<" in cells and ">no<" in cells for mark, cells in rows if not mark)
    captions = {k: e["caption"] for k, e in json.loads((tmp_path / "figures" / "figures.json").read_text()).items()}
    z_dark = [c for k, c in captions.items() if "closure_z_dark" in k]
    z_roll = [c for k, c in captions.items() if "closure_z_rolloff" in k]
    image = [c for k, c in captions.items() if "closure_image_plane" in k]
    assert len(z_dark) == 1 and "against exposure_s" in z_dark[0] and "No table of this experiment" in z_dark[0]
    assert len(z_roll) == 1 and "against spot_x_px" in z_roll[0] and "(spot) in vermillion" in z_roll[0]
    # the image-plane map only for the experiment with pixel positions; its outlined cell is the shifted one
    assert len(image) == 1 and "rolloff" in image[0] and "mean z +" in image[0]


def test_report_without_residual_tests_or_closure_says_so(run):
    """The run fixture's report is built without residual_tests.csv and the closure table: it still has its
    diagnostics section, which says both are missing."""
    sec = _section(run["html"], "diagnostics").split('id="residual-tests"', 1)[1].split("<h3", 1)[0]
    assert "no residual tests" in sec and "No closure table" in sec and "<img" not in sec


def test_summary_rolloff_at_a_field_angle_covers_the_truth(calibrated):
    """The summary's g(60°) of each lens, band and medium of the calibrated tiny camera (seed 5) against the
    simulator's true roll-off at 60° (normalised at the axis as the fitted curve is): with the field angle's
    uncertainty in its sigma (|dg/dθ| times the geometry's stated σθ) the 12 deviations over their sigmas have a
    chi-square below its 99.9 % point for 12 degrees of freedom (32.9). The curve's own sigma leaves out the
    fitted geometry's field-angle error, 0.5 to 0.7° low at 60° on the tiny camera: over 8 seeds the curves
    missed the truth at 60° by an rms of 3.2 (air) and 4.2 (water) of it."""
    import numpy as np
    from scipy import stats

    from pipeline.io.artefact import read_artefact
    from pipeline.radiometry.rolloff import evaluate_rolloff
    from pipeline.report.sections.summary import rolloff_at_angle
    from pipeline.simulate.lens import default_rolloff

    _, _, _, artefacts, _, _ = calibrated
    z, z_curve = [], []
    for lens in ("far", "close"):
        ro = read_artefact(artefacts["rolloff"][lens], "rolloff")
        geo = read_artefact(artefacts["geometry"][lens], "geometry")
        for medium in ("air", "water"):
            for band in ("R", "G", "B"):
                truth = default_rolloff(band, medium, lens)
                g_true = float(evaluate_rolloff(truth, 60.0) / evaluate_rolloff(truth, 0.0))
                g, sigma = rolloff_at_angle(ro, medium, band, 60.0, geo)
                _, sigma_curve = rolloff_at_angle(ro, medium, band, 60.0)
                assert sigma > sigma_curve > 0
                z.append((g - g_true) / sigma)
                z_curve.append((g - g_true) / sigma_curve)
    chi2 = float(np.sum(np.square(z)))
    print(f"g(60°) against the truth: chi2 {chi2:.1f} for 12 (curve's sigma alone {np.sum(np.square(z_curve)):.1f})")
    assert chi2 < stats.chi2.ppf(0.999, len(z)), np.round(z, 2)
