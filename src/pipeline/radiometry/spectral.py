"""Relative spectral response, effective wavelength, bandwidth and band radiance.

Larouche et al. (2024), Sections 2.1, 2.5 and 3.4:

* The response is measured as camera DN per reference-photodiode signal at
  each monochromator wavelength (400-700 nm, 10 nm steps) and divided by its
  peak value, giving the peak-normalised response S_R,i(lambda).
* Effective wavelength, Eq. (8):
  lambda_eff = int lambda S_R dlambda / int S_R dlambda.
* Bandwidth: Lambda_i = int S_R dlambda; the paper quotes
  lambda_eff +/- Lambda_i / 2 (R 600 +/- 38, G 540 +/- 60, B 480 +/- 49 nm),
  so the "half bandwidth" is Lambda_i / 2.
* Effective band radiance, Eq. (3):
  L_i = int L(lambda) S_R,i dlambda / int S_R,i dlambda.

All integrals use the trapezoidal rule, as in the paper.

Wavelengths in nm, radiances in W sr-1 m-2 nm-1 (any unit passes through).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "trapezoid_weights",
    "peak_normalise_response",
    "effective_wavelength",
    "bandwidth",
    "band_weights",
    "band_statistics",
    "effective_band_radiance",
]


def trapezoid_weights(x):
    """Weights w with sum(w * y) == trapezoid(y, x) for a 1-D abscissa x (same unit as x).

    Parameters
    ----------
    x : array_like
        The abscissa, shape (n,) with n >= 2 (e.g. wavelength in nm).

    Returns
    -------
    numpy.ndarray
        The weights, shape (n,), in the unit of ``x``.

    Raises
    ------
    ValueError
        When ``x`` is not 1-D or has fewer than two points.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 1 or x.size < 2:
        raise ValueError("x must be 1-D with at least two points")
    dx = np.diff(x)
    w = np.zeros_like(x)
    w[:-1] += dx / 2.0
    w[1:] += dx / 2.0
    return w


def peak_normalise_response(dn, photodiode, dn_sigma=None, photodiode_sigma=None, return_covariance=False):
    """Peak-normalised relative spectral response from DN and reference photodiode signals.

    r(lambda) = dn / photodiode; S = r / max(r) (Section 2.5).

    Parameters
    ----------
    dn : array_like (..., n_wavelength)
        Dark-corrected camera DN at each wavelength (last axis).
    photodiode : array_like, broadcastable to dn
        Reference photodiode signal at each wavelength (any unit).
    dn_sigma, photodiode_sigma : array_like, optional
        Standard uncertainties, independent between wavelengths.
    return_covariance : bool
        Also return the covariance matrix of S along the last axis.  All
        points share the peak value, so they are positively correlated:
        cov_ij = delta_ij sigma_r,i^2 / r_p^2 + S_i S_j u_p^2 for i, j != p,
        zero on the peak row and column (S_p = 1 exactly), with
        sigma_r^2 = (sigma_dn / pd)^2 + (dn sigma_pd / pd^2)^2 the absolute
        uncertainty of r and u_p = sigma_r,p / r_p.  Written with absolute
        uncertainties of r, so that wavelengths where a band has no signal
        (dn = 0, e.g. R at 400 nm) keep a finite uncertainty.

    Returns
    -------
    S, sigma_S[, cov_S]  (dimensionless).
    """
    dn = np.asarray(dn, dtype=float)
    pd = np.asarray(photodiode, dtype=float)
    r = dn / pd
    sr2 = np.zeros_like(r)
    if dn_sigma is not None:
        sr2 = sr2 + (np.asarray(dn_sigma, dtype=float) / pd) ** 2
    if photodiode_sigma is not None:
        sr2 = sr2 + (dn * np.asarray(photodiode_sigma, dtype=float) / pd**2) ** 2
    ip = np.argmax(r, axis=-1)
    rp = np.take_along_axis(r, ip[..., None], axis=-1)
    up2 = np.take_along_axis(sr2, ip[..., None], axis=-1) / rp**2
    s = r / rp
    n = r.shape[-1]
    not_p = (np.arange(n) != ip[..., None]).astype(float)
    var = not_p * (sr2 / rp**2 + s**2 * up2)
    sigma = np.sqrt(var)
    if not return_covariance:
        return s, sigma
    cov = np.einsum("...i,...j->...ij", s * not_p, s * not_p) * up2[..., None]
    cov = cov + np.einsum("...i,ij->...ij", sr2 * not_p / rp**2, np.eye(n))
    return s, sigma, cov


def bandwidth(wavelength_nm, response, axis=-1):
    """Bandwidth Lambda = int S_R dlambda (nm) of a peak-normalised response (trapezoid, Section 2.5).

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelengths of the response, shape (n,) (nm).
    response : array_like
        Peak-normalised response S_R (dimensionless), n values along ``axis``.
    axis : int, default -1
        Axis of ``response`` that runs over wavelength.

    Returns
    -------
    numpy.ndarray or float
        Bandwidth Lambda (nm), one per response.
    """
    s = np.moveaxis(np.asarray(response, dtype=float), axis, -1)
    return np.sum(trapezoid_weights(wavelength_nm) * s, axis=-1)


def band_weights(wavelength_nm, response):
    """Normalised weights k_j = w_j S_j / sum_l w_l S_l of Eq. (3), w the trapezoid weights.

    Any quantity X(lambda) sampled on ``wavelength_nm`` has the band average
    int X S dlambda / int S dlambda = sum_j k_j X_j: Eq. (3) with X the
    spectral radiance, Eq. (8) with X = lambda. Peak normalisation cancels.

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelengths, shape (n,) (nm).
    response : array_like
        Spectral response, shape (n,) or (..., n), any scale.

    Returns
    -------
    numpy.ndarray
        The weights k (dimensionless), shape of ``response``, summing to 1 along the last axis.
    """
    ws = trapezoid_weights(wavelength_nm) * np.asarray(response, dtype=float)
    return ws / np.sum(ws, axis=-1, keepdims=True)


def effective_wavelength(wavelength_nm, response, axis=-1):
    """Effective wavelength, Eq. (8): int lambda S dlambda / int S dlambda (nm), trapezoid.

    The band average of lambda itself, i.e. Eq. (3) with L(lambda) = lambda
    (:func:`effective_band_radiance`).

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelengths, shape (n,) (nm).
    response : array_like
        Spectral response (any scale), n values along ``axis``.
    axis : int, default -1
        Axis of ``response`` that runs over wavelength.

    Returns
    -------
    numpy.ndarray or float
        Effective wavelength lambda_eff (nm), one per response.
    """
    wl = np.asarray(wavelength_nm, dtype=float)
    s = np.moveaxis(np.asarray(response, dtype=float), axis, -1)
    return effective_band_radiance(wl, wl, s)


def band_statistics(wavelength_nm, response, response_covariance=None):
    """Effective wavelength, bandwidth and half bandwidth of one band, with uncertainties.

    Parameters
    ----------
    wavelength_nm : (n,) nm
    response : (n,) peak-normalised response
    response_covariance : (n, n), optional
        Covariance of the response (e.g. from peak_normalise_response).

    Returns
    -------
    dict: ``effective_wavelength_nm`` (Eq. 8, :func:`effective_wavelength`),
    ``bandwidth_nm`` (:func:`bandwidth`), ``half_bandwidth_nm`` and, with a
    covariance, ``*_sigma`` by linear propagation (gradients of Eq. 8 and
    of Lambda with respect to each S_i).
    """
    wl = np.asarray(wavelength_nm, dtype=float)
    s = np.asarray(response, dtype=float)
    lam_bw = float(bandwidth(wl, s))
    lam_eff = float(effective_wavelength(wl, s))
    out = {
        "effective_wavelength_nm": lam_eff,
        "bandwidth_nm": lam_bw,
        "half_bandwidth_nm": lam_bw / 2.0,
    }
    if response_covariance is not None:
        c = np.asarray(response_covariance, dtype=float)
        w = trapezoid_weights(wl)
        g_bw = w
        g_eff = w * (wl - lam_eff) / lam_bw
        out["bandwidth_nm_sigma"] = float(np.sqrt(g_bw @ c @ g_bw))
        out["half_bandwidth_nm_sigma"] = out["bandwidth_nm_sigma"] / 2.0
        out["effective_wavelength_nm_sigma"] = float(np.sqrt(g_eff @ c @ g_eff))
    return out


def effective_band_radiance(
    wavelength_nm,
    radiance,
    response,
    radiance_sigma=None,
    radiance_sigma_correlated=None,
):
    """Effective band radiance, Eq. (3), by the trapezoidal rule, with its uncertainty.

    L_eff = sum_k w_k L_k S_k / sum_k w_k S_k, with w the trapezoid weights
    (:func:`band_weights`).

    Parameters
    ----------
    wavelength_nm : (n,) nm
    radiance : (..., n) spectral radiance, e.g. W sr-1 m-2 nm-1
        (interpolate the spectrum onto the response grid first).
    response : (n,) or (..., n) spectral response (peak normalisation cancels).
    radiance_sigma : (..., n), optional
        Uncertainty independent from wavelength to wavelength (spectrometer
        noise): sigma^2 = sum (w_k S_k / sum w S)^2 sigma_k^2.
    radiance_sigma_correlated : (..., n), optional
        Uncertainty fully correlated across wavelengths (lamp calibration,
        reference scale): sigma = sum (w_k S_k / sum w S) sigma_k.

    Returns
    -------
    L_eff, or (L_eff, sigma) when any uncertainty is given (the two parts
    add in quadrature), in the unit of ``radiance``.
    """
    L = np.asarray(radiance, dtype=float)
    k = band_weights(wavelength_nm, response)
    l_eff = np.sum(k * L, axis=-1)
    if radiance_sigma is None and radiance_sigma_correlated is None:
        return l_eff
    var = np.zeros_like(l_eff)
    if radiance_sigma is not None:
        var = var + np.sum((k * np.asarray(radiance_sigma, dtype=float)) ** 2, axis=-1)
    if radiance_sigma_correlated is not None:
        var = var + np.sum(k * np.asarray(radiance_sigma_correlated, dtype=float), axis=-1) ** 2
    return l_eff, np.sqrt(var)
