"""Is anything left in the residuals? The chi-square of one table against its degrees of freedom.

A model that holds leaves noise-normalised residuals z whose sum of squares is chi-square distributed
with dof = n - rank(X) degrees of freedom (docs/design.md, "Closure and diagnostics"). For every observation table
(one experiment at one level: frames, settings, heights...) two tests of that sum are made:

* the chi-square tail, P(chi2_dof > sum z^2), exact for independent rows with the stated noise;
* its block-robust equivalents, for tables whose rows share a raw frame or a setting (the blocks of
  :func:`pipeline.diagnostics.missing_effects.blocks_of`), which hold whatever the correlation inside a block:

  - a t test: per block g the excess D_g = sum_{i in g} z_i^2 - sum_{i in g} (1 - h_ii), h the hat matrix
    of the weighted fit, so that E[D_g] = 0 when the model holds; the mean of the D_g over G blocks
    against its own scatter, one-sided with G - 1 degrees of freedom;
  - a bound (:func:`block_bound_p_value`): the tail of sum z^2 were the rows of each block perfectly
    correlated, the worst case at the small tail probabilities used, P(w_max chi2_G > sum z^2) with
    w_g = sum_{i in g} (1 - h_ii);

  the block p-value is twice the smaller of the two (Bonferroni over the pair). The t test alone loses
  its power when the excess sits in a few blocks, because those blocks' D_g also make the scatter it is
  measured against: with one block holding all the excess, t is about 1 however large it is. Measured
  on the tiny dataset (seed 101): a black-level ramp left by ``bias_drift`` in the dark setting table,
  chi2 2764 for 66 dof, t test p 5e-3; a black level quadratic in temperature left by ``temperature``,
  chi2 25440 for 64 dof, p 6e-3; neither reported at 0.001 / 5 tables. The bound estimates no scatter
  from the blocks: 8e-100 and below 1e-300. It pays for allowing any correlation: with blocks of 6 rows
  it needs sum z^2 above about 6 times the chi-square quantile of G, so the t test keeps the diffuse
  excess of many blocks.

The table's p-value is the larger of the chi-square tail and the block p-value (the block test only
counts when it is the less exacting,
as for the candidate effects), and structure is called significant below the family-wise
``diagnostics.structure_level`` divided by the number of tables tested (Bonferroni). After the
candidates the ranking accepted, the excess chi-square alone is no evidence of more structure: a
candidate's linearised columns leave its own measurement noise out of ``sigma_dn`` (``bias_drift``'s
unlit-corner offsets are measured with the corners' noise, which the stage adds to sigma when the effect
is in the model, the diagnostics' column cannot), so structure remaining beside such a candidate
(``Effect.columns_carry_noise``) must also follow a covariate (its F test below the level over the tables
and the covariates scanned; the F test uses the residuals' own scatter and so ignores a mis-scaled noise).
Beside any other candidate the table's p-value alone counts: with a covariate of one value per block
scanned over the block means, a ramp of the black level left beside ``temperature`` (chi2 507 for 64 dof,
block p 3e-14) follows no covariate of the 13 setting means below the level (smallest p 0.40), and would
otherwise go unreported. A per-experiment
pooled rms_z would dilute a setting-level effect with the frame-level rows of the same experiment; one
test per table does not.

Where the residuals sit: the covariate whose grouping of z is most significant (F test of group means;
numeric covariates also as a straight line and in quantile bins; the signal level ``signal_fraction``, the
predicted signal above black over the raw range between the black level and the white level, on a log scale,
where a response whose form the model lacks bends: measured in docs/effects-and-diagnostics.md, "Detection benchmark"; a covariate with
one value per block of rows sharing a frame or setting on the blocks' mean z, :func:`block_means`; one that
varies inside the blocks with their shared noise as a random effect, :func:`block_gls_covariate_test`), and, where
the table has the pixel
position of each measurement, the cell of a coarse grid over the image plane whose mean z departs most.
Nothing here reads a simulator's truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

#: covariates scanned to say where structure sits (``frame_in_setting`` is derived, see :func:`covariates_of`;
#: ``experiment`` names the stage of each row of a table that pools several, the closure's dark corners)
COVARIATES = ("experiment", "exposure_s", "gain", "lens", "band", "sweep", "temperature_c", "frame", "frame_in_setting",
              "file_index", "time_s", "theta_deg", "azimuth_deg", "water_height_cm", "wavelength_nm",
              "signal_fraction")
#: covariates scanned on a logarithmic scale (their straight-line test; the quantile bins do not depend on it):
#: a signal level spanning decades, whose bend shows per decade
LOG_SCALE_COVARIATES = ("signal_fraction",)
#: plain words for a covariate where its column name is not plain enough
COVARIATE_LABELS = {"signal_fraction": "the signal level as a fraction of full scale",
                    "frame_in_setting": "the frame's order within its setting",
                    "source_experiment": "the experiment whose frames the measurement is of"}
#: pixel position columns (band pixels of the lens image) of tables that know where each measurement sits
IMAGE_PLANE_COLUMNS = ("spot_x_px", "spot_y_px")


@dataclass
class TableTest:
    """Residual chi-square of one table and its tails."""

    chi2: float
    dof: int
    n_obs: int
    p_chi2: float
    p_block: float          # NaN when every row is its own block or there are too few blocks
    n_blocks: int
    p_value: float

    @property
    def rms_z(self) -> float:
        return float(np.sqrt(self.chi2 / self.dof)) if self.dof > 0 else float("nan")


def leverage(X: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Diagonal h_ii of the hat matrix of the weighted fit (sum h_ii = rank of X).

    Parameters
    ----------
    X : numpy.ndarray
        The design matrix, shape ``(n, k)``.
    sigma : numpy.ndarray
        The rows' standard uncertainties, shape ``(n,)``.

    Returns
    -------
    numpy.ndarray
        h_ii per row, shape ``(n,)``.
    """
    if X.shape[1] == 0:
        return np.zeros(len(sigma))
    A = X / np.asarray(sigma, float)[:, None]
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    keep = s > s.max() * max(A.shape) * np.finfo(float).eps if s.size else np.zeros(0, bool)
    return np.sum(U[:, keep] ** 2, axis=1)


def block_bound_p_value(chi2: float, block_dof: np.ndarray) -> float:
    """Tail of sum z^2 under the worst correlation inside the blocks: P(w_max chi2_G > chi2).

    Block g holds a Gaussian quadratic form sum_j lambda_gj chi2_1 whose weights, the eigenvalues of its
    residuals' covariance, sum to its degrees of freedom w_g = sum_{i in g} (1 - h_ii) whatever the
    correlation; at the small tail probabilities used here the tail is largest when the weights are
    concentrated in one (rows moving together: Szekely and Bakirov 2003 for one form), so that sum z^2 is
    at most w_max times a chi-square with G degrees of freedom, G the number of blocks. No scatter is
    estimated from the blocks themselves, so that an excess sitting in a few blocks is not taken for their
    spread (the t test's loss of power there).

    Parameters
    ----------
    chi2 : float
        sum z^2 over the table.
    block_dof : numpy.ndarray
        w_g per block.

    Returns
    -------
    float
        The p-value (1 when no block has degrees of freedom).
    """
    block_dof = np.asarray(block_dof, float)
    w_max = float(block_dof.max()) if block_dof.size else 0.0
    if w_max <= 0:
        return 1.0
    return float(stats.chi2.sf(chi2 / w_max, len(block_dof)))


def residual_chi2_test(z: np.ndarray, X: np.ndarray, sigma: np.ndarray, blocks: np.ndarray,
                       dof: int) -> TableTest:
    """Chi-square tail of sum z^2 with ``dof`` degrees of freedom and its block-robust t test.

    Parameters
    ----------
    z : numpy.ndarray
        Noise-normalised residuals, one per row.
    X : numpy.ndarray
        The fit's design matrix, shape ``(n, k)``.
    sigma : numpy.ndarray
        The rows' standard uncertainties.
    blocks : numpy.ndarray
        The block label of every row.
    dof : int
        The fit's degrees of freedom.

    Returns
    -------
    TableTest
        chi^2, dof, the number of rows, the chi-square tail, the block p-value (NaN with too few blocks), the
        number of blocks and the table's p-value (the larger of the two).
    """
    z = np.asarray(z, float)
    chi2 = float(np.sum(z**2))
    p_chi2 = float(stats.chi2.sf(chi2, max(dof, 1)))
    codes = pd.factorize(pd.Series(blocks).astype(str))[0]
    n_blocks = int(codes.max()) + 1 if len(codes) else 0
    p_block = float("nan")
    if 2 < n_blocks < len(z):
        free = 1.0 - leverage(X, sigma)
        d = np.bincount(codes, weights=z**2 - free, minlength=n_blocks)
        spread = float(np.std(d, ddof=1))
        p_t = 1.0
        if spread > 0:
            t = float(np.mean(d)) / (spread / np.sqrt(n_blocks))
            p_t = float(stats.t.sf(t, n_blocks - 1))
        p_block = min(1.0, 2.0 * min(p_t, block_bound_p_value(chi2, np.bincount(codes, weights=free,
                                                                                  minlength=n_blocks))))
    p_value = p_chi2 if not np.isfinite(p_block) else max(p_chi2, p_block)
    return TableTest(chi2=chi2, dof=int(dof), n_obs=len(z), p_chi2=p_chi2, p_block=p_block,
                     n_blocks=n_blocks if np.isfinite(p_block) else 0, p_value=p_value)


def covariates_of(table: pd.DataFrame) -> pd.DataFrame:
    """The table's covariates, plus ``frame_in_setting``: the order of a frame among the frames of its
    setting (from ``file_index``), for frame-level tables that do not carry it (settling after each
    change of setting, warm-up).

    Parameters
    ----------
    table : pandas.DataFrame
        A residual table.

    Returns
    -------
    pandas.DataFrame
        Its columns among ``COVARIATES`` (and ``frame_in_setting``), row for row.
    """
    out = table[[c for c in COVARIATES if c in table]].copy()
    if "frame" not in table and "file_index" in table and "setting" in table:
        keys = [c for c in ("lens", "band", "sweep", "setting") if c in table]
        out["frame_in_setting"] = table.groupby(keys)["file_index"].rank(method="dense").astype(int) - 1
    return out


def covariate_label(name: str) -> str:
    """The covariate in plain words, with its column name: 'the signal level as a fraction of full scale
    (signal_fraction)'; the column name alone where it is plain.

    Parameters
    ----------
    name : str
        The covariate's column name.

    Returns
    -------
    str
        The label.
    """
    label = COVARIATE_LABELS.get(name)
    return f"{label} ({name})" if label else name


def scan_values(name: str, values: pd.Series) -> pd.Series:
    """A covariate's values as scanned: the base-10 logarithm for :data:`LOG_SCALE_COVARIATES` when every
    value is positive, else as they are.

    Parameters
    ----------
    name : str
        The covariate's column name.
    values : pandas.Series
        Its values.

    Returns
    -------
    pandas.Series
        The values as scanned.
    """
    if name in LOG_SCALE_COVARIATES and values.dtype.kind in "fi" and len(values) and bool((values > 0).all()):
        return np.log10(values.astype(float))
    return values


def grouping_test(z: np.ndarray, groups: np.ndarray) -> tuple[float, float]:
    """F-test p-value of group means of the residuals, and the share of their variance they explain.

    The share is adjusted for the number of groups, 1 - (1 - eta^2)(n - 1)/(n - k), so that noise scores
    0 on average (eta^2 = SS_between / SS_total would credit k groups with (k - 1)/(n - 1) of noise).

    Parameters
    ----------
    z : numpy.ndarray
        Noise-normalised residuals, one per row.
    groups : numpy.ndarray
        The group label of every row.

    Returns
    -------
    p : float
        The p-value.
    share : float
        The share of the residuals' variance explained (adjusted for the number of groups; 0 for noise on
        average).
    """
    n, k = len(z), len(np.unique(groups))
    if n - k < 1 or k < 2:
        return 1.0, 0.0
    total = float(np.sum((z - z.mean()) ** 2)) or 1.0
    means = pd.Series(z).groupby(groups).transform("mean").to_numpy()
    between = float(np.sum((means - z.mean()) ** 2))
    within = max(total - between, 1e-300)
    p = float(stats.f.sf((between / (k - 1)) / (within / (n - k)), k - 1, n - k))
    return p, max(0.0, 1.0 - (1.0 - between / total) * (n - 1) / (n - k))


def covariate_tests(z: np.ndarray, values: pd.Series, bins: int) -> tuple[float, float]:
    """Most significant of: a straight line and ``bins`` quantile bins (a numeric covariate with more
    distinct values than bins), or the levels (otherwise).

    Parameters
    ----------
    z : numpy.ndarray
        Noise-normalised residuals, one per row.
    values : pandas.Series
        The covariate's values, row for row.
    bins : int
        The number of quantile bins.

    Returns
    -------
    p : float
        The p-value.
    share : float
        The share of the residuals' variance explained (adjusted for the number of groups; 0 for noise on
        average).
    """
    tests = []
    if values.dtype.kind in "fi" and values.nunique() > bins:
        x = values.to_numpy(float)
        r = np.corrcoef(x, z)[0, 1]
        n = len(z)
        if np.isfinite(r) and n > 2:
            t = r * np.sqrt((n - 2) / max(1.0 - r**2, 1e-300))
            tests.append((float(2 * stats.t.sf(abs(t), n - 2)), max(0.0, 1.0 - (1.0 - r**2) * (n - 1) / (n - 2))))
        tests.append(grouping_test(z, np.asarray(pd.qcut(x, bins, labels=False, duplicates="drop"))))
    else:
        tests.append(grouping_test(z, values.astype(str).to_numpy()))
    return min(tests)


def block_means(z: np.ndarray, values: pd.Series, blocks: np.ndarray | None) -> tuple[np.ndarray, pd.Series]:
    """``z`` and ``values`` as the covariate scan tests them: one row per block (the block's mean z and its
    value) when ``values`` is constant within every block of ``blocks`` and some block holds more than one
    row; the rows as they are otherwise.

    The rows of a block share the block's noise (one raw frame's or one setting's black-level jitter and
    flicker, :func:`pipeline.diagnostics.missing_effects.blocks_of`): a covariate with one value per block, tested over the
    rows, would find the shared noise of the blocks as a difference between its groups, against a
    within-group scatter that leaves it out. Measured on the clean tiny datasets with the lab noise (docs/effects-and-diagnostics.md,
    "Detection benchmark"): the logged temperature of the dark setting table, one value per setting, at p
    8.7e-17 over its 78 rows (seed 311), at 0.058 over its 13 setting means.
    A covariate that varies within blocks (the lens, the band, the signal level) is left to
    :func:`block_gls_covariate_test`.

    Parameters
    ----------
    z : numpy.ndarray
        Noise-normalised residuals, one per row.
    values : pandas.Series
        The covariate's values, row for row.
    blocks : numpy.ndarray or None
        The block label of every row.

    Returns
    -------
    z : numpy.ndarray
        The block means of z, or z itself.
    values : pandas.Series
        The block's value, or the values themselves.
    """
    values = values.reset_index(drop=True)
    if blocks is None or len(blocks) != len(values):
        return z, values
    keys = pd.Series(np.asarray(blocks)).astype(str)
    if keys.nunique() == len(keys) or (values.groupby(keys).nunique(dropna=False) > 1).any():
        return z, values
    grouped = pd.DataFrame({"z": z, "value": values, "block": keys}).groupby("block", sort=False)
    return grouped["z"].mean().to_numpy(float), grouped["value"].first().reset_index(drop=True)


def block_noise_ratio(z: np.ndarray, codes: np.ndarray, n_blocks: int) -> float:
    """The variance of a noise common to a block's rows over the rows' own, tau^2 / sigma^2, from the
    one-way analysis of variance of ``z`` by block (method of moments, unbalanced blocks; 0 when the block
    means scatter no more than the rows would make them).

    Parameters
    ----------
    z : numpy.ndarray
        Noise-normalised residuals, one per row.
    codes : numpy.ndarray
        The block index (0 .. n_blocks - 1) of every row.
    n_blocks : int
        The number of blocks.

    Returns
    -------
    float
        tau^2 / sigma^2, at least 0.
    """
    n = len(z)
    count = np.bincount(codes, minlength=n_blocks).astype(float)
    if n_blocks < 2 or n - n_blocks < 1:
        return 0.0
    means = np.bincount(codes, weights=z, minlength=n_blocks) / count
    msw = float(np.sum((z - means[codes]) ** 2)) / (n - n_blocks)
    msb = float(np.sum(count * (means - z.mean()) ** 2)) / (n_blocks - 1)
    m0 = (n - float(np.sum(count**2)) / n) / (n_blocks - 1)
    return max(0.0, (msb - msw) / m0) / msw if msw > 0 else 0.0


def block_gls_covariate_test(z: np.ndarray, values: pd.Series, blocks: np.ndarray, bins: int) -> tuple[float, float]:
    """A covariate that varies inside the blocks, tested with the noise common to a block's rows as a random effect.

    The block-noise ratio r of :func:`block_noise_ratio`, the rows of block g whitened by (1 + m_g r)^(-1/2) along
    their mean (x - c_g mean_g(x), c_g = 1 - (1 + m_g r)^(-1/2), the intercept too), then the F test of the
    covariate's columns (a straight line and ``bins`` quantile bins of a numeric covariate with more distinct
    values than bins, the levels otherwise) after the intercept, n - 1 - k degrees of freedom; the smaller p of
    the line and the bins, as :func:`covariate_tests` takes it. With r = 0 it is the test over the rows; as r
    grows it leaves the block means to the blocks' own scatter.

    Parameters
    ----------
    z : numpy.ndarray
        Noise-normalised residuals, one per row.
    values : pandas.Series
        The covariate's values, row for row.
    blocks : numpy.ndarray
        The block label of every row.
    bins : int
        The number of quantile bins.

    Returns
    -------
    p : float
        The p-value.
    share : float
        The share of the residuals' variance explained (adjusted for the number of groups; 0 for noise on
        average).
    """
    codes, uniques = pd.factorize(pd.Series(np.asarray(blocks)).astype(str))
    g = len(uniques)
    z = np.asarray(z, float)
    n = len(z)
    count = np.bincount(codes, minlength=g).astype(float)
    c = (1.0 - 1.0 / np.sqrt(1.0 + count * block_noise_ratio(z, codes, g)))[codes]

    def whiten(a):
        means = np.stack([np.bincount(codes, weights=col, minlength=g) for col in a.T], axis=1) / count[:, None]
        return a - c[:, None] * means[codes]

    designs = []
    if values.dtype.kind in "fi" and values.nunique() > bins:
        x = values.to_numpy(float)
        designs.append(x[:, None])
        q = np.asarray(pd.qcut(x, bins, labels=False, duplicates="drop"))
        designs.append((q[:, None] == np.unique(q)[None, 1:]).astype(float))
    else:
        levels = values.astype(str).to_numpy()
        designs.append((levels[:, None] == np.unique(levels)[None, 1:]).astype(float))
    zw = whiten(z[:, None])[:, 0]
    one = whiten(np.ones((n, 1)))
    base = zw - one @ np.linalg.lstsq(one, zw, rcond=None)[0]
    total = float(base @ base)
    out = []
    for X in designs:
        A = np.hstack([one, whiten(X)])
        k = int(np.linalg.matrix_rank(A)) - 1
        dof = n - 1 - k
        if k < 1 or dof < 1 or total <= 0.0:
            continue
        rest = zw - A @ np.linalg.lstsq(A, zw, rcond=None)[0]
        rss = max(float(rest @ rest), 1e-300)
        p = float(stats.f.sf(((total - rss) / k) / (rss / dof), k, dof))
        out.append((p, max(0.0, 1.0 - (rss / total) * (n - 1) / dof)))
    return min(out) if out else (1.0, 0.0)


def _varies_within_blocks(values: pd.Series, blocks: np.ndarray | None) -> bool:
    if blocks is None or len(blocks) != len(values):
        return False
    keys = pd.Series(np.asarray(blocks)).astype(str)
    return keys.nunique() < len(keys) and bool((values.reset_index(drop=True).groupby(keys).nunique(dropna=False)
                                                 > 1).any())


def where_structure_sits(table: pd.DataFrame, z: np.ndarray, bins: int,
                         blocks: np.ndarray | None = None) -> tuple[str, float, float, int]:
    """The covariate whose grouping of ``z`` is most significant.

    With ``blocks`` (the rows sharing a raw frame or setting), a covariate with one value per block is tested on
    the blocks' mean z (:func:`block_means`); one that varies inside the blocks over the rows with the noise a
    block's rows share as a random effect (:func:`block_gls_covariate_test`): over the rows as if independent,
    that noise would follow any covariate whose block means differ (the signal level of frames at different
    exposures).

    Parameters
    ----------
    table : pandas.DataFrame
        The residual table.
    z : numpy.ndarray
        Noise-normalised residuals, one per row.
    bins : int
        The number of quantile bins of a numeric covariate.
    blocks : numpy.ndarray, optional
        The block label of every row.

    Returns
    -------
    name : str
        The covariate ("no single covariate" when none beats p = 1).
    p : float
        Its p-value.
    share : float
        Its share of the residuals' variance.
    n_scanned : int
        The number of covariates scanned.
    """
    best, best_p, best_share, n = "no single covariate", 1.0, 0.0, 0
    for name, values in covariates_of(table).items():
        if values.nunique() < 2:
            continue
        n += 1
        values = values.reset_index(drop=True)
        if _varies_within_blocks(values, blocks):
            p, share = block_gls_covariate_test(z, scan_values(name, values), blocks, bins)
        else:
            z_scan, values_scan = block_means(z, values, blocks)
            p, share = covariate_tests(z_scan, scan_values(name, values_scan), bins)
        if p < best_p:
            best, best_p, best_share = name, p, share
    return best, best_p, best_share, n


def image_plane_pattern(table: pd.DataFrame, z: np.ndarray, cells: int) -> dict | None:
    """Where on the image plane the residuals depart.

    A ``cells`` x ``cells`` grid over the span of the measurements' pixel positions (per lens), the F test of the
    cell means, and the cell whose mean z is farthest from zero, with its pixel bounds.

    Parameters
    ----------
    table : pandas.DataFrame
        The residual table (its pixel-position columns ``IMAGE_PLANE_COLUMNS``).
    z : numpy.ndarray
        Noise-normalised residuals, one per row.
    cells : int
        Cells per side of the grid.

    Returns
    -------
    dict or None
        ``p_value``, ``share``, ``lens``, ``mean_z``, ``n`` (rows in the cell), ``x_px`` and ``y_px`` (the cell's
        bounds, pixels), ``cells``; None when the table has no pixel positions or too few rows.
    """
    if not all(c in table for c in IMAGE_PLANE_COLUMNS):
        return None
    x = table[IMAGE_PLANE_COLUMNS[0]].to_numpy(float)
    y = table[IMAGE_PLANE_COLUMNS[1]].to_numpy(float)
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    if ok.sum() < 2 * cells * cells:
        return None
    lens = table["lens"].astype(str).to_numpy() if "lens" in table else np.full(len(table), "")
    x, y, z, lens = x[ok], y[ok], z[ok], lens[ok]
    edges_x = np.linspace(x.min(), x.max(), cells + 1)
    edges_y = np.linspace(y.min(), y.max(), cells + 1)
    ix = np.clip(np.searchsorted(edges_x, x, side="right") - 1, 0, cells - 1)
    iy = np.clip(np.searchsorted(edges_y, y, side="right") - 1, 0, cells - 1)
    cell = np.char.add(np.char.add(lens, "/"), (iy * cells + ix).astype(str))
    p, share = grouping_test(z, cell)
    frame = pd.DataFrame({"cell": cell, "z": z, "ix": ix, "iy": iy, "lens": lens})
    means = frame.groupby("cell").agg(z=("z", "mean"), n=("z", "size"), ix=("ix", "first"), iy=("iy", "first"),
                                      lens=("lens", "first"))
    # the cell that departs most, in standard errors of its mean (residual spread within the cells)
    scatter = max(float(np.std(z - frame.groupby("cell")["z"].transform("mean").to_numpy(), ddof=1)), 1e-12)
    score = means["z"].abs() / (scatter / np.sqrt(means["n"]))
    top = means.loc[score.idxmax()]
    ix, iy = int(top["ix"]), int(top["iy"])
    return {"p_value": p, "share": share, "lens": str(top["lens"]), "mean_z": float(top["z"]), "n": int(top["n"]),
            "x_px": (float(edges_x[ix]), float(edges_x[ix + 1])), "y_px": (float(edges_y[iy]), float(edges_y[iy + 1])),
            "cells": cells}


def describe_image_plane(pattern: dict | None) -> str:
    """One phrase for a pattern of :func:`image_plane_pattern` ('' when there is none).

    Parameters
    ----------
    pattern : dict or None
        A pattern of :func:`image_plane_pattern`.

    Returns
    -------
    str
        The phrase.
    """
    if not pattern:
        return ""
    lens = f"{pattern['lens']} lens, " if pattern["lens"] else ""
    return (f"{lens}x {pattern['x_px'][0]:.0f} to {pattern['x_px'][1]:.0f} px, y {pattern['y_px'][0]:.0f} to "
            f"{pattern['y_px'][1]:.0f} px (mean z {pattern['mean_z']:+.2f} over {pattern['n']} measurements; "
            f"{pattern['cells']}x{pattern['cells']} grid F test p {pattern['p_value']:.2g})")
