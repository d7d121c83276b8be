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

__all__ = ["ZENITH_LENS", "sphere_coordinates", "sphere_cells", "grid_shape"]

ZENITH_LENS = "close"


def grid_shape(grid_deg: float) -> tuple[int, int]:
    """(zenith, azimuth) cells of the grid: 180 / grid_deg by 360 / grid_deg."""
    return int(round(180.0 / grid_deg)), int(round(360.0 / grid_deg))


def sphere_coordinates(theta_deg, phi_deg, looks_up: bool):
    """Zenith angle and azimuth (deg) of a lens pixel's direction, by the sphere convention of this module."""
    theta, phi = np.asarray(theta_deg), np.asarray(phi_deg)
    # float32 maps stay float32 (as the bundle's are); anything else becomes float64
    theta = theta if theta.dtype.kind == "f" else theta.astype(float)
    phi = phi if phi.dtype.kind == "f" else phi.astype(float)
    if looks_up:
        return theta, np.mod(phi, 360.0)
    return 180.0 - theta, np.mod(-phi, 360.0)


def sphere_cells(zenith_deg, azimuth_deg, grid_deg: float) -> np.ndarray:
    """Index of the zenith/azimuth cell of every direction (row-major on the grid, int32); -1 where undefined."""
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
