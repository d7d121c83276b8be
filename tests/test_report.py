"""The HTML report: self-contained, built from a tiny simulated run's artefacts and diagnostics."""

from __future__ import annotations

import re
from pathlib import Path

import pandas as pd
import pytest

from pipeline.artefact import read_artefact
from pipeline.report import build_report, fmt_uncertain

LENSES = ("far", "close")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from pipeline.config import load_config
    from pipeline.simulate import simulate_dataset
    from pipeline.stage_io import run_dark, run_diagnostics, run_linearity

    tmp = tmp_path_factory.mktemp("report")
    cfg = load_config()
    simulate_dataset(tmp / "data", "tiny", seed=2,
                     effects=[("dark_current", {}), ("hot_pixels", {}), ("shutter_offset", {})],
                     experiments=("dark", "linearity"), progress=False)
    dark = {lens: tmp / "dark" / f"{lens}.nc" for lens in LENSES}
    lin = {lens: tmp / "lin" / f"{lens}.nc" for lens in LENSES}
    run_dark(tmp / "data", cfg, dark)
    run_linearity(tmp / "data", cfg, dark, lin)
    diag = {name: tmp / "diag" / f"{name}.csv"
            for name in ("missing_effects", "unexplained", "run_errors", "error_history")}
    run_diagnostics({"dark": list(dark.values()), "linearity": list(lin.values())}, cfg,
                    diag["missing_effects"], diag["unexplained"], diag["run_errors"], diag["error_history"])
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
    section = html.split('id="skipped"', 1)[1].split("<h2", 1)[0]
    assert "geometry" in section and "dataset has no geometry/ folder" in section
    for title in ("Summary", "Dark frames", "Linearity", "Diagnostics", "Stages not run", "Provenance"):
        assert title in html


def test_fmt_uncertain_rounds_to_the_uncertainty():
    assert fmt_uncertain(0.71960019, 0.00265484) == "0.7196 ± 0.0027"
    assert fmt_uncertain(30560.48, 28.07) == "30560 ± 28"
    assert fmt_uncertain(1.5, float("nan")) == "1.500"
    assert "×10^-4" in fmt_uncertain(4.108e-4, 5.7e-6)
