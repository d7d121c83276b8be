"""The field model of stray light from the sun: the glare a sky frame's mask receives (``stray_light``).

A lens spreads a small part of the flux from every direction over the whole
image (Wei et al. 2012, Section 3.4). In a sky frame only the sun is bright
enough for that to matter far from it: the excess in the zenith mask is, per
band, the sun's direct irradiance at the lens times the lens's spread at the
angle between the sun and the mask. The pipeline knows three things about
that, and the covariate is their product:

* the direct beam in the band, E_b (W m-2 nm-1): the extraterrestrial
  spectrum of ASTM G173-03 (pvlib's reference spectra), corrected for the
  Earth-Sun distance, through a clear atmosphere of Rayleigh optical depth
  (Hansen and Travis 1974 fit, scaled by pressure) and aerosol optical depth
  tau_a(lambda) = ``field.clear_sky_aod700`` (lambda / 700 nm)^-alpha
  (``field.clear_sky_angstrom_exponent``) and ozone's Chappuis band (a
  Gaussian in wavelength, peak cross-section 5.1e-21 cm2 at 602 nm, standard
  width 65 nm: 1.5e-21 at 500 nm; column ``field.clear_sky_ozone_atm_cm``),
  along the relative air mass of Kasten and Young (1989) at the sun's
  apparent zenith angle (Beer's law, no water vapour, which absorbs little
  between 400 and 700 nm), averaged with the band's measured response (Eq. 3);
* whether the sun is seen: the frame has at least ``field.sun_seen_min_pixels``
  band pixels in the lens at ``field.sun_seen_fraction_of_full_scale`` of the
  full scale or above (the exposure keeps the sky lower, so they are the
  saturated sun disc; a cloud in front of it removes both the disc and the
  glare);
* the angle between the sun and the mask: for the mask at the zenith, the
  solar zenith angle Z, and a spread that falls as an inverse power of it,
  (Z_ref / Z)^q (``field.stray_light_angle_exponent`` q,
  ``field.stray_light_reference_angle_deg`` Z_ref; q = 2 is the inverse-square
  law of veiling glare).

covariate_b = E_b x seen x (Z_ref / Z)^q (W m-2 nm-1); its one coefficient,
common to the bands (the far wings of a lens's spread are nearly
achromatic), is the spread at Z_ref from the source in sr-1: the glare
radiance in the mask per unit direct irradiance.
"""

from __future__ import annotations

import numpy as np

#: mean sea-level pressure (Pa) of the Rayleigh optical depth
SEA_LEVEL_PRESSURE_PA = 101325.0
#: molecules per cm2 in an ozone column of 1 atm-cm (Loschmidt's number times 1 cm)
LOSCHMIDT_PER_CM2 = 2.687e19
#: the Chappuis band of ozone as a Gaussian: peak cross-section (cm2), centre and standard width (nm)
CHAPPUIS_PEAK_CM2 = 5.1e-21
CHAPPUIS_CENTRE_NM = 602.0
CHAPPUIS_WIDTH_NM = 65.0


def ozone_optical_depth(wavelength_nm, column_atm_cm: float) -> np.ndarray:
    """Optical depth of the ozone column in the Chappuis band (Gaussian approximation, module docstring).

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelength (nm).
    column_atm_cm : float
        Ozone column (atm-cm; 0.3 is a typical column of 300 Dobson units).

    Returns
    -------
    numpy.ndarray
        Vertical optical depth (dimensionless) at each wavelength.
    """
    wl = np.asarray(wavelength_nm, float)
    sigma = CHAPPUIS_PEAK_CM2 * np.exp(-0.5 * ((wl - CHAPPUIS_CENTRE_NM) / CHAPPUIS_WIDTH_NM) ** 2)
    return column_atm_cm * LOSCHMIDT_PER_CM2 * sigma


def rayleigh_optical_depth(wavelength_nm, pressure_pa: float = SEA_LEVEL_PRESSURE_PA) -> np.ndarray:
    """Rayleigh optical depth of the atmosphere (Hansen and Travis 1974, Eq. 2.29), scaled by pressure.

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelength (nm).
    pressure_pa : float, default 101325.0
        Surface pressure (Pa).

    Returns
    -------
    numpy.ndarray
        Vertical optical depth (dimensionless) at each wavelength.
    """
    um = np.asarray(wavelength_nm, float) / 1000.0
    return 0.008569 * um**-4 * (1.0 + 0.0113 * um**-2 + 0.00013 * um**-4) * pressure_pa / SEA_LEVEL_PRESSURE_PA


def direct_normal_spectrum(wavelength_nm, apparent_zenith_deg, day_of_year: int, aod700: float,
                           angstrom_exponent: float, ozone_atm_cm: float,
                           pressure_pa: float = SEA_LEVEL_PRESSURE_PA) -> np.ndarray:
    """Clear-sky direct-normal spectral irradiance (n_time, n_wavelength), W m-2 nm-1 (module docstring); 0 below
    the horizon.

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelengths, shape (n_wavelength,) (nm).
    apparent_zenith_deg : array_like
        The sun's apparent (refracted) zenith angle at each time, shape (n_time,) (degree).
    day_of_year : int
        Day of the year (1 to 366), for the Earth-Sun distance.
    aod700 : float
        Aerosol optical depth at 700 nm (dimensionless).
    angstrom_exponent : float
        Angstrom exponent alpha of the aerosol optical depth (dimensionless).
    ozone_atm_cm : float
        Ozone column (atm-cm).
    pressure_pa : float, default 101325.0
        Surface pressure (Pa).

    Returns
    -------
    numpy.ndarray
        Direct-normal spectral irradiance (W m-2 nm-1), shape (n_time, n_wavelength).
    """
    from pvlib.atmosphere import get_relative_airmass
    from pvlib.spectrum import get_reference_spectra

    wl = np.asarray(wavelength_nm, float)
    ref = get_reference_spectra(standard="ASTM G173-03")
    top = np.interp(wl, ref.index.to_numpy(float), ref["extraterrestrial"].to_numpy(float))
    top = top * (1.0 + 0.033 * np.cos(2.0 * np.pi * day_of_year / 365.0))
    zen = np.atleast_1d(np.asarray(apparent_zenith_deg, float))
    airmass = np.nan_to_num(np.asarray(get_relative_airmass(zen, model="kastenyoung1989"), float), nan=np.inf)
    tau = (rayleigh_optical_depth(wl, pressure_pa) + aod700 * (wl / 700.0) ** (-angstrom_exponent)
           + ozone_optical_depth(wl, ozone_atm_cm))
    out = top[None, :] * np.exp(-airmass[:, None] * tau[None, :])
    return np.where((zen < 90.0)[:, None], out, 0.0)


def band_direct_irradiance(response_nm, response, apparent_zenith_deg, day_of_year: int, aod700: float,
                           angstrom_exponent: float, ozone_atm_cm: float) -> np.ndarray:
    """E_b (n_time,): the direct-normal spectrum averaged with one band's measured response (Eq. 3).

    Parameters
    ----------
    response_nm : array_like
        Wavelengths of the band's response, shape (n,) (nm).
    response : array_like
        The band's relative spectral response, shape (n,) (NaN counts as 0).
    apparent_zenith_deg : array_like
        The sun's apparent zenith angle at each time, shape (n_time,) (degree).
    day_of_year : int
        Day of the year (1 to 366).
    aod700 : float
        Aerosol optical depth at 700 nm (dimensionless).
    angstrom_exponent : float
        Angstrom exponent of the aerosol optical depth (dimensionless).
    ozone_atm_cm : float
        Ozone column (atm-cm).

    Returns
    -------
    numpy.ndarray
        Band-averaged direct-normal irradiance E_b (W m-2 nm-1), shape (n_time,).
    """
    wl = np.asarray(response_nm, float)
    s = np.nan_to_num(np.asarray(response, float))
    spectrum = direct_normal_spectrum(wl, apparent_zenith_deg, day_of_year, aod700, angstrom_exponent, ozone_atm_cm)
    return np.trapezoid(spectrum * s[None, :], wl, axis=1) / np.trapezoid(s, wl)


def sun_glare_covariate(band_irradiance, sun_seen, angle_from_sun_deg, exponent: float,
                        reference_angle_deg: float) -> np.ndarray:
    """E_b x seen x (Z_ref / angle)^q of the module docstring (W m-2 nm-1).

    Parameters
    ----------
    band_irradiance : array_like
        The band's clear-sky direct irradiance E_b (W m-2 nm-1).
    sun_seen : array_like of bool or float
        Whether the sun's disc is seen in each frame (1 or 0).
    angle_from_sun_deg : array_like
        Angle between the sun and the mask (degree; the solar zenith angle for the mask at the zenith).
    exponent : float
        q, the power with which the spread falls with the angle (dimensionless).
    reference_angle_deg : float
        Z_ref, the angle at which the coefficient is the spread (degree).

    Returns
    -------
    numpy.ndarray
        The covariate (W m-2 nm-1), broadcast over the inputs.

    Raises
    ------
    ValueError
        When an angle is not positive.
    """
    angle = np.asarray(angle_from_sun_deg, float)
    if np.any(angle <= 0):
        raise ValueError("the angle between the sun and the mask must be positive")
    return np.asarray(band_irradiance, float) * np.asarray(sun_seen, float) * (reference_angle_deg / angle) ** exponent
