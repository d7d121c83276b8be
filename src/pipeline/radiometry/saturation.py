"""Saturation found in the data of an exposure or gain sweep (photon transfer, Janesick 2007).

A sensor saturates where its full well fills or where the ADC reaches its top
code, whichever comes first; only the second is visible in the raw values
(the white level). Both leave the same two marks on a sweep ordered by
exposure (t times ISO/100):

* the mean signal stops rising with exposure: it reaches a plateau;
* the temporal variance, which grows with the signal by shot noise, collapses
  (every pixel sits at its own ceiling).

A setting is saturated when its signal rose by less than
``plateau_fraction`` of the rise proportional to exposure since the last
unsaturated setting, or its variance fell below ``variance_drop`` times the
largest variance of the unsaturated settings below it; every setting above a
saturated one is saturated too. A nonlinearity (docs/design.md: about 24 % for the
published camera) bends the rise but does not flatten it, and leaves the
variance growing, so it is not taken for saturation.
"""

from __future__ import annotations

import numpy as np

__all__ = ["saturated_settings", "signal_fraction"]


def saturated_settings(exposure, signal_dn, variance_dn2, plateau_fraction: float,
                       variance_drop: float, clipped=None) -> np.ndarray:
    """Boolean mask of the saturated settings of one sweep (any order of the inputs).

    ``exposure``: t ISO/100 (or any quantity the signal is proportional to);
    ``signal_dn``: dark-corrected mean signal; ``variance_dn2``: temporal
    variance of the same pixels; ``clipped``: settings whose raw values reached
    the white level (saturated whatever their statistics).
    """
    x = np.asarray(exposure, dtype=float)
    s = np.asarray(signal_dn, dtype=float)
    v = np.asarray(variance_dn2, dtype=float)
    out = np.zeros(len(x), dtype=bool) if clipped is None else np.asarray(clipped, dtype=bool).copy()
    order = np.argsort(x, kind="stable")
    last = None                 # index of the last unsaturated setting
    v_max = -np.inf
    saturated = False
    for i in order:
        if not saturated and last is not None and x[i] > x[last] and s[last] > 0:
            expected_rise = s[last] * (x[i] / x[last] - 1.0)
            plateau = (s[i] - s[last]) < plateau_fraction * expected_rise
            collapse = v[i] < variance_drop * v_max
            saturated = bool(plateau or collapse)
        saturated = saturated or bool(out[i])
        out[i] = saturated
        if not saturated:
            if last is None or x[i] > x[last]:
                last = i
            v_max = max(v_max, v[i])
    return out


def signal_fraction(signal_dn, black_dn, white_level_dn) -> np.ndarray:
    """Fraction of the raw range a signal fills: ``signal_dn`` above the black level over the range left
    between the black level ``black_dn`` and the raw files' white level (unit 1; 1 at the ADC top).

    The covariate a response that bends with signal level follows (a nonlinearity whose form the model
    lacks leaves residuals that change sign along it); NaN where the range is not positive."""
    signal = np.asarray(signal_dn, dtype=float)
    span = np.asarray(white_level_dn, dtype=float) - np.asarray(black_dn, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(span > 0, signal / np.where(span > 0, span, 1.0), np.nan)
