"""Match-up statistics of a camera against a reference radiometer (Larouche et al. 2024, Section 2.9, Fig. 10;
Burggraaff et al. 2022, Section 2.6; Wei et al. 2012, Eq. 5).

``y`` is the camera, ``x`` the reference, paired by match-up (same length,
positive radiances for the ratio statistics).

* :func:`mupd`: mean unbiased percentage difference, Larouche Eq. (12),
  2 * 100 / N * sum |x - y| / (x + y); the same number as Wei's SMAPD (Eq. 5)
  for positive values.
* :func:`median_symmetric_accuracy`: zeta = 100 (exp(Med |ln(y/x)|) - 1),
  Burggraaff Eq. (9). The printed Eq. (9) puts the "- 1" inside the
  exponential; the definition the paper cites (Morley et al. 2018) and its
  Eq. (10) have exp(.) - 1 outside the median, as here.
* :func:`signed_symmetric_bias`: SSPB = 100 sgn(Med ln(y/x)) (exp(|Med ln(y/x)|) - 1),
  Burggraaff Eq. (10), in percent.
* :func:`pearson_r`, :func:`rmse_one_to_one`, :func:`rmse_about_fit` (RMS of
  the residuals about the least-squares line, divided by N as the
  paper's "RMSE from the linear fit").
* :func:`ols_fit`: ordinary least squares slope and intercept with
  Student-t intervals at the confidence level (Fig. 10 gives them at 95 %).
* :func:`odr_fit`: errors-in-both (orthogonal distance) regression with
  ``odrpack``, each point weighted by 1/sigma^2 of the camera (y) and the
  reference (x).
* :func:`bootstrap_interval`: paired bootstrap interval of any of the
  statistics above with :func:`scipy.stats.bootstrap` (``paired=True``,
  seeded, stated method and confidence level).

:func:`matchup_statistics` returns all of them for one band and one comparison.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy import stats

__all__ = ["mupd", "median_symmetric_accuracy", "signed_symmetric_bias", "pearson_r", "rmse_one_to_one",
           "rmse_about_fit", "ols_fit", "odr_fit", "bootstrap_interval", "matchup_statistics",
           "BOOTSTRAPPED", "STATISTIC_UNITS"]


def _pair(y, x):
    y = np.asarray(y, float)
    x = np.asarray(x, float)
    if y.shape != x.shape:
        raise ValueError(f"camera and reference differ in shape: {y.shape} and {x.shape}")
    return y, x


def mupd(y, x, axis=-1):
    """Mean unbiased percentage difference (%), Larouche et al. 2024 Eq. (12) = Wei et al. 2012 Eq. (5).

    Parameters
    ----------
    y : array_like
        The camera's values (e.g. radiance, W m-2 sr-1 nm-1), paired with ``x`` by match-up.
    x : array_like
        The reference radiometer's values, same shape and unit as ``y``.
    axis : int, optional
        The axis of the match-ups; default -1 (the last).

    Returns
    -------
    float or numpy.ndarray
        2 * 100 / N * sum |x - y| / (|x| + |y|), percent; the axis of match-ups reduced.
    """
    y, x = _pair(y, x)
    return 2.0 * 100.0 * np.mean(np.abs(x - y) / (np.abs(x) + np.abs(y)), axis=axis)


def median_symmetric_accuracy(y, x, axis=-1):
    """zeta (%) = 100 (exp(Med |ln(y/x)|) - 1), Burggraaff et al. 2022 Eq. (9) (exp(.) - 1 outside the median).

    Parameters
    ----------
    y : array_like
        The camera's values (e.g. radiance, W m-2 sr-1 nm-1), paired with ``x`` by match-up.
    x : array_like
        The reference radiometer's values, same shape and unit as ``y``.
        Both positive (the statistic takes the log of their ratio).
    axis : int, optional
        The axis of the match-ups; default -1 (the last).

    Returns
    -------
    float or numpy.ndarray
        zeta, percent; the axis of match-ups reduced.
    """
    y, x = _pair(y, x)
    return 100.0 * np.expm1(np.median(np.abs(np.log(y / x)), axis=axis))


def signed_symmetric_bias(y, x, axis=-1):
    """SSPB (%) = 100 sgn(Med ln(y/x)) (exp(|Med ln(y/x)|) - 1), Burggraaff et al. 2022 Eq. (10).

    Parameters
    ----------
    y : array_like
        The camera's values (e.g. radiance, W m-2 sr-1 nm-1), paired with ``x`` by match-up.
    x : array_like
        The reference radiometer's values, same shape and unit as ``y``.
        Both positive (the statistic takes the log of their ratio).
    axis : int, optional
        The axis of the match-ups; default -1 (the last).

    Returns
    -------
    float or numpy.ndarray
        SSPB, percent: positive when the camera reads above the reference; the axis of match-ups reduced.
    """
    y, x = _pair(y, x)
    m = np.median(np.log(y / x), axis=axis)
    return 100.0 * np.sign(m) * np.expm1(np.abs(m))


def pearson_r(y, x, axis=-1):
    """Pearson correlation coefficient (Burggraaff Eq. 7).

    Parameters
    ----------
    y : array_like
        The camera's values (e.g. radiance, W m-2 sr-1 nm-1), paired with ``x`` by match-up.
    x : array_like
        The reference radiometer's values, same shape and unit as ``y``.
    axis : int, optional
        The axis of the match-ups; default -1 (the last).

    Returns
    -------
    float or numpy.ndarray
        r, dimensionless; NaN when either side does not vary; the axis of match-ups reduced.
    """
    y, x = _pair(y, x)
    dy = y - y.mean(axis=axis, keepdims=True)
    dx = x - x.mean(axis=axis, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):     # a resample of one repeated pair: NaN
        return np.sum(dx * dy, axis=axis) / np.sqrt(np.sum(dx**2, axis=axis) * np.sum(dy**2, axis=axis))


def rmse_one_to_one(y, x, axis=-1):
    """Root-mean-square difference camera - reference (about the 1:1 line), in the data's units.

    Parameters
    ----------
    y : array_like
        The camera's values (e.g. radiance, W m-2 sr-1 nm-1), paired with ``x`` by match-up.
    x : array_like
        The reference radiometer's values, same shape and unit as ``y``.
    axis : int, optional
        The axis of the match-ups; default -1 (the last).

    Returns
    -------
    float or numpy.ndarray
        The RMS difference, in the unit of ``y`` and ``x``; the axis of match-ups reduced.
    """
    y, x = _pair(y, x)
    return np.sqrt(np.mean((y - x) ** 2, axis=axis))


def rmse_about_fit(y, x, axis=-1):
    """Root-mean-square residual about the OLS line y = a x + b (sum of squares / N).

    Parameters
    ----------
    y : array_like
        The camera's values (e.g. radiance, W m-2 sr-1 nm-1), paired with ``x`` by match-up.
    x : array_like
        The reference radiometer's values, same shape and unit as ``y``.
    axis : int, optional
        The axis of the match-ups; default -1 (the last).

    Returns
    -------
    float or numpy.ndarray
        The RMS residual, in the unit of ``y``; the axis of match-ups reduced.
    """
    y, x = _pair(y, x)
    dx = x - x.mean(axis=axis, keepdims=True)
    dy = y - y.mean(axis=axis, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = np.sum(dx * dy, axis=axis, keepdims=True) / np.sum(dx**2, axis=axis, keepdims=True)
    return np.sqrt(np.mean((dy - slope * dx) ** 2, axis=axis))


#: the statistics that get a paired bootstrap interval, and their units ("data": those of the radiances)
BOOTSTRAPPED = {"mupd": mupd, "median_symmetric_accuracy": median_symmetric_accuracy,
                "signed_symmetric_bias": signed_symmetric_bias, "pearson_r": pearson_r,
                "rmse_one_to_one": rmse_one_to_one, "rmse_about_fit": rmse_about_fit}
STATISTIC_UNITS = {"mupd": "percent", "median_symmetric_accuracy": "percent", "signed_symmetric_bias": "percent",
                   "pearson_r": "1", "rmse_one_to_one": "data", "rmse_about_fit": "data"}


def ols_fit(y, x, level: float = 0.95) -> dict:
    """y = slope x + intercept by ordinary least squares, with Student-t intervals (N - 2 dof) at ``level``.

    Parameters
    ----------
    y : array_like
        Shape (N,): the camera's values, paired with ``x``.
    x : array_like
        Shape (N,): the reference's values, same unit.
    level : float, optional
        Confidence level of the intervals; default 0.95.

    Returns
    -------
    dict
        ``slope`` (dimensionless when both share a unit), ``intercept`` (unit of ``y``), their standard errors
        ``slope_se`` and ``intercept_se``, and the interval bounds ``slope_low``, ``slope_high``,
        ``intercept_low``, ``intercept_high``.
    """
    y, x = _pair(y, x)
    res = stats.linregress(x, y)
    tq = stats.t.ppf(0.5 + level / 2.0, max(len(x) - 2, 1))
    return {"slope": float(res.slope), "slope_se": float(res.stderr),
            "slope_low": float(res.slope - tq * res.stderr), "slope_high": float(res.slope + tq * res.stderr),
            "intercept": float(res.intercept), "intercept_se": float(res.intercept_stderr),
            "intercept_low": float(res.intercept - tq * res.intercept_stderr),
            "intercept_high": float(res.intercept + tq * res.intercept_stderr)}


def odr_fit(y, x, y_sigma, x_sigma, level: float = 0.95) -> dict:
    """Errors-in-both regression y = slope x + intercept (``odrpack.odr_fit``, explicit ODR).

    Weights 1/sigma^2 on both axes. The standard errors are ODRPACK's ``sd_beta``: the covariance scaled by the
    residual variance (so a misstated sigma does not make them too small or too large); intervals Student-t with
    N - 2 dof.

    Parameters
    ----------
    y : array_like
        Shape (N,): the camera's values, paired with ``x``.
    x : array_like
        Shape (N,): the reference's values, same unit.
    y_sigma : float or array_like
        The camera's standard uncertainty, unit of ``y`` (one value or one per match-up); positive.
    x_sigma : float or array_like
        The reference's standard uncertainty, unit of ``x``; positive.
    level : float, optional
        Confidence level of the intervals; default 0.95.

    Returns
    -------
    dict
        ``slope``, ``intercept``, ``slope_se``, ``intercept_se``, the interval bounds ``slope_low``,
        ``slope_high``, ``intercept_low``, ``intercept_high``, ``converged`` (bool) and ``reduced_chi2``
        (ODRPACK's residual variance).

    Raises
    ------
    ValueError
        When an uncertainty is not positive.
    """
    import odrpack

    y, x = _pair(y, x)
    sy = np.asarray(y_sigma, float) * np.ones_like(y)
    sx = np.asarray(x_sigma, float) * np.ones_like(x)
    if np.any(~(sy > 0)) or np.any(~(sx > 0)):
        raise ValueError("the errors-in-both regression needs positive uncertainties on both axes")
    start = stats.linregress(x, y)
    result = odrpack.odr_fit(lambda xx, b: b[0] * xx + b[1], x, y, np.array([start.slope, start.intercept]),
                             weight_x=1.0 / sx**2, weight_y=1.0 / sy**2)
    slope, intercept = (float(v) for v in result.beta)
    se_slope, se_intercept = (float(v) for v in result.sd_beta)
    tq = stats.t.ppf(0.5 + level / 2.0, max(len(x) - 2, 1))
    return {"slope": slope, "slope_se": se_slope, "slope_low": slope - tq * se_slope, "slope_high": slope + tq * se_slope,
            "intercept": intercept, "intercept_se": se_intercept, "intercept_low": intercept - tq * se_intercept,
            "intercept_high": intercept + tq * se_intercept, "converged": bool(result.success),
            "reduced_chi2": float(result.res_var)}


def bootstrap_interval(statistic, y, x, level: float = 0.95, n_resamples: int = 2000, seed: int = 0,
                       method: str = "percentile") -> tuple[float, float]:
    """Paired bootstrap interval of ``statistic(y, x, axis)`` (:func:`scipy.stats.bootstrap`, ``paired=True``).

    Match-ups are resampled as pairs, so the pairing of camera and reference is kept.

    Parameters
    ----------
    statistic : callable
        ``statistic(y, x, axis)``, vectorised over ``axis`` (one of :data:`BOOTSTRAPPED`).
    y : array_like
        Shape (N,): the camera's values.
    x : array_like
        Shape (N,): the reference's values.
    level : float, optional
        Confidence level; default 0.95.
    n_resamples : int, optional
        Number of bootstrap resamples; default 2000.
    seed : int, optional
        Seed of ``numpy.random.default_rng``; default 0.
    method : str, optional
        The interval's method as :func:`scipy.stats.bootstrap` names it (``percentile``, ``basic``, ``BCa``);
        default ``percentile``.

    Returns
    -------
    low : float
        Lower bound, in the statistic's unit; NaN when the statistic does not vary over the resamples.
    high : float
        Upper bound; NaN likewise.
    """
    y, x = _pair(y, x)
    with warnings.catch_warnings():
        # a statistic constant over the resamples (or NaN in some, e.g. r of one repeated pair) has no interval
        warnings.simplefilter("ignore", stats.DegenerateDataWarning)
        res = stats.bootstrap((y, x), statistic, paired=True, vectorized=True, confidence_level=level,
                              n_resamples=n_resamples, method=method, rng=np.random.default_rng(seed))
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def matchup_statistics(y, x, y_sigma, x_sigma, level: float = 0.95, n_resamples: int = 2000, seed: int = 0,
                       method: str = "percentile") -> dict:
    """Every statistic of this module for one band and one comparison: name -> value.

    With fewer than 3 match-ups every value is NaN (no interval, no line).

    Parameters
    ----------
    y : array_like
        Shape (N,): the camera's values (e.g. radiance, W m-2 sr-1 nm-1), paired with ``x``.
    x : array_like
        Shape (N,): the reference radiometer's values, same unit; positive for the ratio statistics.
    y_sigma : float or array_like
        The camera's standard uncertainty, unit of ``y`` (weights of the errors-in-both regression).
    x_sigma : float or array_like
        The reference's standard uncertainty, unit of ``x``.
    level : float, optional
        Confidence level of the intervals; default 0.95.
    n_resamples : int, optional
        Bootstrap resamples per statistic; default 2000.
    seed : int, optional
        Seed of the first statistic's bootstrap; statistic k uses ``seed + k``. Default 0.
    method : str, optional
        The bootstrap interval's method; default ``percentile``.

    Returns
    -------
    dict
        ``n`` (match-ups); each statistic of :data:`BOOTSTRAPPED` with ``<name>_low`` and ``<name>_high``
        (units in :data:`STATISTIC_UNITS`); the regressions' ``ols_*`` and ``odr_*`` (slope, intercept, their
        standard errors and interval bounds).
    """
    y, x = _pair(y, x)
    out: dict = {"n": int(len(y))}
    names = list(BOOTSTRAPPED)
    if len(y) < 3:
        for name in names:
            out[name] = out[f"{name}_low"] = out[f"{name}_high"] = float("nan")
        for fit in ("ols", "odr"):
            for key in ("slope", "slope_se", "slope_low", "slope_high", "intercept", "intercept_se",
                        "intercept_low", "intercept_high"):
                out[f"{fit}_{key}"] = float("nan")
        return out
    for k, name in enumerate(names):
        f = BOOTSTRAPPED[name]
        out[name] = float(f(y, x))
        # one seed per statistic, derived from the configured one: the intervals are reproducible
        out[f"{name}_low"], out[f"{name}_high"] = bootstrap_interval(f, y, x, level, n_resamples, seed + k, method)
    for key, value in ols_fit(y, x, level).items():
        out[f"ols_{key}"] = value
    for key, value in odr_fit(y, x, y_sigma, x_sigma, level).items():
        if key in ("converged", "reduced_chi2"):
            continue
        out[f"odr_{key}"] = value
    return out
