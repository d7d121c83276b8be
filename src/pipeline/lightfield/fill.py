"""The whole sphere: cells no lens calibrates filled by interpolation in zenith angle, with a model uncertainty.

A dual-fisheye camera leaves a band of the sphere unseen between its two
lenses' calibrated fields (about 80 to 100 degrees zenith angle in air, 70 to
110 in water). Model, per azimuth column of the grid (in the camera's frame,
where the band is a band of rows): each run of empty cells between a
calibrated cell above (zenith angle z_a, radiance L_a) and one below (z_b, L_b)
takes the linear interpolation in zenith angle

    L(z) = (1 - t) L_a + t L_b,   t = (z - z_a) / (z_b - z_a).

Its model uncertainty is the error bound of linear interpolation,

    sigma_model(z) = (z - z_a)(z_b - z) / 2 * K,

where K is the largest |d^2 L / dz^2| (per rad^2) of the two quadratic fits
to the last calibrated rows on either side of the run (``fill_fit_span_deg``
of zenith angle, at least three rows), each increased by its own standard
error from the cells' random noise. It holds where the radiance curves no more
inside the band than at its edges, as a scattered light field does; a run with
fewer than three calibrated rows on both sides takes half the step across it,
|L_b - L_a| / 2, and is counted. A run that touches the zenith or the nadir
has no second edge and stays empty (its integrals are NaN).

The filled cells' random noise is that of the two edge cells through the
weights (1 - t) and t, so that a filled cell is a linear map of measured cells
(:class:`Filled` keeps the map), and the integrals propagate it exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Filled", "fill_between_lenses", "FLAG_MEASURED", "FLAG_FILLED", "FLAG_EMPTY"]

FLAG_MEASURED, FLAG_FILLED, FLAG_EMPTY = 0, 1, 2


@dataclass
class Filled:
    """The filled grid of one frame and band (n_zenith, n_azimuth arrays) and the interpolation map."""

    radiance: np.ndarray          # measured cells as given, filled cells interpolated, empty NaN
    random_sigma: np.ndarray      # filled: the edges' random sigma through the weights
    systematic_sigma: np.ndarray  # filled: the edges' (fully correlated) systematic sigma through the weights
    model_sigma: np.ndarray       # 0 for measured cells
    flag: np.ndarray              # FLAG_MEASURED, FLAG_FILLED or FLAG_EMPTY
    above: np.ndarray             # filled cells: row of the calibrated cell above (else -1)
    below: np.ndarray             # filled cells: row of the calibrated cell below (else -1)
    t: np.ndarray                 # filled cells: weight of the cell below
    fallback_cells: int           # filled cells whose model sigma is the fallback half step


def _curvature_filter(n_rows: int, step_rad: float) -> np.ndarray:
    """Weights w so that sum_k w_k y_k is the second derivative of the least-squares quadratic through
    ``n_rows`` equally spaced values ``step_rad`` apart."""
    x = (np.arange(n_rows) - (n_rows - 1) / 2) * step_rad
    design = np.stack([np.ones_like(x), x, x ** 2], axis=1)
    return 2.0 * np.linalg.pinv(design)[2]


def fill_between_lenses(radiance, random_sigma, systematic_sigma, zenith_deg, fit_span_deg: float) -> Filled:
    """Fill the empty cells of one frame and band's camera-frame grid (n_zenith, n_azimuth) by the model above.

    ``zenith_deg`` the cell centres (regular); ``fit_span_deg`` the zenith span of the quadratic fits.
    """
    L = np.asarray(radiance, float)
    sr = np.nan_to_num(np.asarray(random_sigma, float))
    ss = np.nan_to_num(np.asarray(systematic_sigma, float))
    z = np.radians(np.asarray(zenith_deg, float))
    n_z, n_a = L.shape
    valid = np.isfinite(L)
    rows = np.broadcast_to(np.arange(n_z)[:, None], L.shape)
    above = np.maximum.accumulate(np.where(valid, rows, -1), axis=0)
    below = np.minimum.accumulate(np.where(valid, rows, n_z)[::-1], axis=0)[::-1]
    fill = ~valid & (above >= 0) & (below < n_z)
    cols = np.broadcast_to(np.arange(n_a)[None, :], L.shape)
    a_idx, b_idx = np.where(fill, above, 0), np.where(fill, below, 0)
    za, zb = z[a_idx], z[b_idx]
    t = np.where(fill, (z[:, None] - za) / np.where(fill, zb - za, 1.0), 0.0)
    La, Lb = L[a_idx, cols], L[b_idx, cols]
    out = np.where(valid, L, np.where(fill, (1 - t) * La + t * Lb, np.nan))
    rnd = np.where(valid, sr, np.where(fill, np.hypot((1 - t) * sr[a_idx, cols], t * sr[b_idx, cols]), np.nan))
    sys = np.where(valid, ss, np.where(fill, (1 - t) * ss[a_idx, cols] + t * ss[b_idx, cols], np.nan))
    # curvature of the quadratic fit over the m rows starting at each row (NaN where any is not calibrated)
    step = float(z[1] - z[0]) if n_z > 1 else np.pi
    m = max(3, int(round(np.radians(fit_span_deg) / step)))
    w = _curvature_filter(m, step)
    curv = np.full(L.shape, np.nan)
    curv_sigma = np.full(L.shape, np.nan)
    if n_z >= m:
        windows = np.lib.stride_tricks.sliding_window_view(L, m, axis=0)            # (n_z - m + 1, n_a, m)
        swin = np.lib.stride_tricks.sliding_window_view(sr, m, axis=0)
        curv[: n_z - m + 1] = windows @ w
        curv_sigma[: n_z - m + 1] = np.sqrt((swin ** 2) @ (w ** 2))
    bound = np.abs(curv) + curv_sigma                                                  # NaN where unknown
    start_above = a_idx - (m - 1)
    k_above = np.where(start_above >= 0, bound[np.clip(start_above, 0, n_z - 1), cols], np.nan)
    k_below = bound[b_idx, cols]
    k = np.fmax(k_above, k_below)
    known = fill & np.isfinite(k)
    model = np.where(known, (z[:, None] - za) * (zb - z[:, None]) / 2.0 * np.where(known, k, 0.0), 0.0)
    fallback = fill & ~np.isfinite(k)
    model = np.where(fallback, np.abs(Lb - La) / 2.0, model)
    flag = np.where(valid, FLAG_MEASURED, np.where(fill, FLAG_FILLED, FLAG_EMPTY)).astype(np.int8)
    return Filled(out, rnd, sys, np.where(flag == FLAG_EMPTY, np.nan, model), flag,
                  np.where(fill, above, -1), np.where(fill, below, -1), t, int(fallback.sum()))
