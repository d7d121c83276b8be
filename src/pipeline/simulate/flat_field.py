"""A uniformly lit band image of a fisheye lens: bright inside the image circle, dark outside.

Pixel conventions of :mod:`pipeline.geometry.scaramuzza`; the edge is where
the model's theta reaches the half field of view.
"""

from __future__ import annotations

import numpy as np

from pipeline.geometry.scaramuzza import FisheyeModel


def render_flat_field(model: FisheyeModel, *, half_fov_deg: float | None = None,
                      level: float = 1.0, outside: float = 0.0, supersample: int = 4) -> np.ndarray:
    """A bright, uniformly lit band image: ``level`` inside theta <= half FOV, else ``outside``.

    Each pixel is the mean over supersample x supersample sub-pixels.

    Parameters
    ----------
    model : FisheyeModel
        The band image's camera model; its ``shape`` (rows, cols) is the image's.
    half_fov_deg : float, optional
        The half field of view where the lit disc ends, degree; default None (the model's own).
    level : float, optional
        Value inside the image circle; default 1.
    outside : float, optional
        Value outside it; default 0.
    supersample : int, optional
        Sub-pixels per side; default 4.

    Returns
    -------
    numpy.ndarray
        float64, shape (rows, cols): the mean over each pixel's area (between ``outside`` and ``level`` on the edge).
    """
    rows, cols = model.shape
    hf = model.half_fov_deg if half_fov_deg is None else half_fov_deg
    ss = int(supersample)
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    u = (np.arange(cols)[:, None] + offs).ravel()
    v = (np.arange(rows)[:, None] + offs).ravel()
    img = np.empty((rows, cols))
    step = max(1, 2_000_000 // (cols * ss * ss))
    for r0 in range(0, rows, step):
        r1 = min(rows, r0 + step)
        uu, vv = np.meshgrid(u, v[r0 * ss:r1 * ss])
        theta, _ = model.theta_phi(uu, vv)
        val = np.where(theta <= hf, level, outside)
        img[r0:r1] = val.reshape(r1 - r0, ss, cols, ss).mean(axis=(1, 3))
    return img
