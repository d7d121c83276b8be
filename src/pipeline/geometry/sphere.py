"""A lens pixel's direction on the full sphere of a back-to-back (dual-fisheye) camera, and its grid cell.

Convention: the lens named ``zenith_lens`` looks at the zenith, its pixel
(theta, phi) is zenith angle theta and azimuth phi; the other lens looks the
opposite way (nadir): zenith angle 180 - theta and azimuth -phi (mirrored, as
a back-to-back lens sees its sensor's x axis reversed), both mod 360. The
grid is regular in zenith angle and azimuth, cells of ``grid_deg`` degrees,
numbered row-major (zenith first).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ZENITH_LENS", "sphere_coordinates", "sphere_cells", "grid_shape", "wrap_degrees"]

ZENITH_LENS = "close"


def grid_shape(grid_deg: float) -> tuple[int, int]:
    """(zenith, azimuth) cells of the grid: 180 / grid_deg by 360 / grid_deg.

    Parameters
    ----------
    grid_deg : float
        Cell size in zenith angle and azimuth, degree.

    Returns
    -------
    tuple of int
        (number of zenith rows, number of azimuth columns).
    """
    return int(round(180.0 / grid_deg)), int(round(360.0 / grid_deg))


def sphere_coordinates(theta_deg, phi_deg, looks_up: bool, out=None):
    """Zenith angle and azimuth (deg) of a lens pixel's direction, by the sphere convention of this module.

    With ``out = (zenith, azimuth)`` (arrays of the maps' shape and float type) they are computed there.

    Parameters
    ----------
    theta_deg : numpy.ndarray
        Angle of each pixel from its lens's optical axis, degree.
    phi_deg : numpy.ndarray
        Azimuth of each pixel in its lens's camera frame, degree.
    looks_up : bool
        True for the lens that looks at the zenith (``ZENITH_LENS``), False for the one that looks at the nadir.
    out : tuple of numpy.ndarray, optional
        (zenith, azimuth) arrays to write into.

    Returns
    -------
    zenith : numpy.ndarray
        Zenith angle, degree in [0, 180] (for the zenith lens, ``theta_deg`` itself unless ``out`` is given).
    azimuth : numpy.ndarray
        Azimuth, degree in [0, 360).
    """
    theta, phi = np.asarray(theta_deg), np.asarray(phi_deg)
    # float32 maps stay float32 (as the bundle's are); anything else becomes float64
    theta = theta if theta.dtype.kind == "f" else theta.astype(float)
    phi = phi if phi.dtype.kind == "f" else phi.astype(float)
    zen, azi = (None, None) if out is None else out
    if looks_up:
        if zen is None:
            zen = theta
        else:
            np.copyto(zen, theta)
        return zen, wrap_degrees(phi, out=azi)
    zen = np.subtract(180.0, theta, out=zen)
    azi = np.negative(phi, out=azi)
    return zen, wrap_degrees(azi, out=azi)


def wrap_degrees(angle_deg, out=None):
    """``np.mod(angle_deg, 360)``, the same numbers, without its division where every angle is within one turn.

    For |x| < 360 the floating-point remainder is x itself for x > 0, x + 360
    (rounded as NumPy's remainder rounds it) for x < 0 and +0 for x = +-0:
    that is x + 360 [x < 0] (x + 0 turns -0 into +0), three vectorised passes
    instead of a remainder per element. Other angles go through ``np.mod``.
    NaN stays NaN. ``out`` may be ``angle_deg`` itself.

    Parameters
    ----------
    angle_deg : numpy.ndarray
        Angles, degree.
    out : numpy.ndarray, optional
        Array to write into.

    Returns
    -------
    numpy.ndarray
        The angles modulo 360, degree in [0, 360).
    """
    x = np.asarray(angle_deg)
    if x.size == 0 or x.dtype.kind != "f":
        return np.mod(x, 360.0, out=out)
    flat = x.reshape(-1)
    lo, hi = np.fmin.reduce(flat), np.fmax.reduce(flat)   # NaN ignored (both NaN: all NaN)
    if not (np.isnan(lo) or (-360.0 < lo and hi < 360.0)):
        return np.mod(x, 360.0, out=out)
    turn = np.less(x, 0.0).astype(x.dtype)
    turn *= x.dtype.type(360.0)
    return np.add(x, turn, out=out)


def sphere_cells(zenith_deg, azimuth_deg, grid_deg: float) -> np.ndarray:
    """Index of the zenith/azimuth cell of every direction (row-major on the grid, int32); -1 where undefined.

    Parameters
    ----------
    zenith_deg : numpy.ndarray
        Zenith angle of each direction, degree.
    azimuth_deg : numpy.ndarray
        Azimuth of each direction, degree in [0, 360).
    grid_deg : float
        Cell size, degree.

    Returns
    -------
    numpy.ndarray
        Cell index ``zenith_row * n_azimuth + azimuth_column`` (int32) of the shape of ``zenith_deg``; -1 where a
        coordinate is not finite. Angles on or beyond the grid's edge fall in the edge cell.
    """
    n_z, n_a = grid_shape(grid_deg)
    z, a = np.asarray(zenith_deg).ravel(), np.asarray(azimuth_deg).ravel()
    z = z if z.dtype.kind == "f" else z.astype(float)
    a = a if a.dtype.kind == "f" else a.astype(float)
    bad = ~(np.isfinite(z) & np.isfinite(a))
    iz = np.where(bad, 0, z / grid_deg).astype(np.int32)
    np.clip(iz, 0, n_z - 1, out=iz)
    ia = np.where(bad, 0, a / grid_deg).astype(np.int32)
    np.clip(ia, 0, n_a - 1, out=ia)
    iz *= n_a
    iz += ia
    iz[bad] = -1
    return iz.reshape(np.shape(zenith_deg))
