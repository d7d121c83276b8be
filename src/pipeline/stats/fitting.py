"""Weighted linear least squares shared by the stages and the diagnostics.

A stage's model is linear in its parameters: per-group base columns (stored
in the observation table as ``x_<name>``, one block per ``group``) plus columns
shared by all groups (the effects in the model). Residuals are normalised by
the expected noise ``sigma_dn`` so that a correct model leaves unit spread.

Rows that share a raw frame or setting (a block) share its noise: :func:`block_random_effects` estimates
that noise as a random effect per block (an offset and a relative change), :func:`block_gls_drop` tests
added columns by generalised least squares under it (the diagnostics' block test; see
:mod:`pipeline.diagnostics.missing_effects` for why it replaced a cluster-robust sandwich, which loses the effects that sit
in a few high-leverage blocks; the sandwich itself is kept in ``tests/diagnostics/test_block_significance.py`` as the
comparison).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd


@dataclass
class Fit:
    coef: np.ndarray
    cov: np.ndarray
    pred: np.ndarray
    z: np.ndarray
    chi2: float
    dof: int

    @property
    def rms_z(self) -> float:
        """sqrt(chi2 / dof): 1 at the noise floor."""
        return float(np.sqrt(self.chi2 / self.dof)) if self.dof > 0 else float("nan")


def base_design(table: pd.DataFrame) -> tuple[np.ndarray, list[str]]:
    """Block-diagonal design from the table's ``x_*`` columns, one block per group.

    Parameters
    ----------
    table : pandas.DataFrame
        An observation table with a ``group`` column and base columns ``x_<name>`` (numbers, in the units the
        stage's model gives them).

    Returns
    -------
    X : numpy.ndarray
        Shape (rows, columns): column ``x_<name>`` of each group's rows, zero on the other groups' rows; a column
        that is zero throughout is left out.
    names : list of str
        One name per column, ``<group>:<name>``.
    """
    xcols = [c for c in table.columns if c.startswith("x_")]
    groups = pd.Categorical(table["group"])
    blocks, names = [], []
    for gi, g in enumerate(groups.categories):
        sel = (groups.codes == gi)[:, None]
        for c in xcols:
            col = table[c].to_numpy(dtype=float)[:, None] * sel
            if np.any(col):
                blocks.append(col)
                names.append(f"{g}:{c[2:]}")
    return (np.hstack(blocks) if blocks else np.zeros((len(table), 0))), names


def wls(y: np.ndarray, sigma: np.ndarray, X: np.ndarray) -> Fit:
    """Minimise sum(((y - X b) / sigma)^2); covariance from the stated sigma.

    Parameters
    ----------
    y : numpy.ndarray
        Shape (n,): the observed values (e.g. DN).
    sigma : numpy.ndarray
        Shape (n,): the expected noise of each value, same unit as ``y``.
    X : numpy.ndarray
        Shape (n, p): the design; p may be 0.

    Returns
    -------
    Fit
        ``coef`` (p,), ``cov`` (p, p: the pseudo-inverse of the whitened normal matrix, not scaled by the
        residual spread), ``pred`` = X coef (n,), ``z`` = (y - pred) / sigma (n,), ``chi2`` = sum z^2 and
        ``dof`` = n - rank of the whitened design.
    """
    w = 1.0 / np.asarray(sigma, dtype=float)
    if X.shape[1] == 0:
        z = np.asarray(y, float) * w
        return Fit(coef=np.zeros(0), cov=np.zeros((0, 0)), pred=np.zeros(len(y)), z=z,
                   chi2=float(np.sum(z**2)), dof=len(y))
    A = X * w[:, None]
    b = y * w
    coef, *_ = np.linalg.lstsq(A, b, rcond=None)
    pred = X @ coef
    z = (y - pred) * w
    chi2 = float(np.sum(z**2))
    rank = np.linalg.matrix_rank(A) if A.size else 0
    cov = np.linalg.pinv(A.T @ A) if A.size else np.zeros((0, 0))
    return Fit(coef=coef, cov=cov, pred=pred, z=z, chi2=chi2, dof=int(len(y) - rank))


def ols_line(x: np.ndarray, y: np.ndarray, level: float = 0.95) -> dict:
    """Ordinary regression y = slope x + intercept with confidence intervals and Pearson r.

    Parameters
    ----------
    x : numpy.ndarray
        Shape (n,): the abscissae.
    y : numpy.ndarray
        Shape (n,): the ordinates.
    level : float, optional
        Confidence level of the intervals; default 0.95.

    Returns
    -------
    dict
        ``slope`` and ``intercept`` (units of y per x, and of y), ``slope_ci`` and ``intercept_ci`` (half-widths
        of the Student-t intervals with n - 2 degrees of freedom), ``r`` (Pearson) and ``n``.
    """
    from scipy import stats

    x = np.asarray(x, float)
    y = np.asarray(y, float)
    res = stats.linregress(x, y)
    n = len(x)
    tq = stats.t.ppf(0.5 + level / 2, max(n - 2, 1))
    return {
        "slope": res.slope, "slope_ci": tq * res.stderr,
        "intercept": res.intercept, "intercept_ci": tq * res.intercept_stderr,
        "r": res.rvalue, "n": n,
    }


#: forms of the noise common to the rows of one block that :func:`block_random_effects` estimates: an offset
#: in the value's own units (black-level jitter, in DN) and a relative change of the predicted value
#: (source flicker and drift, common to every pixel of a frame)
BLOCK_NOISE_FORMS = ("offset", "relative")


def block_index(blocks: np.ndarray) -> tuple[np.ndarray, int]:
    """Block labels as integer codes.

    Parameters
    ----------
    blocks : numpy.ndarray
        Shape (n,): each row's block label (compared as text).

    Returns
    -------
    codes : numpy.ndarray
        Shape (n,): integer code 0 .. n_blocks - 1 of each row's block, in order of first appearance.
    n_blocks : int
        The number of distinct blocks.
    """
    codes = pd.factorize(pd.Series(blocks).astype(str))[0]
    return codes, (int(codes.max()) + 1 if len(codes) else 0)


def column_space(A: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the columns of A (numerical rank).

    Parameters
    ----------
    A : numpy.ndarray
        Shape (n, p).

    Returns
    -------
    numpy.ndarray
        Shape (n, rank): left singular vectors of the singular values above max(n, p) eps times the largest.
    """
    if A.shape[1] == 0:
        return np.zeros((A.shape[0], 0))
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    keep = s > s.max() * max(A.shape) * np.finfo(float).eps if s.size else np.zeros(0, bool)
    return U[:, keep]


def block_noise_columns(fit: Fit, sigma: np.ndarray, forms=BLOCK_NOISE_FORMS) -> list[np.ndarray]:
    """Whitened loading of each block-noise form on every row.

    1/sigma for an offset (one value per block, in the value's units), prediction/sigma for a relative change
    (one fraction per block).

    Parameters
    ----------
    fit : Fit
        The weighted fit whose prediction loads the relative form.
    sigma : numpy.ndarray
        Shape (n,): the expected noise of each value.
    forms : sequence of str, optional
        Forms among ``BLOCK_NOISE_FORMS`` (``offset``, ``relative``); default both.

    Returns
    -------
    list of numpy.ndarray
        One array of shape (n,) per form, in the order of ``forms``.

    Raises
    ------
    ValueError
        For an unknown form.
    """
    w = 1.0 / np.asarray(sigma, dtype=float)
    out = {"offset": w, "relative": fit.pred * w}
    unknown = set(forms) - set(out)
    if unknown:
        raise ValueError(f"diagnostics.block_noise_forms: unknown form(s) {sorted(unknown)}; known: {sorted(out)}")
    return [out[f] for f in forms]


def moment_design(U: np.ndarray, cols: list[np.ndarray], codes: np.ndarray, n_blocks: int):
    """The moment design of the block random effects.

    The pairs (i, j) of rows of one block, the moment design D (one column per form: (M C_f M)_ij) and the
    offset U_i . U_j (= -M_ij) that :func:`block_random_effects` regresses the residual products on.

    Parameters
    ----------
    U : numpy.ndarray
        Shape (n, rank): orthonormal basis of the whitened design's columns (:func:`column_space`), so that
        M = I - U U'.
    cols : list of numpy.ndarray
        The whitened loadings of each form, each of shape (n,) (:func:`block_noise_columns`).
    codes : numpy.ndarray
        Shape (n,): each row's block code (:func:`block_index`).
    n_blocks : int
        The number of blocks.

    Returns
    -------
    i : numpy.ndarray
        Shape (pairs,): first row of each pair of rows of one block (i < j).
    j : numpy.ndarray
        Shape (pairs,): second row of each pair.
    D : numpy.ndarray
        Shape (pairs, forms): (M C_f M)_ij for each form f.
    offset : numpy.ndarray
        Shape (pairs,): U_i . U_j.
    """
    i, j = np.nonzero(np.triu(codes[:, None] == codes[None, :], 1))
    design = []
    for c in cols:
        # (M C M)_ij within a block: c_i c_j - a_i c_j - c_i a_j + U_i K U_j', a_i = U_i . v_g(i), v_g = U_g' c_g
        v = np.zeros((n_blocks, U.shape[1]))
        np.add.at(v, codes, U * c[:, None])
        a = np.sum(U * v[codes], axis=1)
        K = v.T @ v
        design.append(c[i] * c[j] - a[i] * c[j] - c[i] * a[j] + np.sum((U[i] @ K) * U[j], axis=1))
    D = np.array(design).T if cols else np.zeros((len(i), 0))
    return i, j, D, np.sum(U[i] * U[j], axis=1)


def block_random_effects(fit: Fit, X: np.ndarray, sigma: np.ndarray, blocks: np.ndarray,
                         forms=BLOCK_NOISE_FORMS) -> tuple[np.ndarray, list[np.ndarray]]:
    """Variances of the noise common to the rows of a block, estimated from a weighted fit's residuals.

    Model: value_i = X_i b + e_i + sum_f c_fi u_fg, i in block g, with e_i ~ N(0, sigma_i^2) independent and,
    per block, u_fg ~ N(0, tau_f^2) for each form f of ``forms`` (loadings c_f: 1 for an offset, the
    prediction for a relative change; :func:`block_noise_columns`). In whitened units (z = (y - X b)/sigma)
    the covariance is Sigma = I + sum_f tau_f^2 C_f, C_f block-diagonal with blocks c_fg c_fg' / sigma^2.
    Moments: the residuals r = M z, M = I - H, have E[r r'] = M Sigma M, so for every pair i != j of one
    block r_i r_j - M_ij = sum_f tau_f^2 (M C_f M)_ij + noise; the tau_f^2 >= 0 are the non-negative least
    squares solution over all such pairs (the diagonal, the stated sigma's own business, is left out).

    Parameters
    ----------
    fit : Fit
        The weighted fit (:func:`wls`) of the values on ``X``.
    X : numpy.ndarray
        Shape (n, p): its design.
    sigma : numpy.ndarray
        Shape (n,): the expected noise of each value, in the value's units.
    blocks : numpy.ndarray
        Shape (n,): each row's block label (rows of one raw frame or setting).
    forms : sequence of str, optional
        Forms of block noise among ``BLOCK_NOISE_FORMS``; default both (offset, relative).

    Returns
    -------
    tau2 : numpy.ndarray
        Shape (forms,): variance per form: the offset's in squared units of the value (e.g. DN^2), the relative
        change's as a squared fraction; zeros when no block holds two rows.
    cols : list of numpy.ndarray
        The whitened loadings of each form (:func:`block_noise_columns`).
    """
    from scipy.optimize import nnls

    sigma = np.asarray(sigma, dtype=float)
    cols = block_noise_columns(fit, sigma, forms)
    codes, n_blocks = block_index(blocks)
    nf = len(cols)
    U = column_space(X / sigma[:, None])
    i, j, D, offset = moment_design(U, cols, codes, n_blocks)
    if not len(i) or not nf:
        return np.zeros(nf), cols
    rhs = fit.z[i] * fit.z[j] + offset
    tau2, _ = nnls(D, rhs)
    return tau2, cols


def block_whitener(sigma: np.ndarray, blocks: np.ndarray, tau2: np.ndarray, cols: list[np.ndarray]):
    """A function applying L^-1 to whitened columns, Sigma = L L' the covariance of :func:`block_random_effects`.

    Sigma is block-diagonal: one Cholesky factor per block, the blocks of one size solved together.

    Parameters
    ----------
    sigma : numpy.ndarray
        Shape (n,): the expected noise of each value (not used: the columns given to the function are
        already whitened by it).
    blocks : numpy.ndarray
        Shape (n,): each row's block label.
    tau2 : numpy.ndarray
        Variance per block-noise form (:func:`block_random_effects`).
    cols : list of numpy.ndarray
        The whitened loadings of each form, each of shape (n,).

    Returns
    -------
    callable
        ``solve(M)``: for M of shape (n, k), whitened by sigma, returns L^-1 M, shape (n, k).
    """
    codes, n_blocks = block_index(blocks)
    order = np.argsort(codes, kind="stable")
    sizes = np.bincount(codes, minlength=n_blocks)
    start = np.concatenate([[0], np.cumsum(sizes)])
    groups = []
    for m in np.unique(sizes):
        rows = np.stack([order[start[g]:start[g + 1]] for g in np.nonzero(sizes == m)[0]])   # (blocks, m)
        S = np.broadcast_to(np.eye(m), (len(rows), m, m)).copy()
        for t, c in zip(tau2, cols):
            S += t * c[rows][:, :, None] * c[rows][:, None, :]
        groups.append((rows, np.linalg.cholesky(S)))

    def solve(M: np.ndarray) -> np.ndarray:
        out = np.empty_like(M, dtype=float)
        for rows, L in groups:
            out[rows] = np.linalg.solve(L, M[rows])
        return out

    return solve


@dataclass
class BlockGLSDrop:
    """Chi-square drop of added columns under the block-noise covariance (:func:`block_gls_drop`)."""

    delta_chi2: float
    chi2: float          # of the larger model, generalised least squares
    dof: int
    k: int
    n_blocks: int
    tau2: np.ndarray     # variance per form of diagnostics.block_noise_forms
    coef: np.ndarray     # the added coefficients, generalised least squares
    cov: np.ndarray      # their covariance under the block-noise covariance (unscaled)
def _svd_fit(A: np.ndarray, b: np.ndarray):
    """Least squares by one SVD: (chi2, rank, coef, covariance)."""
    if A.shape[1] == 0:
        return float(b @ b), 0, np.zeros(0), np.zeros((0, 0))
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    keep = s > s.max() * max(A.shape) * np.finfo(float).eps if s.size else np.zeros(0, bool)
    U, s, Vt = U[:, keep], s[keep], Vt[keep]
    coef = Vt.T @ ((U.T @ b) / s)
    r = b - A @ coef
    return float(r @ r), int(keep.sum()), coef, (Vt.T / s**2) @ Vt


def block_gls_drop(y: np.ndarray, sigma: np.ndarray, X0: np.ndarray, X1: np.ndarray, blocks: np.ndarray,
                   forms=BLOCK_NOISE_FORMS, fit1: Fit | None = None) -> BlockGLSDrop:
    """Drop in chi-square from the design ``X0`` to ``X1`` by generalised least squares under block noise.

    ``X1``'s first columns are ``X0``. The covariance is that of noise common to each block
    (:func:`block_random_effects`, estimated from the larger model's residuals ``fit1``, so that the added columns'
    signal is not counted as block noise).

    Parameters
    ----------
    y : numpy.ndarray
        Shape (n,): the observed values.
    sigma : numpy.ndarray
        Shape (n,): their expected noise, same unit.
    X0 : numpy.ndarray
        Shape (n, p0): the smaller design.
    X1 : numpy.ndarray
        Shape (n, p1): the larger design, ``X0`` followed by the added columns.
    blocks : numpy.ndarray
        Shape (n,): each row's block label.
    forms : sequence of str, optional
        Forms of block noise among ``BLOCK_NOISE_FORMS``; default both.
    fit1 : Fit, optional
        The weighted fit of ``y`` on ``X1`` when already made; default None (made here).

    Returns
    -------
    BlockGLSDrop
        The chi-square drop, the larger model's chi-square and degrees of freedom, the number of added
        independent columns ``k``, the number of blocks, the block-noise variances, and the added columns'
        coefficients with their covariance.
    """
    y = np.asarray(y, dtype=float)
    sigma = np.asarray(sigma, dtype=float)
    fit1 = fit1 if fit1 is not None else wls(y, sigma, X1)
    tau2, cols = block_random_effects(fit1, X1, sigma, blocks, forms)
    solve = block_whitener(sigma, blocks, tau2, cols)
    w = 1.0 / sigma
    b = solve((y * w)[:, None])[:, 0]
    chi0, rank0, _, _ = _svd_fit(solve(X0 * w[:, None]), b)
    chi1, rank1, coef, cov = _svd_fit(solve(X1 * w[:, None]), b)
    first = X0.shape[1]
    return BlockGLSDrop(delta_chi2=max(chi0 - chi1, 0.0), chi2=chi1, dof=len(y) - rank1, k=rank1 - rank0,
                        n_blocks=block_index(blocks)[1], tau2=tau2, coef=coef[first:], cov=cov[first:, first:])

