"""Which reference for the block test when one block fixes each tested parameter? F(k, G - 1) or a bootstrap.

    python benchmarks/bench_block_reference.py [--null N] [--power N] [--draws B] [--seed S] [--form-case] [--tanh-case]

The diagnostics test a candidate's drop in chi-square by generalised least squares under noise common to each
block (a random effect per block, ``pipeline.stats.fitting.block_gls_drop``) and refer F = (drop / k) / (chi2 / dof)
to the distribution ``diagnostics.block_reference`` names. Where each tested parameter is fixed by one block
(``iso_gain``: one gain-sweep setting per ISO, k = 5 on 13 settings) F(k, G - 1) for G blocks is a poor
reference. This script measures the alternatives of ``pipeline.stats.block_bootstrap`` (one piece of code with the
diagnostics): the statistic's own null distribution by a parametric bootstrap (the table simulated under the
block-noise model fitted to it, every draw through the same estimator of the block variances and the same
generalised least squares), summarised as F(k, nu) with nu matched to the draws' mean (raised by two
standard errors), used where the rows' F test is below the level (where it can change the verdict). Columns:
F(k, G - 1) (the diagnostics with ``block_reference: f``); the bootstrap at the variances' estimate
(plug-in); with the estimate's uncertainty carried into the draws, each at the variances a first draw at the
estimate estimated (bootstrap: the diagnostics' default); at the estimate plus two standard deviations of
the draws' own estimates (inflated); the larger of the plug-in's and F(k, G - 1)'s p-values (max(p,F)); and
the rows treated as independent. ``--draws`` defaults to ``diagnostics.block_bootstrap_draws``.

On synthetic 13-block linearity setting tables shaped as the tiny camera's (7 exposure settings at ISO 100,
6 gain settings at 8.33 ms, 2 lenses x 3 bands; row noise 0.1 sqrt(DN x ISO/100) + 1 DN) it counts, without
an effect, the false alarms at 0.05 and 0.01 of each, for block noise of a relative 0.3 % and 0.5 DN, of a
relative 0.6 % and 0.5 DN, and of 2 DN offsets alone; and with a gain ladder (ISO/100)^(-0.01), how often each calls ``iso_gain``
significant at 0.001 / 13. ``--form-case`` first prints the same for the linearity setting table of the
tiny dataset (seed 101) with the power-law gain ladder of ``tests/support/effect_forms.py`` written into its raw
frames (amplitude 0.01, rewrite seed 7): the drops in chi-square, the block-noise variances, the F statistic
against F(k, G - 1) and F(k, dof), the bootstrap null distribution of its F (2000 draws at the
variances' estimate) and the diagnostics' references and p-value, and appends them as one row to
``benchmarks/results/bench_block_reference_form_case.csv`` (with ``--null 0 --power 0`` only that);
``--tanh-case`` the residual tests of the linearity setting table of the detection benchmark's tanh case
(seed 521, 4 % at full scale) once ``nonlinearity`` is in the model, their parts, and the mean residual by
signal level. A benchmark, not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from pipeline.config import load_config
from pipeline.stats.block_bootstrap import BlockTestPart, block_bootstrap_reference, block_gls_null_draws, f_reference_dof
from pipeline.diagnostics.tables import Observations, blocks_of
from pipeline.diagnostics.missing_effects import candidate_significance
from pipeline.effects import get as get_effect
from pipeline.stats.fitting import base_design, block_gls_drop, wls
from pipeline.simulate.setting_tables import synthetic_linearity_settings

#: block noise (relative sigma, offset sigma in DN) of the null cases
NULL_CASES = ((0.003, 0.5), (0.006, 0.5), (0.0, 2.0))


def iso_block_test(table: pd.DataFrame, cfg: dict):
    """The iso_gain block test of a linearity setting table: the base and extended designs, the rows'
    sigma and blocks, both weighted fits, the block GLS drop and its F statistic."""
    X, _ = base_design(table)
    X1 = np.hstack([X, get_effect("iso_gain").columns("linearity", "setting", table)])
    y, sigma = table["value_dn"].to_numpy(float), table["sigma_dn"].to_numpy(float)
    blocks, _ = blocks_of(table, cfg["block_keys"])
    fit0, fit1 = wls(y, sigma, X), wls(y, sigma, X1)
    g = block_gls_drop(y, sigma, X, X1, blocks, cfg["block_noise_forms"], fit1)
    f_obs = g.delta_chi2 / g.k / (g.chi2 / g.dof)
    return X, X1, sigma, blocks, fit0, fit1, g, f_obs


#: the references compared, in the order of the columns printed
REFERENCES = ("F(k,G-1)", "plug-in", "bootstrap", "inflated", "max(p,F)")


def bootstrap_p_values(table: pd.DataFrame, config: dict, alpha: float, draws: int, seed: int) -> list[float]:
    """p-values of the iso_gain block test against the plug-in bootstrap, the propagated bootstrap (the
    package's ``diagnostics.block_reference: bootstrap``, :func:`pipeline.stats.block_bootstrap.block_test_p_value`),
    the inflated bootstrap (the variances at their estimate plus two standard deviations of the draws' own
    estimates) and the larger of the plug-in's and F(k, G - 1)'s, each the larger with the rows' F test as the
    diagnostics count it (the F(k, G - 1) p-value where the rows' F test is not below ``alpha``)."""
    cfg = config["diagnostics"]
    X, X1, sigma, blocks, fit0, fit1, g, f_obs = iso_block_test(table, cfg)
    k = fit0.dof - fit1.dof
    p_model = stats.f.sf((fit0.chi2 - fit1.chi2) / k / max(fit1.chi2 / fit1.dof, 1.0), k, fit1.dof)
    p_g = float(stats.f.sf(f_obs, g.k, g.n_blocks - 1))
    if p_model >= alpha:
        return [max(p_model, p_g)] * 4
    forms = tuple(cfg["block_noise_forms"])
    ref = block_bootstrap_reference([BlockTestPart(sigma, X, X1, blocks, fit1, forms)], draws, seed)
    first = block_gls_null_draws(sigma, X, X1, blocks, fit1, forms, draws=draws, seed=seed)
    inflated = block_gls_null_draws(sigma, X, X1, blocks, fit1, forms, draws=draws, seed=seed + 1,
                                    tau2=first.tau2_hat + 2.0 * np.std(first.tau2, axis=0, ddof=1))
    nu_inflated = f_reference_dof(inflated.delta_chi2 / g.k / (inflated.chi2 / g.dof), g.dof)
    p = [float(stats.f.sf(f_obs, g.k, nu)) for nu in (ref.nu_plug_in, ref.nu_propagated, nu_inflated)]
    return [max(p_model, v) for v in (*p, max(p[0], p_g))]


def form_tables(config: dict, name: str, seed: int, rewrite_seed: int, model: list[str]):
    """The dark and linearity observation tables of a clean tiny dataset with a form of tests/support/effect_forms.py
    written into its raw frames at its clear amplitude, the stages run with ``model``."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "support"))
    import yaml
    from effect_forms import FORMS

    from pipeline.io.dataset import open_dataset
    from pipeline.diagnostics.tables import observations_from_artefacts
    from pipeline.simulate import simulate_dataset, truth_dir_for
    from pipeline.stages.dark import analyse_dark, reduce_dark
    from pipeline.stages.linearity import analyse_linearity, reduce_linearity

    with tempfile.TemporaryDirectory(prefix="bench-block-reference-") as tmp:
        root = Path(tmp) / "dataset"
        simulate_dataset(root, scale="tiny", seed=seed, effects=[], experiments=("dark", "linearity"), progress=False)
        truth = yaml.safe_load((truth_dir_for(root) / "truth.yaml").read_text())
        form = FORMS[name]
        form.inject(root, form.amplitudes[0], truth["derived"]["conversion_gain_dn_per_e_iso100"], rewrite_seed)
        ds = open_dataset(root)
        dark = analyse_dark(reduce_dark(ds, config), config, model)
        lin = analyse_linearity(reduce_linearity(ds, dark, config, model), dark, config, model)
        obs = observations_from_artefacts({"dark": list(dark.values()), "linearity": list(lin.values())})
        shutil.rmtree(root, ignore_errors=True)
    return obs


def tanh_case(config: dict) -> None:
    """The tanh nonlinearity at 4 % with ``nonlinearity`` in the model (the detection benchmark's case, seed 521):
    the linearity setting table's residual tests, their parts, and how the residuals follow the signal level."""
    from pipeline.diagnostics.tables import model_design
    from pipeline.diagnostics.missing_effects import rank_missing_effects
    from pipeline.diagnostics.residual_structure import block_bound_p_value, covariate_tests, leverage

    cfg = config["diagnostics"]
    obs = form_tables(config, "nonlinearity_tanh", 521, 521, ["nonlinearity"])
    _, _, tests = rank_missing_effects(obs, ["nonlinearity"], config, with_tests=True)
    level = cfg["structure_level"] / len(obs)
    row = tests.set_index(["experiment", "level"]).loc[("linearity", "setting")]
    o = next(o for o in obs if (o.experiment, o.level) == ("linearity", "setting"))
    t = o.table
    X = model_design(o, ["nonlinearity"])       # each lens its own beta, as the stages fit it
    sigma = t["sigma_dn"].to_numpy(float)
    fit = wls(t["value_dn"].to_numpy(float), sigma, X)
    codes = pd.factorize(pd.Series(blocks_of(t, cfg["block_keys"])[0]))[0]
    n_blocks = int(codes.max()) + 1
    free = 1.0 - leverage(X, sigma)
    d = np.bincount(codes, weights=fit.z**2 - free, minlength=n_blocks)
    t_stat = d.mean() / (d.std(ddof=1) / np.sqrt(n_blocks))
    bound = block_bound_p_value(fit.chi2, np.bincount(codes, weights=free, minlength=n_blocks))
    fraction = pd.Series(t["pred_linear_dn"] / t["full_scale_dn"]).reset_index(drop=True)
    print(f"tiny seed 521, nonlinearity_tanh 0.04, model nonlinearity, linearity settings: chi2 {row['chi2']:.1f} for "
          f"{int(row['dof'])} dof (rms_z {row['rms_z']:.2f}), chi-square tail {row['p_chi2']:.2g}; block t test "
          f"{stats.t.sf(t_stat, n_blocks - 1):.3g} (t {t_stat:.2f}, {n_blocks - 1} dof, excess in "
          f"{int(np.sum(d > 0))} of {n_blocks} blocks), bound {bound:.2g}, block p (twice the smaller) "
          f"{row['p_block']:.3g}; table p {row['p_value']:.3g} against {level:.2g} ({len(obs)} tables): "
          f"{'reported' if row['significant'] else 'not reported'}")
    bins = pd.qcut(fraction, 6, labels=False)
    means = pd.Series(fit.z).groupby(bins).mean()
    edges = fraction.groupby(bins).agg(["min", "max"])
    print("  mean z by signal level (fraction of full scale): " + ", ".join(
        f"{edges.loc[b, 'min']:.3f}-{edges.loc[b, 'max']:.3f}: {means[b]:+.2f}" for b in means.index))
    print(f"  signal level as a covariate (line or 6 bins): p {covariate_tests(fit.z, fraction, 6)[0]:.2g}, its "
          f"logarithm {covariate_tests(fit.z, np.log(fraction), 6)[0]:.2g}; the covariate the diagnostics name: "
          f"{row['covariate']} (p {row['covariate_p_value']:.2g})")


def form_case(config: dict, draws: int = 2000) -> dict:
    """The power-law gain ladder on the tiny dataset: the block test's figures and its bootstrap null, printed and
    returned as one row of ``results/bench_block_reference_form_case.csv`` (figure name -> value)."""
    cfg = config["diagnostics"]
    obs = form_tables(config, "iso_gain_power_law", 101, 7, [])
    table = next(o.table for o in obs if (o.experiment, o.level) == ("linearity", "setting"))
    X, X1, sigma, blocks, fit0, fit1, g, f_obs = iso_block_test(table, cfg)
    null = block_gls_null_draws(sigma, X, X1, blocks, fit1, cfg["block_noise_forms"], draws=draws, seed=0)
    f = null.delta_chi2 / g.k / (null.chi2 / g.dof)
    nu = f_reference_dof(f, g.dof)
    ref = block_bootstrap_reference([BlockTestPart(sigma, X, X1, blocks, fit1, tuple(cfg["block_noise_forms"]))],
                                    cfg["block_bootstrap_draws"], cfg["block_bootstrap_seed"])
    r = candidate_significance("iso_gain", [o for o in obs if o.experiment == "linearity"], [], config, 13)
    print(f"tiny seed 101, iso_gain_power_law 0.01, linearity settings: {len(table)} rows, {g.n_blocks} blocks; "
          f"rows' drop {fit0.chi2 - fit1.chi2:.1f} (chi2 {fit0.chi2:.1f} -> {fit1.chi2:.1f}, dof {fit1.dof}); "
          f"block-noise variances {', '.join(f'{n} {float(v):.3g}' for n, v in zip(cfg['block_noise_forms'], g.tau2))} (offset DN2, relative 1); "
          f"GLS drop {g.delta_chi2:.1f}, chi2 {g.chi2:.1f} for {g.dof} dof; F {f_obs:.2f} on k = {g.k}: "
          f"F(k, G - 1) p {stats.f.sf(f_obs, g.k, g.n_blocks - 1):.2g}, F(k, dof) p {stats.f.sf(f_obs, g.k, g.dof):.2g}")
    print(f"  bootstrap null ({draws} draws at the fitted variances): mean F {f.mean():.3f}, 0.99 and 0.999 quantiles "
          f"{np.quantile(f, 0.99):.2f} {np.quantile(f, 0.999):.2f} (F(k, G - 1) {stats.f.isf(0.01, g.k, g.n_blocks - 1):.2f} "
          f"{stats.f.isf(0.001, g.k, g.n_blocks - 1):.2f}, F(k, dof) {stats.f.isf(0.01, g.k, g.dof):.2f} "
          f"{stats.f.isf(0.001, g.k, g.dof):.2f}); draws above the observed F {int(np.sum(f >= f_obs))}; "
          f"matched nu {nu:.1f}, p {stats.f.sf(f_obs, g.k, nu):.2g}")
    print(f"  the diagnostics' references ({cfg['block_bootstrap_draws']} draws, seed {cfg['block_bootstrap_seed']}): "
          f"plug-in nu {ref.nu_plug_in:.1f}, p {stats.f.sf(f_obs, g.k, ref.nu_plug_in):.2g}; propagated (bootstrap) "
          f"nu {ref.nu_propagated:.1f}, p {stats.f.sf(f_obs, g.k, ref.nu_propagated):.2g}; the diagnostics' "
          f"(the seed from the table): p-value {r['p_value']:.2g}, {r['block_reference']} nu {r['block_reference_dof']:.1f}")
    tau2 = dict(zip(cfg["block_noise_forms"], (float(v) for v in g.tau2)))
    return {"rows": len(table), "blocks": g.n_blocks, "rows_chi2": f"{fit0.chi2:.1f} -> {fit1.chi2:.1f}",
            "rows_dof": fit1.dof, "rows_drop": round(fit0.chi2 - fit1.chi2, 1),
            "tau2_offset_dn2": tau2.get("offset", ""), "tau2_relative": tau2.get("relative", ""),
            "gls_drop": round(g.delta_chi2, 1), "gls_chi2": round(g.chi2, 1), "gls_dof": g.dof, "f": round(f_obs, 2),
            "k": g.k, "p_f_k_g1": stats.f.sf(f_obs, g.k, g.n_blocks - 1), "p_f_k_dof": stats.f.sf(f_obs, g.k, g.dof),
            "null_draws": draws, "null_mean_f": round(float(f.mean()), 3), "null_q999": round(float(np.quantile(f, 0.999)), 2),
            "f_k_g1_q999": round(float(stats.f.isf(0.001, g.k, g.n_blocks - 1)), 2),
            "f_k_dof_q999": round(float(stats.f.isf(0.001, g.k, g.dof)), 2),
            "null_above_f": int(np.sum(f >= f_obs)), "null_nu": round(float(nu), 1), "null_p": stats.f.sf(f_obs, g.k, nu),
            "seed0_bootstrap_nu": round(float(ref.nu_propagated), 1),
            "seed0_bootstrap_p": stats.f.sf(f_obs, g.k, ref.nu_propagated),
            "diagnostics_nu": round(float(r["block_reference_dof"]), 1), "diagnostics_p": r["p_value"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--null", type=int, default=200, help="tables per null case")
    ap.add_argument("--power", type=int, default=40, help="tables with the gain ladder")
    ap.add_argument("--draws", type=int, default=None,
                    help="bootstrap draws per table (default diagnostics.block_bootstrap_draws)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--form-case", action="store_true", help="first the power-law gain ladder on the tiny dataset")
    ap.add_argument("--tanh-case", action="store_true", help="then the tanh nonlinearity's residual tests")
    args = ap.parse_args()
    config = load_config()
    args.draws = args.draws or config["diagnostics"]["block_bootstrap_draws"]
    # the diagnostics with F(k, G - 1) for the first column; the bootstrap references drawn here
    config_f = {**config, "diagnostics": {**config["diagnostics"], "block_reference": "f"}}
    if args.form_case:
        c0 = time.process_time()
        row = form_case(config)
        from record import append_rows

        append_rows("bench_block_reference_form_case", [{**row, "cpu_s": round(time.process_time() - c0)}])
    if args.tanh_case:
        tanh_case(config)
    rng = np.random.default_rng(args.seed)
    t0, c0, load0 = time.perf_counter(), time.process_time(), os.getloadavg()[0]
    records = []
    print(f"{'case':34s} {'level':>6s} " + " ".join(f"{r:>9s}" for r in REFERENCES) + f" {'rows':>9s}"
          "  (counts of p below level)")
    for rel, off in NULL_CASES if args.null else ():
        p = []
        for i in range(args.null):
            table = synthetic_linearity_settings(rng, rel, off)
            r = candidate_significance("iso_gain", [Observations("linearity", "setting", table)], [], config_f)
            p.append((r["p_value"], *bootstrap_p_values(table, config, 0.05, args.draws, args.seed + 10 * i),
                      r["p_value_model"]))
        p = np.array(p)
        for level in (0.05, 0.01):
            below = np.sum(p < level, axis=0)
            records.append({"case": "null", "relative": rel, "offset_dn": off, "level": level, "tables": args.null,
                            **{f"below_{name}": int(n) for name, n in zip((*REFERENCES, "rows"), below)}})
            counts = " ".join(f"{n:>9d}" for n in below)
            print(f"null: relative {rel:.3f}, offset {off:.1f} DN {level:6.2f} {counts}  of {args.null} "
                  f"(expected {args.null * level:.0f}, binomial 0.999 bound {stats.binom.ppf(0.999, args.null, level):.0f})")
    level = config["diagnostics"]["significance_level"] / 13
    for rel, off in ((0.0, 0.0), (0.003, 0.5)) if args.power else ():
        p = []
        for i in range(args.power):
            table = synthetic_linearity_settings(rng, rel, off, gain_deficit=0.01)
            r = candidate_significance("iso_gain", [Observations("linearity", "setting", table)], [], config_f, 13)
            p.append((r["p_value"], *bootstrap_p_values(table, config, level, args.draws, args.seed + 10 * i),
                      r["p_value_model"]))
        below = np.sum(np.array(p) < level, axis=0)
        records.append({"case": "ladder 0.01", "relative": rel, "offset_dn": off, "level": f"{level:.2g}",
                        "tables": args.power, **{f"below_{name}": int(n) for name, n in zip((*REFERENCES, "rows"), below)}})
        counts = " ".join(f"{n:>9d}" for n in below)
        print(f"ladder 0.01: rel {rel:.3f}, off {off:.1f} DN {level:6.1e} {counts}  of {args.power}")
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(f"{wall:.0f} s wall, {cpu:.0f} s CPU")
    if records:
        from record import append_rows

        # the run's cost on each of its rows (the tables of every case drawn in one loop)
        cost = {"draws": args.draws, "run_cpu_s": round(cpu), "run_wall_s": round(wall),
                "load": f"{load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end"}
        append_rows("bench_block_reference", [{**r, **cost} for r in records])


if __name__ == "__main__":
    main()
