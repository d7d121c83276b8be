"""Saturation found in the data of an exposure or gain sweep (photon transfer, Janesick 2007).

A sensor saturates where its full well fills or where the ADC reaches its top
code, whichever comes first; only the second is visible in the raw values
(the white level). Both leave marks on a sweep ordered by exposure (t times ISO/100):

* the mean signal stops rising with exposure: it reaches a plateau;
* the temporal variance, which grows with the signal by shot noise, stops growing
  and then collapses (every pixel sits at its own ceiling). It stops growing first:
  a setting whose pixels touch the ceiling in a few frames keeps nearly all of its
  mean but loses the upper tail of its noise, and left in the photon-transfer fit
  it biases the conversion gain low (an 8-bit sensor whose well fills eight steps
  below its white level: 2 %).

A setting is saturated when

* its signal rose by less than ``plateau_fraction`` of the rise proportional to
  exposure since the last unsaturated setting (a plateau), or
* its variance fell below ``variance_drop`` times the largest variance of the
  unsaturated settings below it (a collapse), or
* its variance rose by less than ``stall_fraction`` of the rise the line of
  variance against exposure through the unsaturated settings below predicts (a stall);

a collapse or a stall counts only when the shortfall exceeds the swing of rounding
(:data:`ROUNDING_SWING_DN2`) plus ``noise_sigma`` standard errors of the two
variances (``variance_rel_se``: a sample variance over N pixels and n frames
scatters by sqrt(2 / (N (n - 1))) of itself). Every setting above a saturated one
is saturated too. A nonlinearity (docs/design.md: about 24 % for the published camera)
bends the rise but does not flatten it, and leaves the variance growing up to a
bend of 1/6 of the full scale (the variance of s (1 - beta s / F) is
(1 - 2 beta s / F)^2 K s), so it is not taken for saturation below that.

A setting taken under other light (a frame series among the sweep whose source
was dimmer or brighter) is not saturation: its signal leaves the sweep's rise and
the next longer setting takes it up again. :func:`non_monotonic_settings` names
those before the saturation is looked for.
"""

from __future__ import annotations

import numpy as np

__all__ = ["QUANTISATION_VARIANCE_DN2", "ROUNDING_SWING_DN2", "expected_between_neighbours", "non_monotonic_settings", "saturated_settings",
           "signal_fraction"]

#: variance rounding to whole DN adds to a noise of half a step or more (uniform over one step): the
#: variance model of a raw pixel is K s + r^2 + 1/12 DN^2
QUANTISATION_VARIANCE_DN2 = 1.0 / 12.0
#: what rounding can do to the variance of a noise below half a step: a pixel that never leaves its code
#: has none, one half-way between two codes flips at even odds, 1/4 DN^2 (3 x 1/12), whatever its
#: model says; a quantised sensor's variance at low signal swings over this much with the signal's
#: position between codes (0.3 DN of dark noise and 0.01 DN per electron: 0.25 DN^2 at 0.5 DN, 0.11 DN^2 at
#: 1 DN), which must not be taken for a collapse
ROUNDING_SWING_DN2 = 3.0 * QUANTISATION_VARIANCE_DN2


def _variance_slope(x, v) -> float:
    """Slope of variance against exposure through the points (NaN with fewer than two exposures)."""
    x = np.asarray(x, dtype=float)
    if len(x) < 2 or np.ptp(x) <= 0:
        return float("nan")
    return float(np.polyfit(x, np.asarray(v, dtype=float), 1)[0])


def saturated_settings(exposure, signal_dn, variance_dn2, plateau_fraction: float,
                       variance_drop: float, clipped=None, *, stall_fraction: float = 0.0,
                       variance_rel_se=0.0, noise_sigma: float = 3.0) -> np.ndarray:
    """Boolean mask of the saturated settings of one sweep (any order of the inputs).

    The tests are the module docstring's (plateau, collapse, stall); every setting above a saturated one is
    saturated too.

    Parameters
    ----------
    exposure : array_like
        t ISO/100 of each setting (s), or any quantity the signal is proportional to.
    signal_dn : array_like
        Dark-corrected mean signal of each setting (DN).
    variance_dn2 : array_like
        Temporal variance of the same pixels (DN2).
    plateau_fraction : float
        A setting whose signal rose by less than this fraction of the rise proportional to exposure since the
        last unsaturated setting is on a plateau (dimensionless).
    variance_drop : float
        A setting whose variance fell below this fraction of the largest variance of the unsaturated
        settings below it has collapsed (dimensionless).
    clipped : array_like of bool, optional
        Settings whose raw values reached the white level (saturated whatever their statistics).
    stall_fraction : float, default 0.0
        A setting whose variance rose by less than this fraction of the rise predicted by the line of
        variance against exposure has stalled; 0 tests only that the variance rose at all.
    variance_rel_se : float or array_like, default 0.0
        Relative standard error of each variance (scalar or per setting; sqrt(2 / (N (n - 1))) for N pixels
        and n frames).
    noise_sigma : float, default 3.0
        Standard errors beyond the rounding swing a collapse or stall's shortfall must exceed.

    Returns
    -------
    numpy.ndarray of bool
        True at the saturated settings, in the order of the inputs.
    """
    x = np.asarray(exposure, dtype=float)
    s = np.asarray(signal_dn, dtype=float)
    v = np.asarray(variance_dn2, dtype=float)
    rel_se = np.broadcast_to(np.asarray(variance_rel_se, dtype=float), x.shape)
    out = np.zeros(len(x), dtype=bool) if clipped is None else np.asarray(clipped, dtype=bool).copy()
    order = np.argsort(x, kind="stable")
    last = None                 # index of the last unsaturated setting
    below = []                  # unsaturated settings so far
    i_max = None                # the unsaturated setting of largest variance
    saturated = False
    for i in order:
        if not saturated and last is not None and x[i] > x[last] and s[last] > 0:
            expected_rise = s[last] * (x[i] / x[last] - 1.0)
            plateau = (s[i] - s[last]) < plateau_fraction * expected_rise

            def beyond_noise(shortfall, j):
                se = np.hypot(rel_se[i] * v[i], rel_se[j] * v[j])
                return shortfall > ROUNDING_SWING_DN2 + noise_sigma * se
            collapse = v[i] < variance_drop * v[i_max] and beyond_noise(v[i_max] - v[i], i_max)
            slope = _variance_slope(x[below], v[below])
            stall = False
            if np.isfinite(slope) and slope > 0:
                expected_v_rise = slope * (x[i] - x[last])
                rise = v[i] - v[last]
                stall = rise < stall_fraction * expected_v_rise and beyond_noise(expected_v_rise - rise, last)
            saturated = bool(plateau or collapse or stall)
        saturated = saturated or bool(out[i])
        out[i] = saturated
        if not saturated:
            if last is None or x[i] > x[last]:
                last = i
            below.append(i)
            if i_max is None or v[i] > v[i_max]:
                i_max = i
    return out


def non_monotonic_settings(exposure, signal_dn, signal_se_dn, noise_sigma: float) -> np.ndarray:
    """Boolean mask of the settings whose mean signal leaves the sweep's rise with exposure (any order).

    A setting between two neighbours (shorter and longer exposure) is a candidate when its signal is
    below its shorter neighbour's, or above its longer neighbour's, by more than ``noise_sigma``
    standard errors of the difference, while its
    neighbours themselves rise in order (the longer above the shorter by as much): a frame series taken
    under other light. A sweep that only stops rising (a plateau) or falls from some setting on is not
    named here; that is saturation's. The candidate departing most from the line through its
    neighbours (in standard errors) is named first and the test repeated without it, so one stray
    setting does not make its neighbours look stray. The shortest and the longest setting
    have one neighbour and are not tested.

    Parameters
    ----------
    exposure : array_like
        t ISO/100 of each setting (s), or any quantity the signal is proportional to.
    signal_dn : array_like
        Dark-corrected mean signal of each setting (DN).
    signal_se_dn : array_like
        Standard error of each setting's mean signal (DN).
    noise_sigma : float
        Standard errors a departure must exceed.

    Returns
    -------
    numpy.ndarray of bool
        True at the settings taken under other light, in the order of the inputs.
    """
    x = np.asarray(exposure, dtype=float)
    s = np.asarray(signal_dn, dtype=float)
    se = np.asarray(signal_se_dn, dtype=float)
    out = np.zeros(len(x), dtype=bool)
    while True:
        kept = [i for i in np.argsort(x, kind="stable") if not out[i]]
        worst, worst_z = None, 0.0
        for p, i, n in zip(kept, kept[1:], kept[2:]):
            if not x[p] < x[i] < x[n]:
                continue
            below_shorter = (s[p] - s[i]) / np.hypot(se[p], se[i]) > noise_sigma
            above_longer = (s[i] - s[n]) / np.hypot(se[i], se[n]) > noise_sigma
            rising = (s[n] - s[p]) / np.hypot(se[n], se[p]) > noise_sigma
            # departure from the line through the neighbours: a dim setting after a good one makes the
            # good one look above its longer neighbour too, but departs less from its own neighbours' line
            w = (x[i] - x[p]) / (x[n] - x[p])
            z = abs(s[i] - (s[p] + w * (s[n] - s[p]))) / np.sqrt(se[i] ** 2 + ((1 - w) * se[p]) ** 2 + (w * se[n]) ** 2)
            if rising and (below_shorter or above_longer) and z > worst_z:
                worst, worst_z = i, z
        if worst is None:
            return out
        out[worst] = True


def expected_between_neighbours(exposure, signal_dn, index: int, left_out) -> float:
    """The signal at setting ``index`` on the line through its nearest kept neighbours in exposure.

    Parameters
    ----------
    exposure : array_like
        t ISO/100 of each setting (s), or any quantity the signal is proportional to.
    signal_dn : array_like
        Mean signal of each setting (DN).
    index : int
        Position of the setting in the inputs.
    left_out : array_like of bool
        Settings that are not neighbours (e.g. those of :func:`non_monotonic_settings`).

    Returns
    -------
    float
        The interpolated signal (DN); NaN without a kept neighbour on each side.
    """
    x = np.asarray(exposure, dtype=float)
    s = np.asarray(signal_dn, dtype=float)
    kept = ~np.asarray(left_out, dtype=bool)
    shorter = np.flatnonzero(kept & (x < x[index]))
    longer = np.flatnonzero(kept & (x > x[index]))
    if not len(shorter) or not len(longer):
        return float("nan")
    p = shorter[np.argmax(x[shorter])]
    n = longer[np.argmin(x[longer])]
    return float(s[p] + (s[n] - s[p]) * (x[index] - x[p]) / (x[n] - x[p]))


def signal_fraction(signal_dn, black_dn, white_level_dn) -> np.ndarray:
    """Fraction of the raw range a signal fills: ``signal_dn`` above the black level over the range left
    between the black level ``black_dn`` and the raw files' white level (unit 1; 1 at the ADC top).

    The covariate a response that bends with signal level follows (a nonlinearity whose form the model
    lacks leaves residuals that change sign along it).

    Parameters
    ----------
    signal_dn : array_like
        Signal above the black level (DN).
    black_dn : array_like
        Black level (DN).
    white_level_dn : array_like
        The raw files' white level (DN).

    Returns
    -------
    numpy.ndarray
        The fraction (dimensionless), broadcast over the inputs; NaN where the range is not positive.
    """
    signal = np.asarray(signal_dn, dtype=float)
    span = np.asarray(white_level_dn, dtype=float) - np.asarray(black_dn, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(span > 0, signal / np.where(span > 0, span, 1.0), np.nan)
