"""Weighted linear least squares shared by the stages and the diagnostics.

A stage's model is linear in its parameters: per-group base columns (stored
in the observation table as ``x_<name>``, one block per ``group``) plus columns
shared by all groups (the effects in the model). Residuals are normalised by
the expected noise ``sigma_dn`` so that a correct model leaves unit spread.
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
    """Block-diagonal design from the table's ``x_*`` columns, one block per group."""
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
    """Minimise sum(((y - X b) / sigma)^2); covariance from the stated sigma."""
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
    """Ordinary regression y = slope x + intercept with confidence intervals and Pearson r."""
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


def cluster_robust_cov(fit: Fit, X: np.ndarray, sigma: np.ndarray, blocks: np.ndarray) -> tuple[np.ndarray, int]:
    """Cluster-robust (sandwich) covariance of a weighted fit's coefficients, rows of one block correlated.

    Rows that share a block (one raw frame, one setting) share that block's fluctuations (source flicker,
    black-level jitter), so their residuals are not independent. With A = X / sigma, the whitened residuals
    z, H_gg = A_g (A'A)^+ A_g' the block's part of the hat matrix and the per-block scores
    u_g = A_g' (I - H_gg)^-1 z_g,
    V = (G - 1)/G (A'A)^+ (sum_g u_g u_g') (A'A)^+
    (CR3, the jackknife-like form whose leverage correction keeps the test honest with a few tens of
    blocks, where the plain sandwich is too small). Returns (V, G); with ``blocks`` all different this is
    the heteroskedasticity-robust covariance HC3.
    """
    w = 1.0 / np.asarray(sigma, dtype=float)
    A = X * w[:, None]
    codes = pd.factorize(pd.Series(blocks).astype(str))[0]
    n_blocks = int(codes.max()) + 1 if len(codes) else 0
    order = np.argsort(codes, kind="stable")
    bounds = np.searchsorted(codes[order], np.arange(n_blocks + 1))
    scores = np.zeros((n_blocks, A.shape[1]))
    for g in range(n_blocks):
        rows = order[bounds[g]:bounds[g + 1]]
        Ag = A[rows]
        Hgg = Ag @ fit.cov @ Ag.T
        adjusted = np.linalg.lstsq(np.eye(len(rows)) - Hgg, fit.z[rows], rcond=None)[0]
        scores[g] = Ag.T @ adjusted
    meat = scores.T @ scores
    factor = (n_blocks - 1) / max(n_blocks, 1)
    return fit.cov @ meat @ fit.cov * factor, n_blocks
