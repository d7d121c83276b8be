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
    "band_statistics",
    "effective_band_radiance",
]


def trapezoid_weights(x):
    """Weights w with sum(w * y) == trapezoid(y, x) for a 1-D abscissa x (same unit as x)."""
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
        cov_ij = S_i S_j (u_i^2 delta_ij + u_p^2 - u_p^2 (delta_ip + delta_jp))
        with u relative uncertainties of r and p the peak index; S_p = 1
        exactly, with zero uncertainty.

    Returns
    -------
    S, sigma_S[, cov_S]  (dimensionless).
    """
    dn = np.asarray(dn, dtype=float)
    pd = np.asarray(photodiode, dtype=float)
    r = dn / pd
    u2 = np.zeros_like(r)
    if dn_sigma is not None:
        u2 = u2 + (np.asarray(dn_sigma, dtype=float) / dn) ** 2
    if photodiode_sigma is not None:
        u2 = u2 + (np.asarray(photodiode_sigma, dtype=float) / pd) ** 2
    ip = np.argmax(r, axis=-1)
    rp = np.take_along_axis(r, ip[..., None], axis=-1)
    up2 = np.take_along_axis(u2, ip[..., None], axis=-1)
    s = r / rp
    n = r.shape[-1]
    is_peak = np.arange(n) == ip[..., None]
    var = np.where(is_peak, 0.0, s**2 * (u2 + up2))
    sigma = np.sqrt(var)
    if not return_covariance:
        return s, sigma
    onehot = is_peak.astype(float)
    # relative covariance of S_i = r_i / r_p: diag(u2) + up2 (1 - e_p)(1 - e_p)^T - diag(u2 at p)
    not_p = 1.0 - onehot
    rel = np.einsum("...i,...j->...ij", not_p, not_p) * up2[..., None]
    rel = rel + np.einsum("...i,ij->...ij", u2 * not_p, np.eye(n))
    cov = rel * np.einsum("...i,...j->...ij", s, s)
    return s, sigma, cov


def bandwidth(wavelength_nm, response, axis=-1):
    """Bandwidth Lambda = int S_R dlambda (nm) of a peak-normalised response (trapezoid)."""
    return np.trapezoid(np.asarray(response, dtype=float), np.asarray(wavelength_nm, dtype=float), axis=axis)


def effective_wavelength(wavelength_nm, response, axis=-1):
    """Effective wavelength, Eq. (8): int lambda S dlambda / int S dlambda (nm), trapezoid."""
    wl = np.asarray(wavelength_nm, dtype=float)
    s = np.moveaxis(np.asarray(response, dtype=float), axis, -1)
    return np.trapezoid(wl * s, wl, axis=-1) / np.trapezoid(s, wl, axis=-1)


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
    dict: ``effective_wavelength_nm``, ``bandwidth_nm``, ``half_bandwidth_nm``
    and, with a covariance, ``*_sigma`` by linear propagation (gradients
    of Eq. 8 and of Lambda with respect to each S_i).
    """
    wl = np.asarray(wavelength_nm, dtype=float)
    s = np.asarray(response, dtype=float)
    w = trapezoid_weights(wl)
    lam_bw = float(np.sum(w * s))
    lam_eff = float(np.sum(w * wl * s) / lam_bw)
    out = {
        "effective_wavelength_nm": lam_eff,
        "bandwidth_nm": lam_bw,
        "half_bandwidth_nm": lam_bw / 2.0,
    }
    if response_covariance is not None:
        c = np.asarray(response_covariance, dtype=float)
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

    L_eff = sum_k w_k L_k S_k / sum_k w_k S_k, with w the trapezoid weights.

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
    wl = np.asarray(wavelength_nm, dtype=float)
    L = np.asarray(radiance, dtype=float)
    s = np.asarray(response, dtype=float)
    ws = trapezoid_weights(wl) * s
    k = ws / np.sum(ws, axis=-1, keepdims=True)
    l_eff = np.sum(k * L, axis=-1)
    if radiance_sigma is None and radiance_sigma_correlated is None:
        return l_eff
    var = np.zeros_like(l_eff)
    if radiance_sigma is not None:
        var = var + np.sum((k * np.asarray(radiance_sigma, dtype=float)) ** 2, axis=-1)
    if radiance_sigma_correlated is not None:
        var = var + np.sum(k * np.asarray(radiance_sigma_correlated, dtype=float), axis=-1) ** 2
    return l_eff, np.sqrt(var)
