"""Where the model fails: this run's residual error per experiment, the missing-effect search, the residual
structure no candidate explains, and the error history across runs (DESIGN, "Closure and diagnostics")."""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from pipeline.diagnostics.missing_effects import shared_excess_sentences  # noqa: E402
from pipeline.stages.observations import dataset_to_table  # noqa: E402
from pipeline.report.content import Details, Group, Items, Markup, Table, Text, draw  # noqa: E402
from pipeline.report.formatting import finite, fmt_value  # noqa: E402
from pipeline.report.palette import OKABE_ITO, category  # noqa: E402
from pipeline.report.registry import section  # noqa: E402
from pipeline.report.sections._closure import closure_figures, lens_tests_table, residual_tests_table  # noqa: E402
from pipeline.diagnostics.residual_structure import covariate_label  # noqa: E402

__all__ = ["as_bool", "top_effect", "amplitude_text", "run_labels", "history_figure", "flagged_experiments"]


def as_bool(x) -> bool:
    """A table cell read as a flag: True, 1 or the text "true", "1" or "yes" (any case); NaN and unreadable values are False.

    Parameters
    ----------
    x : object
        The cell.

    Returns
    -------
    bool
        The flag.
    """
    if isinstance(x, str):
        return x.strip().lower() in ("true", "1", "yes")
    try:
        return bool(x) and not (isinstance(x, float) and math.isnan(x))
    except (TypeError, ValueError):
        return False


def top_effect(missing: pd.DataFrame, experiment: str | None = None):
    """The best-ranked candidate (of one experiment when given), or None.

    Parameters
    ----------
    missing : pandas.DataFrame
        The diagnostics' ``missing_effects.csv``.
    experiment : str or None, optional
        Only that experiment's candidates.

    Returns
    -------
    pandas.Series or None
        The row of the lowest ``rank`` (the first row without the column).
    """
    if missing.empty:
        return None
    m = missing if experiment is None else missing[missing["experiment"].astype(str) == experiment]
    if m.empty:
        return None
    m = m.sort_values("rank") if "rank" in m else m
    return m.iloc[0]


def _units(row) -> str:
    return "" if pd.isna(row.get("units")) or str(row.get("units")) == "1" else f" {row['units']}"


def amplitude_text(row) -> str:
    """A candidate effect's fitted amplitude with its 95 % interval and units, e.g. ``D = 1.2 DN s-1, 95 % interval [0.9, 1.5] DN s-1``.

    Parameters
    ----------
    row : pandas.Series
        A row of ``missing_effects.csv`` (``amplitude``, ``amplitude_low``, ``amplitude_high``, and
        ``amplitude_name`` and units when given).

    Returns
    -------
    str
        The text.
    """
    units = _units(row)
    name = row.get("amplitude_name")
    name = f"{name} = " if isinstance(name, str) and name else ""
    return (f"{name}{fmt_value(row['amplitude'], 3)}{units}, 95 % interval "
            f"[{fmt_value(row['amplitude_low'], 3)}, {fmt_value(row['amplitude_high'], 3)}]{units}")


def _effect_set(text) -> list[str]:
    if not isinstance(text, str):
        return []
    return [e for e in text.replace(",", " ").split() if e]


def run_labels(history: pd.DataFrame) -> list[str]:
    """One label per run (in run order): the first run's effects, then the effects each run added (+)
    or removed (−) against the run before it.

    Parameters
    ----------
    history : pandas.DataFrame
        The diagnostics' ``error_history.csv`` (``run_time``, ``model_effects``).

    Returns
    -------
    list[str]
        One multi-line label per run.
    """
    runs = list(dict.fromkeys(history["run_time"].astype(str)))
    labels, before = [], None
    for i, r in enumerate(runs):
        effs = history.loc[history["run_time"].astype(str) == r, "model_effects"] if "model_effects" in history else []
        now = _effect_set(effs.iloc[0]) if len(effs) else []
        if before is None:
            change = ["\n".join(now) or "(no effects)"]
        else:
            change = [f"+{e}" for e in now if e not in before] + [f"−{e}" for e in before if e not in now]
            change = change or ["(same effects)"]
        labels.append(f"run {i + 1}\n" + "\n".join(change))
        before = now
    return labels


def history_figure(history: pd.DataFrame):
    """rms z per experiment against run, each run labelled by the effects it added or removed; None without history.

    Parameters
    ----------
    history : pandas.DataFrame
        The diagnostics' ``error_history.csv`` (``run_time``, ``experiment``, ``rms_z``, ``model_effects``).

    Returns
    -------
    pipeline.report.content.Figure or None
        The figure.
    """
    if history.empty or not {"run_time", "experiment", "rms_z"} <= set(history.columns):
        return None
    runs = list(dict.fromkeys(history["run_time"].astype(str)))
    idx = {r: i for i, r in enumerate(runs)}
    h = history.assign(run=history["run_time"].astype(str).map(idx))
    labels = run_labels(history)
    fig, ax = plt.subplots(figsize=(min(max(6, 1.4 * len(runs) + 3), 13), 4.4))
    markers = "osD^vP*X"
    for k, (exp, grp) in enumerate(h.groupby("experiment")):
        grp = grp.sort_values("run")
        ax.plot(grp["run"], grp["rms_z"], "-", marker=markers[k % len(markers)], color=category(k), label=str(exp))
    ax.axhline(1.0, color=OKABE_ITO[0], ls="--", lw=0.8, label="noise floor (rms z = 1)")
    ax.set_xticks(range(len(runs)))
    ax.set_xticklabels(labels, fontsize=7)
    ax.set_xlabel("run, labelled by the model effects it added (+) or removed (−)")
    ax.set_ylabel("rms z of the normalised residuals [1]")
    if h["rms_z"].max() > 10 * max(h["rms_z"].min(), 1e-12):
        ax.set_yscale("log")
    ax.set_xlim(-0.5, len(runs) - 0.5)
    ax.legend(fontsize=7, ncol=2, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    return draw(fig, "error_history",
                "Error history: rms of the normalised residuals per experiment for each run (log scale when they span "
                "more than a decade), each run "
                "labelled by the effects it added to or removed from the model (the first run by its whole list). "
                "Adding a missing effect should bring rms z down to 1.",
                alt="rms z per experiment against run, runs labelled by the effects added or removed")


def flagged_experiments(inputs) -> set[str]:
    """Experiments where the diagnostics found a significant missing effect or unexplained structure.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs (``missing_effects`` and ``unexplained``).

    Returns
    -------
    set[str]
        The experiments.
    """
    out = set()
    m = inputs.missing_effects
    if not m.empty and {"experiment", "significant"} <= set(m.columns):
        out |= {str(r["experiment"]) for _, r in m.iterrows() if as_bool(r["significant"])}
    u = inputs.unexplained
    if not u.empty and "experiment" in u:
        out |= set(u["experiment"].astype(str))
    return out


def _rms_figure(errors: pd.DataFrame, flagged: set[str]):
    exps = errors["experiment"].astype(str).tolist()
    rms = errors["rms_z"].astype(float).to_numpy()
    fig, ax = plt.subplots(figsize=(7.5, 3.2))
    colours = [OKABE_ITO[5] if e in flagged else OKABE_ITO[4] for e in exps]
    ax.bar(range(len(exps)), rms, color=colours)
    ax.axhline(1.0, color=OKABE_ITO[0], ls="--", lw=0.8)
    ax.set_xticks(range(len(exps)))
    ax.set_xticklabels(exps, fontsize=8)
    ax.set_xlabel("experiment")
    ax.set_ylabel("rms z [1]")
    if np.nanmax(rms) > 10:
        ax.set_yscale("log")
    fig.tight_layout()
    return draw(fig, "rms_z_per_experiment",
                "Residual error of this run per experiment: rms of the residuals normalised by their expected noise. "
                "1 (dashed) is the noise floor; vermillion bars mark the experiments where the diagnostics found a "
                "significant missing effect or structure no candidate explains, blue bars the others.", alt="rms z per experiment of this run")


def stage_residuals(inputs) -> dict[str, np.ndarray]:
    """The normalised residuals z of every observation table of every artefact, pooled over lenses, per stage
    (used observations only when the table says which were used).

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs.

    Returns
    -------
    dict[str, numpy.ndarray]
        Stage -> its finite z values (dimensionless); a stage without any is left out.
    """
    out = {}
    for stage, by_lens in inputs.artefacts.items():
        zs = []
        for ds in by_lens.values():
            prefixes = sorted({name.split("__", 1)[0] for name in ds.data_vars if name.startswith("obs_") and "__" in name})
            for prefix in prefixes:
                tab = dataset_to_table(ds, prefix)
                if "z" not in tab:
                    continue
                z = tab["z"].to_numpy(dtype=float)
                if "used" in tab:
                    z = z[tab["used"].astype(bool).to_numpy()]
                zs.append(z[np.isfinite(z)])
        if zs and sum(len(z) for z in zs):
            out[stage] = np.concatenate(zs)
    return out


def _residuals_figure(residuals: dict[str, np.ndarray]):
    names = list(residuals)
    ncols = min(len(names), 4)
    nrows = -(-len(names) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(2.9 * ncols, 2.4 * nrows), squeeze=False)
    grid = np.linspace(-5, 5, 201)
    normal = np.exp(-0.5 * grid**2) / np.sqrt(2 * np.pi)
    for ax, name in zip(axes.ravel(), names):
        z = residuals[name]
        clipped = np.clip(z, -5, 5)
        ax.hist(clipped, bins=np.linspace(-5, 5, 26), density=True, color=OKABE_ITO[2], edgecolor=OKABE_ITO[4], lw=0.5)
        ax.plot(grid, normal, "-", color=OKABE_ITO[0], lw=1)
        ax.set_title(f"{name}: n = {len(z)}, √mean z² = {np.sqrt(np.mean(z**2)):.2f}", fontsize=8)
        ax.set_xlabel("normalised residual z [1]")
        ax.set_ylabel("density [1]")
    for ax in axes.ravel()[len(names):]:
        ax.set_visible(False)
    fig.tight_layout()
    return draw(fig, "residual_distributions",
                "Where the model fails: distribution of the normalised residuals z = (data − model)/σ of every "
                "observation table of each stage (lenses pooled; values beyond ±5 piled at the edges) against the "
                "standard normal (black) that a complete model with a correct noise model leaves.",
                alt="histograms of normalised residuals per stage against the standard normal")


def _evidence_figure(missing: pd.DataFrame):
    m = missing.sort_values("rank") if "rank" in missing else missing
    m = m[np.isfinite(m["evidence"].astype(float))].head(12)
    if m.empty:
        return None
    labels = [f"{r['effect']} ({r['experiment']})" for _, r in m.iterrows()]
    sig = [as_bool(s) for s in m["significant"]] if "significant" in m else [False] * len(m)
    fig, ax = plt.subplots(figsize=(7.5, 0.35 * len(m) + 1.3))
    ax.barh(range(len(m)), m["evidence"].astype(float), color=[OKABE_ITO[5] if s else OKABE_ITO[2] for s in sig])
    ax.axvline(0.0, color=OKABE_ITO[0], lw=0.8)
    ax.set_yticks(range(len(m)))
    ax.set_yticklabels(labels, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("evidence: drop in χ² penalised for the added parameters [1]")
    fig.tight_layout()
    return draw(fig, "missing_effect_evidence",
                "Missing-effect search: evidence of each candidate effect per experiment (best first); vermillion "
                "bars are significant after the correction for the number of candidates tried, sky-blue bars are not.",
                alt="evidence of each candidate missing effect")


def _missing_table(missing: pd.DataFrame) -> Table:
    rows = []
    m = missing.sort_values("rank") if "rank" in missing else missing
    for _, r in m.iterrows():
        units = _units(r)
        rows.append([fmt_value(r.get("rank")), r.get("effect"), r.get("experiment"),
                     fmt_value(r.get("evidence"), 3), "yes" if as_bool(r.get("significant")) else "no",
                     fmt_value(r.get("p_value"), 3),
                     f"{100 * float(r['explained_fraction']):.1f} %" if finite(r.get("explained_fraction")) else "n/a",
                     f"{fmt_value(r.get('amplitude'), 3)} [{fmt_value(r.get('amplitude_low'), 3)}, "
                     f"{fmt_value(r.get('amplitude_high'), 3)}]{units}",
                     f"{fmt_value(r.get('detectable_amplitude'), 3)}{units}",
                     "" if pd.isna(r.get("note")) else r.get("note")])
    return Table(["rank", "effect", "experiment", "evidence", "significant", "p", "explained",
                  "amplitude [95 % interval]", "detectable", "note"], rows,
                 "Candidate effects ranked by evidence (drop in χ² penalised for the added parameters). Amplitudes "
                 "with their 95 % interval; “detectable” is the smallest amplitude this dataset would have revealed.",
                 left=3)


def _diagnostics_setting(inputs, name: str):
    """A diagnostics setting the report shows (``report_settings``), the schema default when not given."""
    if name in inputs.settings:
        return inputs.settings[name]
    from pipeline.config import load_config

    return load_config()["diagnostics"][name]


def _residual_test_blocks(inputs) -> list:
    tests = inputs.residual_tests
    blocks = []
    if tests.empty or "experiment" not in tests:
        blocks.append(Text("The diagnostics wrote no residual tests for this run.", "note"))
    else:
        blocks.append(residual_tests_table(tests))
    if not inputs.lens_tests.empty and "effect" in inputs.lens_tests:
        blocks.append(lens_tests_table(inputs.lens_tests))
    if inputs.closure is None:
        blocks.append(Text("No closure table (results/closure/residuals.nc) was given: no per-measurement views.",
                           "note"))
    else:
        blocks += closure_figures(inputs.closure, tests, int(_diagnostics_setting(inputs, "covariate_bins")),
                                  int(_diagnostics_setting(inputs, "image_plane_cells")))
    return blocks


@section("diagnostics", "Diagnostics: where the model fails", order=100,
         intro="Closure of every stage against its own measurements and the field, the residual tests of every "
               "table with the measurements' z against the covariate their structure follows, the candidate "
               "effects the residuals point to, structure no candidate explains, and how the error changed from run to run.")
def diagnostics_section(inputs) -> list:
    """The "Diagnostics: where the model fails" section.

    This run's residual errors, the residual tests per table (with the per-lens tests and the closure
    figures), the missing-effect search, the structure left unexplained and the error history.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs.

    Returns
    -------
    list
        The section's blocks (:mod:`pipeline.report.content`).
    """
    out = []
    errors = inputs.run_errors
    this_run = []
    if not errors.empty and {"experiment", "rms_z"} <= set(errors.columns):
        this_run.append(_rms_figure(errors, flagged_experiments(inputs)))
        this_run.append(Table(["experiment", "rms z", "χ²", "dof", "observations"],
                              [[r["experiment"], fmt_value(r["rms_z"], 3), fmt_value(r.get("chi2"), 4),
                                fmt_value(r.get("dof"), 4), fmt_value(r.get("n_obs"), 4)] for _, r in errors.iterrows()]))
    else:
        this_run.append(Text("The diagnostics wrote no residual errors for this run.", "note"))
    residuals = stage_residuals(inputs)
    if residuals:
        this_run.append(_residuals_figure(residuals))
    out.append(Group("Residual error of this run", this_run, id="run-errors"))
    missing = inputs.missing_effects
    search = []
    if missing.empty:
        search.append(Text("No candidate effects were tested.", "note"))
    else:
        fig = _evidence_figure(missing)
        if fig is not None:
            search.append(fig)
        search.append(_missing_table(missing))
    out.append(Group("Residual tests per table", _residual_test_blocks(inputs), id="residual-tests"))
    out.append(Group("Missing-effect search", search, id="missing-effects"))
    unexp = inputs.unexplained
    if unexp.empty:
        structure = [Text("No residual structure was found that the candidate effects leave unexplained.")]
    else:
        items = []
        for _, r in unexp.iterrows():
            extra = []
            if "rms_z" in r and finite(r["rms_z"]):
                extra.append(f"rms z {fmt_value(r['rms_z'], 3)}")
            if "covariate" in r and isinstance(r["covariate"], str):
                extra.append(f"covariate {covariate_label(r['covariate'])}")
            if "association" in r and finite(r["association"]):
                extra.append(f"association {fmt_value(r['association'], 3)}")
            items.append(Markup("<b>{}</b>: {} <span class='note'>({})</span>").format(
                r.get("experiment", ""), r.get("message", ""), "; ".join(extra)))
        structure = [Items(items)]
    shared = shared_excess_sentences(inputs.residual_tests)
    if shared:
        structure.append(Text("Above the stated noise, but not called structure: the excess is shared by the rows "
                              "of a frame or setting, as their common noise would be.", "note"))
        structure.append(Items([f"{t[0].upper()}{t[1:]}." for t in shared]))
    out.append(Group("Unexplained structure", structure, id="unexplained"))
    history = inputs.error_history
    hist = []
    fig = history_figure(history)
    hist.append(fig if fig is not None else Text("No error history yet.", "note"))
    if not history.empty:
        cols = [c for c in ("run_time", "experiment", "model_effects", "rms_z", "chi2", "dof", "n_obs") if c in history]
        rows = [[r[c] if c in ("run_time", "experiment", "model_effects") else fmt_value(r[c], 4) for c in cols]
                for _, r in history.iterrows()]
        hist.append(Details("Error history table", [Table(cols, rows, left=3)]))
    out.append(Group("Error history", hist, id="error-history"))
    return out
