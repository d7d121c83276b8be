"""Refractive index of water and air.

The index of water follows the empirical equation of Quan and Fry (1995),
"Empirical equation for the index of refraction of seawater", Appl. Opt. 34,
3477-3480 (reference [63] of Larouche et al. 2024, Section 3.6, where it is
used to bound the effect of temperature and salinity on the immersion factor):

    n(S, T, lambda) = n0 + (n1 + n2 T + n3 T^2) S + n4 T^2
                      + (n5 + n6 S + n7 T) / lambda + n8 / lambda^2 + n9 / lambda^3

with lambda in nm, T in degrees Celsius and S in parts per thousand (taken
equal to PSU here). Quan and Fry fitted it to the data of Austin and Halikas
(1976) for 400-700 nm, 0-30 C and 0-35 per mille; the stated accuracy is
about 3e-5 inside that range.  Larouche et al. used it for -2 to 25 C.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "QUAN_FRY_COEFFICIENTS",
    "QUAN_FRY_VALID_WAVELENGTH_NM",
    "refractive_index_water",
    "refractive_index_air",
]

#: Coefficients n0..n9 of Quan and Fry (1995), Eq. (4) of that paper.
QUAN_FRY_COEFFICIENTS = {
    "n0": 1.31405,
    "n1": 1.779e-4,
    "n2": -1.05e-6,
    "n3": 1.6e-8,
    "n4": -2.02e-6,
    "n5": 15.868,
    "n6": 0.01155,
    "n7": -0.00423,
    "n8": -4382.0,
    "n9": 1.1455e6,
}

#: Wavelength range (nm) of the data Quan and Fry fitted.
QUAN_FRY_VALID_WAVELENGTH_NM = (400.0, 700.0)


def refractive_index_water(wavelength_nm, temperature_c=20.0, salinity_psu=0.0):
    """Real refractive index of (sea) water relative to vacuum-ish air, Quan and Fry (1995).

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelength in nm (the fit covers 400-700 nm; values outside are
        extrapolated without warning, the 1/lambda^3 form is smooth).
    temperature_c : array_like
        Water temperature in degrees Celsius (fit range 0-30 C).
    salinity_psu : array_like
        Salinity in PSU, treated as parts per thousand (fit range 0-35).

    Returns
    -------
    numpy.ndarray
        Refractive index (dimensionless), broadcast over the inputs.
        About 1.3330 at 589 nm, 20 C, 0 PSU; 1.3322 at 600 nm, 25 C.
    """
    lam = np.asarray(wavelength_nm, dtype=float)
    t = np.asarray(temperature_c, dtype=float)
    s = np.asarray(salinity_psu, dtype=float)
    c = QUAN_FRY_COEFFICIENTS
    return (
        c["n0"]
        + (c["n1"] + c["n2"] * t + c["n3"] * t**2) * s
        + c["n4"] * t**2
        + (c["n5"] + c["n6"] * s + c["n7"] * t) / lam
        + c["n8"] / lam**2
        + c["n9"] / lam**3
    )


def refractive_index_air(wavelength_nm=None):
    """Refractive index of air, taken as 1.0 (true value ~1.0003 in the visible).

    The 3e-4 departure changes an air-water Fresnel transmittance by under
    1e-5 and is far below every calibration uncertainty here.

    Parameters
    ----------
    wavelength_nm : array_like, optional
        Wavelengths (nm); only their shape is used.

    Returns
    -------
    float or numpy.ndarray
        1.0, or an array of ones shaped like ``wavelength_nm`` when given (dimensionless).
    """
    if wavelength_nm is None:
        return 1.0
    return np.ones_like(np.asarray(wavelength_nm, dtype=float))
