"""The lab's systematic errors, drawn once per simulated dataset from its seed.

A real calibration lab gets its scales from instruments whose own
calibrations are wrong by unknown amounts, the same for every frame of the
session. The simulator draws them once per dataset (from the seed alone, on a
random stream of their own, so switching them on changes no other draw) and
writes the drawn values to the truth folder; the pipeline sees only the
sidecars the lab wrote with them, and their stated uncertainties.

Sizes (Larouche et al. 2024, Sections 2.5 and 3.5):

* Spectrometer calibration lamp (Ocean Optics HL-3P-INT-CAL): the
  manufacturer states 9.1 % at 400 nm and 6.9 % at 800 nm. The error is drawn
  as a wavelength-independent scale part s ~ N(0, sigma_s) times the exact
  Planck ratio B(lambda, T + dT) / B(lambda, T) of a colour-temperature error
  dT ~ N(0, sigma_T) of the tungsten-halogen lamp: a smooth shape across
  wavelength, about proportional to 1/lambda. sigma_s and sigma_T are the
  split of the two stated numbers into a constant and a 1/lambda part,
  u(lambda)^2 = sigma_s^2 + (c / lambda)^2 (Wien's approximation,
  d ln B / dT = c2 / (lambda T^2)): sigma_s = 6.0 %, c = 27.4 nm (6.9 % at
  400 nm), sigma_T = c T^2 / c2 = 14.9 K at T = 2796 K (the paper gives no
  colour temperature for the calibration lamp; the source lamp's is used).
* Reference radiometer (C-OPS) at 589 nm: a scale error ~ N(0, 2.5 %), "a
  conservative uncertainty of 2.5 %" (Section 3.5), which its sidecar states.
* Reference photodiode of the spectral experiment: the beam it reads differs
  from the one reaching the camera by "smaller than 2 % in the visible"
  (Section 2.5). Drawn as a scale (cancels in the peak normalisation) times a
  smooth shape, 1 + a0 + a1 x + a2 (3 x^2 - 1) / 2 with x = -1 at 400 nm and
  +1 at 700 nm and each a ~ N(0, 0.6 %), so that the shape (a1 and a2 terms)
  stays within 2 % over 400-700 nm in 96 % of datasets. The spectral stage states no term for it; its effect on R^-1
  (through Eq. 3, the band-average of a smooth tilt) is about 0.1 %.
"""

from __future__ import annotations

import numpy as np

from pipeline.radiometry.source import QTH_TEMPERATURE_K, planck_radiance

#: second radiation constant h c / k_B, nm K
SECOND_RADIATION_CONSTANT_NM_K = 1.438777e7
#: manufacturer's relative uncertainty of the spectrometer's calibration lamp (Section 3.5)
LAMP_RELATIVE_SIGMA_400NM = 0.091
LAMP_RELATIVE_SIGMA_800NM = 0.069
#: colour temperature whose error shapes the lamp error (the source lamp's, Section 2.2)
LAMP_TEMPERATURE_K = QTH_TEMPERATURE_K
#: the reference radiometer's stated relative uncertainty at 589 nm (Section 3.5)
REFERENCE_RELATIVE_SIGMA = 0.025
#: photodiode-to-camera beam difference: sigma of each Legendre coefficient (Section 2.5: under 2 %)
PHOTODIODE_COEFFICIENT_SIGMA = 0.006
PHOTODIODE_RANGE_NM = (400.0, 700.0)
#: the draws' own random stream: [seed, this]
STREAM = 60221


def lamp_error_sizes(at_400_nm: float = LAMP_RELATIVE_SIGMA_400NM, at_800_nm: float = LAMP_RELATIVE_SIGMA_800NM,
                     temperature_k: float = LAMP_TEMPERATURE_K) -> dict[str, float]:
    """Scale sigma (1) and colour-temperature sigma (K) reproducing the stated sigma at 400 and 800 nm.

    u(lambda)^2 = sigma_s^2 + (c / lambda)^2, solved for sigma_s and c from the two stated numbers; the
    colour-temperature sigma is c T^2 / c2 (Wien's approximation).

    Parameters
    ----------
    at_400_nm : float, optional
        The lamp's stated relative uncertainty at 400 nm; default 0.091.
    at_800_nm : float, optional
        Its stated relative uncertainty at 800 nm; default 0.069.
    temperature_k : float, optional
        The lamp's colour temperature, K; default ``LAMP_TEMPERATURE_K`` (the source lamp's).

    Returns
    -------
    dict[str, float]
        ``scale_sigma`` (relative, dimensionless), ``shape_nm`` (c, nm) and ``colour_temperature_sigma_K`` (K).
    """
    c2 = (at_400_nm**2 - at_800_nm**2) / (1 / 400.0**2 - 1 / 800.0**2)
    scale = np.sqrt(at_800_nm**2 - c2 / 800.0**2)
    return {"scale_sigma": float(scale), "shape_nm": float(np.sqrt(c2)),
            "colour_temperature_sigma_K": float(np.sqrt(c2) * temperature_k**2 / SECOND_RADIATION_CONSTANT_NM_K)}


def draw_lab_errors(seed: int) -> dict[str, float]:
    """The lab's systematic errors of one dataset (dimensionless, K).

    Drawn from ``numpy.random.default_rng([seed, STREAM])``: a stream of their own, so switching them on
    changes no other draw.

    Parameters
    ----------
    seed : int
        The dataset's seed.

    Returns
    -------
    dict
        ``lamp_scale`` (relative), ``lamp_colour_temperature_error_K`` (K), ``reference_relative_error``
        (relative, the reference radiometer's scale) and ``photodiode_coefficients`` (three Legendre
        coefficients, relative).
    """
    rng = np.random.default_rng([seed, STREAM])
    sizes = lamp_error_sizes()
    z = rng.standard_normal(6)
    return {"lamp_scale": float(sizes["scale_sigma"] * z[0]),
            "lamp_colour_temperature_error_K": float(sizes["colour_temperature_sigma_K"] * z[1]),
            "reference_relative_error": float(REFERENCE_RELATIVE_SIGMA * z[2]),
            "photodiode_coefficients": [float(PHOTODIODE_COEFFICIENT_SIGMA * v) for v in z[3:6]]}


def no_lab_errors() -> dict[str, float]:
    """A perfect lab: every systematic error zero.

    Returns
    -------
    dict
        The keys of :func:`draw_lab_errors`, all zero.
    """
    return {"lamp_scale": 0.0, "lamp_colour_temperature_error_K": 0.0, "reference_relative_error": 0.0,
            "photodiode_coefficients": [0.0, 0.0, 0.0]}


def lamp_factor(wavelength_nm, errors: dict) -> np.ndarray:
    """1 + relative error of the spectrometer's calibrated spectrum at ``wavelength_nm``.

    (1 + scale) B(lambda, T + dT) / B(lambda, T), B Planck's law at the lamp's colour temperature T.

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelength, nm.
    errors : dict
        The lab's errors (:func:`draw_lab_errors`): ``lamp_scale`` and ``lamp_colour_temperature_error_K``.

    Returns
    -------
    numpy.ndarray
        The factor on the true spectrum, dimensionless, shaped like ``wavelength_nm``.
    """
    wl = np.asarray(wavelength_nm, dtype=float)
    t = LAMP_TEMPERATURE_K
    ratio = planck_radiance(wl, t + errors["lamp_colour_temperature_error_K"]) / planck_radiance(wl, t)
    return (1.0 + errors["lamp_scale"]) * ratio


def photodiode_factor(wavelength_nm, errors: dict) -> np.ndarray:
    """1 + relative error of the photodiode reading against the beam reaching the camera.

    1 + a0 + a1 x + a2 (3 x^2 - 1) / 2, x = -1 at 400 nm and +1 at 700 nm.

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelength, nm.
    errors : dict
        The lab's errors (:func:`draw_lab_errors`): ``photodiode_coefficients`` (a0, a1, a2).

    Returns
    -------
    numpy.ndarray
        The factor, dimensionless, shaped like ``wavelength_nm``.
    """
    lo, hi = PHOTODIODE_RANGE_NM
    x = (2.0 * np.asarray(wavelength_nm, dtype=float) - lo - hi) / (hi - lo)
    a0, a1, a2 = errors["photodiode_coefficients"]
    return 1.0 + a0 + a1 * x + a2 * 0.5 * (3.0 * x**2 - 1.0)
