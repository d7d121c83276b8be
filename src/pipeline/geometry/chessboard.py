"""A planar chessboard: its corners in the board frame and their projection through a fisheye model.

Board frame (mm): the board lies in z = 0, its z axis points *into* the board
(away from a camera that sees its front), inner corners are at
``x = (i - (nx - 1) / 2) * square_mm``, ``y = (j - (ny - 1) / 2) * square_mm``
for ``i = 0..nx-1``, ``j = 0..ny-1``, listed row by row (``i`` fastest), which
is OpenCV's order for ``patternSize = (nx, ny)``. Square ``(p, q)``
(``p = 0..nx``, ``q = 0..ny``) is black when ``p + q`` is even, so square
(0, 0), diagonally outward from corner 0, is black. With ``nx + ny`` odd the
square diagonally outward from the last corner is white, which fixes the
180-degree ambiguity (see :mod:`pipeline.geometry.corners`).

A pose is ``(rvec, tvec)``: camera = R(rvec) @ board + tvec, tvec in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .scaramuzza import FisheyeModel


@dataclass(frozen=True)
class Board:
    """Chessboard: inner corners (nx, ny), square size (mm), white margin (squares)."""

    nx: int = 7
    ny: int = 6
    square_mm: float = 30.0
    margin_squares: float = 0.5

    def corners_mm(self) -> np.ndarray:
        """Inner corners (nx*ny, 3) in the board frame, OpenCV order (i fastest).

        Returns
        -------
        numpy.ndarray
            Board-frame positions of the inner corners, mm, shape ``(nx * ny, 3)`` with z = 0.
        """
        i, j = np.meshgrid(np.arange(self.nx), np.arange(self.ny))
        x = (i.ravel() - (self.nx - 1) / 2) * self.square_mm
        y = (j.ravel() - (self.ny - 1) / 2) * self.square_mm
        return np.stack([x, y, np.zeros_like(x)], axis=1)

    def half_extent_mm(self) -> tuple[float, float]:
        """Half width and height of the board including its white margin (mm).

        Returns
        -------
        tuple of float
            (half width along x, half height along y), mm.
        """
        return ((self.nx + 1) / 2 + self.margin_squares) * self.square_mm, \
               ((self.ny + 1) / 2 + self.margin_squares) * self.square_mm

    def outline_mm(self, n_per_side: int = 16) -> np.ndarray:
        """Points along the outer edge of the board (incl. margin), (k, 3) mm.

        Parameters
        ----------
        n_per_side : int, default 16
            Points per side.

        Returns
        -------
        numpy.ndarray
            Board-frame points, mm, shape ``(4 * n_per_side, 3)`` with z = 0, going round the board.
        """
        hx, hy = self.half_extent_mm()
        s = np.linspace(-1, 1, n_per_side, endpoint=False)
        pts = np.concatenate([
            np.stack([s * hx, -hy + 0 * s], 1), np.stack([hx + 0 * s, s * hy], 1),
            np.stack([-s * hx, hy + 0 * s], 1), np.stack([-hx + 0 * s, -s * hy], 1)])
        return np.concatenate([pts, np.zeros((len(pts), 1))], axis=1)


def rotation_matrix(rvec) -> np.ndarray:
    """3x3 rotation matrix of a rotation vector (radians).

    Parameters
    ----------
    rvec : array_like
        Rotation vector (axis times angle), radians, 3 elements.

    Returns
    -------
    numpy.ndarray
        Rotation matrix, shape ``(3, 3)``.
    """
    return cv2.Rodrigues(np.asarray(rvec, dtype=float).reshape(3, 1))[0]


def project_points(model: FisheyeModel, points_mm, rvec, tvec) -> np.ndarray:
    """Pixel positions (k, 2) of board-frame points through the model at a pose.

    Parameters
    ----------
    model : FisheyeModel
        The lens's geometric model.
    points_mm : numpy.ndarray
        Board-frame points, mm, shape ``(k, 3)``.
    rvec : array_like
        Rotation vector of the pose (board to camera), radians.
    tvec : array_like
        Translation of the pose, mm: camera = R(rvec) board + tvec.

    Returns
    -------
    numpy.ndarray
        Pixel coordinates (u, v), shape ``(k, 2)``; NaN where the model does not see the point.
    """
    R = rotation_matrix(rvec)
    cam = np.asarray(points_mm, float) @ R.T + np.asarray(tvec, float).reshape(1, 3)
    u, v = model.world2cam(cam)
    return np.stack([u, v], axis=-1)
