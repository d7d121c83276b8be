"""Closure and missing-effect diagnostics (DESIGN.md, "Closure and diagnostics").

Each stage stores its observation tables: one row per independent
measurement (a setting, or a frame), the measured value, the expected noise
``sigma_dn`` and the model's base columns ``x_*``. Here, for every effect of the
catalogue that the model lacks, the effect's signature columns are added to
the model's design and the fit is redone on the same observations; the drop
in chi-square measures how well the signature explains the residuals.

* significance: F test of the drop against the residual variance of the
  larger model (robust to a mis-scaled noise), Bonferroni-corrected for the
  number of candidates tried;
* evidence: drop in chi-square, divided by the larger model's reduced
  chi-square when it exceeds 1, minus the BIC penalty k ln(n) for the k
  parameters the effect adds; candidates are ranked by it;
* explained fraction: the share of the excess chi-square (above its
  expectation) that the effect removes;
* amplitude: the fitted physical parameter with its 95 % interval, and the
  smallest amplitude each experiment could have detected.

Nothing here reads a simulator's truth: only the stage artefacts.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from pipeline.effects import available, get as get_effect
from pipeline.fitting import base_design, wls
from pipeline.stages.dark import dataset_to_table

#: covariates scanned to say where unexplained structure sits
COVARIATES = ("exposure_s", "gain", "lens", "band", "sweep", "temperature_c", "frame")


@dataclass
class Observations:
    experiment: str
    level: str
    table: pd.DataFrame


def observations_from_artefacts(artefacts: dict[str, list]) -> list[Observations]:
    """Observation tables per experiment and level, lenses concatenated."""
    out = []
    for experiment, datasets in artefacts.items():
        levels = sorted({name.split("__", 1)[0][4:] for ds in datasets for name in ds.data_vars
                         if name.startswith("obs_") and "__" in name})
        for level in levels:
            tables = [dataset_to_table(ds, f"obs_{level}") for ds in datasets]
            tables = [t for t in tables if len(t)]
            if not tables:
                continue
            table = pd.concat(tables, ignore_index=True)
            if "used" in table:
                table = table[table["used"].astype(int) == 1].reset_index(drop=True)
            out.append(Observations(experiment, level, table))
    return out


def model_design(obs: Observations, model_effects: list[str]) -> np.ndarray:
    X, _ = base_design(obs.table)
    cols = [X]
    for name in model_effects:
        effect = get_effect(name)
        if effect.corrects_data:
            continue
        c = effect.columns(obs.experiment, obs.level, obs.table)
        if c is not None:
            cols.append(c)
    return np.hstack(cols)


def _fit(obs: Observations, X: np.ndarray):
    return wls(obs.table["value_dn"].to_numpy(float), obs.table["sigma_dn"].to_numpy(float), X)


def error_figures(observations: list[Observations], model_effects: list[str]) -> pd.DataFrame:
    """rms_z (1 at the noise floor), chi-square and dof per experiment for the current model."""
    rows = {}
    for obs in observations:
        fit = _fit(obs, model_design(obs, model_effects))
        r = rows.setdefault(obs.experiment, {"experiment": obs.experiment, "chi2": 0.0, "dof": 0, "n_obs": 0})
        r["chi2"] += fit.chi2
        r["dof"] += fit.dof
        r["n_obs"] += len(obs.table)
    out = pd.DataFrame(rows.values())
    out["rms_z"] = np.sqrt(out["chi2"] / out["dof"].clip(lower=1))
    return out


def rank_missing_effects(observations: list[Observations], model_effects: list[str],
                         config: dict) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Rank the effects missing from the model; also report unexplained structure.

    Returns (missing_effects, unexplained) tables.
    """
    cfg = config["diagnostics"]
    candidates = [name for name in available() if name not in model_effects]
    results = []
    base_fits = {}
    for obs in observations:
        X = model_design(obs, model_effects)
        base_fits[(obs.experiment, obs.level)] = (X, _fit(obs, X))
    for name in candidates:
        effect = get_effect(name)
        parts = []
        for obs in observations:
            S = effect.columns(obs.experiment, obs.level, obs.table)
            if S is None or not np.any(S):
                continue
            X, fit0 = base_fits[(obs.experiment, obs.level)]
            k0 = np.linalg.matrix_rank(X) if X.size else 0
            Xf = np.hstack([X, S])
            k = np.linalg.matrix_rank(Xf) - k0
            if k <= 0:
                continue
            fit1 = _fit(obs, Xf)
            coef = fit1.coef[X.shape[1]:]
            cov = fit1.cov[X.shape[1]:, X.shape[1]:]
            parts.append({"obs": obs, "fit0": fit0, "fit1": fit1, "k": k, "coef": coef, "cov": cov})
        if not parts:
            continue
        d_chi2 = sum(p["fit0"].chi2 - p["fit1"].chi2 for p in parts)
        k = sum(p["k"] for p in parts)
        chi2_1 = sum(p["fit1"].chi2 for p in parts)
        dof_1 = sum(p["fit1"].dof for p in parts)
        excess = sum(p["fit0"].chi2 - p["fit0"].dof for p in parts)
        n = sum(len(p["obs"].table) for p in parts)
        s2 = max(chi2_1 / max(dof_1, 1), 1.0)
        f_stat = (d_chi2 / k) / s2
        p_value = float(stats.f.sf(f_stat, k, max(dof_1, 1)))
        best = max(parts, key=lambda p: p["fit0"].chi2 - p["fit1"].chi2)
        # scale the coefficient covariance by the residual variance when the noise is underestimated
        amp, lo, hi = effect.amplitude(best["obs"].experiment, best["obs"].level, best["obs"].table,
                                       best["coef"], best["cov"] * max(best["fit1"].chi2 / max(best["fit1"].dof, 1), 1.0))
        se = float(np.sqrt(max(best["cov"][0, 0], 0.0)))
        results.append({
            "effect": name,
            "experiment": "+".join(sorted({p["obs"].experiment for p in parts})),
            "evidence": d_chi2 / s2 - k * np.log(max(n, 2)),
            "delta_chi2": d_chi2,
            "n_params": k,
            "p_value": p_value,
            "explained_fraction": float(np.clip(d_chi2 / excess, 0.0, 1.0)) if excess > 0 else 0.0,
            "amplitude": amp, "amplitude_low": lo, "amplitude_high": hi,
            "units": effect.amplitude_units,
            "amplitude_name": effect.amplitude_name,
            "detectable_amplitude": se * stats.norm.isf(cfg["significance_level"] / max(len(candidates), 1) / 2),
        })
    table = pd.DataFrame(results)
    if len(table):
        m = len(candidates)
        table["significant"] = (table["p_value"] < cfg["significance_level"] / m) & (table["evidence"] > 0)
        table = table.sort_values("evidence", ascending=False).reset_index(drop=True)
        table.insert(0, "rank", np.arange(1, len(table) + 1))
        table["note"] = ""
        # two candidates that explain the residuals equally well: say so instead of picking one
        sig = table[table["significant"]]
        if len(sig) >= 2:
            e1, e2 = sig["evidence"].iloc[0], sig["evidence"].iloc[1]
            if abs(e1 - e2) < 2.0:
                names = f"{sig['effect'].iloc[0]} and {sig['effect'].iloc[1]}"
                table.loc[sig.index[:2], "note"] = f"{names} explain the residuals equally well (evidence within 2)"
    unexplained = _unexplained(observations, model_effects, table, cfg)
    return table, unexplained


def _unexplained(observations, model_effects, ranked: pd.DataFrame, cfg) -> pd.DataFrame:
    """Experiments whose residuals stay structured with no significant candidate explaining them."""
    figures = error_figures(observations, model_effects)
    rows = []
    for _, row in figures.iterrows():
        if row["rms_z"] <= cfg["structured_rms_z"]:
            continue
        exp = row["experiment"]
        if len(ranked):
            here = ranked[ranked["experiment"].str.contains(exp) & ranked["significant"]]
            if len(here) and here["explained_fraction"].max() >= cfg["min_explained_fraction"]:
                continue
        where, strength = _where(observations, exp, model_effects)
        rows.append({"experiment": exp, "rms_z": row["rms_z"], "covariate": where,
                     "association": strength,
                     "message": f"{exp}: residuals are structured (rms_z {row['rms_z']:.2f}) and no candidate "
                                f"effect explains them; they follow {where} most closely"})
    return pd.DataFrame(rows, columns=["experiment", "rms_z", "covariate", "association", "message"])


def _where(observations, experiment, model_effects) -> tuple[str, float]:
    """The covariate that explains most of the residual variance (eta squared / R^2)."""
    best, best_val = "no single covariate", 0.0
    for obs in observations:
        if obs.experiment != experiment:
            continue
        z = _fit(obs, model_design(obs, model_effects)).z
        total = float(np.sum((z - z.mean()) ** 2)) or 1.0
        for cov in COVARIATES:
            if cov not in obs.table:
                continue
            values = obs.table[cov]
            if values.dtype.kind in "fi" and values.nunique() > 6:
                r = np.corrcoef(values.to_numpy(float), z)[0, 1]
                val = float(r**2) if np.isfinite(r) else 0.0
            else:
                means = pd.Series(z).groupby(values.to_numpy()).transform("mean")
                val = float(np.sum((means - z.mean()) ** 2) / total)
            if val > best_val:
                best, best_val = f"{cov} ({obs.level} level)", val
    return best, best_val


def append_error_history(path: str | Path, figures: pd.DataFrame, model_effects: list[str],
                         run_time: str | None = None) -> pd.DataFrame:
    """Append one row per experiment for this run to the ledger (created if absent)."""
    path = Path(path)
    run_time = run_time or datetime.now(timezone.utc).isoformat(timespec="seconds")
    rows = figures.assign(run_time=run_time, model_effects=" ".join(model_effects) or "(base model)")
    rows = rows[["run_time", "experiment", "model_effects", "rms_z", "chi2", "dof", "n_obs"]]
    path.parent.mkdir(parents=True, exist_ok=True)
    rows.to_csv(path, mode="a", header=not path.exists(), index=False)
    return pd.read_csv(path)
