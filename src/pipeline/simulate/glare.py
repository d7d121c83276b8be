"""Glare from the sun in the field frames: the far wings of the lens's point-spread function.

The sun disc is the one source in a sky frame bright enough for the far
wings of the point-spread function to matter: its irradiance is tens of
times the whole sky's radiance per steradian, so a wing at 1e-4 sr-1 sixty
degrees away adds a fraction of a percent to a few percent of the zenith sky
(Wei et al. 2012, Section 3.4: the point spread of a wide lens has a core and
long wings; veiling glare of consumer lenses is a few percent).

Form (the simulator's own; the pipeline's field term is another law, see
:class:`pipeline.effects.optics.StrayLight`): a rotationally symmetric
kernel in the image plane with power-law wings, a Moffat-like profile

    K(d) = f (p - 2) / (2 pi d0^2) * (1 + (d / d0)^2)^(-p / 2)      [sr-1]

whose integral over the plane is the spread fraction f. The image-plane
distance ``d`` (rad) between a pixel and the sun's image is taken in the
equidistant approximation of the fisheye, r = theta: the pixel at
(theta, phi) sits at theta (cos phi, sin phi) and the sun at its zenith
angle and camera azimuth; for directions at different azimuths that differs
from the angle between them on the sky. The sun is a point of irradiance
E_b = the band average of the SPECTRL2 direct-normal spectrum times the
cloud layer's transmission towards the sun, exp(-tau_sun / cos Z_sun); the
excess the pixel sees is E_b K(d), in radiance units. It is added to the
scene radiance, so it goes through the renderer's roll-off and noise like
the sky (at the mask around the axis the roll-off is 1 to 1e-3). Only the
sun's wings are drawn: the sky's own spread (its flux is spread by the lab
form of the effect, :meth:`StrayLight.spread_light`, when that is on) is
smooth and, at the mask, mostly cancels.
"""

from __future__ import annotations

import numpy as np


def wing_kernel_per_sr(distance_rad, fraction: float, core_rad: float, index: float) -> np.ndarray:
    """K(d) of the module docstring (sr-1): the image-plane kernel's wings, integral ``fraction``.

    Parameters
    ----------
    distance_rad : array_like
        Image-plane distance d from the sun's image, rad (:func:`image_plane_distance_rad`).
    fraction : float
        The spread fraction f: the kernel's integral over the plane, dimensionless.
    core_rad : float
        The core width d0, rad.
    index : float
        The wing index p (the wings fall as d^-p); above 2.

    Returns
    -------
    numpy.ndarray
        K(d), sr-1, shaped like ``distance_rad``.

    Raises
    ------
    ValueError
        When ``index`` is 2 or less (no finite integral).
    """
    if index <= 2.0:
        raise ValueError(f"the wing index p must exceed 2 for a finite integral, got {index}")
    d = np.asarray(distance_rad, float)
    norm = fraction * (index - 2.0) / (2.0 * np.pi * core_rad**2)
    return norm * (1.0 + (d / core_rad) ** 2) ** (-index / 2.0)


def image_plane_distance_rad(theta_deg, phi_deg, sun_theta_deg: float, sun_phi_deg: float) -> np.ndarray:
    """Distance in the equidistant image plane (r = theta, rad) between pixels and the sun's image.

    Parameters
    ----------
    theta_deg : array_like
        The pixels' field angle, degree.
    phi_deg : array_like
        The pixels' azimuth in the camera, degree.
    sun_theta_deg : float
        The sun's field angle (its zenith angle for the zenith-looking lens), degree.
    sun_phi_deg : float
        The sun's azimuth in the camera, degree.

    Returns
    -------
    numpy.ndarray
        The distance, rad, the pixels' broadcast shape.
    """
    t, p = np.radians(np.asarray(theta_deg, float)), np.radians(np.asarray(phi_deg, float))
    ts, ps = np.radians(sun_theta_deg), np.radians(sun_phi_deg)
    return np.hypot(t * np.cos(p) - ts * np.cos(ps), t * np.sin(p) - ts * np.sin(ps))


class SunGlare:
    """The glare pattern of every frame: ``pattern(theta, phi, i)`` is E-free, K(d) times the sun's transmission."""

    def __init__(self, params: dict, sun_zenith_deg, sun_camera_azimuth_deg, sun_transmission):
        self.fraction = float(params["fraction"])
        self.core_rad = np.radians(float(params["core_deg"]))
        self.index = float(params["index"])
        self.sun_zenith_deg = np.asarray(sun_zenith_deg, float)
        self.sun_phi_deg = np.asarray(sun_camera_azimuth_deg, float)
        self.transmission = np.asarray(sun_transmission, float)

    def pattern(self, theta_deg, phi_deg, i: int) -> np.ndarray:
        """The glare at the pixels in frame ``i``, per unit of the sun's irradiance: K(d) times the sun's transmission.

        Parameters
        ----------
        theta_deg : array_like
            The pixels' field angle, degree (above 90: no glare).
        phi_deg : array_like
            The pixels' azimuth in the camera, degree.
        i : int
            The frame's index into the sun positions and transmissions.

        Returns
        -------
        numpy.ndarray
            sr-1: multiplied by the sun's band direct-normal irradiance (W m-2 nm-1; the clouds' transmission is
            in the pattern) it is the excess radiance, W m-2 sr-1 nm-1; zero for theta above 90 degrees.
        """
        d = image_plane_distance_rad(theta_deg, phi_deg, self.sun_zenith_deg[i], self.sun_phi_deg[i])
        out = wing_kernel_per_sr(d, self.fraction, self.core_rad, self.index) * self.transmission[i]
        return np.where(np.asarray(theta_deg, float) <= 90.0, out, 0.0)
