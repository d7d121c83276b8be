"""What a workflow run found, in a few lines for the terminal (printed when a run ends).

Reads only the diagnostics' tables and the stages' artefacts: where the report
is, one line per experiment (at the noise floor, or the effect most likely
missing with its amplitude and the config line that adds it, or structure no
catalogue effect explains), and the stages that were skipped and why.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from pipeline.errors import InputError

from pipeline.report import read_csv_or_empty as _read

__all__ = ["job_error_line", "report_after_failure", "stages_not_finished", "summarise_run"]


def _amplitude(row) -> str:
    try:
        value, low, high = (float(row[k]) for k in ("amplitude", "amplitude_low", "amplitude_high"))
    except (KeyError, TypeError, ValueError):
        return ""
    units = row.get("units", "")
    # "1" is the unit of a dimensionless amplitude: nothing to print
    units = "" if pd.isna(units) or str(units) == "1" else f" {units}"
    return f" {value:.3g}{units} (95 % interval {low:.3g} to {high:.3g})"


def summarise_run(results: str | Path, model_effects: list[str], skipped: dict[str, str] | None = None,
                  structured_rms_z: float = 1.5, *, diagnostics: Path | None = None,
                  report: Path | None = None) -> list[str]:
    """The lines to print after a run.

    The field match-up's line begins with its scale closure (``field_scale.csv``: the camera/reference scale
    against the lab calibration's prediction), the one test of the absolute radiance against an instrument
    the calibration was not fitted to. The last line gives one ``--config`` that adds every effect the
    run found, in the order the diagnostics accepted them (following one experiment's suggestion alone
    would drop the others').

    Parameters
    ----------
    results : str or pathlib.Path
        The workflow's results folder.
    model_effects : list of str
        The effects of the run's ``model.effects``.
    skipped : dict[str, str], optional
        Stage -> why it was skipped; one line each.
    structured_rms_z : float, default 1.5
        RMS of the normalised residuals (dimensionless) at or below which an experiment without a significant
        candidate is at the noise floor (``diagnostics.structured_rms_z``).
    diagnostics : pathlib.Path, optional
        Folder of the diagnostics' tables, when not ``results/diagnostics``.
    report : pathlib.Path, optional
        The report's HTML file, when not ``results/report/index.html``.

    Returns
    -------
    list of str
        The lines: where the report is, one per experiment, the ``--config`` that adds what was found, the
        plausibility findings and the skipped stages.
    """
    from pipeline.diagnostics.missing_effects import accepted_effects, field_scale_sentence

    results = Path(results)
    diag = diagnostics or results / "diagnostics"
    report = report or results / "report" / "index.html"
    lines = [f"Calibration report: {report.resolve()}" if report.exists() else "No report was written."]
    errors = _read(diag / "run_errors.csv")
    ranked = _read(diag / "missing_effects.csv")
    unexplained = _read(diag / "unexplained.csv")
    scale = _read(diag / "field_scale.csv")
    found_all = [e for e in accepted_effects(ranked) if e not in model_effects] if len(ranked) else []
    width = max([len(str(e)) for e in errors.get("experiment", [])] + [9])
    for _, row in errors.iterrows():
        exp = str(row["experiment"])
        head = f"  {exp:<{width}}  rms_z {float(row['rms_z']):5.2f}: "
        if exp == "field" and len(scale):
            head += field_scale_sentence(scale, ranked) + ". Match-up: "
        found = ranked[(ranked["experiment"].astype(str).str.split("+").map(lambda names: exp in names))
                       & ranked["significant"].astype(bool)] if len(ranked) else ranked
        if len(found):
            top = found.sort_values("rank").iloc[0]
            lines.append(f"{head}{top['effect']} is most likely missing,{_amplitude(top)}")
            continue
        left = unexplained[unexplained["experiment"].astype(str) == exp] if len(unexplained) else unexplained
        if len(left):
            lines.append(f"{head}structured residuals that no catalogue effect explains; they follow "
                         f"{left.iloc[0]['covariate']} (see the report)")
        elif float(row["rms_z"]) <= structured_rms_z:
            lines.append(f"{head}at the noise floor")
        else:
            lines.append(f"{head}above the noise floor, no significant candidate (see the report)")
    if found_all:
        effects = ", ".join(list(model_effects) + found_all)
        lines.append(f"  to add every effect this run found ({', '.join(found_all)}): --config 'model={{effects: "
                     f"[{effects}]}}' (or model.effects in config/config.yaml)")
    lines += plausibility_summary(diag / "plausibility.csv")
    for stage, why in (skipped or {}).items():
        lines.append(f"  skipped: {stage} ({why})")
    return lines


def plausibility_summary(path: Path) -> list[str]:
    """One line per fitted quantity outside its physical range, with the value and the range.

    The sentence is :func:`pipeline.diagnostics.plausibility.finding_sentence`'s.

    Parameters
    ----------
    path : pathlib.Path
        The diagnostics' ``plausibility.csv`` (absent or empty: no line).

    Returns
    -------
    list of str
        One line per finding, beginning with its status.
    """
    from pipeline.diagnostics.plausibility import finding_sentence, findings

    return [f"  {row['status']}: {finding_sentence(row)}" for _, row in findings(_read(path)).iterrows()]


# --------------------------------------------------------------------------- a run with failed jobs

#: the lines a job's log (``results/logs/<stage>/<lens>.log``) gives an error on: the pipeline's
#: ``ERROR`` record (bad input, an impossible result, or an unexpected exception)
_LOG_ERROR = " ERROR "
#: where a failed run's diagnostics and report go, inside the results folder
FAILED_RUN_DIR = "failed_run"


def job_error_line(log_path: str | Path, since: float | None = None) -> str | None:
    """The error of a failed job from its log.

    Parameters
    ----------
    log_path : str or pathlib.Path
        The job's log (``results/logs/<stage>/<lens>.log``).
    since : float, optional
        A time stamp (s since the epoch, as ``time.time()``): a log last written before it belongs to a job of
        an earlier run and gives None.

    Returns
    -------
    str or None
        The message of its last ERROR record (bad input, an impossible result, or
        ``unexpected <Exception>: ...``); None when the log is absent, older than ``since`` or holds none.
    """
    path = Path(log_path)
    if not path.is_file() or (since is not None and path.stat().st_mtime < since):
        return None
    errors = [line.split(_LOG_ERROR, 1)[1].strip() for line in path.read_text(errors="replace").splitlines()
              if _LOG_ERROR in line]
    return errors[-1] if errors else None


def stages_not_finished(results: str | Path, stage_lenses: dict[str, list[str]],
                        since: float | None = None) -> dict[str, str]:
    """Stage -> why it has no artefact for some lens after a failed run (from the jobs' logs).

    A job that ran and failed gives its error line (``failed for lens far: <file>: <problem> (log: ...)``);
    a stage that did not run says which failed stage it needed, or that the run stopped before it.

    Parameters
    ----------
    results : str or pathlib.Path
        The workflow's results folder.
    stage_lenses : dict[str, list of str]
        Every stage the run was to run -> its lenses.
    since : float, optional
        The run's start (s since the epoch): logs older than it belong to earlier runs.

    Returns
    -------
    dict[str, str]
        Stage -> the reason, for the stages that lack an artefact of some lens.
    """
    from pipeline.runner.workflow import STAGES

    results = Path(results)
    failed: dict[str, str] = {}
    missing: dict[str, list[str]] = {}
    for stage, lenses in stage_lenses.items():
        for lens in lenses:
            if (results / stage / f"{lens}.nc").exists():
                continue
            log = results / "logs" / stage / f"{lens}.log"
            error = job_error_line(log, since)
            if error is not None and stage not in failed:
                failed[stage] = f"failed for lens {lens}: {error} (log: {log})"
            elif error is None:
                missing.setdefault(stage, []).append(lens)
    out = dict(failed)
    for stage in missing:
        if stage in out:
            continue
        spec = STAGES[stage]
        needs = [up for up in spec.upstream + spec.optional_upstream if up in failed or up in missing]
        out[stage] = (f"not run: it needs {', '.join(needs)}, which did not finish" if needs else
                      "not run: the run stopped at a failed job before it (snakemake --keep-going runs "
                      "every job that does not depend on a failed one)")
    return out


def report_after_failure(results: str | Path, stage_lenses: dict[str, list[str]], config: dict,
                         skipped: dict[str, str] | None = None, since: float | None = None) -> list[str]:
    """After a run in which jobs failed: the diagnostics and the report on the artefacts that were
    written, the report naming each stage that did not finish and why.

    Writes the diagnostics' tables and the report into ``results/failed_run/`` (one more entry in
    the diagnostics' ledger), never over the outputs of the diagnostics and report rules: Snakemake
    would take those for up to date and not rerun the failed jobs below them.

    Parameters
    ----------
    results : str or pathlib.Path
        The workflow's results folder.
    stage_lenses : dict[str, list of str]
        Every stage the run was to run -> its lenses.
    config : dict
        The run's validated configuration.
    skipped : dict[str, str], optional
        Stage -> why it was skipped (the dataset lacks its experiment).
    since : float, optional
        The run's start (s since the epoch), so that the log of a job that failed in an earlier run and did
        not run in this one is not taken for this run's error.

    Returns
    -------
    list of str
        The lines to print: the stages that did not finish and why, the failed jobs after the stages, then
        :func:`summarise_run`'s lines on the stages that finished (or why there are none).
    """
    from pipeline.io.artefact import BUNDLE_STAGES
    from pipeline.config import stage_params
    from pipeline.diagnostics.missing_effects import diagnose_artefacts
    from pipeline.report import build_report, report_settings
    from pipeline.runner.workflow import STAGES, artefacts_by_lens

    results = Path(results)
    not_finished = stages_not_finished(results, stage_lenses, since)
    lines = ["Jobs failed; stages that did not finish:"]
    lines += [f"  {stage}: {why}" for stage, why in not_finished.items()]
    # the jobs after the stages (bundle, diagnostics, report) write one log each
    for log in [*sorted((results / "logs" / "calibration").glob("*.log")), results / "logs" / "diagnostics.log",
                results / "logs" / "report.log"]:
        error = job_error_line(log, since)
        if error is not None:
            lines.append(f"  {log.stem if log.parent.name == 'logs' else 'calibration'}: failed: {error} (log: {log})")
    written = {stage: [str(results / stage / f"{lens}.nc") for lens in lenses
                       if (results / stage / f"{lens}.nc").exists()]
               for stage, lenses in stage_lenses.items() if stage in STAGES}
    written = {stage: paths for stage, paths in written.items() if paths}
    if not written:
        return lines + ["No stage finished: no diagnostics and no report."]
    diag = results / FAILED_RUN_DIR
    try:
        diagnose_artefacts(written, stage_params(config, "diagnostics"), diag / "missing_effects.csv",
                           diag / "unexplained.csv", diag / "run_errors.csv", results / "diagnostics" / "ledger",
                           diag / "error_history.csv", diag / "residual_tests.csv", diag / "residuals.nc")
        # a bundle left by an earlier run is stale when one of its stages did not finish in this one
        calibration = [] if set(BUNDLE_STAGES) & set(not_finished) else sorted((results / "calibration").glob("*.nc"))
        build_report(**{stage: artefacts_by_lens(written.get(stage, [])) for stage in STAGES},
                     missing_effects=diag / "missing_effects.csv", unexplained=diag / "unexplained.csv",
                     run_errors=diag / "run_errors.csv", error_history=diag / "error_history.csv",
                     residual_tests=diag / "residual_tests.csv", closure=diag / "residuals.nc",
                     lens_tests=diag / "lens_tests.csv",
                     plausibility=diag / "plausibility.csv",
                     out_html=diag / "index.html", skipped=skipped, failed=not_finished,
                     calibration=calibration[0] if calibration else None, settings=report_settings(config))
    except InputError as exc:
        return lines + [f"The diagnostics and report on the stages that finished failed too: {exc}"]
    found = summarise_run(results, config["model"]["effects"], skipped, config["diagnostics"]["structured_rms_z"],
                          diagnostics=diag, report=diag / "index.html")
    return lines + [f"Diagnostics and report on the stages that finished ({', '.join(written)}):"] + found
