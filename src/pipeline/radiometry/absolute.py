"""Absolute radiance calibration: inverse responsivity R^-1 by Eq. (9), with its budget.

Larouche et al. (2024), Sections 2.1, 2.6 and 3.5.

* Eq. (2): y_DN = (y_raw - y_bias) / (t_int * S_ISO * 0.01), in ADU/s at ISO 100
  (S_ISO * 0.01 = 1 at ISO 100); :func:`pipeline.radiometry.exposure.dn_per_second`,
  re-exported here.
* Eq. (9): R_i^-1 = L_i,source / y_DN,i,source, in W sr-1 m-2 nm-1 per ADU/s,
  where L_i,source is the effective band radiance of the source, Eq. (3).
* Table 1 (W sr-1 m-2 nm-1, ADU/s): R 0.74e-3 / 61e3 = 1.21e-8,
  G 0.48e-3 / 65e3 = 7.4e-9 (published 7.5e-9), B 0.26e-3 / 21.9e3 = 1.19e-8;
  published uncertainties 10.4, 10.6, 11.0 %.

Which terms dominate (Section 3.5 and Table 1)
    Table 1 gives L_source relative uncertainties of 10.8, 10.4, 11.5 %
    (0.08/0.74, 0.05/0.48, 0.03/0.26) against 1.6, 1.5, 2.3 % for y_DN
    (1/61, 1/65, 0.5/21.9): the source radiance makes up more than 95 % of
    the variance.  Inside it the paper names the spectrometer's calibration
    lamp (manufacturer: 9.1 % at 400 nm, 6.9 % at 800 nm, about 8 % inside
    the bands) as the largest part, then the C-OPS reference (2.5 % quoted,
    2/68 = 2.9 % from the reading) and spectrometer noise.  Counting them as
    the paper does (``lamp_model="profile"``, rho = 0) the budget below gives
    8.6, 8.9, 9.3 % (R, G, B, default response, 2796 K Planck source, Table 1
    DN, reference 2/68); the published
    10.4-11 % implies about 6 % more in the source radiance that the text
    does not break down (spectrometer noise/stray light, sphere drift);
    one further component of 0.06 gives 10.5, 10.7, 11.1 %. So
    ``spectrometer_noise`` or a named ``extra_components`` entry must carry
    it to reproduce the paper; by default there is none.  By default
    (``lamp_model="colour_temperature"``, below) the same inputs give 3.4,
    3.3, 3.8 %: most of the lamp's error cancels in the rescaling.

What of the lamp error propagates (``lamp_model``)
    The spectrometer's spectrum is only relative: it is rescaled so that its
    value at 589 nm equals the reference reading.  A lamp error e(lambda)
    therefore enters the band radiance as <e>_LS - e(589 nm), with <.>_LS the
    band average weighted by source radiance times response: a scale part
    (the same at every wavelength) cancels exactly, a shape part does not.
    The manufacturer gives only the size at two wavelengths, 9.1 % at 400 nm
    and 6.9 % at 800 nm; ``"colour_temperature"`` (default) reads them as a
    constant part and a colour-temperature part of the tungsten-halogen lamp,
    u(lambda)^2 = sigma_s^2 + (c / lambda)^2 (Wien: d ln B / dT = c2 /
    (lambda T^2), a shape ~ 1/lambda), which gives sigma_s = 6.0 % (cancels)
    and c = 27.4 nm; the stated lamp term is c |<1/lambda>_LS - 1/589 nm|,
    about 0.1, 0.3 and 0.9 % for R, G and B (Table 1 DN, 2796 K source).  So R^-1's stated uncertainty is
    about 2.5-3 % (reference and image), not the paper's 10.4-11 %, and a
    coverage test over simulated labs (``tests/stages/test_coverage_over_seeds.py``)
    checks that this is what propagates.  ``"profile"`` is the paper's own
    counting: the interpolated profile u(lambda) taken as fully correlated,
    the lamp term |u_band - rho u(589 nm)| with ``lamp_reference_correlation``
    rho; rho = 0 counts the lamp in full as the paper does (8 % of the
    8.6-9.3 % above), rho = 1 cancels its scale but keeps its linear tilt.
"""

from __future__ import annotations

import numpy as np

from .exposure import dn_per_second
from .source import (
    REFERENCE_RADIANCE_SIGMA_W_SR_M2_NM,
    REFERENCE_RADIANCE_W_SR_M2_NM,
    REFERENCE_WAVELENGTH_NM,
    scale_to_reference,
)
from .spectral import effective_band_radiance

__all__ = [
    "dn_per_second",
    "inverse_responsivity",
    "lamp_calibration_relative_sigma",
    "lamp_colour_temperature_shape_nm",
    "absolute_calibration_budget",
]


def inverse_responsivity(effective_radiance, dn_per_s, effective_radiance_sigma=None, dn_per_s_sigma=None):
    """Eq. (9): R^-1 = L_eff / y_DN, in (radiance unit) per ADU/s.

    With L_eff in W sr-1 m-2 nm-1 and y_DN in ADU/s at ISO 100 the result is
    in W sr-1 m-2 nm-1 s ADU-1.  Relative uncertainties of the two
    (independent) inputs add in quadrature.

    Parameters
    ----------
    effective_radiance : array_like
        Effective band radiance of the source L_eff, Eq. (3) (e.g. W sr-1 m-2 nm-1).
    dn_per_s : array_like
        The source's signal y_DN (ADU s-1 at ISO 100).
    effective_radiance_sigma : array_like, optional
        Standard uncertainty of L_eff (same unit).
    dn_per_s_sigma : array_like, optional
        Standard uncertainty of y_DN (ADU s-1).

    Returns
    -------
    inverse_responsivity : numpy.ndarray
        R^-1 (radiance unit per ADU s-1), broadcast over the inputs.
    sigma : numpy.ndarray
        Its standard uncertainty (same unit); returned, as the second element of a tuple, only when a sigma
        is given.
    """
    l_eff = np.asarray(effective_radiance, dtype=float)
    y = np.asarray(dn_per_s, dtype=float)
    r_inv = l_eff / y
    if effective_radiance_sigma is None and dn_per_s_sigma is None:
        return r_inv
    u2 = np.zeros_like(r_inv)
    if effective_radiance_sigma is not None:
        u2 = u2 + (np.asarray(effective_radiance_sigma, dtype=float) / l_eff) ** 2
    if dn_per_s_sigma is not None:
        u2 = u2 + (np.asarray(dn_per_s_sigma, dtype=float) / y) ** 2
    return r_inv, np.abs(r_inv) * np.sqrt(u2)


def lamp_calibration_relative_sigma(wavelength_nm, at_400_nm=0.091, at_800_nm=0.069):
    """Relative uncertainty of the spectrometer's irradiance calibration lamp.

    Linear in wavelength between the manufacturer's 9.1 % at 400 nm and
    6.9 % at 800 nm (Ocean Optics HL-3P-INT-CAL, Section 3.5), held
    constant outside.

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelength (nm).
    at_400_nm : float, default 0.091
        Relative standard uncertainty at 400 nm (dimensionless).
    at_800_nm : float, default 0.069
        Relative standard uncertainty at 800 nm (dimensionless).

    Returns
    -------
    numpy.ndarray
        Relative standard uncertainty of the lamp at each wavelength (dimensionless).
    """
    wl = np.asarray(wavelength_nm, dtype=float)
    return np.interp(wl, [400.0, 800.0], [at_400_nm, at_800_nm])


def lamp_colour_temperature_shape_nm(at_400_nm=0.091, at_800_nm=0.069):
    """c (nm) of the lamp error's colour-temperature part c / lambda, from its stated sigma at 400 and 800 nm.

    u(lambda)^2 = sigma_s^2 + (c / lambda)^2 at 400 and 800 nm (see the
    module docstring): c^2 = (u400^2 - u800^2) / (400^-2 - 800^-2). The
    manufacturer's 9.1 and 6.9 % give c = 27.4 nm and sigma_s = 6.0 %.

    Parameters
    ----------
    at_400_nm : float, default 0.091
        The lamp's relative standard uncertainty at 400 nm (dimensionless).
    at_800_nm : float, default 0.069
        The lamp's relative standard uncertainty at 800 nm (dimensionless).

    Returns
    -------
    float
        c (nm): the relative uncertainty of the colour-temperature part at wavelength lambda is c / lambda.

    Raises
    ------
    ValueError
        When the two numbers allow no such split (u400 < u800, or a negative constant part).
    """
    c2 = (at_400_nm**2 - at_800_nm**2) / (1 / 400.0**2 - 1 / 800.0**2)
    if c2 < 0 or at_800_nm**2 < c2 / 800.0**2:
        raise ValueError(f"lamp uncertainty {at_400_nm:g} at 400 nm and {at_800_nm:g} at 800 nm cannot be split "
                         "into a constant and a colour-temperature (1/lambda) part; use lamp_model 'profile'")
    return float(np.sqrt(c2))


def absolute_calibration_budget(
    wavelength_nm,
    source_spectrum,
    response,
    dn_per_s,
    dn_per_s_sigma,
    spectrum_noise_sigma=None,
    reference_wavelength_nm=REFERENCE_WAVELENGTH_NM,
    reference_value=REFERENCE_RADIANCE_W_SR_M2_NM,
    reference_sigma=REFERENCE_RADIANCE_SIGMA_W_SR_M2_NM,
    lamp_relative_sigma="manufacturer",
    lamp_reference_correlation=0.0,
    extra_components=None,
    lamp_model="colour_temperature",
    response_relative_sigma=0.0,
):
    """R^-1 of one band from the source spectrum, the reference reading and the image DN.

    Section 2.6: the relative source spectrum is scaled to the reference
    reading at 589 nm, reduced to an effective band radiance by Eq. (3),
    and divided by the source's y_DN (Eq. 9).

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelengths, shape (n,), increasing, covering the band and the reference wavelength (nm).
    source_spectrum : array_like
        Relative source spectrum from the spectrometer, shape (n,), any unit.
    response : array_like
        Relative spectral response of the band, shape (n,) (dimensionless).
    dn_per_s : float
        The source's y_DN (ADU s-1 at ISO 100).
    dn_per_s_sigma : float
        Its standard uncertainty (ADU s-1; the paper: standard deviation in the mask).
    spectrum_noise_sigma : array_like, optional
        Spectrometer noise, shape (n,), same unit as ``source_spectrum``, independent per wavelength (also
        enters through the value at 589 nm).
    reference_wavelength_nm : float, default 589.0
        Wavelength of the reference reading used for scaling (nm).
    reference_value : float, default 0.68e-3
        The reference reading (W sr-1 m-2 nm-1; default the C-OPS 0.68 mW sr-1 m-2 nm-1).
    reference_sigma : float, default 0.02e-3
        Its standard uncertainty (W sr-1 m-2 nm-1).
    lamp_relative_sigma : str, float, tuple or numpy.ndarray or None, default "manufacturer"
        ``"manufacturer"`` (9.1 % at 400 nm to 6.9 % at 800 nm) or None to leave it out; with
        ``lamp_model="colour_temperature"`` also a pair (sigma at 400 nm, sigma at 800 nm); with ``"profile"``
        also a scalar or an (n,) array (relative, dimensionless).
    lamp_reference_correlation : float, default 0.0
        rho in [0, 1], ``"profile"`` only; see the module docstring.
    extra_components : dict[str, float], optional
        Name -> relative standard uncertainty of the source radiance that the user supplies (e.g. sphere drift
        measured in the lab); independent of each other and of the other terms; each is reported as
        ``extra:<name>``, their quadrature sum as ``extra``.
    lamp_model : str, default "colour_temperature"
        ``"colour_temperature"`` (the scale part cancels in the rescaling, the 1/lambda part propagates) or
        ``"profile"`` (the paper's counting); see the module docstring.
    response_relative_sigma : float, default 0.0
        Relative uncertainty of y_DN from the fitted response corrections (shutter offset, ISO gain factor,
        nonlinearity) applied by the measurement chain; common to every frame of the band.

    Returns
    -------
    dict
        ``inverse_responsivity`` (W sr-1 m-2 nm-1 per ADU s-1), ``inverse_responsivity_sigma`` (same unit),
        ``relative_sigma`` (dimensionless), ``effective_radiance`` (W sr-1 m-2 nm-1),
        ``effective_radiance_sigma``, ``contributions`` (relative standard uncertainty of each term:
        ``lamp_calibration``, ``reference``, ``spectrometer_noise``, ``extra``, ``image``, ``response`` and each
        ``extra:<name>``) and ``dominant`` (name of the largest term).

    Raises
    ------
    ValueError
        On an unknown ``lamp_model`` or ``lamp_relative_sigma``, a negative extra component, or a lamp
        uncertainty that :func:`lamp_colour_temperature_shape_nm` cannot split.
    """
    wl = np.asarray(wavelength_nm, dtype=float)
    spec = np.asarray(source_spectrum, dtype=float)
    s = np.asarray(response, dtype=float)
    scaled = scale_to_reference(wl, spec, reference_wavelength_nm, reference_value, reference_sigma)
    radiance = scaled["radiance"]
    l_eff = float(effective_band_radiance(wl, radiance, s))
    contrib = {"reference": float(reference_sigma / reference_value)}

    if lamp_relative_sigma is None:
        contrib["lamp_calibration"] = 0.0
    elif lamp_model == "colour_temperature":
        if isinstance(lamp_relative_sigma, str):
            if lamp_relative_sigma != "manufacturer":
                raise ValueError("lamp_relative_sigma must be 'manufacturer', a pair (400 nm, 800 nm) or None")
            at_400, at_800 = 0.091, 0.069
        else:
            at_400, at_800 = (float(v) for v in lamp_relative_sigma)
        c_nm = lamp_colour_temperature_shape_nm(at_400, at_800)
        weight = radiance * s
        inv_band = float(np.trapezoid(weight / wl, wl) / np.trapezoid(weight, wl))
        contrib["lamp_calibration"] = float(c_nm * abs(inv_band - 1.0 / reference_wavelength_nm))
    elif lamp_model == "profile":
        if isinstance(lamp_relative_sigma, str):
            if lamp_relative_sigma != "manufacturer":
                raise ValueError("lamp_relative_sigma must be 'manufacturer', a number, an array or None")
            u_lamp = lamp_calibration_relative_sigma(wl)
        else:
            u_lamp = np.broadcast_to(np.asarray(lamp_relative_sigma, dtype=float), wl.shape)
        _, band_abs = effective_band_radiance(wl, radiance, s, radiance_sigma_correlated=u_lamp * radiance)
        u_band = band_abs / l_eff
        u_ref_lamp = float(np.interp(reference_wavelength_nm, wl, u_lamp))
        contrib["lamp_calibration"] = float(abs(u_band - lamp_reference_correlation * u_ref_lamp))
    else:
        raise ValueError(f"lamp_model must be 'colour_temperature' or 'profile', got {lamp_model!r}")

    if spectrum_noise_sigma is None:
        contrib["spectrometer_noise"] = 0.0
    else:
        noise = np.asarray(spectrum_noise_sigma, dtype=float)
        sc = scaled["scale"]
        _, band_noise = effective_band_radiance(wl, radiance, s, radiance_sigma=noise * sc)
        # noise of the (interpolated) spectrum at the reference wavelength,
        # common to all wavelengths after scaling
        ref_noise = float(
            scale_to_reference(wl, spec, reference_wavelength_nm, reference_value, 0.0, spectrum_sigma=noise)[
                "relative_sigma_correlated"
            ]
        )
        # the band average and the reference point are treated as independent
        # (the reference point enters the band average with a small weight)
        contrib["spectrometer_noise"] = float(np.hypot(band_noise / l_eff, ref_noise))

    extras = {f"extra:{name}": float(value) for name, value in (extra_components or {}).items()}
    if any(v < 0 for v in extras.values()):
        raise ValueError(f"extra uncertainty components must be >= 0, got {extras}")
    contrib["extra"] = float(np.sqrt(sum(v**2 for v in extras.values())))
    contrib["image"] = float(dn_per_s_sigma / dn_per_s)
    contrib["response"] = float(response_relative_sigma)
    u_l = float(np.sqrt(sum(v**2 for k, v in contrib.items() if k not in ("image", "response"))))
    contrib.update(extras)      # listed one by one; already in u_l through their sum 'extra'
    y_sigma = float(dn_per_s) * float(np.hypot(contrib["image"], contrib["response"]))
    r_inv, r_inv_sigma = inverse_responsivity(l_eff, float(dn_per_s), l_eff * u_l, y_sigma)
    r_inv, r_inv_sigma = float(r_inv), float(r_inv_sigma)
    return {
        "inverse_responsivity": r_inv,
        "inverse_responsivity_sigma": r_inv_sigma,
        "relative_sigma": r_inv_sigma / abs(r_inv),
        "effective_radiance": l_eff,
        "effective_radiance_sigma": l_eff * u_l,
        "contributions": contrib,
        "dominant": max((k for k in contrib if not k.startswith("extra:")), key=contrib.get),
    }
