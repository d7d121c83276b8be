"""Parametric bootstrap of the block test: the null distribution of its F statistic under the block-noise model.

The diagnostics test a candidate's drop in chi-square by generalised least squares under noise common to each
block (:func:`pipeline.stats.fitting.block_gls_drop`) and refer F = (drop / k) / (chi2 / dof) to a reference
distribution. F(k, G - 1), G the number of blocks, assumes the block variances' uncertainty is that of G blocks
whatever the tested columns; where each tested parameter is fixed by one block (the ISO gain factors, one
gain-sweep setting per ISO) it is too liberal with large relative block noise and too conservative without.
Here the statistic's own null distribution is drawn instead: each draw is the table simulated under the
block-noise model fitted to it (:func:`block_gls_null_draws`), put through the same estimator of the block
variances and the same generalised least squares, and the draws are summarised as F(k, nu) with nu matched to
their mean (:func:`f_reference_dof`), so that a p-value far below 1 / draws can still be read off.

The variances the draws are made at are themselves estimates from G blocks; at their estimate (the plug-in)
the reference is too liberal where they are underestimated by chance (large block offsets estimated small).
:func:`block_bootstrap_reference` therefore also carries the estimate's own uncertainty into the draws: a first
set of draws at the estimate gives each draw's estimated variances, and a second set is drawn each at one of
those (``propagated``). :func:`block_test_p_value` reads the p-value off the reference that
``diagnostics.block_reference`` names (docs/effects-and-diagnostics.md, "Closure and diagnostics", for the false-alarm rates and the power
of each, measured by ``benchmarks/bench_block_reference.py``).

Deterministic: every draw comes from ``numpy.random.default_rng(seed)``.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
from scipy import stats

from pipeline.stats.fitting import (BLOCK_NOISE_FORMS, Fit, block_index, column_space, moment_design,
                              block_random_effects)


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


@dataclass
class NullDraws:
    """Bootstrap draws of the block test under the null (:func:`block_gls_null_draws`)."""

    delta_chi2: np.ndarray     # per draw: drop in chi-square, generalised least squares
    chi2: np.ndarray           # per draw: chi-square of the larger model
    tau2: np.ndarray           # per draw and form: the block-noise variances the draw estimated
    tau2_hat: np.ndarray       # per form: the variances estimated from the observed table


def block_gls_null_draws(sigma: np.ndarray, X0: np.ndarray, X1: np.ndarray, blocks: np.ndarray, fit1: Fit,
                         forms=BLOCK_NOISE_FORMS, draws: int = 400, seed: int = 0,
                         batch_values: float = 4e6, tau2=None) -> NullDraws:
    """Parametric bootstrap of :func:`pipeline.stats.fitting.block_gls_drop` under the null.

    The drop in chi-square and the chi-square of the larger model for each of ``draws`` simulated tables.
    Each table is the smaller model's fit plus the noise the block-noise model says the rows have, with the
    variances estimated from the observed larger model's residuals (:func:`block_random_effects`), or ``tau2``:
    independent N(0, sigma_i^2) per row and, per block and form, N(0, tau_f^2) times the form's loading. Every
    draw then goes through the same steps as the observed table: its block-noise variances by moments from its
    own residuals of the larger model (non-negative least squares over the within-block pairs), its drop and
    chi-square by generalised least squares under them. The statistic is invariant to the smaller model's
    coefficients, so the draws start from zero. Two simplifications, both far below the noise: the relative
    form's loading is the observed fit's prediction in every draw (a draw's own prediction differs from it by the
    noise), and the generalised least squares use the Woodbury identity per block,
    (I + C T C')^-1 = I - C T (I + C'C T)^-1 C' (C the block's loadings, T the variances), instead of a Cholesky
    factor.

    Parameters
    ----------
    sigma : numpy.ndarray
        Shape (n,): the expected noise of each row, in the value's units.
    X0 : numpy.ndarray
        Shape (n, p0): the smaller design.
    X1 : numpy.ndarray
        Shape (n, p1): the larger design, ``X0`` followed by the tested columns.
    blocks : numpy.ndarray
        Shape (n,): each row's block label (raw frame or setting).
    fit1 : Fit
        The observed table's weighted fit on ``X1`` (its residuals give the variances; with ``draws`` 0 its
        values are put through the steps).
    forms : sequence of str, optional
        Forms of block noise (``BLOCK_NOISE_FORMS``: offset, relative); default both.
    draws : int, optional
        Number of simulated tables; default 400. 0: the observed table through the same steps (a check of the
        two routes).
    seed : int, optional
        Seed of ``numpy.random.default_rng``; default 0.
    batch_values : float, optional
        Bound on the numbers held at once (draws x rows, draws x pairs); default 4e6.
    tau2 : numpy.ndarray, optional
        Variances to draw at: one per form, or shape (draws, forms), each draw at its own; default None (the
        estimate from ``fit1``).

    Returns
    -------
    NullDraws
        Per draw the drop in chi-square and the larger model's chi-square, per draw and form the variances the
        draw estimated, and the variances estimated from the observed table.
    """
    sigma = np.asarray(sigma, dtype=float)
    w = 1.0 / sigma
    tau2_hat, cols = block_random_effects(fit1, X1, sigma, blocks, forms)
    tau2 = tau2_hat if tau2 is None else np.asarray(tau2, float)
    codes, n_blocks = block_index(blocks)
    n, nf = len(sigma), len(cols)
    A1 = X1 * w[:, None]
    U = column_space(A1)
    # unit columns: the normal equations below square the design's condition number
    norms = np.linalg.norm(A1, axis=0)
    A1 = A1 / np.where(norms > 0, norms, 1.0)
    rcond = max(A1.shape) * np.finfo(float).eps
    first = X0.shape[1]
    C = np.column_stack(cols) if nf else np.zeros((n, 0))
    # the moment estimator of block_random_effects: pairs of one block, design D, offset
    i, j, D, offset = moment_design(U, cols, codes, n_blocks)
    gram = D.T @ D
    # per block: loadings' products with the design (P_g = A_g' C_g) and with themselves (Q_g = C_g' C_g)
    onehot = np.zeros((n, n_blocks))
    onehot[np.arange(n), codes] = 1.0
    P = np.einsum("np,nf,ng->gpf", A1, C, onehot, optimize=True)
    Q = np.einsum("ne,nf,ng->gef", C, C, onehot, optimize=True)
    AtA = A1.T @ A1
    taus: list[np.ndarray] = []

    def statistic(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Drop and chi-square of the whitened tables ``b`` (draws x rows), each with its own variances."""
        m = len(b)
        if nf and len(i):
            z = b - (b @ U) @ U.T
            t = _nonnegative_least_squares_many(gram, (z[:, i] * z[:, j] + offset) @ D)
        else:
            t = np.zeros((m, nf))
        T = t[:, None, :, None] * np.eye(nf)[None, None]                      # (draws, 1, nf, nf)
        R = T @ np.linalg.inv(np.eye(nf) + Q[None] @ T)                         # T (I + Q_g T)^-1
        cb = np.einsum("nf,bn,ng->bgf", C, b, onehot, optimize=True)                           # C_g' b
        H = AtA[None] - np.einsum("gpf,bgfh,gqh->bpq", P, R, P)
        s = b @ A1 - np.einsum("gpf,bgfh,bgh->bp", P, R, cb)
        bb = np.sum(b * b, axis=1) - np.einsum("bgf,bgfh,bgh->b", cb, R, cb)

        def chi2_of(ncols: int) -> np.ndarray:
            Hc, sc = H[:, :ncols, :ncols], s[:, :ncols]
            return bb - np.einsum("bp,bp->b", sc,
                                  np.einsum("bpq,bq->bp", np.linalg.pinv(Hc, rcond=rcond, hermitian=True), sc))

        chi1 = chi2_of(A1.shape[1])
        chi0 = chi2_of(first) if first else bb
        taus.append(t)
        return np.maximum(chi0 - chi1, 0.0), chi1

    if draws <= 0:
        drop, chi1 = statistic((fit1.z + fit1.pred * w)[None])
        return NullDraws(drop, chi1, np.concatenate(taus), tau2_hat)
    rng = np.random.default_rng(seed)
    per_draw = tau2.ndim == 2
    batch = max(1, int(batch_values // max(n, len(i), A1.shape[1] ** 2, 1)))
    drops, chi2s = [], []
    for start in range(0, draws, batch):
        m = min(batch, draws - start)
        b = rng.standard_normal((m, n))
        if nf:
            scale = np.sqrt(tau2[start:start + m])[:, :, None] if per_draw else np.sqrt(tau2)[None, :, None]
            u = rng.standard_normal((m, nf, n_blocks)) * scale
            b += np.einsum("nf,bfn->bn", C, u[:, :, codes])
        drop, chi1 = statistic(b)
        drops.append(drop)
        chi2s.append(chi1)
    return NullDraws(np.concatenate(drops), np.concatenate(chi2s), np.concatenate(taus), tau2_hat)


def f_reference_dof(f_draws: np.ndarray, dof_max: float) -> float:
    """Denominator degrees of freedom nu of the F(k, nu) that matches bootstrap draws of an F statistic.

    E[F(k, nu)] = nu / (nu - 2), solved with the draws' mean raised by two standard errors (so that the few
    hundred draws do not make the reference too thin-tailed by chance), at most ``dof_max``.

    Parameters
    ----------
    f_draws : numpy.ndarray
        Bootstrap draws of the F statistic.
    dof_max : float
        The residual chi-square's own degrees of freedom: the bound on nu.

    Returns
    -------
    float
        nu; ``dof_max`` when the raised mean is at or below that of F(k, dof_max).
    """
    f_draws = np.asarray(f_draws, dtype=float)
    mean = float(np.mean(f_draws)) + 2.0 * float(np.std(f_draws, ddof=1)) / np.sqrt(len(f_draws))
    if mean <= dof_max / max(dof_max - 2.0, 1e-9):
        return float(dof_max)
    return float(min(2.0 * mean / (mean - 1.0), dof_max))


@dataclass
class BlockTestPart:
    """One table of a block test: the rows' sigma, the smaller and larger designs, the blocks and the larger
    model's weighted fit (the variances are estimated from its residuals), as :func:`block_gls_drop` takes them."""

    sigma: np.ndarray
    X0: np.ndarray
    X1: np.ndarray
    blocks: np.ndarray
    fit1: Fit
    forms: tuple = BLOCK_NOISE_FORMS


#: batches of the draws left out one at a time for the Monte Carlo error of a bootstrap p-value
#: (:func:`jackknife_sd`): ten, so that each holds ``diagnostics.block_bootstrap_draws`` / 10 draws
MC_BATCHES = 10


@dataclass
class BlockReference:
    """The bootstrap references of a block test: F(k, nu) with nu matched to the draws, and nu matched again
    with each of :data:`MC_BATCHES` batches of the draws left out (the jackknife of the Monte Carlo error)."""

    k: int
    dof: int
    nu_plug_in: float       # draws at the variances' estimate
    nu_propagated: float    # each draw at the variances one draw at the estimate estimated
    nu_plug_in_without: tuple = ()       # per batch left out
    nu_propagated_without: tuple = ()


def jackknife_sd(values_without: np.ndarray) -> float:
    """Standard error of an estimate from its values with each of B batches of the draws left out.

    sqrt((B - 1) / B sum (v_j - mean v)^2), over the finite values.

    Parameters
    ----------
    values_without : numpy.ndarray
        Shape (B,): the estimate with batch j of the draws left out.

    Returns
    -------
    float
        The jackknife standard error, in the estimate's units; NaN with fewer than two finite values.
    """
    v = np.asarray(values_without, float)
    v = v[np.isfinite(v)]
    if v.size < 2:
        return float("nan")
    return float(np.sqrt((v.size - 1) / v.size * np.sum((v - v.mean()) ** 2)))


def _nu_without_batches(f_draws: np.ndarray, dof_max: float) -> tuple:
    """nu of :func:`f_reference_dof` with each of :data:`MC_BATCHES` consecutive batches of ``f_draws`` left out."""
    batches = np.array_split(np.arange(len(f_draws)), MC_BATCHES)
    return tuple(f_reference_dof(np.delete(f_draws, b), dof_max) for b in batches)


def block_bootstrap_reference(parts: list[BlockTestPart], draws: int, seed: int,
                              propagated: bool = True) -> BlockReference:
    """The null distribution of the block test's F over ``parts``, summarised as F(k, nu).

    F = (sum of drops / k) / (sum of chi2 / sum of dof) over the tables a candidate touches, drawn
    independently, the draws of one index combined: at the block-noise variances estimated from each table
    (plug-in), and with each draw at the variances estimated by a first draw at the estimate (propagated: the
    estimate's own sampling spread carried into the reference). 2 x ``draws`` tables are simulated per part, from
    the seeds ``seed + j`` and ``seed + j + 7919`` for part j.

    Parameters
    ----------
    parts : list of BlockTestPart
        The tables of the test.
    draws : int
        Simulated tables per part and set.
    seed : int
        Base seed (:func:`table_seed`).
    propagated : bool, optional
        Also draw the propagated reference; default True. False: only the first ``draws`` per part
        (``nu_propagated`` NaN).

    Returns
    -------
    BlockReference
        k (tested parameters, at least 1), the residual degrees of freedom, nu of the plug-in and propagated
        references, and nu with each of ``MC_BATCHES`` batches of the draws left out.
    """
    k, dof = 0, 0
    drop_plug, chi_plug, drop_prop, chi_prop = 0.0, 0.0, 0.0, 0.0
    for j, p in enumerate(parts):
        first = block_gls_null_draws(p.sigma, p.X0, p.X1, p.blocks, p.fit1, p.forms, draws=draws, seed=seed + j)
        drop_plug, chi_plug = drop_plug + first.delta_chi2, chi_plug + first.chi2
        if propagated:
            second = block_gls_null_draws(p.sigma, p.X0, p.X1, p.blocks, p.fit1, p.forms, draws=draws,
                                          seed=seed + j + 7919, tau2=first.tau2)
            drop_prop, chi_prop = drop_prop + second.delta_chi2, chi_prop + second.chi2
        k += _rank(p.sigma, p.X1) - _rank(p.sigma, p.X0)
        dof += len(p.sigma) - _rank(p.sigma, p.X1)
    k = max(k, 1)
    f_plug = drop_plug / k / (chi_plug / max(dof, 1))
    nu_plug_in = f_reference_dof(f_plug, dof)
    out = BlockReference(k=k, dof=dof, nu_plug_in=nu_plug_in, nu_propagated=float("nan"),
                         nu_plug_in_without=_nu_without_batches(f_plug, dof))
    if propagated:
        f_prop = drop_prop / k / (chi_prop / max(dof, 1))
        out.nu_propagated = f_reference_dof(f_prop, dof)
        out.nu_propagated_without = _nu_without_batches(f_prop, dof)
    return out


def _rank(sigma: np.ndarray, X: np.ndarray) -> int:
    return int(column_space(X / np.asarray(sigma, float)[:, None]).shape[1]) if X.shape[1] else 0


def columns_within_blocks(part: BlockTestPart) -> bool:
    """Whether every column the test adds is non-zero in one block only.

    Each tested parameter is then fixed by one block: the ISO gain factors, one gain-sweep setting per ISO.

    Parameters
    ----------
    part : BlockTestPart
        One table of the test.

    Returns
    -------
    bool
        True when the test adds at least one column and each added column is non-zero within one block at most.
    """
    codes, _ = block_index(part.blocks)
    added = part.X1[:, part.X0.shape[1]:]
    return added.shape[1] > 0 and all(len(np.unique(codes[c != 0])) <= 1 for c in added.T)


def table_seed(parts: list[BlockTestPart], seed: int) -> int:
    """The seed of one test's draws: ``seed`` and a checksum of the tables' normalised residuals (rounded to 1e-6).

    The Monte Carlo error of the reference is so independent between tables, as
    ``benchmarks/bench_block_reference.py`` measured it, while the same tables always give the same draws. (One
    seed for every table gave nu 11.7 on each of eight gain-ladder tables without block noise where seeds
    1 and 2 gave 20 and 15: the same draws for tables of one shape.)

    Parameters
    ----------
    parts : list of BlockTestPart
        The tables of the test.
    seed : int
        The configured seed (``diagnostics.block_bootstrap_seed``).

    Returns
    -------
    int
        A 32-bit seed from ``numpy.random.SeedSequence``.
    """
    crc = [zlib.crc32(np.ascontiguousarray(np.round(p.fit1.z, 6)).tobytes()) for p in parts]
    return int(np.random.SeedSequence([seed, *crc]).generate_state(1)[0])


#: values of ``diagnostics.block_reference``: F(k, G - 1); the bootstrap with the variances' uncertainty carried
#: into the draws (the default, docs/effects-and-diagnostics.md, "Closure and diagnostics"); the bootstrap at the variances' estimate
BLOCK_REFERENCES = ("f", "bootstrap", "plug_in")


def block_test_p_value(f_stat: float, k: int, n_blocks: int, parts: list[BlockTestPart], p_rows: float,
                       alpha: float, cfg: dict) -> tuple[float, str, float, float]:
    """p-value of the block test's F on k parameters over tables of at least ``n_blocks`` blocks.

    With it: the reference it was read from, that reference's denominator degrees of freedom, and the Monte
    Carlo standard error of log10 of the p-value (NaN for F(k, G - 1), which has none): the jackknife over
    :data:`MC_BATCHES` batches of the draws (:func:`jackknife_sd`), so that a verdict near the level can be
    seen to rest on the draws.

    ``diagnostics.block_reference`` ``f``: F(k, G - 1). ``bootstrap`` (``plug_in``): F(k, nu) matched to the
    propagated (plug-in) draws of :func:`block_bootstrap_reference`, ``diagnostics.block_bootstrap_draws`` of
    them from ``diagnostics.block_bootstrap_seed`` and the tables (:func:`table_seed`). Drawn only where it can
    change the verdict, where the rows' F test ``p_rows`` is below the level ``alpha`` (the p-value that counts
    is the larger of the two, so elsewhere the candidate is not significant whichever the reference, and
    F(k, G - 1) is reported), and only where each tested column sits in one block (:func:`columns_within_blocks`:
    the case F(k, G - 1) fails and the bootstrap was measured on). Elsewhere F(k, G - 1) is kept: where a
    candidate's signature only approximates the effect, its misfit is estimated as block noise, the draws'
    tails grow with it, and the bootstrap loses real effects that F(k, G - 1) finds (on the tiny dataset a
    tanh nonlinearity, nu 4.7 and p 1e-4 against 5e-8; a black level quadratic in temperature, 2e-3 against
    7e-6; ``tests/effects/test_effect_forms.py``).

    Parameters
    ----------
    f_stat : float
        The observed F = (drop / k) / (chi2 / dof).
    k : int
        Number of tested parameters.
    n_blocks : int
        G, the fewest blocks of the tables.
    parts : list of BlockTestPart
        The tables of the test (used by the bootstrap).
    p_rows : float
        p-value of the rows' F test.
    alpha : float
        The significance level.
    cfg : dict
        The ``diagnostics`` config section: ``block_reference`` (default ``f``), ``block_bootstrap_draws``,
        ``block_bootstrap_seed``.

    Returns
    -------
    p_value : float
        The p-value read off the reference.
    reference : str
        ``F(k, G - 1)``, ``bootstrap F(k, nu)`` or ``plug_in F(k, nu)``.
    dof : float
        The reference's denominator degrees of freedom (G - 1 or nu).
    log10_p_sd : float
        Monte Carlo standard error of log10 of the p-value; NaN for F(k, G - 1).

    Raises
    ------
    ValueError
        For an unknown ``block_reference``.
    """
    method = cfg.get("block_reference", "f")
    if method not in BLOCK_REFERENCES:
        raise ValueError(f"diagnostics.block_reference: unknown {method!r}; known: {', '.join(BLOCK_REFERENCES)}")
    if method == "f" or not p_rows < alpha or not all(columns_within_blocks(p) for p in parts):
        return float(stats.f.sf(f_stat, k, n_blocks - 1)), "F(k, G - 1)", float(n_blocks - 1), float("nan")
    ref = block_bootstrap_reference(parts, int(cfg["block_bootstrap_draws"]),
                                    table_seed(parts, int(cfg["block_bootstrap_seed"])), propagated=method == "bootstrap")
    nu, without = ((ref.nu_propagated, ref.nu_propagated_without) if method == "bootstrap"
                   else (ref.nu_plug_in, ref.nu_plug_in_without))
    log_p = np.log10(np.maximum(stats.f.sf(f_stat, k, np.asarray(without, float)), 1e-300))
    return float(stats.f.sf(f_stat, k, nu)), f"{method} F(k, nu)", nu, jackknife_sd(log_p)
