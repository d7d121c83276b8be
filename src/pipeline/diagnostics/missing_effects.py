"""Closure and missing-effect diagnostics (docs/design.md, "Closure and diagnostics").

Each stage stores its observation tables: one row per independent
measurement (a setting, or a frame), the measured value, the expected noise
``sigma_dn`` and the model's base columns ``x_*``. Here, for every effect of the
catalogue that the model lacks, the effect's signature columns are added to
the model's design and the fit is redone on the same observations; the drop
in chi-square measures how well the signature explains the residuals.

* significance: F test of the drop against the residual variance of the
  larger model (robust to a mis-scaled noise), and the same drop tested with
  the noise common to each block allowed for (below); the larger of the two
  p-values is Bonferroni-corrected for the number of candidates tried;
* evidence: drop in chi-square, divided by the larger model's reduced
  chi-square when it exceeds 1, minus the BIC penalty k ln(n) for the k
  parameters the effect adds; candidates are ranked by it;
* explained fraction: the share of the excess chi-square (above its
  expectation) that the effect removes;
* amplitude: the fitted physical parameter with its 95 % interval, and the
  smallest amplitude each experiment could have detected.

Rows are not independent measurements when they share a raw frame or a
setting: every pixel of a frame sees the same source flicker and the same
black-level jitter, so the three bands (and both lenses) of one frame, or of
one setting's mean over its frames, move together. Treating them as
independent makes any signature that varies between frames look significant.
The rows of a table are therefore grouped into blocks (the first of
``diagnostics.block_keys`` present in the table: the raw frame's
``file_index``, the ``frame``, the ``sweep`` and ``setting``, the ``setting``),
and the noise common to a block is modelled as what it physically is, a random
effect per block (:func:`pipeline.stats.fitting.block_random_effects`): an offset in
the value's units (black-level jitter) and a relative change of the prediction
(flicker, drift), ``diagnostics.block_noise_forms``, each with a variance
tau^2 estimated by moments from the within-block products of the larger
model's residuals (so that the candidate's own signal is not counted as block
noise). The drop in chi-square is then recomputed by generalised least squares
under that covariance (:func:`pipeline.stats.fitting.block_gls_drop`) and
F = (drop / k) / (chi2 / dof), both from that fit, is referred to the distribution
``diagnostics.block_reference`` names: by default (``bootstrap``) the statistic's own
null distribution, a parametric bootstrap of the tables under the block-noise model
fitted to them with the variances' own uncertainty carried into the draws,
summarised as F(k, nu) (:mod:`pipeline.stats.block_bootstrap`), drawn only where the rows'
F test is below the level (elsewhere the candidate is not significant whatever the
block reference, and F(k, G - 1) is reported); ``f``, F(k, G - 1) for G blocks (the
fewest over the tables the candidate touches). ``block_reference`` and
``block_reference_dof`` say which was read, with its nu, and ``block_reference_mc_sd_log10`` the bootstrap's
Monte Carlo standard error of log10 of the block p-value (jackknife over batches of the draws). The scale chi2 / dof is not floored at
1 as in the F test of the rows: a stage's sigma may already hold noise common
to a block (the field's reference-window term is common to the bands of a
frame), which the random effect then counts twice (the field's glare: F test
1e-9, the block test 2e-4 with the floor, 1e-6 without); the p-value that
counts is the larger of the two tests, so the floored F test still bounds it. A table with G - 1 <= k cannot be tested this way;
the candidate keeps the F test alone (``p_value_block`` NaN, ``n_blocks`` 0).
The block test's p-value is used only when it is the larger, and the
amplitude interval uses its covariance, with the t(G - 1) quantile, when that
is the wider. Forward selection, evidence and explained fraction still use the
drop in chi-square of the rows, for ranking only.

Why not a cluster-robust (sandwich) covariance, the former test (CR3,
kept for comparison in ``tests/diagnostics/test_block_significance.py``): it estimates the coefficients'
covariance from the spread of the G per-block scores, so the structure that a
candidate's approximate signature leaves in a few high-leverage blocks is
taken for block noise. Measured on the tiny dataset (seed 101, the linearity
setting table, 13 blocks of 6 rows): a tanh nonlinearity, F test p 4e-25,
CR3 Wald 3.05 (p 0.11), the same sandwich without CR3's leverage correction
191 (1e-8): the two longest exposures carry the leverage (largest eigenvalue
of H_gg 0.90 and 0.68, (I - H_gg)^-1 multiplying their residuals by up to 10
and 3) and there the quadratic signature misfits the tanh (sum z^2 32 and 19
over 6 rows); a shutter offset of each lens's own, 3e-14 against 7e-4 (the
shortest exposures: leverage 0.51, sum z^2 25 in one block); a black level
quadratic in temperature, 6e-219 against 2e-4 (two terms over the 13
settings, one over the 65 frames; the linear terms' misfit up to 5800 over 6
rows in 8 settings). Where
one block alone fixes a parameter (the ISO gain factors, one setting per ISO)
its leverage is 1, its residuals are zero and (I - H_gg) is singular: the
sandwich is degenerate either way (the simulated phone's iso_gain p 1.0 at
rms_z 12.7, the power-law gain ladder's 2e-24). The random effect costs two
variances per table instead of a k x k covariance from G scores: the same
three give 5e-8, 5e-7 and 7e-6 (``tests/effects/test_effect_forms.py``). A wild
cluster bootstrap with the null imposed is no way out with 13 blocks: its
2^13 Rademacher sign patterns give no p-value below 2/8192 = 2.4e-4, above the
Bonferroni level 7.7e-5. The reference F(k, G - 1) rather than the rows' dof:
with 13 blocks and a setting-level covariate the rows' dof gave 64, 24 and 6
false alarms in 800 draws at 0.05, 0.01 and 0.001 (block noise half sigma; measured with the scale floored at 1), a
Satterthwaite mix of the two 61, 21 and 6, F(k, G - 1) 50, 7 and 1 (expected 40, 8 and 0.8). Assumption
behind F(k, G - 1): the block variances' uncertainty is that of G blocks whatever the tested columns; where
each tested parameter is fixed by one block and the relative block noise is about its standard error
(``iso_gain``, 13 settings, 0.6 %) it is 1.6 to 2 times too liberal, and without block noise it misses half
the gain ladders the bootstrap finds; the bootstrap at the variances' estimate (plug-in) is too liberal with
large offsets, underestimated by chance; carrying the estimate's uncertainty into the draws keeps the false
alarms within their binomial interval in the three null cases measured (``benchmarks/bench_block_reference.py``,
docs/effects-and-diagnostics.md, "Closure and diagnostics", for the counts).

Then every table (experiment and level) has its residual chi-square tested against its degrees of
freedom, after the accepted candidates (:func:`residual_tests`, :mod:`pipeline.diagnostics.residual_structure`):
structure left there is reported where it sits, beside the candidate that explains part of it if any.
:func:`closure_table` gathers every measurement with its prediction, residual, noise and covariates
(``results/closure/residuals.nc``).

Tables a candidate is never fitted to (:data:`PREDICTED_TABLES`: the field scale closure, one row per band,
ln of the camera/reference scale against the lab's prediction). A free parameter there would explain
any departure of the scale (a gain change of the camera between lab and field would pass for a
shutter offset), so a candidate's share in them is *predicted* from the parameter another table fits
(``Effect.predicted_from``, ``Effect.predicted_shift``; the shutter offset from the linearity sweeps, the
spectral mismatch and the glare from the match-up table): the shift, with its uncertainty (the parameter's
covariance through the shift's derivative) added to the rows' variance, and the chi-square it removes
(same weights before and after) joins the candidate's drop, evidence and explained fraction; it adds no
parameter and no block to the test, so that a candidate without evidence of its own in the table that
fits it is not made significant by the scale alone. Once accepted, a candidate's shift is taken out of
those rows before the next round and in the residual tests after the accepted candidates.

Nothing here reads a simulator's truth: only the stage artefacts.
"""

from __future__ import annotations

import logging
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr
from scipy import stats

from pipeline.effects import available, load_plugins
from pipeline.effects import get as get_effect
from pipeline.stats.block_bootstrap import BlockTestPart, block_test_p_value
from pipeline.stats.fitting import block_gls_drop
from pipeline.diagnostics.tables import (
    Observations,
    observations_from_artefacts,
    is_predicted,
    Anchor,
    predicted_shift,
    predicted_total,
    with_predictions,
    model_design,
    blocks_of,
    fit_observations,
)
from pipeline.diagnostics.residual_structure import (
    covariate_label,
    covariates_of,
    describe_image_plane,
    image_plane_pattern,
    residual_chi2_test,
    where_structure_sits,
)

log = logging.getLogger("pipeline.diagnostics.missing_effects")


def error_figures(observations: list[Observations], model_effects: list[str]) -> pd.DataFrame:
    """rms_z (1 at the noise floor), chi-square and dof per experiment for the current model.

    Parameters
    ----------
    observations : list of Observations
        The residual tables, per experiment and level.
    model_effects : list of str
        The effects of the model.

    Returns
    -------
    pandas.DataFrame
        One row per experiment: ``experiment``, ``chi2``, ``dof``, ``n_obs`` and ``rms_z`` = sqrt(chi2 / dof).
    """
    rows = {}
    for obs in observations:
        fit = fit_observations(obs, model_design(obs, model_effects))
        r = rows.setdefault(obs.experiment, {"experiment": obs.experiment, "chi2": 0.0, "dof": 0, "n_obs": 0})
        r["chi2"] += fit.chi2
        r["dof"] += fit.dof
        r["n_obs"] += len(obs.table)
    out = pd.DataFrame(rows.values())
    out["rms_z"] = np.sqrt(out["chi2"] / out["dof"].clip(lower=1))
    return out


def _candidate_stats(name: str, observations: list[Observations], designs: dict, cfg: dict,
                     n_candidates: int) -> dict | None:
    """Drop in chi-square, F test, evidence and amplitude of one candidate added to ``designs``."""
    effect = get_effect(name)
    parts = []
    for obs in observations:
        if is_predicted(obs):
            continue
        S = effect.columns(obs.experiment, obs.level, obs.table)
        if S is None or not np.any(S):
            continue
        X, fit0 = designs[(obs.experiment, obs.level)]
        k0 = np.linalg.matrix_rank(X) if X.size else 0
        Xf = np.hstack([X, S])
        k = np.linalg.matrix_rank(Xf) - k0
        if k <= 0:
            continue
        fit1 = fit_observations(obs, Xf)
        coef = fit1.coef[X.shape[1]:]
        cov = fit1.cov[X.shape[1]:, X.shape[1]:]
        blocks, _ = blocks_of(obs.table, cfg["block_keys"])
        sigma = obs.table["sigma_dn"].to_numpy(float)
        gls = block_gls_drop(obs.table["value_dn"].to_numpy(float), sigma, X, Xf, blocks, cfg["block_noise_forms"],
                             fit1)
        parts.append({"obs": obs, "fit0": fit0, "fit1": fit1, "k": k, "coef": coef, "cov": cov,
                      "gls": gls if gls.k > 0 and gls.n_blocks - 1 > gls.k else None,
                      "test": BlockTestPart(sigma, X, Xf, blocks, fit1, tuple(cfg["block_noise_forms"]))})
    if not parts:
        return None
    predicted = _predicted_parts(effect, parts, observations, designs)
    d_chi2 = sum(p["fit0"].chi2 - p["fit1"].chi2 for p in parts) + sum(p["drop"] for p in predicted)
    k = sum(p["k"] for p in parts)
    chi2_1 = sum(p["fit1"].chi2 for p in parts)
    dof_1 = sum(p["fit1"].dof for p in parts)
    excess = sum(p["fit0"].chi2 - p["fit0"].dof for p in parts) + sum(p["chi2_0"] - p["n"] for p in predicted)
    n = sum(len(p["obs"].table) for p in parts) + sum(p["n"] for p in predicted)
    s2 = max(chi2_1 / max(dof_1, 1), 1.0)
    f_stat = (d_chi2 / k) / s2
    p_model = float(stats.f.sf(f_stat, k, max(dof_1, 1)))
    # the same drop tested at the level of blocks (generalised least squares under the block noise)
    alpha = cfg["significance_level"] / max(n_candidates, 1)
    p_value, p_block, n_blocks, reference, nu, mc_sd = p_model, float("nan"), 0, "", float("nan"), float("nan")
    if all(p["gls"] is not None for p in parts):
        n_blocks = min(p["gls"].n_blocks for p in parts)
        k_gls = sum(p["gls"].k for p in parts)
        # the scale from the residuals, not floored at 1: a stage's sigma may already hold the noise common to
        # a block (the field's reference-window term), which the random effect then counts twice; the F test
        # of the rows (floored) still bounds the p-value from below
        s2_gls = sum(p["gls"].chi2 for p in parts) / max(sum(p["gls"].dof for p in parts), 1)
        f_gls = sum(p["gls"].delta_chi2 for p in parts) / k_gls / s2_gls
        p_block, reference, nu, mc_sd = block_test_p_value(f_gls, k_gls, n_blocks, [p["test"] for p in parts],
                                                           p_model, alpha, cfg)
        p_value = max(p_model, p_block)
    best = max(parts, key=lambda p: p["fit0"].chi2 - p["fit1"].chi2)
    cov_amp = _amplitude_cov(best)
    amp, lo, hi = effect.amplitude(best["obs"].experiment, best["obs"].level, best["obs"].table,
                                   best["coef"], cov_amp)
    # the smallest amplitude the counted test would call significant: the larger of the rows' test (normal
    # quantile, the scaled model covariance) and the block test (its t(G - 1) quantile, its own scale), as
    # the p-value that counts is the larger of the two
    var_model = best["cov"][0, 0] * max(best["fit1"].chi2 / max(best["fit1"].dof, 1), 1.0)
    detectable = float(np.sqrt(max(var_model, 0.0))) * stats.norm.isf(alpha / 2)
    if best["gls"] is not None:
        g = best["gls"]
        var_block = g.cov[0, 0] * g.chi2 / max(g.dof, 1)
        detectable = max(detectable, float(np.sqrt(max(var_block, 0.0))) * stats.t.isf(alpha / 2, g.n_blocks - 1))
    evidence = d_chi2 / s2 - k * np.log(max(n, 2))
    amplitude_name, units = effect.amplitude_label(best["obs"].experiment)
    scale = [p for p in predicted if p["obs"].level == "scale"]
    return {
        "effect": name,
        "experiment": "+".join(sorted({p["obs"].experiment for p in parts + predicted})),
        "field_scale_factor": " ".join(f"{b}:{np.exp(v):.4g}" for p in scale
                                       for b, v in zip(p["obs"].table["band"].astype(str), p["shift"])),
        "field_scale_explained": (float(sum(p["drop"] for p in scale) / sum(p["chi2_0"] for p in scale))
                                  if scale and sum(p["chi2_0"] for p in scale) > 0 else float("nan")),
        "_anchor": predicted[0]["anchor"] if predicted else None,
        "evidence": evidence,
        "delta_chi2": d_chi2,
        "n_params": k,
        "p_value": p_value,
        "p_value_model": p_model,
        "p_value_block": p_block,
        "n_blocks": n_blocks,
        "block_reference": reference,
        "block_reference_dof": nu,
        "block_reference_mc_sd_log10": mc_sd,
        "significant": bool(p_value < cfg["significance_level"] / max(n_candidates, 1) and evidence > 0),
        "explained_fraction": float(np.clip(d_chi2 / excess, 0.0, 1.0)) if excess > 0 else 0.0,
        "amplitude": amp, "amplitude_low": lo, "amplitude_high": hi,
        "units": units,
        "amplitude_name": amplitude_name,
        "detectable_amplitude": detectable,
    }


def _amplitude_cov(part: dict) -> np.ndarray:
    """A part's coefficient covariance scaled by its residual variance when the noise is underestimated; the
    block-noise covariance (interval from t(G - 1), not the normal 1.96) when that is wider."""
    cov_amp = part["cov"] * max(part["fit1"].chi2 / max(part["fit1"].dof, 1), 1.0)
    if part["gls"] is not None:
        g = part["gls"]
        t_ratio = stats.t.isf(0.025, g.n_blocks - 1) / stats.norm.isf(0.025)
        cov_block = g.cov * max(g.chi2 / max(g.dof, 1), 1.0) * t_ratio**2
        d_model, d_block = np.diag(cov_amp), np.diag(cov_block)
        if d_block.shape == d_model.shape and np.mean(d_block[d_model > 0] / d_model[d_model > 0]) > 1.0:
            cov_amp = cov_block
    return cov_amp


def _predicted_parts(effect, parts: list[dict], observations: list[Observations], designs: dict) -> list[dict]:
    """The candidate's predicted shift in each predicted table, from its coefficients on the table its
    ``predicted_from`` names (one of ``parts``), and the chi-square it removes there, the rows weighted alike
    before and after (their noise plus the shift's variance)."""
    source = [p for p in parts if (p["obs"].experiment, p["obs"].level) == effect.predicted_from]
    if not source:
        return []
    p = source[0]
    anchor = Anchor(effect.name, np.asarray(p["coef"], float), _amplitude_cov(p), p["obs"].table,
                    f"{p['obs'].experiment}/{p['obs'].level}")
    out = []
    for obs in observations:
        if not is_predicted(obs):
            continue
        found = predicted_shift(anchor, obs)
        if found is None or not np.all(np.isfinite(found[0])):
            continue
        shift, var = found
        _, fit0 = designs[(obs.experiment, obs.level)]
        r0 = obs.table["value_dn"].to_numpy(float) - fit0.pred
        w = 1.0 / (obs.table["sigma_dn"].to_numpy(float) ** 2 + var)
        chi2_0 = float(np.sum(w * r0**2))
        out.append({"obs": obs, "anchor": anchor, "shift": shift, "chi2_0": chi2_0, "n": len(r0),
                    "drop": chi2_0 - float(np.sum(w * (r0 - shift) ** 2))})
    return out


def candidate_significance(name: str, observations: list[Observations], model_effects: list[str], config: dict,
                           n_candidates: int = 1) -> dict | None:
    """Drop in chi-square, significance (model and block tests), evidence and amplitude of one candidate
    effect added to the model, as :func:`rank_missing_effects` computes them for every candidate.

    Parameters
    ----------
    name : str
        The candidate effect.
    observations : list of Observations
        The residual tables, per experiment and level.
    model_effects : list of str
        The effects of the model.
    config : dict
        The configuration (its ``diagnostics`` section).
    n_candidates : int, default 1
        The number of candidates tested (the Bonferroni factor of the significance level).

    Returns
    -------
    dict or None
        The candidate's row of ``missing_effects.csv`` (chi-square drop, p-values, evidence, amplitude and its
        interval, ...); None when no table carries its columns.
    """
    designs = _designs(observations, model_effects, [])
    out = _candidate_stats(name, observations, designs, config["diagnostics"], n_candidates)
    if out is not None:
        out.pop("_anchor")
    return out


def _designs(observations: list[Observations], model_effects: list[str], selected: list[str]) -> dict:
    """Design and fit per table: the model, plus the columns of candidates already accepted."""
    out = {}
    for obs in observations:
        X = model_design(obs, model_effects)
        extra = [get_effect(n).columns(obs.experiment, obs.level, obs.table) for n in selected]
        extra = [c for c in extra if c is not None]
        if extra:
            X = np.hstack([X] + extra)
        out[(obs.experiment, obs.level)] = (X, fit_observations(obs, X))
    return out


def rank_missing_effects(observations: list[Observations], model_effects: list[str],
                         config: dict, *, with_tests: bool = False, with_scale: bool = False
                         ) -> tuple[pd.DataFrame, ...]:
    """Rank the effects missing from the model; also report unexplained structure.

    Forward selection: the candidate with the most evidence is ranked first; if
    it is significant, it is added to the model and the remaining candidates
    are tested again given it, so that one missing effect does not make its
    look-alikes significant too. ``conditional_on`` lists the effects already
    accepted when a row was tested. Then every table's residuals are tested against their degrees of
    freedom, after the accepted candidates (:func:`residual_tests`); a candidate that leaves significant
    structure gets a note saying so.

    Parameters
    ----------
    observations : list of Observations
        The residual tables, per experiment and level.
    model_effects : list of str
        The effects of the model.
    config : dict
        The configuration (its ``diagnostics`` section).
    with_tests : bool, default False
        Also return the residual tests.
    with_scale : bool, default False
        Also return the residual tests and the field scale closure (:func:`field_scale_table`).

    Returns
    -------
    missing_effects : pandas.DataFrame
        One row per candidate and round, ranked (``missing_effects.csv``).
    unexplained : pandas.DataFrame
        The tables whose residuals stay structured (:func:`unexplained_structure`).
    residual_tests : pandas.DataFrame
        With ``with_tests`` or ``with_scale``: :func:`residual_tests`.
    field_scale : pandas.DataFrame
        With ``with_scale``: :func:`field_scale_table`.
    """
    cfg = config["diagnostics"]
    candidates = [name for name in available() if name not in model_effects]
    m = len(candidates)
    selected: list[str] = []
    anchors: list[Anchor] = []
    rows = []
    remaining = list(candidates)
    first_round = None
    while remaining:
        now = with_predictions(observations, anchors)
        designs = _designs(now, model_effects, selected)
        stats_now = [r for r in (_candidate_stats(n, now, designs, cfg, m) for n in remaining) if r]
        if not stats_now:
            break
        stats_now.sort(key=lambda r: r["evidence"], reverse=True)
        found = {r["effect"]: r.pop("_anchor") for r in stats_now}
        if first_round is None:
            first_round = stats_now
        top = stats_now[0]
        top["conditional_on"] = " ".join(selected)
        if not top["significant"]:
            for r in stats_now:
                r["conditional_on"] = " ".join(selected)
            rows.extend(stats_now)
            break
        rows.append(top)
        selected.append(top["effect"])
        if found[top["effect"]] is not None:
            anchors.append(found[top["effect"]])
        remaining.remove(top["effect"])
    table = pd.DataFrame(rows)
    if len(table):
        table.insert(0, "rank", np.arange(1, len(table) + 1))
        table["note"] = ""
        # two candidates that explain the same residuals equally well: say so instead of picking one
        if first_round and len(first_round) >= 2 and first_round[0]["significant"]:
            e1, e2 = first_round[0]["evidence"], first_round[1]["evidence"]
            if first_round[1]["significant"] and abs(e1 - e2) < max(2.0, 0.02 * abs(e1)):
                names = f"{first_round[0]['effect']} and {first_round[1]['effect']}"
                table.loc[table["effect"].isin([first_round[0]["effect"], first_round[1]["effect"]]), "note"] = (
                    f"{names} explain the residuals equally well; this dataset cannot tell them apart")
    tests = residual_tests(observations, model_effects, table, cfg, anchors)
    _note_remaining_structure(table, tests)
    if with_scale:
        scale = field_scale_table(observations, anchors, float(cfg["field_scale_departure_sigma"]))
        return table, unexplained_structure(tests), tests, scale
    if with_tests:
        return table, unexplained_structure(tests), tests
    return table, unexplained_structure(tests)


def accepted_effects(ranked: pd.DataFrame) -> list[str]:
    """The candidates forward selection accepted, in order: the ranked rows up to the first not significant.

    Parameters
    ----------
    ranked : pandas.DataFrame
        The ranked missing effects (:func:`rank_missing_effects`).

    Returns
    -------
    list of str
        The accepted effects.
    """
    out = []
    for _, row in ranked.sort_values("rank").iterrows() if len(ranked) else ():
        if not bool(row["significant"]):
            break
        out.append(str(row["effect"]))
    return out


def residual_tests(observations: list[Observations], model_effects: list[str], ranked: pd.DataFrame,
                   cfg: dict, anchors: list[Anchor] | None = None) -> pd.DataFrame:
    """Per experiment and level, the residual chi-square against its dof (:mod:`pipeline.diagnostics.residual_structure`),
    for the model and for the model plus the candidates the ranking accepted; where structure remains,
    the covariate and image-plane cell it follows. One row per table (columns: :data:`RESIDUAL_TEST_COLUMNS`).

    Parameters
    ----------
    observations : list of Observations
        The residual tables, per experiment and level.
    model_effects : list of str
        The effects of the model.
    ranked : pandas.DataFrame
        The ranked missing effects (:func:`rank_missing_effects`).
    cfg : dict
        The ``diagnostics`` section of the configuration.
    anchors : list of Anchor, optional
        The accepted candidates' fits, whose shifts are taken out of the predicted tables.

    Returns
    -------
    pandas.DataFrame
        One row per table, columns ``RESIDUAL_TEST_COLUMNS``.
    """
    accepted = accepted_effects(ranked)
    shifted = with_predictions(observations, anchors or [])
    before = _designs(observations, model_effects, [])
    after = _designs(shifted, model_effects, accepted)
    n_tables = max(len(observations), 1)
    level = cfg["structure_level"] / n_tables
    rows = []
    for obs, obs_after in zip(observations, shifted):
        key = (obs.experiment, obs.level)
        sigma = obs.table["sigma_dn"].to_numpy(float)
        blocks, block_key = blocks_of(obs.table, cfg["block_keys"])
        X0, fit0 = before[key]
        X1, fit1 = after[key]
        t0 = residual_chi2_test(fit0.z, X0, sigma, blocks, fit0.dof)
        t1 = residual_chi2_test(fit1.z, X1, obs_after.table["sigma_dn"].to_numpy(float), blocks, fit1.dof)
        here = [e for e in accepted if get_effect(e).columns(obs.experiment, obs.level, obs.table) is not None]
        if is_predicted(obs):
            here = predicted_total(obs, anchors or [])[2]
        covariate, p_cov, share, n_cov = where_structure_sits(obs.table, fit1.z, cfg["covariate_bins"], blocks)
        significant = bool(t1.p_value < level)
        if any(get_effect(e).columns_carry_noise for e in here):
            # beside a candidate whose columns carry noise sigma leaves out, the excess must also follow a
            # covariate (residual_structure)
            significant = significant and p_cov < level / max(n_cov, 1)
        pattern = image_plane_pattern(obs.table, fit1.z, cfg["image_plane_cells"])
        # the rows' chi-square above its dof, but not the block-robust test: an excess that the rows of one
        # frame or setting share, as their common noise would (shared_excess_sentence)
        shared_excess = bool(not significant and t1.p_chi2 < level and np.isfinite(t1.p_block)
                             and t1.p_block >= level)
        rows.append({
            "experiment": obs.experiment, "level": obs.level, "n_obs": t1.n_obs,
            "chi2": t1.chi2, "dof": t1.dof, "rms_z": t1.rms_z, "p_chi2": t1.p_chi2, "p_block": t1.p_block,
            "n_blocks": t1.n_blocks, "block_key": block_key, "p_value": t1.p_value,
            "significant": significant, "shared_excess": shared_excess,
            "test_level": level, "accounted_by": " ".join(here),
            "chi2_model": t0.chi2, "p_value_model": t0.p_value,
            "covariate": covariate, "covariate_p_value": p_cov, "association": share,
            "image_plane": describe_image_plane(pattern),
            "image_plane_p_value": pattern["p_value"] if pattern else float("nan"),
        })
    return pd.DataFrame(rows, columns=list(RESIDUAL_TEST_COLUMNS))


#: columns of ``residual_tests.csv``, one row per experiment and level (docs/effects-and-diagnostics.md, "Diagnostics")
RESIDUAL_TEST_COLUMNS = ("experiment", "level", "n_obs", "chi2", "dof", "rms_z", "p_chi2", "p_block", "n_blocks",
                         "block_key", "p_value", "test_level", "significant", "shared_excess", "accounted_by",
                         "chi2_model", "p_value_model",
                         "covariate", "covariate_p_value", "association", "image_plane", "image_plane_p_value")
#: columns of ``unexplained.csv``: the tables whose residuals stay significantly structured
UNEXPLAINED_COLUMNS = ("experiment", "level", "rms_z", "chi2", "dof", "p_value", "accounted_by", "covariate",
                       "association", "image_plane", "message")


def unexplained_structure(tests: pd.DataFrame) -> pd.DataFrame:
    """The tables whose residuals stay significant after the accepted candidates, with a sentence each:
    beside the candidate when one was accepted there (it explains part, not all), alone otherwise.

    Parameters
    ----------
    tests : pandas.DataFrame
        The residual tests (:func:`residual_tests`).

    Returns
    -------
    pandas.DataFrame
        One row per structured table, columns ``UNEXPLAINED_COLUMNS`` (``message`` the sentence).
    """
    rows = []
    for _, t in tests[tests["significant"].astype(bool)].iterrows():
        where = f"they follow {covariate_label(str(t['covariate']))} most closely"
        p_cov = float(t.get("covariate_p_value", float("nan")))
        if np.isfinite(p_cov):
            where += f" (F test of the grouping, p {p_cov:.2g})"
        if t["image_plane"]:
            where += f"; on the image plane they depart most at {t['image_plane']}"
        stat = f"chi2 {t['chi2']:.1f} for {int(t['dof'])} dof, p {t['p_value']:.2g}"
        if t["accounted_by"]:
            message = (f"{t['experiment']} ({t['level']} level): significant structure remains beside "
                       f"{t['accounted_by']} ({stat}); {t['accounted_by']} explains part of it, not all; {where}")
        else:
            message = (f"{t['experiment']} ({t['level']} level): the residuals are structured ({stat}) and no "
                       f"candidate effect explains them; {where}")
        rows.append({**{k: t[k] for k in UNEXPLAINED_COLUMNS if k in t}, "message": message})
    return pd.DataFrame(rows, columns=list(UNEXPLAINED_COLUMNS))


def shared_excess_sentence(t) -> str:
    """The sentence for a table whose chi-square exceeds its dof while the block-robust test does not call it
    structure (``shared_excess`` in ``residual_tests.csv``): the rows' stated noise does not hold the scatter,
    but the excess is shared by the rows of each block (frame or setting), as noise common to a block
    (source flicker or drift, black-level jitter) would be, and the tests cannot tell it from a misfit
    common to the block (a bend of the response that follows the signal level of a setting). Said, not
    called structure, so that "at the noise floor" is never claimed for it.

    Parameters
    ----------
    t : pandas.Series or dict
        A row of ``residual_tests.csv``.

    Returns
    -------
    str
        The sentence.
    """
    where = ""
    if isinstance(t["covariate"], str) and t["covariate"]:
        where = f"; its residuals follow {covariate_label(str(t['covariate']))} most closely"
        p_cov = float(t.get("covariate_p_value", float("nan")))
        if np.isfinite(p_cov):
            where += f" (F test of the grouping, p {p_cov:.2g})"
    beside = f" beside {t['accounted_by']}" if isinstance(t["accounted_by"], str) and t["accounted_by"] else ""
    key = str(t.get("block_key", ""))
    unit = "setting" if "setting" in key else "frame" if key in ("frame", "file_index") else "block"
    n = int(t["n_blocks"])
    return (f"{t['experiment']} ({t['level']} level){beside}: chi2 {float(t['chi2']):.1f} for {int(t['dof'])} dof, "
            f"more than the stated noise holds (chi-square tail {float(t['p_chi2']):.2g}), but shared by the rows "
            f"of each {unit} ({n} blocks; block-robust p {float(t['p_block']):.2g} against the level "
            f"{float(t['test_level']):.2g}), as noise common to a {unit} would be; not called structure: the "
            f"stated noise may leave out noise common to a {unit}, or a misfit common to a {unit} may be too "
            f"small for {n} blocks to show{where}")


def shared_excess_sentences(tests: pd.DataFrame) -> list[str]:
    """:func:`shared_excess_sentence` for every table of ``tests`` (``residual_tests.csv``) marked so.

    Parameters
    ----------
    tests : pandas.DataFrame
        The residual tests (``residual_tests.csv``).

    Returns
    -------
    list of str
        The sentences.
    """
    if not len(tests) or "shared_excess" not in tests:
        return []
    marked = tests["shared_excess"].astype(str).str.strip().str.lower().isin(("true", "1"))
    return [shared_excess_sentence(t) for _, t in tests[marked].iterrows()]


#: columns of ``field_scale.csv``, one row per lens and band of the field scale closure
FIELD_SCALE_COLUMNS = ("lens", "band", "reference", "n_matchups", "k_b", "k_predicted", "departure_percent",
                       "sigma_percent", "z", "departs", "sigma_fit_percent", "sigma_camera_calibration_percent",
                       "sigma_reference_calibration_percent", "sigma_spectral_mismatch_prediction_percent",
                       "explained_by", "predicted_factor", "remaining_percent", "remaining_sigma_percent",
                       "z_remaining", "departs_remaining")


def field_scale_table(observations: list[Observations], anchors: list[Anchor], departure_sigma: float) -> pd.DataFrame:
    """The field scale closure per lens and band (``field_scale.csv``): the camera/reference scale against the lab
    calibration's prediction, its stated budget (percent), z, and what the accepted candidates predict of it
    with what remains (module docstring, :data:`PREDICTED_TABLES`).

    Parameters
    ----------
    observations : list of Observations
        The residual tables, per experiment and level.
    anchors : list of Anchor
        The accepted candidates' fits.
    departure_sigma : float
        A scale departs when |z| exceeds this (``diagnostics.field_scale_departure_sigma``).

    Returns
    -------
    pandas.DataFrame
        One row per lens and band, columns ``FIELD_SCALE_COLUMNS``: the scale ``k_b`` and its prediction, the
        departure and its stated sigma (percent, and per term), z, what the candidates predict and what remains
        (percent, z).
    """
    rows = []
    for obs in observations:
        if (obs.experiment, obs.level) != ("field", "scale"):
            continue
        t = obs.table
        value, sigma = t["value_dn"].to_numpy(float), t["sigma_dn"].to_numpy(float)
        shift, var, names = predicted_total(obs, anchors)
        remaining_sigma = np.sqrt(sigma**2 + var)
        for i, r in t.reset_index(drop=True).iterrows():
            z, z_left = value[i] / sigma[i], (value[i] - shift[i]) / remaining_sigma[i]
            rows.append({
                "lens": r.get("lens", ""), "band": r["band"], "reference": r.get("reference", ""),
                "n_matchups": int(r.get("n_matchups", 0)), "k_b": float(r["k_b"]),
                "k_predicted": float(r.get("k_predicted", 1.0)),
                "departure_percent": 100.0 * float(np.expm1(value[i])), "sigma_percent": 100.0 * float(sigma[i]),
                "z": float(z), "departs": bool(abs(z) > departure_sigma),
                **{f"sigma_{term}_percent": 100.0 * float(r.get(f"sigma_{term}", np.nan))
                   for term in ("fit", "camera_calibration", "reference_calibration", "spectral_mismatch_prediction")},
                "explained_by": " ".join(names), "predicted_factor": float(np.exp(shift[i])),
                "remaining_percent": 100.0 * float(np.expm1(value[i] - shift[i])),
                "remaining_sigma_percent": 100.0 * float(remaining_sigma[i]), "z_remaining": float(z_left),
                "departs_remaining": bool(abs(z_left) > departure_sigma)})
    return pd.DataFrame(rows, columns=list(FIELD_SCALE_COLUMNS))


def _truth(value) -> bool:
    return str(value).strip().lower() in ("true", "1", "1.0", "yes")


def field_scale_sentence(scale: pd.DataFrame, ranked: pd.DataFrame | None = None) -> str:
    """The field verdict's first sentence (``field_scale.csv``): whether the camera/reference scale departs from
    the lab calibration's prediction, by how much and at how many sigma, what it means, and what the candidates
    the diagnostics accepted predict of it (each at the value the table its ``predicted_from`` names fits: the
    rows of ``missing_effects.csv``); '' without a field scale closure.

    Parameters
    ----------
    scale : pandas.DataFrame
        The field scale closure (``field_scale.csv``, :func:`field_scale_table`).
    ranked : pandas.DataFrame, optional
        The ranked missing effects (``missing_effects.csv``).

    Returns
    -------
    str
        The sentence.
    """
    if not len(scale):
        return ""
    bands = "/".join(str(b) for b in scale["band"])
    ratio = ", ".join(f"{float(v):.3g}" for v in scale["k_b"])
    percent = ", ".join(f"{float(v):+.3g} %" for v in scale["departure_percent"])
    stated = ", ".join(f"{float(v):.2g}" for v in scale["sigma_percent"])
    zs = ", ".join(f"{float(v):+.1f}" for v in scale["z"])
    head = (f"camera/reference {ratio} ({bands}), {percent} against a stated {stated} % (z {zs})")
    if not scale["departs"].map(_truth).any():
        text = f"field scale within its stated uncertainty: {head}"
    else:
        worst = scale.loc[scale["z"].abs().idxmax()]
        text = (f"field scale DEPARTS: {head}: the lab calibration and the reference disagree by "
                f"{float(worst['departure_percent']):+.3g} % at {abs(float(worst['z'])):.1f} sigma ({worst['band']})")
    named = [n for n in str(scale["explained_by"].iloc[0]).split() if n != "nan"] \
        if "explained_by" in scale and pd.notna(scale["explained_by"].iloc[0]) else []
    if named:
        parts = []
        for name in named:
            row = ranked[ranked["effect"] == name].iloc[0] if ranked is not None and len(ranked) \
                and (ranked["effect"] == name).any() else None
            if row is None:
                parts.append(name)
                continue
            source = (get_effect(name).predicted_from or ("", ""))[0]
            factors = "/".join(f"x{float(v.split(':')[1]):.3g}" for v in str(row.get("field_scale_factor", "")).split())
            share = float(row.get("field_scale_explained", np.nan))
            what = (f", {'explaining' if share >= 0 else 'adding'} {abs(100.0 * share):.0f} % of the scale's chi-square"
                    if np.isfinite(share) else "")
            parts.append(f"{name} ({row['amplitude']:.3g} {'' if str(row.get('units')) in ('1', 'nan') else row['units']}"
                         f" as {'the match-up' if source == 'field' else 'the ' + source + ' experiment'} fits it) "
                         f"{factors}{what}".replace(" )", ")").replace("  ", " "))
        left = ", ".join(f"{float(r['remaining_percent']):+.2g} % (z {float(r['z_remaining']):+.1f})"
                         for _, r in scale.iterrows())
        tail = ("within the stated uncertainty" if not scale["departs_remaining"].map(_truth).any()
                else "still beyond the stated uncertainty: an effect the catalogue lacks, or a change of the camera "
                     "or the reference between lab and field")
        text += f"; predicted by {'; '.join(parts)}; left: {left}, {tail}"
    elif scale["departs"].map(_truth).any():
        text += ("; no catalogue effect's lab-fitted value predicts it: a change of the camera or of the reference "
                 "between the lab and the field, or a calibration term stated too small")
    return text


def _note_remaining_structure(ranked: pd.DataFrame, tests: pd.DataFrame) -> None:
    """Beside each accepted candidate, the tables where significant structure remains after it."""
    if not len(ranked):
        return
    for i, row in ranked.iterrows():
        if not bool(row["significant"]):
            continue
        left = tests[tests["significant"].astype(bool)
                     & tests["accounted_by"].str.split().apply(lambda names, e=row["effect"]: e in names)]
        if len(left):
            places = ", ".join(f"{t.experiment} ({t.level} level, p {t.p_value:.2g})" for t in left.itertuples())
            note = f"leaves significant structure in {places}: it is not the whole story"
            ranked.loc[i, "note"] = f"{ranked.loc[i, 'note']}; {note}" if ranked.loc[i, "note"] else note


def record_error_history(ledger_dir: str | Path, figures: pd.DataFrame, model_effects: list[str],
                         history_csv: str | Path, run_time: str | None = None) -> pd.DataFrame:
    """File this run's error figures in the ledger and rebuild the error history from it.

    The ledger is a folder with one CSV per run, never rewritten: a run adds a
    file, so the history survives reruns of the diagnostics (whose outputs the
    workflow replaces). ``history_csv`` is all the ledger's rows in time order.

    Parameters
    ----------
    ledger_dir : str or pathlib.Path
        The ledger folder (created when absent).
    figures : pandas.DataFrame
        This run's error figures (:func:`error_figures`).
    model_effects : list of str
        The effects of the run's model.
    history_csv : str or pathlib.Path
        The error history to rewrite.
    run_time : str, optional
        The run's time stamp (ISO 8601); now (UTC) when None.

    Returns
    -------
    pandas.DataFrame
        The error history, columns ``HISTORY_COLUMNS``, in time order.
    """
    ledger = Path(ledger_dir)
    ledger.mkdir(parents=True, exist_ok=True)
    run_time = run_time or datetime.now(timezone.utc).isoformat(timespec="microseconds")
    rows = figures.assign(run_time=run_time, model_effects=" ".join(model_effects) or "(base model)")
    rows = rows[list(HISTORY_COLUMNS)]
    stem = run_time.replace(":", "").replace("+", "Z")
    entry = ledger / f"{stem}.csv"
    k = 1
    while entry.exists():           # never overwrite an earlier run's entry
        entry = ledger / f"{stem}-{k}.csv"
        k += 1
    _write_csv_atomic(rows, entry)
    parts = [pd.read_csv(p) for p in sorted(ledger.glob("*.csv"))]
    history = pd.concat(parts, ignore_index=True) if parts else rows.iloc[:0]
    history = history.sort_values("run_time", kind="stable").reset_index(drop=True)
    _write_csv_atomic(history, Path(history_csv))
    return history


#: columns of the error history, one row per run and experiment
HISTORY_COLUMNS = ("run_time", "experiment", "model_effects", "rms_z", "chi2", "dof", "n_obs")


def _write_csv_atomic(table: pd.DataFrame, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    table.to_csv(tmp, index=False)
    tmp.replace(path)


#: units of a table's value where the stage's observation is not a signal in DN and its artefact does not
#: state them: the flat field's spatial variance, the roll-off normalised by its on-axis fit, the immersion
#: stage's mean ln DN
VALUE_UNITS = {("linearity", "flat"): "DN2", ("rolloff", "setting"): "1", ("rolloff", "water"): "1",
               ("immersion", "height"): "1"}
#: covariates of the closure table and their units (NaN, or '' for text, where a table lacks one)
CLOSURE_COVARIATES = {"exposure_s": "s", "iso": "1", "gain": "1", "temperature_c": "degree_C",
                      "file_index": "1", "setting": "1", "frame": "1", "frame_in_setting": "1", "time_s": "s",
                      "theta_deg": "degree", "phi_deg": "degree", "azimuth_deg": "degree", "angle_deg": "degree",
                      "spot_x_px": "pixel", "spot_y_px": "pixel", "water_height_cm": "cm",
                      "wavelength_nm": "nm", "signal_fraction": "1"}
CLOSURE_TEXT = ("lens", "band", "sweep", "medium", "kind")
#: the closure table's column naming the experiment whose frames a row measures: the row's own experiment, or
#: for a cross-experiment closure table that pools several (``closure/dark_corners``) the one its covariate
#: ``experiment`` names, which the table's ``experiment`` column (``closure``) cannot hold
SOURCE_EXPERIMENT = "source_experiment"


def closure_table(observations: list[Observations], model_effects: list[str], config: dict) -> xr.Dataset:
    """Every measurement of every experiment with the model's prediction, residual, expected noise and
    covariates: one row per row of each observation table (the rows its fits use), along ``measurement``.

    The prediction is the fit of the model (base columns plus the model's effect columns) that
    ``run_errors.csv`` and ``residual_tests.csv`` are computed from, so that sum(z^2) over one
    experiment and level is that table's chi2; ``block`` names the rows that share a frame or setting.

    Parameters
    ----------
    observations : list of Observations
        The residual tables, per experiment and level.
    model_effects : list of str
        The effects of the model.
    config : dict
        The configuration (its ``diagnostics`` section).

    Returns
    -------
    xarray.Dataset
        Along ``measurement``: experiment, level, ``value_units``, group, block, value, prediction, residual and
        sigma (in ``value_units``), z, and the covariates.
    """
    cfg = config["diagnostics"]
    parts = []
    for obs in observations:
        t = obs.table
        fit = fit_observations(obs, model_design(obs, model_effects))
        blocks, block_key = blocks_of(t, cfg["block_keys"])
        covs = covariates_of(t)
        part = pd.DataFrame({
            "experiment": obs.experiment, "level": obs.level,
            "value_units": obs.value_units or VALUE_UNITS.get((obs.experiment, obs.level), "DN"),
            "group": t["group"].astype(str).to_numpy(),
            "block": [f"{block_key}={b}" for b in blocks],
            "value": t["value_dn"].to_numpy(float), "prediction": fit.pred,
            "residual": t["value_dn"].to_numpy(float) - fit.pred, "sigma": t["sigma_dn"].to_numpy(float),
            "z": fit.z})
        for name in CLOSURE_TEXT:
            part[name] = t[name].astype(str).to_numpy() if name in t else ""
        part[SOURCE_EXPERIMENT] = t["experiment"].astype(str).to_numpy() if "experiment" in t else obs.experiment
        for name in CLOSURE_COVARIATES:
            source = covs[name] if name in covs else (t[name] if name in t else None)
            part[name] = pd.to_numeric(source, errors="coerce").to_numpy(float) if source is not None else np.nan
        parts.append(part)
    columns = ["experiment", "level", "value_units", "group", "block", "value", "prediction", "residual", "sigma",
               "z", *CLOSURE_TEXT, SOURCE_EXPERIMENT, *CLOSURE_COVARIATES]
    table = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=columns)
    table = table[columns]
    described = {
        "experiment": ("experiment (stage) of the measurement", None),
        "level": ("level of the measurement: frame, setting, flat, water, height...", None),
        "value_units": ("units of value, prediction, residual and sigma on this row", None),
        "group": ("block of the stage's base model (lens, band, sweep, setting...)", None),
        "block": ("rows sharing a raw frame or setting (diagnostics.block_keys)", None),
        "value": ("measured value (units in value_units)", None),
        "prediction": ("the model's prediction of value (model.effects)", None),
        "residual": ("value minus prediction (units in value_units)", None),
        "sigma": ("expected noise of value (shot, read, quantisation, reference...; units in value_units)", None),
        "z": ("noise-normalised residual of the weighted fit", "1"),
        SOURCE_EXPERIMENT: ("experiment whose frames the row measures (its own experiment, or for a closure "
                            "table pooling several the one the covariate experiment names)", None),
    }
    data = {}
    for name in columns:
        values = table[name].to_numpy()
        if name in described or name in CLOSURE_TEXT:
            long_name, units = described.get(name, (f"covariate: {name}", None))
        else:
            long_name, units = f"covariate: {name} (NaN where the experiment has none)", CLOSURE_COVARIATES[name]
        attrs = {"long_name": long_name}
        if units:
            attrs["units"] = units
        if values.dtype == object:
            values = values.astype(str)
        data[name] = ("measurement", values, attrs)
    return xr.Dataset(data, attrs={
        "title": "closure table: every measurement of every experiment with the model's prediction",
        "model_effects": " ".join(model_effects)})


def write_closure_table(observations: list[Observations], model_effects: list[str], config: dict, path,
                        inputs: dict[str, str]) -> Path:
    """:func:`closure_table` written as the versioned ``closure`` artefact (``results/closure/residuals.nc``).

    Parameters
    ----------
    observations : list of Observations
        The residual tables, per experiment and level.
    model_effects : list of str
        The effects of the model.
    config : dict
        The configuration.
    path : str or pathlib.Path
        The artefact to write.
    inputs : dict[str, str]
        The stage artefacts it is made from: {name: sha256}.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    from pipeline.io.artefact import write_artefact

    return write_artefact(closure_table(observations, model_effects, config), path, stage="closure",
                          inputs=inputs, config_subset={k: config[k] for k in ("model", "diagnostics")},
                          effects=model_effects)


def write_plausibility(artefacts: dict[str, list[str | Path]], loaded: dict[str, list[xr.Dataset]], config: dict,
                       path) -> pd.DataFrame:
    """Every fitted quantity with a physical range checked against it (:func:`pipeline.diagnostics.plausibility.check_artefacts`:
    the lens of an artefact is its file's stem, ``results/<stage>/<lens>.nc``), each finding logged, the table
    written to ``path``.

    Parameters
    ----------
    artefacts : dict[str, list of str or pathlib.Path]
        The artefact paths per stage.
    loaded : dict[str, list of xarray.Dataset]
        The same artefacts, read.
    config : dict
        The configuration (its ``plausibility`` section).
    path : str or pathlib.Path
        The CSV to write.

    Returns
    -------
    pandas.DataFrame
        The checks (:func:`pipeline.diagnostics.plausibility.check_artefacts`).
    """
    from pipeline.diagnostics.plausibility import check_artefacts, finding_sentence, findings

    by_lens = {exp: {Path(p).stem: ds for p, ds in zip(artefacts[exp], loaded[exp])} for exp in loaded}
    checks = check_artefacts(by_lens, config)
    for _, row in findings(checks).iterrows():
        log.warning("plausibility: %s", finding_sentence(row))
    _write_csv_atomic(checks, Path(path))
    return checks


def diagnose_artefacts(artefacts: dict[str, list[str | Path]], config: dict, missing_csv, unexplained_csv,
                       errors_csv, ledger_dir, history_csv, residual_tests_csv=None, closure_nc=None,
                       lens_tests_csv=None, field_scale_csv=None, plausibility_csv=None) -> pd.DataFrame:
    """Rank missing effects over the stages' artefacts and the cross-experiment closure tables.

    The closure tables come from :mod:`pipeline.diagnostics.cross_closure`; every table's residuals are tested,
    and whether one value shared by the lenses is enough; this run's figures and the error history are written.

    Parameters
    ----------
    artefacts : dict[str, list of str or pathlib.Path]
        The artefact paths per stage.
    config : dict
        The configuration.
    missing_csv : str or pathlib.Path
        Where the ranked missing effects are written.
    unexplained_csv : str or pathlib.Path
        Where the unexplained structure is written.
    errors_csv : str or pathlib.Path
        Where this run's error figures are written.
    ledger_dir : str or pathlib.Path
        The error ledger's folder (:func:`record_error_history`).
    history_csv : str or pathlib.Path
        The error history.
    residual_tests_csv : str or pathlib.Path, optional
        Default ``residual_tests.csv`` beside ``unexplained_csv``.
    closure_nc : str or pathlib.Path, optional
        Where the closure table is written; not written when None.
    lens_tests_csv : str or pathlib.Path, optional
        Default ``lens_tests.csv`` beside ``unexplained_csv``.
    field_scale_csv : str or pathlib.Path, optional
        Default ``field_scale.csv`` beside ``unexplained_csv``.
    plausibility_csv : str or pathlib.Path, optional
        The plausibility of the fitted physics (:func:`write_plausibility`); default ``plausibility.csv`` beside
        ``unexplained_csv``.

    Returns
    -------
    pandas.DataFrame
        The error history (:func:`record_error_history`).
    """
    from pipeline.io.artefact import read_artefact, sha256_file
    from pipeline.diagnostics.cross_closure import closure_observations, describe_closure, lens_interaction_tests

    load_plugins(config["model"].get("plugins", []))
    effects = list(config["model"]["effects"])
    loaded = {exp: [read_artefact(p, exp) for p in paths] for exp, paths in artefacts.items() if paths}
    obs = observations_from_artefacts(loaded) + closure_observations(loaded, config)
    ranked, unexplained, tests, scale = rank_missing_effects(obs, effects, config, with_scale=True)
    unexplained = describe_closure(unexplained, obs, effects)
    figures = error_figures(obs, effects)
    residual_tests_csv = residual_tests_csv or Path(unexplained_csv).with_name("residual_tests.csv")
    lens_tests_csv = lens_tests_csv or Path(unexplained_csv).with_name("lens_tests.csv")
    field_scale_csv = field_scale_csv or Path(unexplained_csv).with_name("field_scale.csv")
    for _, r in scale.iterrows():
        log.info("field scale %s %s: %+.1f %% (stated %.1f %%, z %+.1f); after %s: %+.1f %% (z %+.1f)", r["lens"],
                 r["band"], r["departure_percent"], r["sigma_percent"], r["z"], r["explained_by"] or "nothing",
                 r["remaining_percent"], r["z_remaining"])
    for path, table in ((missing_csv, ranked), (unexplained_csv, unexplained), (errors_csv, figures),
                        (residual_tests_csv, tests), (lens_tests_csv, lens_interaction_tests(obs, effects, config)),
                        (field_scale_csv, scale)):
        _write_csv_atomic(table, Path(path))
    write_plausibility(artefacts, loaded, config, plausibility_csv or Path(unexplained_csv).with_name("plausibility.csv"))
    if closure_nc is not None:
        inputs = {f"{exp}/{Path(p).name}": sha256_file(p) for exp, paths in artefacts.items() for p in paths}
        write_closure_table(obs, effects, config, closure_nc, inputs)
    return record_error_history(ledger_dir, figures, effects, history_csv)
