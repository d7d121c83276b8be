"""Is F(k, G - 1) the right reference for the block test when one block fixes each tested parameter?

    python benchmarks/bench_block_reference.py [--null N] [--power N] [--draws B] [--seed S] [--form-case] [--tanh-case]

The diagnostics test a candidate's drop in chi-square by generalised least squares under noise common to each
block (a random effect per block, ``pipeline.fitting.block_gls_drop``) and refer F = (drop / k) / (chi2 / dof)
to F(k, G - 1) for G blocks. Where each tested parameter is fixed by one block (``iso_gain``: one gain-sweep
setting per ISO, k = 5 on 13 settings) that reference has little power. This script measures an alternative:
the statistic's own null distribution by a parametric bootstrap (the table simulated under the block-noise
model fitted to it, every draw through the same estimator of the block variances and the same generalised
least squares), summarised as F(k, nu) with nu matched to the draws' mean (raised by two standard errors),
used where the rows' F test is below the level (where it can change the verdict). Two variants: the
variances at their estimate (plug-in), and at the estimate plus two standard deviations of the draws' own
estimates (inflated).

On synthetic 13-block linearity setting tables shaped as the tiny camera's (7 exposure settings at ISO 100,
6 gain settings at 8.33 ms, 2 lenses x 3 bands; row noise 0.1 sqrt(DN x ISO/100) + 1 DN) it counts, without
an effect, the false alarms at 0.05 and 0.01 of F(k, G - 1), of the two bootstrap references and of the rows
treated as independent, for block noise of a relative 0.3 % and 0.5 DN, of a relative 0.6 % and 0.5 DN, and
of 2 DN offsets alone; and with a gain ladder (ISO/100)^(-0.01), how often each calls ``iso_gain``
significant at 0.001 / 13. ``--form-case`` first prints the same for the linearity setting table of the
tiny dataset (seed 101) with the power-law gain ladder of ``tests/effect_forms.py`` written into its raw
frames (amplitude 0.01, rewrite seed 7): the drops in chi-square, the block-noise variances, the F statistic
against F(k, G - 1) and F(k, dof), and the bootstrap null distribution of its F (2000 draws);
``--tanh-case`` the residual tests of the linearity setting table of the detection benchmark's tanh case
(seed 521, 4 % at full scale) once ``nonlinearity`` is in the model, their parts, and the mean residual by
signal level. A benchmark, not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from pipeline.config import load_config
from pipeline.diagnostics import Observations, blocks_of, candidate_significance
from pipeline.effects import get as get_effect
from pipeline.fitting import (BLOCK_NOISE_FORMS, Fit, _block_index, _column_space, _moment_design, base_design,
                              block_gls_drop, block_random_effects, wls)

EXPOSURES_S = (0.00833, 0.01667, 0.03333, 0.06667, 0.1, 0.2, 0.5)
ISOS = (100.0, 200.0, 400.0, 800.0, 1600.0, 3200.0)
#: DN per second at ISO 100 in the linearity mask, per band (the tiny camera, seed 101)
RATES_DN_PER_S = {"R": 30500.0, "G": 32400.0, "B": 10900.0}
#: block noise (relative sigma, offset sigma in DN) of the null cases
NULL_CASES = ((0.003, 0.5), (0.006, 0.5), (0.0, 2.0))


def _nonnegative_least_squares_many(gram: np.ndarray, q: np.ndarray) -> np.ndarray:
    """argmin_{t >= 0} t' gram t - 2 t' q for every row of ``q`` (draws x forms): the best of the unconstrained
    solutions on every subset of the forms that is non-negative (exact for the few forms of a block-noise model,
    2^forms subsets; the subset with all forms at zero always qualifies)."""
    n_draws, nf = q.shape
    best = np.zeros((n_draws, nf))
    best_obj = np.zeros(n_draws)
    for mask in range(1, 2**nf):
        idx = [f for f in range(nf) if mask >> f & 1]
        sub = gram[np.ix_(idx, idx)]
        if np.linalg.matrix_rank(sub) < len(idx):
            continue
        t = np.linalg.solve(sub, q[:, idx].T).T
        ok = np.all(t >= 0, axis=1)
        obj = np.einsum("bi,ij,bj->b", t, sub, t) - 2 * np.sum(t * q[:, idx], axis=1)
        better = ok & (obj < best_obj)
        full = np.zeros((n_draws, nf))
        full[:, idx] = t
        best[better] = full[better]
        best_obj[better] = obj[better]
    return best


def block_gls_null_draws(sigma: np.ndarray, X0: np.ndarray, X1: np.ndarray, blocks: np.ndarray, fit1: Fit,
                         forms=BLOCK_NOISE_FORMS, draws: int = 4000, seed: int = 0,
                         batch_values: float = 4e6, tau2=None, return_tau2: bool = False):
    """Parametric bootstrap of :func:`block_gls_drop` under the null: (drop in chi-square, chi-square of the
    larger model) for each of ``draws`` simulated tables.

    Each table is the smaller model's fit plus the noise the block-noise model says the rows have, with the
    variances estimated from the observed larger model's residuals (:func:`block_random_effects`): independent
    N(0, sigma_i^2) per row and, per block and form, N(0, tau_f^2) times the form's loading. Every draw then
    goes through the same steps as the observed table: its block-noise variances by moments from its own
    residuals of the larger model (non-negative least squares over the within-block pairs), its drop and
    chi-square by generalised least squares under them. The statistic is invariant to the smaller model's
    coefficients, so the draws start from zero. Two simplifications, both far below the noise: the relative
    form's loading is the observed fit's prediction in every draw (a draw's own prediction differs from it by
    the noise), and the generalised least squares use the Woodbury identity per block, (I + C T C')^-1 =
    I - C T (I + C'C T)^-1 C' (C the block's loadings, T the variances), instead of a Cholesky factor.
    ``batch_values`` bounds the numbers held at once (draws x rows, draws x pairs)."""
    sigma = np.asarray(sigma, dtype=float)
    w = 1.0 / sigma
    tau2_hat, cols = block_random_effects(fit1, X1, sigma, blocks, forms)
    tau2 = tau2_hat if tau2 is None else np.asarray(tau2, float)
    codes, n_blocks = _block_index(blocks)
    n, nf = len(sigma), len(cols)
    A1 = X1 * w[:, None]
    U = _column_space(A1)
    # unit columns: the normal equations below square the design's condition number
    norms = np.linalg.norm(A1, axis=0)
    A1 = A1 / np.where(norms > 0, norms, 1.0)
    rcond = max(A1.shape) * np.finfo(float).eps
    first = X0.shape[1]
    C = np.column_stack(cols) if nf else np.zeros((n, 0))
    # the moment estimator of block_random_effects: pairs of one block, design D, offset
    i, j, D, offset = _moment_design(U, cols, codes, n_blocks)
    gram = D.T @ D
    # per block: loadings' products with the design (P_g = A_g' C_g) and with themselves (Q_g = C_g' C_g)
    onehot = np.zeros((n, n_blocks))
    onehot[np.arange(n), codes] = 1.0
    P = np.einsum("np,nf,ng->gpf", A1, C, onehot, optimize=True)
    Q = np.einsum("ne,nf,ng->gef", C, C, onehot, optimize=True)
    AtA = A1.T @ A1

    def statistic(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Drop and chi-square of the whitened tables ``b`` (draws x rows), each with its own variances."""
        m = len(b)
        if nf:
            z = b - (b @ U) @ U.T
            t = _nonnegative_least_squares_many(gram, (z[:, i] * z[:, j] + offset) @ D)
            T = t[:, None, :, None] * np.eye(nf)[None, None]                  # (draws, 1, nf, nf)
            R = T @ np.linalg.inv(np.eye(nf) + Q[None] @ T)                     # T (I + Q_g T)^-1
        else:
            R = np.zeros((m, n_blocks, 0, 0))
        cb = np.einsum("nf,bn,ng->bgf", C, b, onehot, optimize=True)                           # C_g' b
        H = AtA[None] - np.einsum("gpf,bgfh,gqh->bpq", P, R, P)
        s = b @ A1 - np.einsum("gpf,bgfh,bgh->bp", P, R, cb)
        bb = np.sum(b * b, axis=1) - np.einsum("bgf,bgfh,bgh->b", cb, R, cb)

        def chi2_of(cols: int) -> np.ndarray:
            Hc, sc = H[:, :cols, :cols], s[:, :cols]
            return bb - np.einsum("bp,bp->b", sc, np.einsum("bpq,bq->bp", np.linalg.pinv(Hc, rcond=rcond, hermitian=True), sc))

        chi1 = chi2_of(A1.shape[1])
        chi0 = chi2_of(first) if first else bb
        taus.append(t if nf else np.zeros((m, 0)))
        return np.maximum(chi0 - chi1, 0.0), chi1

    taus = []
    if draws <= 0:      # the observed table through the same steps (a check of the two routes)
        return statistic((fit1.z + fit1.pred * w)[None])
    rng = np.random.default_rng(seed)
    batch = max(1, int(batch_values // max(n, len(i), A1.shape[1] ** 2, 1)))
    drops, chi2s = [], []
    for start in range(0, draws, batch):
        m = min(batch, draws - start)
        b = rng.standard_normal((m, n))
        if nf:
            u = rng.standard_normal((m, nf, n_blocks)) * np.sqrt(tau2)[None, :, None]
            b += np.einsum("nf,bfn->bn", C, u[:, :, codes])
        drop, chi1 = statistic(b)
        drops.append(drop)
        chi2s.append(chi1)
    if return_tau2:
        return np.concatenate(drops), np.concatenate(chi2s), tau2_hat, np.concatenate(taus)
    return np.concatenate(drops), np.concatenate(chi2s)


def f_reference_dof(f_draws: np.ndarray, dof_max: int) -> float:
    """Denominator degrees of freedom nu of the F(k, nu) that matches bootstrap draws of an F statistic:
    E[F(k, nu)] = nu / (nu - 2), solved with the draws' mean raised by two standard errors (so that the few
    thousand draws do not make the reference too thin-tailed by chance), at most ``dof_max`` (the residual
    chi-square's own degrees of freedom)."""
    f_draws = np.asarray(f_draws, dtype=float)
    mean = float(np.mean(f_draws)) + 2.0 * float(np.std(f_draws, ddof=1)) / np.sqrt(len(f_draws))
    if mean <= dof_max / max(dof_max - 2.0, 1e-9):
        return float(dof_max)
    return float(min(2.0 * mean / (mean - 1.0), dof_max))


def synthetic_linearity_settings(rng, rel_sigma: float, offset_dn: float, gain_deficit: float = 0.0) -> pd.DataFrame:
    """A linearity setting table: one block per setting, noise common to a block (a relative change of
    ``rel_sigma`` and an offset of ``offset_dn``), the analogue gain (ISO/100)^(1 - ``gain_deficit``)."""
    settings = [("exposure", t, 100.0) for t in EXPOSURES_S] + [("gain", EXPOSURES_S[0], iso) for iso in ISOS]
    rows = []
    for s, (sweep, t, iso) in enumerate(settings):
        rel, off = rel_sigma * rng.standard_normal(), offset_dn * rng.standard_normal()
        for lens in ("far", "close"):
            for band, rate in RATES_DN_PER_S.items():
                linear = rate * t * iso / 100.0
                true = linear * (iso / 100.0) ** (-gain_deficit)
                sigma = 0.1 * np.sqrt(true * iso / 100.0) + 1.0
                rows.append({"lens": lens, "band": band, "sweep": sweep, "setting": s, "iso": iso, "exposure_s": t,
                             "gain": iso / 100.0, "x_rate": t * iso / 100.0, "pred_linear_dn": linear,
                             "full_scale_dn": 15576.0, "sigma_dn": sigma,
                             "value_dn": true * (1 + rel) + off + sigma * rng.standard_normal()})
    table = pd.DataFrame(rows)
    table["group"] = table["lens"] + "/" + table["band"] + "/" + table["sweep"]
    return table


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


def bootstrap_p_values(table: pd.DataFrame, config: dict, alpha: float, draws: int, seed: int) -> tuple[float, float]:
    """p-values of the iso_gain block test against the plug-in and the inflated bootstrap references (the
    F(k, G - 1) p-value where the rows' F test is not below ``alpha``)."""
    cfg = config["diagnostics"]
    X, X1, sigma, blocks, fit0, fit1, g, f_obs = iso_block_test(table, cfg)
    k = fit0.dof - fit1.dof
    p_model = stats.f.sf((fit0.chi2 - fit1.chi2) / k / max(fit1.chi2 / fit1.dof, 1.0), k, fit1.dof)
    p_g = float(stats.f.sf(f_obs, g.k, g.n_blocks - 1))
    if p_model >= alpha:
        return max(p_model, p_g), max(p_model, p_g)
    out = []
    args = (sigma, X, X1, blocks, fit1, cfg["block_noise_forms"])
    _, _, tau2_hat, tau2_draws = block_gls_null_draws(*args, draws=max(draws // 4, 50), seed=seed, return_tau2=True)
    for tau2 in (tau2_hat, tau2_hat + 2.0 * np.std(tau2_draws, axis=0, ddof=1)):
        d, c = block_gls_null_draws(*args, draws=draws, seed=seed + 1, tau2=tau2)
        nu = f_reference_dof(d / g.k / (c / g.dof), g.dof)
        out.append(max(p_model, float(stats.f.sf(f_obs, g.k, nu))))
    return out[0], out[1]


def form_tables(config: dict, name: str, seed: int, rewrite_seed: int, model: list[str]):
    """The dark and linearity observation tables of a clean tiny dataset with a form of tests/effect_forms.py
    written into its raw frames at its clear amplitude, the stages run with ``model``."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import yaml
    from effect_forms import FORMS

    from pipeline.dataset import open_dataset
    from pipeline.diagnostics import observations_from_artefacts
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
    from pipeline.diagnostics import model_design, rank_missing_effects
    from pipeline.residual_structure import block_bound_p_value, covariate_tests, leverage

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


def form_case(config: dict, draws: int = 2000) -> None:
    """The power-law gain ladder on the tiny dataset: the block test's figures and its bootstrap null."""
    cfg = config["diagnostics"]
    obs = form_tables(config, "iso_gain_power_law", 101, 7, [])
    table = next(o.table for o in obs if (o.experiment, o.level) == ("linearity", "setting"))
    X, X1, sigma, blocks, fit0, fit1, g, f_obs = iso_block_test(table, cfg)
    d, c = block_gls_null_draws(sigma, X, X1, blocks, fit1, cfg["block_noise_forms"], draws=draws, seed=0)
    f = d / g.k / (c / g.dof)
    nu = f_reference_dof(f, g.dof)
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--null", type=int, default=200, help="tables per null case")
    ap.add_argument("--power", type=int, default=40, help="tables with the gain ladder")
    ap.add_argument("--draws", type=int, default=400, help="bootstrap draws per table")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--form-case", action="store_true", help="first the power-law gain ladder on the tiny dataset")
    ap.add_argument("--tanh-case", action="store_true", help="then the tanh nonlinearity's residual tests")
    args = ap.parse_args()
    config = load_config()
    if args.form_case:
        form_case(config)
    if args.tanh_case:
        tanh_case(config)
    rng = np.random.default_rng(args.seed)
    t0, c0 = time.perf_counter(), time.process_time()
    print(f"{'case':34s} {'level':>6s} {'F(k,G-1)':>9s} {'plug-in':>8s} {'inflated':>8s} {'rows':>5s}  (counts of p below level)")
    for rel, off in NULL_CASES if args.null else ():
        p = []
        for i in range(args.null):
            table = synthetic_linearity_settings(rng, rel, off)
            r = candidate_significance("iso_gain", [Observations("linearity", "setting", table)], [], config)
            p.append((r["p_value"], *bootstrap_p_values(table, config, 0.05, args.draws, args.seed + 10 * i),
                      r["p_value_model"]))
        p = np.array(p)
        for level in (0.05, 0.01):
            counts = " ".join(f"{n:>8d}" for n in np.sum(p < level, axis=0))
            print(f"null: relative {rel:.3f}, offset {off:.1f} DN {level:6.2f} {counts}  of {args.null} "
                  f"(expected {args.null * level:.0f}, binomial 0.999 bound {stats.binom.ppf(0.999, args.null, level):.0f})")
    level = config["diagnostics"]["significance_level"] / 13
    for rel, off in ((0.0, 0.0), (0.003, 0.5)) if args.power else ():
        p = []
        for i in range(args.power):
            table = synthetic_linearity_settings(rng, rel, off, gain_deficit=0.01)
            r = candidate_significance("iso_gain", [Observations("linearity", "setting", table)], [], config, 13)
            p.append((r["p_value"], *bootstrap_p_values(table, config, level, args.draws, args.seed + 10 * i),
                      r["p_value_model"]))
        counts = " ".join(f"{n:>8d}" for n in np.sum(np.array(p) < level, axis=0))
        print(f"ladder 0.01: rel {rel:.3f}, off {off:.1f} DN {level:6.1e} {counts}  of {args.power}")
    print(f"{time.perf_counter() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU")


if __name__ == "__main__":
    main()
