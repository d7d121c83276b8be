"""The calibration report: one self-contained HTML page, and each figure as a PNG file.

:func:`build_report` reads the stage artefacts (NetCDF), the calibration bundle and the diagnostics
tables (CSV); every section module of :mod:`pipeline.report.sections` turns them into figures and
tables with captions (:mod:`pipeline.report.content`); the Jinja2 templates of the package make the
page: figures embedded as base64 PNG, the style sheet inline, nothing loaded from the network.
Every number in the report is read from those inputs; the package holds no calibration values.
"""

from __future__ import annotations

import os
from contextlib import ExitStack
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

from pipeline.io.artefact import read_artefact
from pipeline.report.formatting import fmt_uncertain, fmt_value, quantity, units_text
from pipeline.report.inputs import ReportInputs, read_csv_or_empty

if TYPE_CHECKING:
    from pipeline.report.render import RenderedSection

# the modules that draw (matplotlib) and render (jinja2) are imported when a report is built, not with the
# package: the workflow's start-up reads report_settings and the run summary read_csv_or_empty, and
# matplotlib's import was a quarter of every Snakemake start's CPU (0.7 of 2.9 s on a tiny dataset)

__all__ = ["build_report", "build_sections", "fmt_value", "fmt_uncertain", "quantity", "units_text",
           "read_csv_or_empty", "snr_against_radiance", "ReportInputs", "report_settings"]

#: the stages whose artefacts the report reads, in the order of the chain
REPORT_STAGES = ("dark", "linearity", "geometry", "rolloff", "spectral", "absolute", "immersion", "field")


def __getattr__(name: str):
    """``snr_against_radiance``, imported on first use (it draws with matplotlib)."""
    if name == "snr_against_radiance":
        from pipeline.report.sections.noise_floor import snr_against_radiance

        return snr_against_radiance
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def build_sections(inputs: ReportInputs) -> list[RenderedSection]:
    """Every registered section's blocks, in page order.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The artefacts, diagnostics tables and run facts the sections read.

    Returns
    -------
    list[pipeline.report.render.RenderedSection]
        One per registered section (:func:`pipeline.report.sections.registered_sections`): its anchor, title,
        introduction and blocks.
    """
    from pipeline.report.palette import apply_style
    from pipeline.report.render import RenderedSection
    from pipeline.report.sections import registered_sections

    apply_style()
    return [RenderedSection(s.id, s.title, s.intro, s.build(inputs)) for s in registered_sections()]


def report_settings(config: dict) -> dict:
    """What the report reads of the configuration.

    The ``report`` section and the diagnostics' ``structured_rms_z`` (the rms z above which an experiment's
    residuals are called structured), ``covariate_bins`` and ``image_plane_cells`` (the bins and the grid of
    the residual tests, which the closure figures show).

    Parameters
    ----------
    config : dict
        The run's configuration.

    Returns
    -------
    dict
        The ``report`` section's settings with the three diagnostics settings added.
    """
    diag = config["diagnostics"]
    return {**config["report"], **{k: diag[k] for k in ("structured_rms_z", "covariate_bins", "image_plane_cells")}}


def _default_settings() -> dict:
    from pipeline.config import load_config

    return report_settings(load_config())


def build_report(*, dark: dict[str, Path], linearity: dict[str, Path], missing_effects: Path,
                 unexplained: Path, run_errors: Path, error_history: Path, out_html: Path,
                 skipped: dict[str, str] | None = None, figures_dir: Path | None = None,
                 geometry: dict[str, Path] | None = None, rolloff: dict[str, Path] | None = None,
                 spectral: dict[str, Path] | None = None, absolute: dict[str, Path] | None = None,
                 immersion: dict[str, Path] | None = None, calibration: Path | None = None,
                 field: dict[str, Path] | None = None, failed: dict[str, str] | None = None,
                 dataset: dict | None = None, settings: dict | None = None,
                 residual_tests: Path | None = None, closure: Path | None = None,
                 lens_tests: Path | None = None, field_scale: Path | None = None,
                 plausibility: Path | None = None) -> Path:
    """Write the calibration report as one self-contained HTML file and return its path.

    A stage given as None or empty gets a section saying it was not run, with its reason from ``skipped``.
    The diagnostics tables are optional: absent, the diagnostics section says so. The artefacts are opened
    lazily and closed once the page is rendered. The HTML is written to a temporary sibling and renamed.

    Parameters
    ----------
    dark : dict[str, pathlib.Path]
        Lens -> the dark artefact.
    linearity : dict[str, pathlib.Path]
        Lens -> the linearity artefact.
    missing_effects : pathlib.Path
        The diagnostics' ``missing_effects.csv``: the effects missing from the model, ranked by how well each
        one's signature explains the residuals.
    unexplained : pathlib.Path
        The diagnostics' ``unexplained.csv``: the tables with significant structure, a sentence each.
    run_errors : pathlib.Path
        The diagnostics' ``run_errors.csv``: each experiment's fit (rms z, chi-square, dof).
    error_history : pathlib.Path
        The diagnostics' ``error_history.csv``: one row per experiment and run, for the history figure.
    out_html : pathlib.Path
        The report's file.
    skipped : dict[str, str] or None, optional
        Stage -> why it was not run.
    figures_dir : pathlib.Path or None, optional
        When given, every figure is also written there as ``NN_name.png`` with ``figures.json`` naming each
        one's section and caption (:func:`pipeline.report.render.write_figures`).
    geometry, rolloff, spectral, absolute, immersion, field : dict[str, pathlib.Path] or None, optional
        Lens -> that stage's artefact.
    calibration : pathlib.Path or None, optional
        The calibration bundle (noise floor).
    failed : dict[str, str] or None, optional
        After a run with failed jobs, a stage that did not finish -> its error line: the summary names them
        first.
    dataset : dict or None, optional
        ``path``, ``camera`` (make, model, serial) and ``experiments``, for the summary.
    settings : dict or None, optional
        :func:`report_settings` of the run's configuration; the schema defaults when None.
    residual_tests : pathlib.Path or None, optional
        The diagnostics' ``residual_tests.csv``.
    closure : pathlib.Path or None, optional
        The closure table ``residuals.nc``.
    lens_tests : pathlib.Path or None, optional
        ``lens_tests.csv``: one value shared by the lenses against one per lens.
    field_scale : pathlib.Path or None, optional
        ``field_scale.csv``: the field scale closure.
    plausibility : pathlib.Path or None, optional
        ``plausibility.csv``: each fitted quantity with a physical range against it.

    Returns
    -------
    pathlib.Path
        ``out_html``.

    Raises
    ------
    pipeline.errors.ArtefactError
        If an artefact given is missing, unreadable or of another stage or version.
    """
    from pipeline.report.render import number_figures, render_page, write_figures

    out_html = Path(out_html)
    failed = dict(failed or {})
    given = {"dark": dark, "linearity": linearity, "geometry": geometry, "rolloff": rolloff, "spectral": spectral,
             "absolute": absolute, "immersion": immersion, "field": field}
    paths = {st: {lens: Path(p) for lens, p in dict(given[st] or {}).items()} for st in REPORT_STAGES}
    # the artefacts and the calibration bundle opened lazily and closed once the page is rendered: a section
    # reads only the variables it uses (and keeps those read), so the report does not hold a bundle's
    # per-pixel maps it never draws (at the full resolution the bundle alone is 989 MB, and loading every
    # artefact whole made the report's job the largest of the workflow, 2,344 MiB)
    with ExitStack() as opened:
        def lazy(path, stage):
            return opened.enter_context(read_artefact(path, stage, load=False))

        inputs = ReportInputs(
            artefacts={st: {lens: lazy(p, st) for lens, p in by_lens.items()} for st, by_lens in paths.items()},
            paths=paths,
            missing_effects=read_csv_or_empty(Path(missing_effects)),
            unexplained=read_csv_or_empty(Path(unexplained)),
            run_errors=read_csv_or_empty(Path(run_errors)),
            error_history=read_csv_or_empty(Path(error_history)),
            residual_tests=read_csv_or_empty(Path(residual_tests)) if residual_tests is not None else pd.DataFrame(),
            closure=lazy(closure, "closure") if closure is not None and Path(closure).exists() else None,
            lens_tests=read_csv_or_empty(Path(lens_tests)) if lens_tests is not None else pd.DataFrame(),
            field_scale=read_csv_or_empty(Path(field_scale)) if field_scale is not None else pd.DataFrame(),
            plausibility=read_csv_or_empty(Path(plausibility)) if plausibility is not None else pd.DataFrame(),
            skipped={**dict(skipped or {}), **failed}, failed=failed,
            calibration=lazy(calibration, "calibration") if calibration is not None else None,
            dataset=dict(dataset or {}),
            settings=dict(settings) if settings is not None else _default_settings())
        rendered = build_sections(inputs)
        figures = number_figures(rendered)
        if figures_dir is not None:
            write_figures(figures, Path(figures_dir))
        doc = render_page("Camera calibration report", rendered,
                          datetime.now(timezone.utc).isoformat(timespec="seconds"), len(figures))
    out_html.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_html.with_name(f".{out_html.name}.tmp")
    try:
        tmp.write_text(doc, encoding="utf-8")
        os.replace(tmp, out_html)
    finally:
        if tmp.exists():
            tmp.unlink()
    return out_html
