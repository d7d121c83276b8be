"""The simulator's true optics: where each raw pixel looks, and how much light reaches it.

Geometry: the published Scaramuzza fits of DESIGN.md (full 3456-pixel lens
image, tan(theta) = rho / f(rho)), scaled to the simulated lens size.
"""

from __future__ import annotations

import numpy as np

#: Published fits on the full 3456-pixel lens image (DESIGN.md): ascending
#: coefficients of f(rho) with a1 = 0, and the centre (x = column, y = row).
PUBLISHED_GEOMETRY = {
    "close": {"poly": (1019.25, 0.0, -3.0382e-4, -2.1491e-8, -2.8016e-11), "centre_xy": (1731.51, 1710.86)},
    "far": {"poly": (1016.48, 0.0, -3.9436e-4, 1.5171e-7, -1.1177e-10), "centre_xy": (1743.76, 1724.99)},
}
FULL_LENS_PX = 3456
HALF_FOV_DEG = {"air": 91.0, "water": 76.0}


def theta_map_deg(lens: str, lens_px: int) -> np.ndarray:
    """Field angle (degrees) of every raw pixel centre of a ``lens_px`` square lens region, in air."""
    geo = PUBLISHED_GEOMETRY[lens]
    s = lens_px / FULL_LENS_PX
    # pixel centres in full-resolution coordinates
    coords = (np.arange(lens_px) + 0.5) / s - 0.5
    x = coords[None, :] - geo["centre_xy"][0]
    y = coords[:, None] - geo["centre_xy"][1]
    rho = np.hypot(x, y)
    f = np.polynomial.polynomial.polyval(rho, geo["poly"])
    return np.degrees(np.arctan2(rho, f))


def lit_mask(theta_deg: np.ndarray, medium: str = "air") -> np.ndarray:
    """Pixels inside the image circle (the rest are never lit)."""
    return theta_deg <= HALF_FOV_DEG[medium]
