"""In-water roll-off predicted from the in-air roll-off: the outer surface's incidence angles and Fresnel.

A pixel of the sensor sees the world through the same internal optics in air
and in water: traced backwards from the pixel, the ray inside the front
element's glass is the same in both media, and only its refraction at the
outer surface changes. Hence, for the pixel at image radius rho with field
angle theta_a(rho) in air and theta_w(rho) in water (the geometric
calibration of each medium):

* vignetting and the pixel's internal etendue are the same in both media;
* the solid angle the pixel sees outside changes, but basic radiance L / n^2
  and basic etendue n^2 cos(i) dOmega are conserved across the outer surface
  (Snell's law in solid-angle form, n_1^2 cos i_1 dOmega_1 = n_2^2 cos i_2
  dOmega_2), so that change is the n-squared law already inside the
  immersion factor (Larouche et al. 2024, Section 2.7, Eq. 10; its flat
  window form I = n_w (n_w + n_g)^2 / (1 + n_g)^2 is n_w^2 T_ag(0) / T_wg(0));
  counting it again would double it;
* what remains with field angle is the Fresnel transmission of the outer
  surface at the incidence angle of each medium.

So the in-water roll-off at the pixel is

    g_w(theta_w) = g_a(theta_a) * [T_wg(i_w) / T_wg(0)] / [T_ag(i_a) / T_ag(0)]

with T_xg the unpolarised power transmittance from medium x into the glass
(:mod:`pipeline.radiometry.fresnel`). The incidence angles follow from the two
field angles alone: a surface whose normal is tilted by beta from the optical
axis at the point the chief ray crosses it has i_a = theta_a - beta and
i_w = theta_w - beta, and Snell through the glass, sin i_a = n_g sin i_g =
n_w sin i_w, gives

    tan beta = (sin theta_a - n_w sin theta_w) / (cos theta_a - n_w cos theta_w)

(the glass index cancels). A flat port is beta = 0 (theta_a from Snell); the
measured 91 and 76 degree half fields (a compression the flat port cannot give)
need a convex outer surface, beta about 41 degrees at the edge.

Angles in degrees; indices and transmittances dimensionless.
"""

from __future__ import annotations

import numpy as np

from .fresnel import fresnel_transmittance

__all__ = ["outer_surface_incidence_deg", "water_rolloff_factor"]


def outer_surface_incidence_deg(theta_air_deg, theta_water_deg, n_water):
    """Incidence angles (i_air, i_water) in degrees on the outer surface for the same internal ray.

    Both angles 0 on the axis.

    Parameters
    ----------
    theta_air_deg : array_like
        Field angle theta_a of the pixel in air (degree).
    theta_water_deg : array_like
        Field angle theta_w of the same pixel in water (degree).
    n_water : array_like
        Refractive index of the water (dimensionless; air taken as 1).

    Returns
    -------
    i_air : numpy.ndarray
        Incidence angle on the outer surface from air, theta_a - beta (degree).
    i_water : numpy.ndarray
        Incidence angle on the outer surface from water, theta_w - beta (degree).
    """
    ta = np.radians(np.asarray(theta_air_deg, dtype=float))
    tw = np.radians(np.asarray(theta_water_deg, dtype=float))
    n = np.asarray(n_water, dtype=float)
    num = np.sin(ta) - n * np.sin(tw)
    den = np.cos(ta) - n * np.cos(tw)
    with np.errstate(invalid="ignore", divide="ignore"):
        beta = np.where(np.abs(den) > 0, np.arctan(num / np.where(den == 0, 1.0, den)), np.pi / 2)
    return np.degrees(ta - beta), np.degrees(tw - beta)


def water_rolloff_factor(theta_air_deg, theta_water_deg, n_water, n_glass):
    """g_w(theta_w) / g_a(theta_a) for one pixel: the ratio of the outer surface's Fresnel transmissions.

    Each transmission is relative to its value on the axis (the axial ratio is
    in the immersion factor). 1 on the axis; slightly above 1 off the axis,
    because the air-side incidence is the steeper one (about 1.4 % at 70 deg in
    water for the default camera).

    Parameters
    ----------
    theta_air_deg : array_like
        Field angle of the pixel in air (degree).
    theta_water_deg : array_like
        Field angle of the same pixel in water (degree).
    n_water : array_like
        Refractive index of the water (dimensionless).
    n_glass : array_like
        Refractive index of the outer element's glass (dimensionless).

    Returns
    -------
    numpy.ndarray
        Factor on the in-air roll-off (dimensionless), broadcast over the inputs.
    """
    i_a, i_w = outer_surface_incidence_deg(theta_air_deg, theta_water_deg, n_water)
    t_w = fresnel_transmittance(n_water, n_glass, i_w) / fresnel_transmittance(n_water, n_glass, 0.0)
    t_a = fresnel_transmittance(1.0, n_glass, i_a) / fresnel_transmittance(1.0, n_glass, 0.0)
    return t_w / t_a
