"""Per-pixel viewing-direction and solid-angle maps of a band image.

Angles are in degrees: theta from the optical axis, phi = atan2(y, x) in the
camera frame (x along +u, y along +v), in (-180, 180]. Pixel centres are at
integer (u, v) = (col, row). Solid angles are in steradians.
"""

from __future__ import annotations

import numpy as np

from .scaramuzza import FisheyeModel


def pixel_grid(shape):
    """(u, v) coordinates of the pixel centres of an image of shape (rows, cols).

    Parameters
    ----------
    shape : tuple of int
        (rows, cols) of the image.

    Returns
    -------
    u : numpy.ndarray
        Column coordinate of every pixel centre, pixels, shape ``(rows, cols)``.
    v : numpy.ndarray
        Row coordinate of every pixel centre, pixels, shape ``(rows, cols)``.
    """
    rows, cols = shape
    v, u = np.mgrid[0:rows, 0:cols].astype(float)
    return u, v


def theta_phi_maps(model: FisheyeModel, shape=None):
    """theta and phi (degrees) at every pixel centre; shape defaults to model.shape.

    Parameters
    ----------
    model : FisheyeModel
        The lens's geometric model.
    shape : tuple of int, optional
        (rows, cols) of the image; ``model.shape`` when None.

    Returns
    -------
    theta : numpy.ndarray
        Angle from the optical axis at every pixel centre, degree, shape ``(rows, cols)``.
    phi : numpy.ndarray
        Azimuth in the camera frame at every pixel centre, degree in (-180, 180], shape ``(rows, cols)``.
    """
    u, v = pixel_grid(model.shape if shape is None else shape)
    return model.theta_phi(u, v, degrees=True)


def solid_angle_map(model: FisheyeModel, shape=None, supersample: int = 1) -> np.ndarray:
    """Solid angle (sr) seen by every pixel.

    The closed-form Jacobian of the ray mapping (see
    ``FisheyeModel.solid_angle_density``) integrated over the pixel with a
    supersample x supersample midpoint rule (1: the pixel centre alone).

    Parameters
    ----------
    model : FisheyeModel
        The lens's geometric model.
    shape : tuple of int, optional
        (rows, cols) of the image; ``model.shape`` when None.
    supersample : int, default 1
        Midpoint-rule samples per pixel side.

    Returns
    -------
    numpy.ndarray
        Solid angle of every pixel, sr, shape ``(rows, cols)``.
    """
    rows, cols = model.shape if shape is None else shape
    ss = int(supersample)
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    out = np.zeros((rows, cols))
    u, v = pixel_grid((rows, cols))
    for du in offs:
        for dv in offs:
            out += model.solid_angle_density(u + du, v + dv)
    return out / ss**2


def mask_within(theta_map, half_angle_deg: float) -> np.ndarray:
    """Boolean mask of pixels whose theta is at most half_angle_deg.

    Parameters
    ----------
    theta_map : numpy.ndarray
        Angle from the optical axis of every pixel, degree.
    half_angle_deg : float
        Largest angle kept, degree.

    Returns
    -------
    numpy.ndarray
        Boolean mask of the shape of ``theta_map`` (NaN angles are False).
    """
    return np.asarray(theta_map) <= half_angle_deg


def pixel_of_direction(model: FisheyeModel, theta_deg, phi_deg):
    """Pixel coordinates (u, v) of the direction (theta, phi) in degrees (NaN if unseen).

    Parameters
    ----------
    model : FisheyeModel
        The lens's geometric model.
    theta_deg : float or numpy.ndarray
        Angle from the optical axis, degree.
    phi_deg : float or numpy.ndarray
        Azimuth in the camera frame, degree.

    Returns
    -------
    u : numpy.ndarray
        Column coordinate, pixels (NaN where the model does not see the direction).
    v : numpy.ndarray
        Row coordinate, pixels (NaN where the model does not see the direction).
    """
    th = np.radians(np.asarray(theta_deg, float))
    ph = np.radians(np.asarray(phi_deg, float))
    rays = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=-1)
    return model.world2cam(rays)
