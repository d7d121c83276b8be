"""The whole sphere: cells no lens calibrates filled by interpolation in zenith angle, with a model uncertainty.

A dual-fisheye camera leaves a band of the sphere unseen between its two
lenses' calibrated fields (about 80 to 100 degrees zenith angle in air, 70 to
110 in water). Model, per azimuth column of the grid (in the camera's frame,
where the band is a band of rows): each run of empty cells between a
calibrated cell above (zenith angle z_a, radiance L_a) and one below (z_b, L_b)
takes the linear interpolation in zenith angle

    L(z) = (1 - t) L_a + t L_b,   t = (z - z_a) / (z_b - z_a).

Its model uncertainty is the error bound of linear interpolation,

    sigma_model(z) = (z - z_a)(z_b - z) / 2 * K(z),

where K(z) bounds |d^2 L / dz^2| (per rad^2) in the run from the quadratic
fits to the last calibrated rows on either side (``fill_fit_span_deg`` of
zenith angle, at least three rows): the larger of each side's edge curvature
and that curvature carried on to z at the rate it changes between the edge
window and the next one out (so that a maximum inside the run, as the
zenith's in water, is not missed), each with its standard error from the
cells' random noise. It holds where the curvature changes no faster inside
the run than it does at its edges, as in a scattered light field; a run with
fewer than three calibrated rows on both sides takes half the step across it,
|L_b - L_a| / 2, and is counted. A column continues over each pole into the
opposite column (azimuth + 180), the great circle of the meridian, so that an
empty cap about the zenith or the nadir (the few cells near a lens's axis a
coarse image leaves without a pixel) is interpolated across the pole in the
same way; only a grid with an odd number of azimuths, which has no opposite
column, leaves such a cap empty (its integrals are NaN).

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
    above: np.ndarray             # filled cells: flat index (row * n_azimuth + column) of the edge cell above
    below: np.ndarray             # filled cells: flat index of the edge cell below (else -1 for both)
    t: np.ndarray                 # filled cells: weight of the cell below
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
    out = np.where(valid, L, np.where(fill, (1 - t) * La + t * Lb, np.nan))
    rnd = np.where(valid, sr, np.where(fill, np.hypot((1 - t) * sr[a_idx, colgrid], t * sr[b_idx, colgrid]), np.nan))
    sys = np.where(valid, ss, np.where(fill, (1 - t) * ss[a_idx, colgrid] + t * ss[b_idx, colgrid], np.nan))
    # curvature of the quadratic fit over the m rows starting at each row (NaN where any is not calibrated),
    # and its change from one window to the next (rows i + 1 ... i + m against i ... i + m - 1)
    step = float(z0[1] - z0[0]) if n_z > 1 else np.pi
    m = max(3, int(round(np.radians(fit_span_deg) / step)))
    w = _curvature_filter(m, step)
    wd = np.concatenate([[0.0], w]) - np.concatenate([w, [0.0]])
    curv, curv_sigma = _filtered(L, sr, w)
    dcurv, dcurv_sigma = _filtered(L, sr, wd)
    r = np.arange(n_s)[:, None]
    k = np.full(L.shape, np.nan)
    for edge, next_window, change, centre in ((a_idx - (m - 1), a_idx - m, 1.0, a_idx - (m - 1) / 2),
                                               (b_idx, b_idx + 1, -1.0, b_idx + (m - 1) / 2)):
        # this side's edge window, the one beyond it and the distance (rows) from the edge window's centre
        c_edge, s_edge = _at(curv, edge, colgrid), _at(curv_sigma, edge, colgrid)
        slope = change * _at(dcurv, next_window if change > 0 else edge, colgrid)
        s_slope = _at(dcurv_sigma, next_window if change > 0 else edge, colgrid)
        d = np.abs(r - centre)
        k = np.fmax(k, np.abs(c_edge) + s_edge)
        k = np.fmax(k, np.abs(c_edge + slope * d) + s_edge + s_slope * d)
    known = fill & np.isfinite(k)
    model = np.where(known, (z[:, None] - za) * (zb - z[:, None]) / 2.0 * np.where(known, k, 0.0), 0.0)
    fallback = fill & ~np.isfinite(k)
    model = np.where(fallback, np.abs(Lb - La) / 2.0, model)
    # the grid itself: the middle third of the meridian
    mid = slice(n_z, 2 * n_z)
    fill_m, valid_m = fill[mid], valid[mid]
    flag = np.where(valid_m, FLAG_MEASURED, np.where(fill_m, FLAG_FILLED, FLAG_EMPTY)).astype(np.int8)
    return Filled(out[mid], rnd[mid], sys[mid], np.where(flag == FLAG_EMPTY, np.nan, model[mid]), flag,
                  np.where(fill_m, index[a_idx, colgrid][mid], -1), np.where(fill_m, index[b_idx, colgrid][mid], -1),
                  t[mid], int(fallback[mid].sum()))
