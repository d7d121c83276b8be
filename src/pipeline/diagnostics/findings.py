"""``python -m pipeline diagnose``: what the diagnostics found, one plain sentence per finding.

Reads only what the workflow's diagnostics rule wrote (``results/diagnostics/*.csv`` and the closure
table ``results/closure/residuals.nc``); it recomputes nothing. Findings:

* each missing effect the ranking accepted, with the signature the catalogue gives it, its fitted
  amplitude and the config line that adds it ("the linearity residuals: DN per second departs from
  constant as 1/t at short exposures, as a shutter_offset of 0.000406 s would; add `shutter_offset` to
  model.effects");
* each table (experiment and level) whose residuals stay structured, with the covariate and the
  image-plane cell they follow, beside the candidate that explains part of them if there is one; the
  cross-experiment closure tables (experiment ``closure``, :mod:`pipeline.diagnostics.cross_closure`) among them, with
  what they compare and their largest departure;
* each effect whose value differs between the two lenses (``lens_tests.csv``: one value shared by the
  sensors against one per lens), with both values and their intervals.
* each fitted quantity outside its physical range (``plausibility.csv``, :mod:`pipeline.diagnostics.plausibility`): an
  immersion factor whose implied outer-window index no lens material has, a conversion gain at or below 0,
  a roll-off above its on-axis value, a negative dark current, with the value and the range.

``--explain EFFECT`` prints the effect's physics and signature, whether the model has it, and how it
fared in this run's ranking (p-values, evidence, amplitude, the smallest amplitude the data could show).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.diagnostics.missing_effects import field_scale_sentence, shared_excess_sentences
from pipeline.effects import CATALOGUE, load_plugins
from pipeline.effects import get as get_effect
from pipeline.errors import InputError
from pipeline.diagnostics.plausibility import finding_sentence, summary_lines
from pipeline.diagnostics.plausibility import findings as plausibility_findings

__all__ = ["diagnosis_lines", "explain_lines", "read_diagnostics"]

#: the files the diagnostics rule writes, relative to the results folder
FILES = {"missing_effects": "diagnostics/missing_effects.csv", "unexplained": "diagnostics/unexplained.csv",
         "residual_tests": "diagnostics/residual_tests.csv", "run_errors": "diagnostics/run_errors.csv",
         "error_history": "diagnostics/error_history.csv", "closure": "closure/residuals.nc",
         "lens_tests": "diagnostics/lens_tests.csv", "field_scale": "diagnostics/field_scale.csv",
         "plausibility": "diagnostics/plausibility.csv"}
#: files a results folder written before they existed may lack (read as empty tables)
OPTIONAL = ("lens_tests", "field_scale", "plausibility")
#: runs of the error history that ``diagnose`` prints (the latest)
HISTORY_RUNS = 5


def read_diagnostics(results: str | Path) -> dict:
    """The diagnostics' tables and the closure table's attributes; one line naming a missing file.

    Parameters
    ----------
    results : str or pathlib.Path
        The results folder of a workflow run.

    Returns
    -------
    dict
        The tables of ``FILES`` (pandas.DataFrame; the ``OPTIONAL`` ones empty when absent), ``closure_attrs``,
        ``n_measurements``, ``model_effects`` (list of str) and ``plugins`` (list of str).

    Raises
    ------
    InputError
        When a required file is missing or a table is not readable CSV.
    """
    results = Path(results)
    out = {}
    for key, rel in FILES.items():
        path = results / rel
        if not path.exists() and key in OPTIONAL:
            out[key] = pd.DataFrame()
            continue
        if not path.exists():
            raise InputError(path, "not found: run the workflow first (snakemake --cores 2), whose diagnostics "
                                   "rule writes it, or give the results folder with --results DIR")
        if key == "closure":
            with xr.open_dataset(path) as ds:
                out["closure_attrs"] = dict(ds.attrs)
                out["n_measurements"] = int(ds.sizes.get("measurement", 0))
            continue
        try:
            out[key] = pd.read_csv(path, keep_default_na=True)
        except pd.errors.EmptyDataError:
            out[key] = pd.DataFrame()
        except (pd.errors.ParserError, UnicodeDecodeError) as exc:
            raise InputError(path, f"not a readable CSV table ({type(exc).__name__})") from None
    attrs = out["closure_attrs"]
    out["model_effects"] = [e for e in str(attrs.get("model_effects", "")).split(",") if e]
    try:
        out["plugins"] = list(json.loads(attrs.get("config", "{}")).get("model", {}).get("plugins", []) or [])
    except json.JSONDecodeError:
        out["plugins"] = []
    return out


def _truthy(value) -> bool:
    if isinstance(value, str):
        return value.strip().lower() in ("true", "1", "yes")
    return bool(value) and not (isinstance(value, float) and np.isnan(value))


def _amount(value, units) -> str:
    units = "" if pd.isna(units) or str(units) in ("1", "") else f" {units}"
    return f"{float(value):.3g}{units}"


def _add_line(effects: list[str], name: str) -> str:
    return f"add `{name}` to model.effects (or --config 'model={{effects: [{', '.join(effects + [name])}]}}')"


def effect_sentence(row: pd.Series, model_effects: list[str]) -> str:
    """One accepted candidate as a plain sentence: signature, amplitude, what to add.

    Parameters
    ----------
    row : pandas.Series
        A row of the ranked missing effects (``missing_effects.csv``).
    model_effects : list of str
        The effects of the run's model.

    Returns
    -------
    str
        The sentence.
    """
    name = str(row["effect"])
    signature = CATALOGUE.get(name, ("", "its signature in the residuals"))[1]
    experiments = " and ".join(str(row["experiment"]).split("+"))
    given = f" (given {row['conditional_on']})" if isinstance(row.get("conditional_on"), str) and \
        row.get("conditional_on") else ""
    amount = ""
    if np.isfinite(float(row.get("amplitude", np.nan))):
        amount = (f" of {_amount(row['amplitude'], row.get('units'))} (95 % interval "
                  f"{_amount(row['amplitude_low'], row.get('units'))} to {_amount(row['amplitude_high'], row.get('units'))})")
    sentence = (f"the {experiments} residuals: {signature}, as a {name}{amount} would{given}; "
                f"{_add_line(model_effects, name)}")
    note = row.get("note")
    if isinstance(note, str) and note:
        sentence += f". Note: {note}"
    return sentence


def diagnosis_lines(found: dict, results: str | Path = "results") -> list[str]:
    """The report of ``diagnose``: the error per experiment, then one sentence per finding.

    Parameters
    ----------
    found : dict
        The diagnostics read by :func:`read_diagnostics`.
    results : str or pathlib.Path, default "results"
        The results folder, named in the heading.

    Returns
    -------
    list of str
        The report's lines.
    """
    model = found["model_effects"]
    lines = [f"Diagnosis of {results} (model: {', '.join(model) or 'the base model'}; "
             f"{found['n_measurements']} measurements in {FILES['closure']})", "",
             "Error per experiment (rms_z = sqrt(chi2/dof), 1 at the noise floor):"]
    errors = found["run_errors"]
    for _, row in errors.iterrows():
        lines.append(f"  {row['experiment']:<10} rms_z {float(row['rms_z']):5.2f} "
                     f"(chi2 {float(row['chi2']):.1f} for {int(row['dof'])} dof)")
    scale = found.get("field_scale", pd.DataFrame())
    if len(scale):
        lines += ["", "Field scale closure (camera / reference per band against the lab calibration's prediction; "
                      "stated: the quadrature sum of the fit, the camera calibration, the reference's calibration and "
                      "the spectral-mismatch prediction):"]
        for _, r in scale.iterrows():
            lines.append(f"  {r['lens']} {r['band']}: {float(r['k_b']):.4g} ({float(r['departure_percent']):+.2f} %, "
                         f"stated {float(r['sigma_percent']):.2f} %, z {float(r['z']):+.1f}); after "
                         f"{r['explained_by'] if isinstance(r['explained_by'], str) and r['explained_by'] else 'nothing'}"
                         f": {float(r['remaining_percent']):+.2f} % (z {float(r['z_remaining']):+.1f})")
        lines.append(f"  {field_scale_sentence(scale, found['missing_effects'])}")
    tests = found["residual_tests"]
    if len(tests):
        lines += ["", "Residual chi-square per experiment and level, after the accepted candidates (p: the larger "
                      "of the chi-square tail and its block-robust test):"]
        for _, t in tests.iterrows():
            mark = ("  structured" if _truthy(t["significant"])
                    else "  excess shared by blocks" if _truthy(t.get("shared_excess", False)) else "")
            after = t["accounted_by"] if isinstance(t["accounted_by"], str) and t["accounted_by"] else ""
            before = f" (model alone {float(t['chi2_model']):.1f}; with {after})" if after else ""
            lines.append(f"  {t['experiment'] + '/' + t['level']:<20} chi2 {float(t['chi2']):8.1f} for "
                         f"{int(t['dof']):4d} dof, p {float(t['p_value']):.2g}{before}{mark}")
    findings = []
    ranked = found["missing_effects"]
    if len(ranked):
        for _, row in ranked.sort_values("rank").iterrows():
            if not _truthy(row["significant"]):
                break
            findings.append(effect_sentence(row, model))
    unexplained = found["unexplained"]
    for _, row in unexplained.iterrows():
        findings.append(str(row["message"]))
    lens_tests = found.get("lens_tests", pd.DataFrame())
    if len(lens_tests):
        lines += ["", "Per-lens parameters (one value shared by the two sensors against one per lens):"]
        for _, t in lens_tests.iterrows():
            verdict = "differ" if _truthy(t["significant"]) else "shared value enough"
            values = ", ".join(f"{lens} {_amount(v, t['units'])}" for lens, v in
                               zip(str(t["lenses"]).split(), str(t["values"]).split()))
            lines.append(f"  {t['effect'] + ' (' + t['experiment'] + '/' + t['level'] + ')':<36} {values}; "
                         f"p {float(t['p_value']):.2g}  {verdict}")
            if _truthy(t["significant"]):
                findings.append(str(t["message"]))
    plausibility = found.get("plausibility", pd.DataFrame())
    if len(plausibility):
        lines += ["", "Plausibility of the fitted physics (each value with a physical range against it, beyond "
                      "plausibility.margin_sigma of its stated uncertainty):"]
        lines += [f"  {text}" for text in summary_lines(plausibility)]
        findings += [finding_sentence(row) for _, row in plausibility_findings(plausibility).iterrows()]
    shared = shared_excess_sentences(tests)
    lines += ["", "Findings:"]
    if not findings and not shared:
        lines.append("  none: no candidate effect is significant and every table's residuals are at the noise "
                     "floor for their degrees of freedom")
    elif not findings:
        lines.append("  none: no candidate effect is significant and no table's residuals are structured; the "
                     "tables below are above their noise floor all the same")
    for i, text in enumerate(findings, 1):
        lines.append(f"  {i}. {text[0].upper()}{text[1:]}.")
    if shared:
        lines += ["", "Above the stated noise, not called structure (the excess is shared by the rows of a block):"]
        lines += [f"  - {text[0].upper()}{text[1:]}." for text in shared]
    history = found["error_history"]
    if len(history) and "run_time" in history:
        runs = list(dict.fromkeys(history["run_time"]))[-HISTORY_RUNS:]
        lines += ["", f"Error history (rms_z, the last {len(runs)} run(s), oldest first):"]
        for exp, rows in history[history["run_time"].isin(runs)].groupby("experiment", sort=False):
            steps = " -> ".join(f"{float(r.rms_z):.2f} [{r.model_effects}]" for r in rows.itertuples())
            lines.append(f"  {exp:<10} {steps}")
    return lines


def explain_lines(found: dict, name: str) -> list[str]:
    """``diagnose --explain EFFECT``: the effect's physics and signature and how it fared in this run.

    Parameters
    ----------
    found : dict
        The diagnostics read by :func:`read_diagnostics`.
    name : str
        The effect's name.

    Returns
    -------
    list of str
        The lines.

    Raises
    ------
    InputError
        When the effect is not implemented (neither in the package nor in a plugin of the run).
    """
    load_plugins(found["plugins"])
    effect = get_effect(name)           # an unknown name: one line naming the implemented ones
    if name in CATALOGUE:
        physics, signature = CATALOGUE[name]
    else:
        doc = (effect.__doc__ or "").strip().splitlines()
        physics = doc[0] if doc else "an effect registered by a plugin"
        signature = "the shape of its model columns (a plugin effect, not in the catalogue)"
    model = found["model_effects"]
    lines = [f"{name}: {physics}", f"  signature: {signature}",
             f"  experiments whose residuals carry it: {', '.join(effect.experiments) or '(not stated)'}"]
    if name in model:
        lines.append("  in the model: yes (fitted by the stages; the diagnostics do not test it as a candidate)")
        return lines
    lines.append("  in the model: no")
    ranked = found["missing_effects"]
    rows = ranked[ranked["effect"].astype(str) == name] if len(ranked) else ranked
    if not len(rows):
        lines.append("  not tested in this run: no experiment it touches has rows (or the ranking stopped before it)")
        return lines
    for _, row in rows.iterrows():
        given = f", given {row['conditional_on']}" if isinstance(row.get("conditional_on"), str) and \
            row.get("conditional_on") else ""
        verdict = "significant" if _truthy(row["significant"]) else "not significant"
        reference = row.get("block_reference")
        against = f" against {reference}" if isinstance(reference, str) and reference else ""
        mc_sd = float(row.get("block_reference_mc_sd_log10", float("nan")))
        if against and np.isfinite(mc_sd):
            # the bootstrap reference's own Monte Carlo error: a verdict near the level may rest on the draws
            against += (f", nu {float(row['block_reference_dof']):.1f}, Monte Carlo error of log10 p "
                        f"{mc_sd:.2f}, p {10 ** -mc_sd * float(row['p_value_block']):.2g} to "
                        f"{10 ** mc_sd * float(row['p_value_block']):.2g} within one")
        lines.append(f"  tested on {row['experiment']}{given}: rank {int(row['rank'])}, {verdict} (p {float(row['p_value']):.2g}; "
                     f"F test {float(row['p_value_model']):.2g}, block test {float(row['p_value_block']):.2g}{against} over "
                     f"{int(row['n_blocks'])} blocks), evidence {float(row['evidence']):.1f}, explains "
                     f"{float(row['explained_fraction']):.0%} of the excess chi-square")
        label = row.get("amplitude_name") if isinstance(row.get("amplitude_name"), str) else "amplitude"
        lines.append(f"  {label}: {_amount(row['amplitude'], row.get('units'))} (95 % interval "
                     f"{_amount(row['amplitude_low'], row.get('units'))} to {_amount(row['amplitude_high'], row.get('units'))}); "
                     f"the smallest this dataset could detect: {_amount(row['detectable_amplitude'], row.get('units'))}")
        if isinstance(row.get("note"), str) and row["note"]:
            lines.append(f"  note: {row['note']}")
        if _truthy(row["significant"]):
            lines.append(f"  {_add_line(model, name)}")
    return lines
