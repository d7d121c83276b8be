"""The field scale closure: each band's camera/reference scale against what the lab calibration predicts
(Larouche et al. 2024, Sections 2.6, 2.9, 3.5 and 4).

The field match-up is the one comparison of the calibration with an instrument it was not fitted to. Its
frame table fits one free scale k_b per band (camera = k_b x reference) and tests the shape of the hour
about it; the scale itself is the calibration's absolute claim. With every effect of the model applied,
the lab calibration predicts k_b = 1 against the reference the model compares with (the band-convolved
channels with ``spectral_mismatch`` in the model, the nearest channel otherwise). The closure's row of a
band is ln(k_b), its noise the relative standard uncertainty of the scale, the quadrature sum of
:data:`SCALE_TERMS`:

* ``fit``: the scale's standard error from the match-up fit (scaled up by the frame table's rms z when
  the hour's shape is not at its noise floor);
* ``camera_calibration``: the bundle's systematic terms over the mask's pixels (R^-1's budget, roll-off
  and field angle, flat field, the response corrections; the chain's systematic sigma), common to every
  frame of a band and so absent from the match-up noise;
* ``reference_calibration``: the reference radiometer's own calibration (site.yaml
  ``reference.calibration_relative_sigma``); counted as independent of the lab's reference reading of the
  source, which is conservative when the same instrument served both (Section 2.6 scaled the source to
  the C-OPS that later stood in the field: its absolute error then cancels in part);
* ``spectral_mismatch_prediction``: how far the reference the model compares with may sit from the band
  radiance. The band-convolved reference: the response's position (the effective wavelength's
  uncertainty times the scene's in-band spectral slope, d ln L / d ln lambda) and the part of the response
  outside the channels' span, which the convolution leaves out (a share f of the response whose radiance
  is unknown: uniform within +-f, f / sqrt 3). The nearest channel (without ``spectral_mismatch`` in the
  model): besides those, its own departure from the band-convolved reference over the match-ups,
  |ln(convolved / nearest)| (:func:`nearest_channel_relative_sigma`). A broad band's nearest channel
  is one wavelength of the sky's spectrum, and which channel is nearest turns on a few nanometres of the
  effective wavelength (the default camera's close-lens G band, 544.4 nm, lies 10.6 nm from 555 and
  12.4 nm from 532 nm; the clear sky differs by 7 % between them): the comparison states that
  difference, which the reference itself measures, instead of taking the channel for the band.

Effects the model lacks move the scale by what their lab-fitted parameter predicts at the field frames'
setting against the absolute experiment's (the effects' ``predicted_shift``); the field stage writes the
covariates they need only for the effects the model lacks (the chain corrects the others).
"""

from __future__ import annotations

import numpy as np

__all__ = ["SCALE_TERMS", "mismatch_prediction_relative_sigma", "nearest_channel_relative_sigma",
           "scale_relative_sigma"]

#: the terms of a band's field scale budget, relative standard uncertainties
SCALE_TERMS = ("fit", "camera_calibration", "reference_calibration", "spectral_mismatch_prediction")


def mismatch_prediction_relative_sigma(spectral_slope, wavelength_nm: float, wavelength_sigma_nm: float,
                                       outside_fraction: float) -> float:
    """Relative uncertainty of the band-convolved reference as the band radiance (see the module docstring):
    |d ln L / d ln lambda| x sigma_lambda / lambda in quadrature with outside_fraction / sqrt(3).

    NaN inputs count as 0.

    Parameters
    ----------
    spectral_slope : float
        The scene's in-band spectral slope d ln L / d ln lambda (dimensionless).
    wavelength_nm : float
        The band's effective wavelength lambda (nm).
    wavelength_sigma_nm : float
        Standard uncertainty of the effective wavelength sigma_lambda (nm).
    outside_fraction : float
        Share f of the band's response outside the reference channels' span (dimensionless).

    Returns
    -------
    float
        The ``spectral_mismatch_prediction`` term, a relative standard uncertainty (dimensionless).
    """
    slope = float(np.nan_to_num(spectral_slope))
    position = abs(slope) * float(np.nan_to_num(wavelength_sigma_nm)) / float(wavelength_nm)
    return float(np.hypot(position, float(np.nan_to_num(outside_fraction)) / np.sqrt(3.0)))


def nearest_channel_relative_sigma(mismatch_factor: float, convolved_sigma: float) -> float:
    """Relative uncertainty of the nearest reference channel as the band radiance (see the module docstring).

    Parameters
    ----------
    mismatch_factor : float
        The band-convolved over the nearest channel's reference, mean over the match-ups.
    convolved_sigma : float
        Relative uncertainty of the band-convolved reference as the band radiance
        (:func:`mismatch_prediction_relative_sigma`).

    Returns
    -------
    float
        |ln(mismatch_factor)| in quadrature with ``convolved_sigma`` (``convolved_sigma`` alone when the
        factor is not finite and positive).
    """
    m = float(mismatch_factor)
    departure = abs(np.log(m)) if np.isfinite(m) and m > 0 else 0.0
    return float(np.hypot(departure, float(np.nan_to_num(convolved_sigma))))


def scale_relative_sigma(terms: dict[str, float]) -> float:
    """Quadrature sum of a band's :data:`SCALE_TERMS` (relative).

    Parameters
    ----------
    terms : dict[str, float]
        Term name -> relative standard uncertainty (dimensionless); a missing or NaN term counts as 0, a name
        outside :data:`SCALE_TERMS` is ignored.

    Returns
    -------
    float
        Relative standard uncertainty of the band's field scale (dimensionless).
    """
    return float(np.sqrt(sum(float(np.nan_to_num(terms.get(t, 0.0))) ** 2 for t in SCALE_TERMS)))
