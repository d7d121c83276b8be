"""What a workflow run found, in a few lines for the terminal (printed when a run ends).

Reads only the diagnostics' tables and the stages' artefacts: where the report
is, one line per experiment (at the noise floor, or the effect most likely
missing with its amplitude and the config line that adds it, or structure no
catalogue effect explains), and the stages that were skipped and why.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from pipeline.report import read_csv_or_empty as _read

__all__ = ["summarise_run"]


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
                  structured_rms_z: float = 1.5) -> list[str]:
    """The lines to print after a run; ``results`` is the workflow's results folder."""
    results = Path(results)
    diag = results / "diagnostics"
    report = results / "report" / "index.html"
    lines = [f"Calibration report: {report.resolve()}" if report.exists() else "No report was written."]
    errors = _read(diag / "run_errors.csv")
    ranked = _read(diag / "missing_effects.csv")
    unexplained = _read(diag / "unexplained.csv")
    width = max([len(str(e)) for e in errors.get("experiment", [])] + [9])
    for _, row in errors.iterrows():
        exp = str(row["experiment"])
        head = f"  {exp:<{width}}  rms_z {float(row['rms_z']):5.2f}: "
        found = ranked[(ranked["experiment"].astype(str).str.contains(exp, regex=False))
                       & ranked["significant"].astype(bool)] if len(ranked) else ranked
        if len(found):
            top = found.sort_values("rank").iloc[0]
            effects = ", ".join(list(model_effects) + [str(top["effect"])])
            lines.append(f"{head}{top['effect']} is most likely missing,{_amplitude(top)}; add it with "
                         f"--config 'model={{effects: [{effects}]}}' (or model.effects in config/config.yaml)")
            continue
        left = unexplained[unexplained["experiment"].astype(str) == exp] if len(unexplained) else unexplained
        if len(left):
            lines.append(f"{head}structured residuals that no catalogue effect explains; they follow "
                         f"{left.iloc[0]['covariate']} (see the report)")
        elif float(row["rms_z"]) <= structured_rms_z:
            lines.append(f"{head}at the noise floor")
        else:
            lines.append(f"{head}above the noise floor, no significant candidate (see the report)")
    for stage, why in (skipped or {}).items():
        lines.append(f"  skipped: {stage} ({why})")
    return lines
