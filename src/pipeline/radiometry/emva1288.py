"""The EMVA1288 figures of a sensor (EMVA Standard 1288, release 3.0: the linear camera model).

Pure functions of the quantities the dark and linearity stages measure; every signal is the mean dark-corrected
digital value of one pixel (DN), every noise the temporal noise of one raw pixel (DN):

* :func:`saturation_capacity_e`: the electrons at the saturation point, mu_e,sat = mu_y,sat / K; with the photon
  counts, the standard's eta mu_p,sat (the linear response at the saturation point's photons, the bend of the
  curve left out);
* :func:`dynamic_range`: DR = mu_e,sat / (sigma_y,dark / K + 1/2) (the standard's mu_p,sat / mu_p,min, the
  absolute sensitivity threshold mu_p,min = (sigma_y,dark / K + 1/2) / eta), with :func:`decibels` and
  :func:`bits`;
* :func:`snr_max`: the largest signal-to-noise ratio, sqrt(mu_e,sat) (shot noise at saturation);
* :func:`responsivity`: R = d mu_y / d mu_p (DN per photon), the slope through the origin of the mean signal
  against the photons per pixel up to 70 % of the saturation signal; the quantum efficiency is R / K;
* :func:`linearity_error`: the relative deviation of the mean signal from the straight line a mu_p + b fitted
  from 5 % to 95 % of the saturation signal so as to minimise the relative deviations (weights 1 / mu_y), its
  least and largest value in per cent (LE_min, LE_max); any quantity proportional to the light (the exposure
  time of a sweep under a steady source) serves for mu_p, since the deviation is relative;
* :func:`spatial_nonuniformity`: DSNU1288 (DN) and PRNU1288 (%) from the per-pixel means and temporal variances
  of a bright and a dark stack of L frames at one setting: the spatial variance of the mean image less the part
  its temporal noise leaves in it (sigma^2 / L).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PTC_FIT_FRACTION", "LINEARITY_RANGE", "saturation_capacity_e", "dynamic_range", "snr_max", "decibels",
           "bits", "responsivity", "linearity_error", "LinearityError", "spatial_nonuniformity",
           "SpatialNonuniformity"]

#: the standard fits the responsivity (and the photon transfer) from 0 to this fraction of the saturation signal
PTC_FIT_FRACTION = 0.7
#: the standard's range of the linearity fit, as fractions of the saturation signal
LINEARITY_RANGE = (0.05, 0.95)
#: the half electron the standard adds to the dark noise in the absolute sensitivity threshold (mu_p,min)
THRESHOLD_OFFSET_E = 0.5


def saturation_capacity_e(saturation_signal_dn: float, conversion_gain_dn_per_e: float) -> float:
    """mu_e,sat = mu_y,sat / K (electrons).

    Parameters
    ----------
    saturation_signal_dn : float
        Mean dark-corrected signal at the saturation point mu_y,sat (DN).
    conversion_gain_dn_per_e : float
        Conversion gain K (DN per electron).

    Returns
    -------
    float
        Saturation capacity mu_e,sat (electrons).
    """
    return float(saturation_signal_dn) / float(conversion_gain_dn_per_e)


def dynamic_range(saturation_capacity: float, temporal_dark_noise_dn: float, conversion_gain_dn_per_e: float) -> float:
    """DR = mu_e,sat / (sigma_y,dark / K + 1/2), a ratio (1).

    Parameters
    ----------
    saturation_capacity : float
        Saturation capacity mu_e,sat (electrons).
    temporal_dark_noise_dn : float
        Temporal dark noise of one raw pixel sigma_y,dark (DN).
    conversion_gain_dn_per_e : float
        Conversion gain K (DN per electron).

    Returns
    -------
    float
        Dynamic range (dimensionless ratio).
    """
    return float(saturation_capacity) / (float(temporal_dark_noise_dn) / float(conversion_gain_dn_per_e)
                                         + THRESHOLD_OFFSET_E)


def snr_max(saturation_capacity: float) -> float:
    """SNR_max = sqrt(mu_e,sat), a ratio (1).

    Parameters
    ----------
    saturation_capacity : float
        Saturation capacity mu_e,sat (electrons).

    Returns
    -------
    float
        Largest signal-to-noise ratio (dimensionless).
    """
    return float(np.sqrt(saturation_capacity))


def decibels(ratio) -> float:
    """20 log10 of an amplitude ratio.

    Parameters
    ----------
    ratio : float
        An amplitude ratio (dimensionless), e.g. the dynamic range.

    Returns
    -------
    float
        The ratio in dB.
    """
    return float(20.0 * np.log10(ratio))


def bits(ratio) -> float:
    """log2 of a ratio.

    Parameters
    ----------
    ratio : float
        A ratio (dimensionless), e.g. the dynamic range.

    Returns
    -------
    float
        The ratio in bits.
    """
    return float(np.log2(ratio))


def responsivity(photons_per_pixel, signal_dn, saturation_signal_dn: float,
                 fraction: float = PTC_FIT_FRACTION) -> tuple[float, float, int]:
    """The least-squares slope through the origin of ``signal_dn`` against ``photons_per_pixel``.

    The fit takes the points at or below ``fraction`` of ``saturation_signal_dn``; the error comes from the
    residual scatter.

    Parameters
    ----------
    photons_per_pixel : array_like
        Mean photons per pixel mu_p of each point (photons).
    signal_dn : array_like
        Mean dark-corrected signal mu_y of each point (DN).
    saturation_signal_dn : float
        Signal at the saturation point mu_y,sat (DN).
    fraction : float, default 0.7
        Largest signal used, as a fraction of the saturation signal (:data:`PTC_FIT_FRACTION`).

    Returns
    -------
    responsivity : float
        R (DN per photon); NaN when no point with photons is in range.
    sigma : float
        Its standard error (DN per photon); NaN with fewer than two points.
    n_points : int
        Points used.
    """
    x = np.asarray(photons_per_pixel, float)
    y = np.asarray(signal_dn, float)
    use = np.isfinite(x) & np.isfinite(y) & (y <= fraction * float(saturation_signal_dn))
    x, y = x[use], y[use]
    if len(x) < 1 or not np.any(x > 0):
        return float("nan"), float("nan"), int(len(x))
    sxx = float(np.sum(x * x))
    r = float(np.sum(x * y) / sxx)
    if len(x) < 2:
        return r, float("nan"), 1
    resid = y - r * x
    return r, float(np.sqrt(np.sum(resid**2) / (len(x) - 1) / sxx)), int(len(x))


@dataclass(frozen=True)
class LinearityError:
    """The standard's linearity error: the least and largest relative deviation (%) over the fit range, the line
    (slope per unit of x, offset in DN), and each point's deviation (%) and whether it was in the fit range."""

    min_pct: float
    max_pct: float
    slope: float
    offset_dn: float
    deviation_pct: np.ndarray
    in_range: np.ndarray


def linearity_error(x, signal_dn, saturation_signal_dn: float,
                    signal_range: tuple[float, float] = LINEARITY_RANGE) -> LinearityError:
    """Fit y = a x + b to the points with ``signal_range[0]`` mu_y,sat <= y <= ``signal_range[1]`` mu_y,sat,
    minimising sum(((y - a x - b) / y)^2), and return the relative deviations 100 (y - line) / line.

    Parameters
    ----------
    x : array_like
        Any quantity proportional to the light of each point: photons per pixel, or the exposure time (s) of
        a sweep under a steady source.
    signal_dn : array_like
        Mean dark-corrected signal of each point (DN).
    saturation_signal_dn : float
        Signal at the saturation point mu_y,sat (DN).
    signal_range : tuple of float, default (0.05, 0.95)
        Fit range as fractions of the saturation signal (:data:`LINEARITY_RANGE`).

    Returns
    -------
    LinearityError
        LE_min and LE_max (%), the line (slope per unit of x, offset in DN), each point's deviation (%) and
        whether it was in the fit range; NaN figures with fewer than three points in range.
    """
    x = np.asarray(x, float)
    y = np.asarray(signal_dn, float)
    low, high = (f * float(saturation_signal_dn) for f in signal_range)
    use = np.isfinite(x) & np.isfinite(y) & (y >= low) & (y <= high) & (y > 0)
    nan = np.full(len(y), np.nan)
    if use.sum() < 3:
        return LinearityError(float("nan"), float("nan"), float("nan"), float("nan"), nan, use)
    design = np.column_stack([x[use], np.ones(int(use.sum()))]) / y[use, None]
    (a, b), *_ = np.linalg.lstsq(design, np.ones(int(use.sum())), rcond=None)
    line = a * x + b
    dev = 100.0 * (y - line) / line
    return LinearityError(float(dev[use].min()), float(dev[use].max()), float(a), float(b), dev, use)


@dataclass(frozen=True)
class SpatialNonuniformity:
    """DSNU1288 (DN), PRNU1288 (%), and the spatial variances they come from (DN^2, temporal part removed)."""

    dsnu_dn: float
    prnu_pct: float
    bright_spatial_var_dn2: float
    dark_spatial_var_dn2: float
    signal_dn: float


def spatial_nonuniformity(bright_mean_dn, bright_var_dn2, n_bright: int, dark_mean_dn, dark_var_dn2,
                          n_dark: int) -> SpatialNonuniformity:
    """DSNU1288 and PRNU1288 from the per-pixel mean and temporal variance images of a bright and a dark stack.

    With ``n_bright`` and ``n_dark`` frames (the same pixels): s^2 = var_spatial(mean image) -
    mean(variance image) / L, DSNU1288 = sqrt(s^2_dark) (NaN when negative), PRNU1288 = 100
    sqrt(s^2_bright - s^2_dark) / (mu_bright - mu_dark).

    Parameters
    ----------
    bright_mean_dn : array_like
        Per-pixel mean of the bright stack (DN).
    bright_var_dn2 : array_like
        Per-pixel temporal variance (``ddof=1``) of the bright stack (DN2).
    n_bright : int
        Frames L in the bright stack.
    dark_mean_dn : array_like
        Per-pixel mean of the dark stack (DN).
    dark_var_dn2 : array_like
        Per-pixel temporal variance (``ddof=1``) of the dark stack (DN2).
    n_dark : int
        Frames L in the dark stack.

    Returns
    -------
    SpatialNonuniformity
        DSNU1288 (DN), PRNU1288 (%), the spatial variances (DN2) and the mean signal above dark (DN).
    """
    bm, bv, dm, dv = (np.asarray(a, float).ravel() for a in (bright_mean_dn, bright_var_dn2, dark_mean_dn,
                                                             dark_var_dn2))
    s2_bright = float(np.var(bm, ddof=1) - bv.mean() / int(n_bright))
    s2_dark = float(np.var(dm, ddof=1) - dv.mean() / int(n_dark))
    signal = float(bm.mean() - dm.mean())
    dsnu = float(np.sqrt(s2_dark)) if s2_dark >= 0 else float("nan")
    excess = s2_bright - s2_dark
    prnu = float(100.0 * np.sqrt(excess) / signal) if excess >= 0 and signal > 0 else float("nan")
    return SpatialNonuniformity(dsnu, prnu, s2_bright, s2_dark, signal)
