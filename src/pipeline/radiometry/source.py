"""Calibration source spectrum: Planck radiance and scaling to a reference reading.

Larouche et al. (2024), Sections 2.2 and 2.6: the source is a 2796 K
quartz-tungsten-halogen lamp behind an integrating sphere; its relative
spectrum (fibre spectrometer) is scaled so that its value at 589 nm equals
the C-OPS radiance there, 0.68 +/- 0.02 mW sr-1 m-2 nm-1.

Units: wavelength in nm, radiance in W sr-1 m-2 nm-1, temperature in K.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "PLANCK_H_J_S",
    "SPEED_OF_LIGHT_M_S",
    "BOLTZMANN_J_K",
    "QTH_TEMPERATURE_K",
    "REFERENCE_WAVELENGTH_NM",
    "REFERENCE_RADIANCE_W_SR_M2_NM",
    "REFERENCE_RADIANCE_SIGMA_W_SR_M2_NM",
    "planck_radiance",
    "scale_to_reference",
]

PLANCK_H_J_S = 6.62607015e-34
SPEED_OF_LIGHT_M_S = 299792458.0
BOLTZMANN_J_K = 1.380649e-23

#: Colour temperature of the QTH lamp (Section 2.2).
QTH_TEMPERATURE_K = 2796.0
#: C-OPS reference channel and reading (Section 3.5): 0.68 +/- 0.02 mW sr-1 m-2 nm-1.
REFERENCE_WAVELENGTH_NM = 589.0
REFERENCE_RADIANCE_W_SR_M2_NM = 0.68e-3
REFERENCE_RADIANCE_SIGMA_W_SR_M2_NM = 0.02e-3


def planck_radiance(wavelength_nm, temperature_k):
    """Blackbody spectral radiance B(lambda, T) in W sr-1 m-2 nm-1.

    B = 2 h c^2 / lambda^5 / (exp(h c / (lambda k T)) - 1), per metre of
    wavelength, times 1e-9 m/nm.  At 589 nm and 2796 K, B = 269.9
    W sr-1 m-2 nm-1 (the tests check Wien's displacement law and the
    Stefan-Boltzmann integral).

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelength in vacuum (nm).
    temperature_k : array_like
        Temperature of the blackbody (K).

    Returns
    -------
    numpy.ndarray
        Spectral radiance (W sr-1 m-2 nm-1), broadcast over the inputs.
    """
    lam_m = np.asarray(wavelength_nm, dtype=float) * 1e-9
    t = np.asarray(temperature_k, dtype=float)
    x = PLANCK_H_J_S * SPEED_OF_LIGHT_M_S / (lam_m * BOLTZMANN_J_K * t)
    return 2.0 * PLANCK_H_J_S * SPEED_OF_LIGHT_M_S**2 / lam_m**5 / np.expm1(x) * 1e-9


def scale_to_reference(
    wavelength_nm,
    spectrum,
    reference_wavelength_nm=REFERENCE_WAVELENGTH_NM,
    reference_value=REFERENCE_RADIANCE_W_SR_M2_NM,
    reference_sigma=REFERENCE_RADIANCE_SIGMA_W_SR_M2_NM,
    spectrum_sigma=None,
):
    """Scale a relative spectrum so that its value at the reference wavelength equals a reading.

    The spectrum is linearly interpolated at ``reference_wavelength_nm``;
    factor = reference_value / spectrum(reference).  The reference uncertainty
    becomes a relative uncertainty common to every wavelength (fully
    correlated): u_ref = reference_sigma / reference_value (2/68 = 2.9 % for
    the paper's C-OPS reading; the paper quotes a conservative 2.5 %).  When
    ``spectrum_sigma`` (independent per wavelength) is given, the noise of
    the interpolated spectrum at the reference wavelength adds to that
    common relative term.

    Parameters
    ----------
    wavelength_nm : (n,) nm, increasing
    spectrum : (..., n) relative spectrum (any unit)
    reference_wavelength_nm, reference_value, reference_sigma : reading and its
        standard uncertainty, in the radiance unit wanted for the output
    spectrum_sigma : (..., n), optional

    Returns
    -------
    dict with ``radiance`` (scaled spectrum), ``scale`` (factor),
    ``relative_sigma_correlated`` (scalar or (...,) relative uncertainty
    shared by all wavelengths) and, if ``spectrum_sigma`` was given,
    ``radiance_sigma_independent`` (scaled noise per wavelength).
    """
    wl = np.asarray(wavelength_nm, dtype=float)
    s = np.asarray(spectrum, dtype=float)
    j = np.searchsorted(wl, reference_wavelength_nm)
    if j <= 0 or j >= wl.size:
        if np.isclose(wl[0], reference_wavelength_nm):
            j = 1
        else:
            raise ValueError("reference wavelength outside the spectrum's range")
    f = (reference_wavelength_nm - wl[j - 1]) / (wl[j] - wl[j - 1])
    s_ref = (1.0 - f) * s[..., j - 1] + f * s[..., j]
    scale = reference_value / s_ref
    u_rel2 = (reference_sigma / reference_value) ** 2
    out = {"scale": scale}
    if spectrum_sigma is not None:
        ss = np.asarray(spectrum_sigma, dtype=float)
        s_ref_sigma = np.hypot((1.0 - f) * ss[..., j - 1], f * ss[..., j])
        u_rel2 = u_rel2 + (s_ref_sigma / s_ref) ** 2
        out["radiance_sigma_independent"] = ss * np.asarray(scale)[..., None]
    out["radiance"] = s * np.asarray(scale)[..., None]
    out["relative_sigma_correlated"] = np.sqrt(u_rel2)
    return out
