"""Fresnel reflectance and transmittance of a flat interface for unpolarised light.

Standard electromagnetic results (e.g. Born and Wolf, Principles of Optics,
Section 1.5; Mobley, Light and Water, Section 4.2).  Larouche et al. (2024),
Section 3.6, use the Fresnel transmittance at the air-water interface t_aw in
the n-squared law of the immersion factor (Eq. 11 and Table 2).

All angles are in degrees, measured from the interface normal.  Radiant power
is conserved: T = 1 - R.  Beyond the critical angle (n1 > n2) R = 1, T = 0.
"""

from __future__ import annotations

import numpy as np

from .water import refractive_index_air, refractive_index_water

__all__ = [
    "fresnel_reflectance",
    "fresnel_transmittance",
    "fresnel_reflectance_normal",
    "fresnel_transmittance_normal",
    "refraction_angle_deg",
    "transmittance_air_water",
]


def refraction_angle_deg(n1, n2, incidence_deg):
    """Refraction angle (degrees) by Snell's law n1 sin(i) = n2 sin(t); NaN beyond the critical angle.

    Parameters
    ----------
    n1 : array_like
        Refractive index of the incident medium (dimensionless).
    n2 : array_like
        Refractive index of the transmitting medium (dimensionless).
    incidence_deg : array_like
        Incidence angle from the normal (degree).

    Returns
    -------
    numpy.ndarray
        Refraction angle t from the normal (degree), broadcast over the inputs; NaN beyond the critical angle.
    """
    n1 = np.asarray(n1, dtype=float)
    n2 = np.asarray(n2, dtype=float)
    s = n1 / n2 * np.sin(np.deg2rad(np.asarray(incidence_deg, dtype=float)))
    with np.errstate(invalid="ignore"):
        return np.rad2deg(np.where(np.abs(s) <= 1.0, np.arcsin(np.clip(s, -1, 1)), np.nan))


def fresnel_reflectance_normal(n1, n2):
    """Power reflectance at normal incidence, R = ((n1 - n2) / (n1 + n2))^2 (dimensionless).

    Parameters
    ----------
    n1 : array_like
        Refractive index of the incident medium (dimensionless).
    n2 : array_like
        Refractive index of the transmitting medium (dimensionless).

    Returns
    -------
    numpy.ndarray
        Reflectance R in [0, 1], broadcast over the inputs.
    """
    n1 = np.asarray(n1, dtype=float)
    n2 = np.asarray(n2, dtype=float)
    return ((n1 - n2) / (n1 + n2)) ** 2


def fresnel_transmittance_normal(n1, n2):
    """Power transmittance at normal incidence, T = 4 n1 n2 / (n1 + n2)^2 = 1 - R (dimensionless).

    Parameters
    ----------
    n1 : array_like
        Refractive index of the incident medium (dimensionless).
    n2 : array_like
        Refractive index of the transmitting medium (dimensionless).

    Returns
    -------
    numpy.ndarray
        Transmittance T in [0, 1], broadcast over the inputs.
    """
    n1 = np.asarray(n1, dtype=float)
    n2 = np.asarray(n2, dtype=float)
    return 4.0 * n1 * n2 / (n1 + n2) ** 2


def fresnel_reflectance(n1, n2, incidence_deg):
    """Unpolarised power reflectance R = (R_s + R_p) / 2 at a flat n1 -> n2 interface.

    Parameters
    ----------
    n1, n2 : array_like
        Refractive indices of the incident and transmitting media.
    incidence_deg : array_like
        Incidence angle in degrees from the normal (0 to 90).

    Returns
    -------
    numpy.ndarray
        Reflectance in [0, 1]; 1 beyond the critical angle.
    """
    n1 = np.asarray(n1, dtype=float)
    n2 = np.asarray(n2, dtype=float)
    ti = np.deg2rad(np.asarray(incidence_deg, dtype=float))
    ci = np.cos(ti)
    s = n1 / n2 * np.sin(ti)
    tir = np.abs(s) >= 1.0
    ct = np.sqrt(np.clip(1.0 - s**2, 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        rs = ((n1 * ci - n2 * ct) / (n1 * ci + n2 * ct)) ** 2
        rp = ((n1 * ct - n2 * ci) / (n1 * ct + n2 * ci)) ** 2
    r = 0.5 * (rs + rp)
    return np.where(tir, 1.0, r)


def fresnel_transmittance(n1, n2, incidence_deg):
    """Unpolarised power transmittance T = 1 - R at a flat n1 -> n2 interface (dimensionless).

    Parameters
    ----------
    n1, n2 : array_like
        Refractive indices of the incident and transmitting media (dimensionless).
    incidence_deg : array_like
        Incidence angle from the normal (degree, 0 to 90).

    Returns
    -------
    numpy.ndarray
        Transmittance T in [0, 1], broadcast over the inputs; 0 beyond the critical angle.
    """
    return 1.0 - fresnel_reflectance(n1, n2, incidence_deg)


def transmittance_air_water(wavelength_nm, temperature_c=25.0, salinity_psu=0.0):
    """Air -> water power transmittance t_aw at normal incidence (dimensionless).

    Uses n_air = 1 and n_w from Quan and Fry (1995).  At normal incidence the
    Fresnel transmittance is symmetric, so t_aw = t_wa.  About 0.9797 at
    600 nm (Larouche et al. 2024, Section 3.6 / Table 2 example).

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelength (nm).
    temperature_c : array_like, default 25.0
        Water temperature (degree Celsius).
    salinity_psu : array_like, default 0.0
        Salinity (PSU).

    Returns
    -------
    numpy.ndarray
        Transmittance t_aw (dimensionless), broadcast over the inputs.
    """
    n_w = refractive_index_water(wavelength_nm, temperature_c, salinity_psu)
    return fresnel_transmittance_normal(refractive_index_air(), n_w)
