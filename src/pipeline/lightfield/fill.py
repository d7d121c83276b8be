"""The whole sphere: cells no lens calibrates filled by interpolation in zenith angle, with a model uncertainty.

A dual-fisheye camera leaves a band of the sphere unseen between its two
lenses' calibrated fields (about 80 to 100 degrees zenith angle in air, 70 to
110 in water). Model, per azimuth column of the grid (in the camera's frame,
where the band is a band of rows): each run of empty cells between a
calibrated cell above (zenith angle z_a, radiance L_a) and one below (z_b, L_b)
takes the linear interpolation of ln L in zenith angle (where L_a and L_b are
both positive; else of L, with the fallback sigma below)

    ln L(z) = (1 - t) ln L_a + t ln L_b,   t = (z - z_a) / (z_b - z_a).

Why ln L: a light field falls off near exponentially with zenith angle across
the horizon (the diffuse field exp(k cos z) in water, 10 to 1 over the band),
which the linear interpolation of L overestimates. Measured on the water truth
test (tests/lightfield/test_underwater_truth.py, 20 seeds x 3 bands), without
any fill sigma in the statement: the mean deviation of E_u over its other
sigmas went from +2.94 (linear in L) to +0.58 (linear in ln L), that of mu_u
from -2.02 to +0.04. A cubic Hermite in L through the edges' slopes was not
taken: its slopes come from windows that reach Snell's window's edge and the
sun, and a filled cell would no longer be a map of two measured cells.

Its model uncertainty is the error of linear interpolation of ln L,

    sigma_model(z) = L(z) (z - z_a)(z_b - z) / 2 * K,

where K is the larger over the two sides of |d^2 ln L / dz^2| (per rad^2)
from the quadratic fit to ln L over the last calibrated rows on that side
(``fill_fit_span_deg`` of zenith angle, at least three rows), taken as the
larger of the edge window's curvature and that curvature carried on to the
run's far edge at the rate it changes between the edge window and the next
one out (so that a maximum inside the run, as the zenith's in water, is
covered), each with its standard error from the cells' random noise. A side's
window is not used where its curvature changes by more than its own size (plus
three standard errors) from one row to the next: a sharp feature (Snell's
window's edge, the sun) and not the smooth field the model is for. In ln L a
smooth field's curvature is small and varies little (k cos z for the diffuse
field), so that K is close to the curvature the run actually has: measured on
the air test's field exp(2.5 cos z)(1 + 0.2 sin z cos phi) (2 degree grid, band
70 to 110 degrees and the zenith cap below 6 degrees) the ratio of error to
sigma_model per cell has median 0.15 and maximum 0.43 in the band, 0.96 and
0.97 in the cap, where the curvature (-2.5) is the run's own. A run with no
usable window on either side, or an edge that is not positive, takes half the
step across it, |L_b - L_a| / 2, and is counted.

A column continues over each pole into the opposite column (azimuth + 180),
the great circle of the meridian, so that an empty cap about the zenith or
the nadir (the few cells near a lens's axis a coarse image leaves without a
pixel) is interpolated across the pole in the same way; only a grid with an
odd number of azimuths, which has no opposite column, leaves such a cap empty
(its integrals are NaN).

The filled cells' random noise is that of the two edge cells through the
derivatives of the interpolation, dL/dL_a = (1 - t) L / L_a and dL/dL_b =
t L / L_b (first order), so that a filled cell is a linear map of measured
cells (:class:`Filled` keeps the map), and the integrals propagate it; a
systematic sigma proportional to L goes through it exactly.
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
    above: np.ndarray             # filled cells: flat index (row * n_azimuth + column) of the edge cell above
    below: np.ndarray             # filled cells: flat index of the edge cell below (else -1 for both)
    weight_above: np.ndarray      # filled cells: d(filled value) / d(edge cell above)
    weight_below: np.ndarray      # filled cells: d(filled value) / d(edge cell below)
    fallback_cells: int           # filled cells whose model sigma is the fallback half step


def _curvature_filter(n_rows: int, step_rad: float) -> np.ndarray:
    """Weights w so that sum_k w_k y_k is the second derivative of the least-squares quadratic through
    ``n_rows`` equally spaced values ``step_rad`` apart."""
    x = (np.arange(n_rows) - (n_rows - 1) / 2) * step_rad
    design = np.stack([np.ones_like(x), x, x ** 2], axis=1)
    return 2.0 * np.linalg.pinv(design)[2]


def _filtered(values: np.ndarray, sigma: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """sum_k w_k v[i + k] per start row i and its standard deviation from the independent sigmas; NaN where
    the window leaves the array or holds a NaN."""
    n, m = values.shape[0], weights.size
    out, out_sigma = np.full(values.shape, np.nan), np.full(values.shape, np.nan)
    if n >= m:
        out[: n - m + 1] = np.lib.stride_tricks.sliding_window_view(values, m, axis=0) @ weights
        out_sigma[: n - m + 1] = np.sqrt(np.lib.stride_tricks.sliding_window_view(sigma ** 2, m, axis=0)
                                         @ weights ** 2)
    return out, out_sigma


def _at(array: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """array[rows, cols], NaN where a row is outside the array."""
    inside = (rows >= 0) & (rows < array.shape[0])
    return np.where(inside, array[np.clip(rows, 0, array.shape[0] - 1).astype(int), cols], np.nan)


def _log_curvature(L, sigma, a_idx, b_idx, colgrid, step: float, fit_span_deg: float) -> np.ndarray:
    """Per meridian cell of a run: the model's bound K on |d^2 ln L / dz^2| (per rad^2) from the quadratic fits to
    ln L of the edge windows (NaN where neither side's window is smooth or calibrated; see the module docstring).

    Parameters
    ----------
    L, sigma : numpy.ndarray
        The meridian's radiance and random sigma, shape ``(3 n_zenith, n_azimuth)``.
    a_idx, b_idx : numpy.ndarray
        Per cell: the meridian row of the run's calibrated edge cell above and below.
    colgrid : numpy.ndarray
        Per cell: its column.
    step : float
        The grid's zenith step, rad.
    fit_span_deg : float
        The zenith span of the quadratic fits, degree (at least three rows).

    Returns
    -------
    numpy.ndarray
        K per cell, same shape as ``L``.
    """
    m = max(3, int(round(np.radians(fit_span_deg) / step)))
    w = _curvature_filter(m, step)
    wd = np.concatenate([[0.0], w]) - np.concatenate([w, [0.0]])
    positive = L > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        log_l = np.where(positive, np.log(np.where(positive, L, 1.0)), np.nan)
        log_sigma = np.where(positive, sigma / np.where(positive, L, 1.0), 0.0)
    curv, curv_sigma = _filtered(log_l, log_sigma, w)
    dcurv, dcurv_sigma = _filtered(log_l, log_sigma, wd)
    k = np.full(L.shape, np.nan)
    for edge, next_window, change, centre, far_edge in ((a_idx - (m - 1), a_idx - m, 1.0, a_idx - (m - 1) / 2, b_idx),
                                                         (b_idx, b_idx + 1, -1.0, b_idx + (m - 1) / 2, a_idx)):
        # this side's edge window, the change of curvature to the next window out (per row) and the distance
        # (rows) from the edge window's centre to the run's far edge
        c_edge, s_edge = _at(curv, edge, colgrid), _at(curv_sigma, edge, colgrid)
        window = next_window if change > 0 else edge
        slope, s_slope = change * _at(dcurv, window, colgrid), _at(dcurv_sigma, window, colgrid)
        far = np.abs(far_edge - centre)
        smooth = np.abs(slope) <= np.abs(c_edge) + 3.0 * s_slope
        side = np.fmax(np.abs(c_edge + slope * far) + np.hypot(s_edge, s_slope * far), np.abs(c_edge) + s_edge)
        k = np.fmax(k, np.where(smooth, side, np.nan))
    return k


def _meridian(values: np.ndarray) -> np.ndarray:
    """(3 n_zenith, n_azimuth): each column continued over both poles by the opposite column (azimuth + 180),
    reversed: the great circle through the poles, as one coordinate s = -z', z, 360 - z' (NaN beyond the
    poles when the grid has no opposite column, an odd number of azimuths)."""
    n_z, n_a = values.shape
    if n_a % 2:
        beyond = np.full_like(values, np.nan)
    else:
        beyond = np.roll(values, n_a // 2, axis=1)[::-1]
    return np.concatenate([beyond, values, beyond], axis=0)


def fill_between_lenses(radiance, random_sigma, systematic_sigma, zenith_deg, fit_span_deg: float) -> Filled:
    """Fill the empty cells of one frame and band's camera-frame grid by the model above.

    Each azimuth column is taken with its opposite column beyond the poles (the meridian's great circle), so that
    an empty cap about a pole is interpolated across it.

    Parameters
    ----------
    radiance : numpy.ndarray
        Cell radiance, W m-2 sr-1 nm-1, shape ``(n_zenith, n_azimuth)``; NaN where empty.
    random_sigma : numpy.ndarray
        Its random standard uncertainty, same unit and shape.
    systematic_sigma : numpy.ndarray
        Its systematic standard uncertainty, same unit and shape.
    zenith_deg : numpy.ndarray
        The cell centres' zenith angles (regular), degree, shape ``(n_zenith,)``.
    fit_span_deg : float
        The zenith span of the quadratic fits of the curvature, degree.

    Returns
    -------
    Filled
        The filled grid, its sigmas (the interpolation's model sigma apart), the flags and the interpolation map.
    """
    L0 = np.asarray(radiance, float)
    n_z, n_a = L0.shape
    z0 = np.radians(np.asarray(zenith_deg, float))
    # the meridian coordinate and the flat index of each of its cells in the grid
    z = np.concatenate([-z0[::-1], z0, 2 * np.pi - z0[::-1]])
    cols = np.arange(n_a)
    opposite = (cols + n_a // 2) % n_a
    flat = np.arange(n_z * n_a).reshape(n_z, n_a)
    index = np.concatenate([flat[::-1][:, opposite], flat, flat[::-1][:, opposite]], axis=0)
    L = _meridian(L0)
    sr = np.nan_to_num(_meridian(np.asarray(random_sigma, float)))
    ss = np.nan_to_num(_meridian(np.asarray(systematic_sigma, float)))
    n_s = L.shape[0]
    valid = np.isfinite(L)
    rows = np.broadcast_to(np.arange(n_s)[:, None], L.shape)
    above = np.maximum.accumulate(np.where(valid, rows, -1), axis=0)
    below = np.minimum.accumulate(np.where(valid, rows, n_s)[::-1], axis=0)[::-1]
    fill = ~valid & (above >= 0) & (below < n_s)
    colgrid = np.broadcast_to(cols[None, :], L.shape)
    a_idx, b_idx = np.where(fill, above, 0), np.where(fill, below, 0)
    za, zb = z[a_idx], z[b_idx]
    t = np.where(fill, (z[:, None] - za) / np.where(fill, zb - za, 1.0), 0.0)
    La, Lb = L[a_idx, colgrid], L[b_idx, colgrid]
    # log-linear interpolation where both edges are positive (else linear); weights dL/dL_a, dL/dL_b
    positive = fill & (La > 0) & (Lb > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        geo = np.exp((1 - t) * np.log(np.where(positive, La, 1.0)) + t * np.log(np.where(positive, Lb, 1.0)))
        lin = (1 - t) * La + t * Lb
        value = np.where(positive, geo, lin)
        wa = np.where(positive, (1 - t) * geo / np.where(positive, La, 1.0), 1 - t)
        wb = np.where(positive, t * geo / np.where(positive, Lb, 1.0), t)
    out = np.where(valid, L, np.where(fill, value, np.nan))
    rnd = np.where(valid, sr, np.where(fill, np.hypot(wa * sr[a_idx, colgrid], wb * sr[b_idx, colgrid]), np.nan))
    sys = np.where(valid, ss, np.where(fill, wa * ss[a_idx, colgrid] + wb * ss[b_idx, colgrid], np.nan))
    step = float(z0[1] - z0[0]) if n_z > 1 else np.pi
    k = _log_curvature(L, sr, a_idx, b_idx, colgrid, step, fit_span_deg)
    known = positive & np.isfinite(k)
    model = np.where(known, value * (z[:, None] - za) * (zb - z[:, None]) / 2.0 * np.where(known, k, 0.0), 0.0)
    fallback = fill & ~known
    model = np.where(fallback, np.abs(Lb - La) / 2.0, model)
    # the grid itself: the middle third of the meridian
    mid = slice(n_z, 2 * n_z)
    fill_m, valid_m = fill[mid], valid[mid]
    flag = np.where(valid_m, FLAG_MEASURED, np.where(fill_m, FLAG_FILLED, FLAG_EMPTY)).astype(np.int8)
    return Filled(out[mid], rnd[mid], sys[mid], np.where(flag == FLAG_EMPTY, np.nan, model[mid]), flag,
                  np.where(fill_m, index[a_idx, colgrid][mid], -1), np.where(fill_m, index[b_idx, colgrid][mid], -1),
                  wa[mid], wb[mid], int(fallback[mid].sum()))
