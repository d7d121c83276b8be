"""Quadrature over a regular zenith/azimuth sphere grid: exact cell solid angles and cap weights.

A cell spans zenith angles [z0, z1] and azimuths [a0, a1] (radians). Its solid
angle is exactly (cos z0 - cos z1)(a1 - a0), and the integral of the unit
direction n = (sin z cos a, sin z sin a, cos z) over it is, in closed form,

    V_x = [z/2 - sin(2z)/4] [sin a],  V_y = [z/2 - sin(2z)/4] [-cos a],  V_z = [sin^2 z / 2] (a1 - a0)

(each bracket taken between the cell's edges). The radiance of a cell is taken
as constant over it (the mean of the pixels binned into it, or the value at its
centre for a grid made by hand), so every light-field integral is a weighted
sum of the cells' radiances with weights that are exact integrals over each
cell of the part inside a spherical cap {n : n . u > c} (a hemisphere when
c = 0, a narrow cone around the zenith or nadir otherwise):

    W0 = int_{cell & cap} dOmega,        W1 = int_{cell & cap} (n . u) dOmega

A cell wholly inside the cap has W0 = solid angle and W1 = u . V exactly; a
cell the cap's edge crosses is divided into k x k sub-cells, each with its own
exact solid angle and V, counted by whether its centre lies in the cap (the
only approximation of the weights, of order of a sub-cell along the edge).

The error of taking the radiance constant over each cell is estimated by the
same sums on the grid of half resolution (2 x 2 cells merged, their radiance
the solid-angle-weighted mean): for this second-order rule the half-resolution
sum errs about four times as much as the full one, so their difference is
about three times the full grid's error. A grid whose values are samples at
the cell centres (one made by hand from a formula) rather than cell means (the
mean of the pixels binned into a cell, as ``apply`` writes) is first turned
into cell means by :func:`cell_means_from_centres` (the local quadratic
averaged over the cell), and that correction's size is added to the stated
quadrature error.
"""

from __future__ import annotations

import numpy as np

__all__ = ["GridEdges", "cell_solid_angles", "cell_direction_integrals", "cell_centre_directions", "cap_weights",
           "coarsen", "unit_vector", "cell_means_from_centres"]


class GridEdges:
    """Cell edges (radians) of a zenith/azimuth grid covering the sphere: zenith 0 to pi, azimuth 0 to 2 pi."""

    def __init__(self, zenith_edges_rad, azimuth_edges_rad):
        self.zenith = np.asarray(zenith_edges_rad, float)
        self.azimuth = np.asarray(azimuth_edges_rad, float)
        self.n_zenith, self.n_azimuth = self.zenith.size - 1, self.azimuth.size - 1

    @classmethod
    def regular(cls, n_zenith: int, n_azimuth: int) -> GridEdges:
        """The regular grid of ``n_zenith`` by ``n_azimuth`` cells.

        Parameters
        ----------
        n_zenith : int
            Cells in zenith angle, from 0 to pi.
        n_azimuth : int
            Cells in azimuth, from 0 to 2 pi.

        Returns
        -------
        GridEdges
            The grid.
        """
        return cls(np.linspace(0.0, np.pi, int(n_zenith) + 1), np.linspace(0.0, 2.0 * np.pi, int(n_azimuth) + 1))

    def halved(self) -> GridEdges:
        """The grid of half resolution: every other edge (an odd last row or column stays one cell wide).

        Returns
        -------
        GridEdges
            The grid of half resolution.
        """
        def every_other(e):
            kept = e[::2]
            return kept if kept[-1] == e[-1] else np.append(kept, e[-1])
        return GridEdges(every_other(self.zenith), every_other(self.azimuth))

    @property
    def key(self) -> tuple:
        return (self.zenith.tobytes(), self.azimuth.tobytes())

    @property
    def shape(self) -> tuple[int, int]:
        return self.n_zenith, self.n_azimuth

    @property
    def zenith_centres_deg(self) -> np.ndarray:
        return np.degrees(0.5 * (self.zenith[:-1] + self.zenith[1:]))

    @property
    def azimuth_centres_deg(self) -> np.ndarray:
        return np.degrees(0.5 * (self.azimuth[:-1] + self.azimuth[1:]))


def unit_vector(zenith_rad, azimuth_rad) -> np.ndarray:
    """(..., 3) unit vectors (sin z cos a, sin z sin a, cos z) of the directions.

    Parameters
    ----------
    zenith_rad : numpy.ndarray
        Zenith angles, radians.
    azimuth_rad : numpy.ndarray
        Azimuths, radians (broadcast with ``zenith_rad``).

    Returns
    -------
    numpy.ndarray
        Unit vectors, shape ``(..., 3)``.
    """
    z, a = np.asarray(zenith_rad, float), np.asarray(azimuth_rad, float)
    return np.stack(np.broadcast_arrays(np.sin(z) * np.cos(a), np.sin(z) * np.sin(a), np.cos(z)), axis=-1)


def _omega(z0, z1, a0, a1):
    return (np.cos(z0) - np.cos(z1)) * (a1 - a0)


def _vector(z0, z1, a0, a1):
    zz = (z1 / 2 - np.sin(2 * z1) / 4) - (z0 / 2 - np.sin(2 * z0) / 4)
    return np.stack(np.broadcast_arrays(zz * (np.sin(a1) - np.sin(a0)), zz * (np.cos(a0) - np.cos(a1)),
                                        (np.sin(z1) ** 2 - np.sin(z0) ** 2) / 2 * (a1 - a0)), axis=-1)


def cell_solid_angles(edges: GridEdges) -> np.ndarray:
    """(n_zenith, n_azimuth) exact solid angle of every cell (sr); they sum to 4 pi.

    Parameters
    ----------
    edges : GridEdges
        The grid's cell edges, radians.

    Returns
    -------
    numpy.ndarray
        Solid angle of each cell, sr, shape ``(n_zenith, n_azimuth)``.
    """
    z, a = edges.zenith, edges.azimuth
    return _omega(z[:-1, None], z[1:, None], a[None, :-1], a[None, 1:])


def cell_direction_integrals(edges: GridEdges) -> np.ndarray:
    """(n_zenith, n_azimuth, 3) exact integral of the unit direction over every cell (sr).

    Parameters
    ----------
    edges : GridEdges
        The grid's cell edges, radians.

    Returns
    -------
    numpy.ndarray
        Integral V of the unit direction over each cell, sr, shape ``(n_zenith, n_azimuth, 3)``.
    """
    z, a = edges.zenith, edges.azimuth
    return _vector(z[:-1, None], z[1:, None], a[None, :-1], a[None, 1:])


def cell_centre_directions(edges: GridEdges) -> np.ndarray:
    """(n_zenith, n_azimuth, 3) unit vectors of the cell centres (mid zenith, mid azimuth).

    Parameters
    ----------
    edges : GridEdges
        The grid's cell edges, radians.

    Returns
    -------
    numpy.ndarray
        Unit vectors, shape ``(n_zenith, n_azimuth, 3)``.
    """
    z, a = edges.zenith, edges.azimuth
    return unit_vector(0.5 * (z[:-1, None] + z[1:, None]), 0.5 * (a[None, :-1] + a[None, 1:]))


def _cell_radius(edges: GridEdges) -> np.ndarray:
    """(n_zenith, n_azimuth) largest angle (rad) between a cell's centre and its corners and edge midpoints."""
    z, a = edges.zenith, edges.azimuth
    zc, ac = 0.5 * (z[:-1] + z[1:]), 0.5 * (a[:-1] + a[1:])
    centre = unit_vector(zc[:, None], ac[None, :])
    radius = np.zeros(edges.shape)
    for zz in (z[:-1], zc, z[1:]):
        for aa in (a[:-1], ac, a[1:]):
            point = unit_vector(zz[:, None], aa[None, :])
            radius = np.maximum(radius, np.arccos(np.clip(np.sum(point * centre, axis=-1), -1.0, 1.0)))
    return radius


_RADIUS_CACHE: dict = {}


def cap_weights(edges: GridEdges, axis, cos_half_angle: float, subcells: int) -> tuple[np.ndarray, np.ndarray]:
    """(W0, W1): per cell, the solid angle inside the cap {n . axis > cos_half_angle} and the integral of n . axis there.

    ``axis`` a unit 3-vector in the grid's own frame; ``subcells`` the k of the k x k division of the cells
    the cap's edge crosses.

    Parameters
    ----------
    edges : GridEdges
        The grid's cell edges, radians.
    axis : array_like
        The cap's axis u, a 3-vector in the grid's frame (normalised here).
    cos_half_angle : float
        Cosine c of the cap's half angle (0: a hemisphere).
    subcells : int
        k of the k x k division of the cells the cap's edge crosses.

    Returns
    -------
    W0 : numpy.ndarray
        Solid angle of each cell inside the cap, sr, shape ``(n_zenith, n_azimuth)``.
    W1 : numpy.ndarray
        Integral of n . u over each cell's part inside the cap, sr, shape ``(n_zenith, n_azimuth)``.
    """
    u = np.asarray(axis, float)
    u = u / np.linalg.norm(u)
    omega, vec = cell_solid_angles(edges), cell_direction_integrals(edges)
    key = edges.key
    if key not in _RADIUS_CACHE:
        _RADIUS_CACHE[key] = _cell_radius(edges)
    radius = _RADIUS_CACHE[key]
    centre = cell_centre_directions(edges)
    angle = np.arccos(np.clip(centre @ u, -1.0, 1.0))
    edge_angle = np.arccos(np.clip(cos_half_angle, -1.0, 1.0))
    # a margin of 1e-9 rad keeps a cell whose corner lies on the cap's edge among those divided
    inside = angle + radius < edge_angle - 1e-9
    crossed = np.abs(angle - edge_angle) <= radius + 1e-9
    w0 = np.where(inside, omega, 0.0)
    w1 = np.where(inside, vec @ u, 0.0)
    iz, ia = np.nonzero(crossed & ~inside)
    if iz.size:
        k = int(subcells)
        frac = np.arange(k + 1) / k
        z0, z1 = edges.zenith[iz], edges.zenith[iz + 1]
        a0, a1 = edges.azimuth[ia], edges.azimuth[ia + 1]
        zs = z0[:, None] + (z1 - z0)[:, None] * frac[None, :]          # (cells, k + 1)
        as_ = a0[:, None] + (a1 - a0)[:, None] * frac[None, :]
        zlo, zhi = zs[:, :-1, None], zs[:, 1:, None]                      # (cells, k, 1)
        alo, ahi = as_[:, None, :-1], as_[:, None, 1:]                    # (cells, 1, k)
        sub_omega = _omega(zlo, zhi, alo, ahi)                            # (cells, k, k)
        sub_vec = _vector(zlo, zhi, alo, ahi)                             # (cells, k, k, 3)
        sub_centre = unit_vector(0.5 * (zlo + zhi), 0.5 * (alo + ahi))
        member = (sub_centre @ u) > cos_half_angle
        w0[iz, ia] = np.sum(np.where(member, sub_omega, 0.0), axis=(1, 2))
        w1[iz, ia] = np.sum(np.where(member, sub_vec @ u, 0.0), axis=(1, 2))
    return w0, w1


def coarsen(values: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """``values`` on the grid of half resolution: 2 x 2 cells merged, the solid-angle-weighted mean (an odd last
    row or column is merged alone). NaN stays NaN.

    Parameters
    ----------
    values : numpy.ndarray
        Cell values, shape ``(..., n_zenith, n_azimuth)``.
    omega : numpy.ndarray
        Cell solid angles, sr, shape ``(n_zenith, n_azimuth)`` (:func:`cell_solid_angles`).

    Returns
    -------
    numpy.ndarray
        The merged values, shape ``(..., ceil(n_zenith / 2), ceil(n_azimuth / 2))``, in the unit of ``values``.
    """
    n_z, n_a = omega.shape
    rz, ra = np.arange(n_z) // 2, np.arange(n_a) // 2
    weighted = values * omega
    out_shape = values.shape[:-2] + (rz[-1] + 1, ra[-1] + 1)
    total = np.zeros(out_shape)
    weight = np.zeros(out_shape[-2:])
    np.add.at(weight, (rz[:, None], ra[None, :]), omega)
    acc = np.zeros(values.shape[:-2] + (rz[-1] + 1, n_a))
    for i in range(n_z):
        acc[..., rz[i], :] += weighted[..., i, :]
    for j in range(n_a):
        total[..., ra[j]] += acc[..., j]
    return total / weight


#: 12-point Gauss-Legendre nodes and weights on [-1, 1] (exact for the moments' smooth integrands)
_GAUSS = np.polynomial.legendre.leggauss(12)
_MOMENTS_CACHE: dict = {}


def _zenith_moments(edges: GridEdges) -> tuple[np.ndarray, np.ndarray]:
    """Per row, the solid-angle means of (z - z_c) and (z - z_c)^2 over the cell (rad, rad^2)."""
    if edges.key not in _MOMENTS_CACHE:
        _MOMENTS_CACHE.clear()
        _MOMENTS_CACHE[edges.key] = _moments(edges)
    return _MOMENTS_CACHE[edges.key]


def _moments(edges: GridEdges) -> tuple[np.ndarray, np.ndarray]:
    nodes, w = _GAUSS
    z0, z1 = edges.zenith[:-1, None], edges.zenith[1:, None]
    zc = 0.5 * (z0 + z1)
    z = zc + 0.5 * (z1 - z0) * nodes[None, :]
    weight = w[None, :] * np.sin(z)
    norm = weight.sum(axis=1)
    return (((z - zc) * weight).sum(axis=1) / norm, (((z - zc) ** 2) * weight).sum(axis=1) / norm)


def cell_means_from_centres(values: np.ndarray, edges: GridEdges) -> np.ndarray:
    """Cell means (solid-angle weighted) of a field sampled at the cell centres of a regular grid.

    Per cell, the local quadratic in zenith angle through the cell and its neighbours (one-sided at the poles)
    and in azimuth (periodic) averaged over the cell: L + L'_z <z - z_c> + L''_z <(z - z_c)^2> / 2
    + L''_a h_a^2 / 24. Where a neighbour is NaN the cell is left as it is.

    Parameters
    ----------
    values : numpy.ndarray
        The field at the cell centres (e.g. radiance, W m-2 sr-1 nm-1), shape ``(..., n_zenith, n_azimuth)``.
    edges : GridEdges
        The grid's cell edges, radians.
        Regular in zenith angle.

    Returns
    -------
    numpy.ndarray
        The cell means, of the shape and unit of ``values`` (a copy unchanged for fewer than three zenith rows).
    """
    L = np.asarray(values, float)
    n_z = L.shape[-2]
    if n_z < 3:
        return L.copy()
    hz = edges.zenith[1] - edges.zenith[0]
    m1, m2 = _zenith_moments(edges)
    up, dn = np.roll(L, 1, axis=-2), np.roll(L, -1, axis=-2)
    d1 = (dn - up) / (2 * hz)
    d2 = (dn - 2 * L + up) / hz ** 2
    # first and last rows: the quadratic through the row and the next two (previous two)
    d1[..., 0, :] = (-3 * L[..., 0, :] + 4 * L[..., 1, :] - L[..., 2, :]) / (2 * hz)
    d2[..., 0, :] = (L[..., 0, :] - 2 * L[..., 1, :] + L[..., 2, :]) / hz ** 2
    d1[..., -1, :] = (3 * L[..., -1, :] - 4 * L[..., -2, :] + L[..., -3, :]) / (2 * hz)
    d2[..., -1, :] = (L[..., -1, :] - 2 * L[..., -2, :] + L[..., -3, :]) / hz ** 2
    dz = d1 * m1[:, None] + d2 * m2[:, None] / 2
    da = (np.roll(L, 1, axis=-1) - 2 * L + np.roll(L, -1, axis=-1)) / 24.0
    delta = dz + da
    return np.where(np.isfinite(delta), L + delta, L)
