"""Immersion factor of the camera: n-squared law, fit of Zibordi's method, Eq. (10).

Larouche et al. (2024), Sections 2.7 and 3.6.  The measurement equation (4)
divides the in-air responsivity by the immersion factor I_i in water.

n-squared law
    Radiance crossing the air -> water surface rises by t_aw n_w^2 (radiance
    over n^2 is conserved across a flat interface, less the Fresnel loss).
    Eq. (11) is printed with t_aw n_w, but the text, Table 2 and the worked
    value 0.9797 x 1.3317^2 = 1.737 at 600 nm use t_aw n_w^2 (see
    docs/design.md, "Immersion"), which is what is implemented.

Experimental immersion factor (Eq. 11, Zibordi 2006 procedure)
    I = y_DN(0+) / y_DN(0-) * t_aw n_w^2
    y_DN(0-) is the intercept of ln y_DN(z) = ln y_DN(0-) - K z over water
    heights z above the camera (6 to 11 cm in 0.5 cm steps, 5 frames each).

Theoretical immersion factor of a flat external window (Eq. 10, Section 2.7, line "I = n_w (n_w + n_g)^2 / (1 + n_g)^2" of the paper)
    I = n_w (n_w + n_g)^2 / (1 + n_g)^2, with n_g the index of the external
    optical surface.  Its inverse has the closed form
    n_g = (n_w - r) / (r - 1), r = sqrt(I / n_w).

Units: heights in cm, attenuation coefficients in m^-1, digital numbers in
ADU or ADU/s (any consistent unit; ratios only).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from .fresnel import transmittance_air_water
from .water import refractive_index_water

__all__ = [
    "n_squared_law_factor",
    "n_squared_law_factor_at",
    "ImmersionFit",
    "fit_log_linear_attenuation",
    "immersion_factor_from_intercept",
    "fit_immersion_factor",
    "immersion_factor_flat_window",
    "window_index_from_immersion_factor",
    "in_water_dn",
]


def n_squared_law_factor(t_aw, n_w):
    """Radiance gain across the air -> water surface, t_aw * n_w^2 (dimensionless).

    E.g. 0.9797 * 1.3317^2 = 1.737 (Larouche et al. 2024, Table 2 at 600 nm).

    Parameters
    ----------
    t_aw : array_like
        Air -> water Fresnel power transmittance at normal incidence (dimensionless).
    n_w : array_like
        Refractive index of the water (dimensionless).

    Returns
    -------
    numpy.ndarray
        t_aw n_w^2 (dimensionless), broadcast over the inputs.
    """
    return np.asarray(t_aw, dtype=float) * np.asarray(n_w, dtype=float) ** 2


def n_squared_law_factor_at(wavelength_nm, temperature_c=25.0, salinity_psu=0.0):
    """t_aw n_w^2 at a wavelength from Quan and Fry n_w and the normal-incidence Fresnel t_aw.

    About 1.7387, 1.7437, 1.7503 at 600, 540, 480 nm, 25 C, 0 PSU (the paper's
    Table 2, from Hale and Querry 1973 indices, has 1.738, 1.742, 1.748).

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelength, e.g. the band's effective wavelength (nm).
    temperature_c : array_like, default 25.0
        Water temperature (degree Celsius).
    salinity_psu : array_like, default 0.0
        Salinity (PSU).

    Returns
    -------
    numpy.ndarray
        t_aw n_w^2 (dimensionless), broadcast over the inputs.
    """
    n_w = refractive_index_water(wavelength_nm, temperature_c, salinity_psu)
    return n_squared_law_factor(transmittance_air_water(wavelength_nm, temperature_c, salinity_psu), n_w)


@dataclass(frozen=True)
class ImmersionFit:
    """Result of the immersion-factor fit; DN in the unit of the inputs.

    Attributes
    ----------
    dn_below : y_DN(0-), exp(intercept) of the log-linear fit.
    dn_below_sigma : standard uncertainty of y_DN(0-) (delta method, dn_below * se(intercept)).
    dn_below_ci95 : (low, high) 95 % interval, exp of intercept +/- t(0.975, n-2) se.
    attenuation_per_cm, attenuation_per_cm_sigma : slope K (cm^-1) and its standard error.
    dof : residual degrees of freedom of the regression (n - 2).
    r_squared : coefficient of determination of the log-linear fit.
    dn_air, dn_air_sigma : y_DN(0+) and its standard uncertainty.
    n2_factor : t_aw n_w^2 used.
    immersion_factor, immersion_factor_sigma : I by Eq. (11) and its standard uncertainty.
    immersion_factor_ci95 : (low, high), Welch-Satterthwaite degrees of freedom (GUM G.4).
    residuals : ln y_DN - fitted, per input point.
    """

    dn_below: float
    dn_below_sigma: float
    dn_below_ci95: tuple
    attenuation_per_cm: float
    attenuation_per_cm_sigma: float
    dof: int
    r_squared: float
    dn_air: float
    dn_air_sigma: float
    n2_factor: float
    immersion_factor: float
    immersion_factor_sigma: float
    immersion_factor_ci95: tuple
    residuals: np.ndarray


def fit_log_linear_attenuation(height_cm, dn):
    """Ordinary least squares ln(dn) = c - K z.

    Parameters
    ----------
    height_cm : array_like, shape (n,)
        Water height z above the camera for each frame (cm).
    dn : array_like, shape (n,)
        Dark-corrected, exposure-normalised digital number per frame (> 0).

    Returns
    -------
    dict with ``intercept`` (ln DN at z = 0), ``intercept_se``, ``slope_per_cm``
    (K, positive for attenuation), ``slope_se``, ``dof`` (n - 2),
    ``r_squared``, ``residuals`` (ln units).  Standard errors use the residual
    variance (the scatter is dominated by surface wavelets and bubbles,
    Section 3.6, not by a known noise model).
    """
    z = np.asarray(height_cm, dtype=float).ravel()
    y = np.log(np.asarray(dn, dtype=float).ravel())
    if z.size != y.size:
        raise ValueError("height_cm and dn must have the same length")
    if z.size < 3:
        raise ValueError("need at least 3 points for a line with an error estimate")
    if not np.all(np.isfinite(y)):
        raise ValueError("dn must be positive and finite")
    n = z.size
    zm = z.mean()
    sxx = np.sum((z - zm) ** 2)
    if sxx == 0:
        raise ValueError("need at least two distinct water heights")
    slope = np.sum((z - zm) * (y - y.mean())) / sxx
    intercept = y.mean() - slope * zm
    resid = y - (intercept + slope * z)
    dof = n - 2
    s2 = np.sum(resid**2) / dof
    slope_se = np.sqrt(s2 / sxx)
    intercept_se = np.sqrt(s2 * (1.0 / n + zm**2 / sxx))
    sst = np.sum((y - y.mean()) ** 2)
    r2 = 1.0 - np.sum(resid**2) / sst if sst > 0 else np.nan
    return {
        "intercept": float(intercept),
        "intercept_se": float(intercept_se),
        "slope_per_cm": float(-slope),
        "slope_se": float(slope_se),
        "dof": int(dof),
        "r_squared": float(r2),
        "residuals": resid,
    }


def immersion_factor_from_intercept(dn_air, dn_air_sigma, dn_below, dn_below_sigma, n2_factor):
    """Eq. (11) with n^2: I = dn_air / dn_below * t_aw n_w^2, and its standard uncertainty.

    Relative uncertainties of the two DN add in quadrature (independent);
    ``n2_factor`` is treated as exact (the paper does so).  Vectorised.
    Table 2 check: 5267 +/- 68 over 3111 +/- 12 (already divided by
    t_aw n_w^2, so n2_factor = 1) gives 1.693 +/- 0.023.

    Parameters
    ----------
    dn_air : array_like
        In-air signal y_DN(0+) (any DN unit, e.g. DN s-1).
    dn_air_sigma : array_like
        Its standard uncertainty (same unit).
    dn_below : array_like
        In-water signal just below the surface y_DN(0-), the fit's extrapolation (same unit).
    dn_below_sigma : array_like
        Its standard uncertainty (same unit).
    n2_factor : array_like
        t_aw n_w^2 (dimensionless).

    Returns
    -------
    immersion_factor : numpy.ndarray
        I (dimensionless).
    immersion_factor_sigma : numpy.ndarray
        Its standard uncertainty (dimensionless).
    """
    dn_air = np.asarray(dn_air, dtype=float)
    dn_below = np.asarray(dn_below, dtype=float)
    i = dn_air / dn_below * np.asarray(n2_factor, dtype=float)
    rel = np.hypot(np.asarray(dn_air_sigma) / dn_air, np.asarray(dn_below_sigma) / dn_below)
    return i, i * rel


def fit_immersion_factor(height_cm, dn_water, dn_air, n2_factor, dn_air_sigma=None, confidence=0.95):
    """Immersion factor by the log-linear extrapolation of Zibordi (2006), Eq. (11).

    Parameters
    ----------
    height_cm : array_like (n,)
        Water height above the camera per in-water frame, cm.
    dn_water : array_like (n,)
        In-water DN per frame (dark corrected, normalised by exposure), > 0.
    dn_air : float or array_like
        In-air DN y_DN(0+), same normalisation.  An array is taken as one
        value per frame: its mean is used, with the standard error of the
        mean as uncertainty and len - 1 degrees of freedom.  A scalar needs
        ``dn_air_sigma`` (taken as having infinite degrees of freedom).
        (The paper quotes the spread inside the averaging region instead.)
    n2_factor : float
        t_aw n_w^2 at the band's effective wavelength (n_squared_law_factor_at).
    dn_air_sigma : float, optional
        Standard uncertainty of a scalar dn_air.
    confidence : float
        Level of the reported intervals (default 0.95).

    Returns
    -------
    ImmersionFit
        The 95 % interval of ln I = ln dn_air - c + ln n2 uses the
        Welch-Satterthwaite effective degrees of freedom of the intercept
        (n - 2) and the in-air mean (m - 1).
    """
    fit = fit_log_linear_attenuation(height_cm, dn_water)
    air = np.asarray(dn_air, dtype=float)
    if air.ndim == 0:
        if dn_air_sigma is None:
            raise ValueError("a scalar dn_air needs dn_air_sigma")
        air_mean = float(air)
        air_sigma = float(dn_air_sigma)
        air_dof = np.inf
    else:
        air = air.ravel()
        if air.size < 2:
            raise ValueError("need at least two in-air frames, or a scalar with dn_air_sigma")
        air_mean = float(air.mean())
        air_sigma = float(air.std(ddof=1) / np.sqrt(air.size)) if dn_air_sigma is None else float(dn_air_sigma)
        air_dof = air.size - 1
    c, se = fit["intercept"], fit["intercept_se"]
    tq = stats.t.ppf(0.5 + confidence / 2.0, fit["dof"])
    dn_below = float(np.exp(c))
    i, i_sigma = immersion_factor_from_intercept(air_mean, air_sigma, dn_below, dn_below * se, n2_factor)
    # log-space combined uncertainty and Welch-Satterthwaite dof
    u_air = air_sigma / air_mean
    u_log = np.hypot(u_air, se)
    denom = se**4 / fit["dof"] + (u_air**4 / air_dof if np.isfinite(air_dof) else 0.0)
    nu = u_log**4 / denom if denom > 0 else np.inf
    k = stats.t.ppf(0.5 + confidence / 2.0, nu) if np.isfinite(nu) else stats.norm.ppf(0.5 + confidence / 2.0)
    i = float(i)
    return ImmersionFit(
        dn_below=dn_below,
        dn_below_sigma=float(dn_below * se),
        dn_below_ci95=(float(np.exp(c - tq * se)), float(np.exp(c + tq * se))),
        attenuation_per_cm=fit["slope_per_cm"],
        attenuation_per_cm_sigma=fit["slope_se"],
        dof=fit["dof"],
        r_squared=fit["r_squared"],
        dn_air=air_mean,
        dn_air_sigma=air_sigma,
        n2_factor=float(n2_factor),
        immersion_factor=i,
        immersion_factor_sigma=float(i_sigma),
        immersion_factor_ci95=(i * float(np.exp(-k * u_log)), i * float(np.exp(k * u_log))),
        residuals=fit["residuals"],
    )


def immersion_factor_flat_window(n_w, n_g):
    """Theoretical immersion factor, Eq. (10): I = n_w (n_w + n_g)^2 / (1 + n_g)^2.

    E.g. n_w = 1.3322, n_g = 1.60 gives 1.694 (Larouche et al. 2024, Section 3.6, red band).

    Parameters
    ----------
    n_w : array_like
        Refractive index of water (dimensionless).
    n_g : array_like
        Refractive index of the external optical surface (dimensionless).

    Returns
    -------
    numpy.ndarray
        Immersion factor I (dimensionless), broadcast over the inputs.
    """
    n_w = np.asarray(n_w, dtype=float)
    n_g = np.asarray(n_g, dtype=float)
    return n_w * (n_w + n_g) ** 2 / (1.0 + n_g) ** 2


def window_index_from_immersion_factor(immersion_factor, n_w, immersion_factor_sigma=None):
    """Invert Eq. (10) for the external-surface index n_g.

    With r = sqrt(I / n_w), (n_w + n_g) / (1 + n_g) = r gives
    n_g = (n_w - r) / (r - 1), defined for 1 < r < n_w, i.e. n_w < I < n_w^3
    (NaN outside).  The inverse is steep: dn_g/dI ~ 10 near I = 1.69, so an
    uncertainty of 0.02 in I is ~0.2 in n_g.

    Parameters
    ----------
    immersion_factor : array_like
        Immersion factor I (dimensionless).
    n_w : array_like
        Refractive index of water (dimensionless).
    immersion_factor_sigma : array_like, optional
        Standard uncertainty of I (dimensionless).

    Returns
    -------
    n_g : numpy.ndarray
        Refractive index of the external surface (dimensionless); NaN where I is outside (n_w, n_w^3).
    sigma_n_g : numpy.ndarray
        Its standard uncertainty by first-order propagation; returned, as the second element of a tuple,
        only when ``immersion_factor_sigma`` is given.
    """
    i = np.asarray(immersion_factor, dtype=float)
    n_w = np.asarray(n_w, dtype=float)
    r = np.sqrt(i / n_w)
    ok = (r > 1.0) & (r < n_w)
    with np.errstate(divide="ignore", invalid="ignore"):
        n_g = np.where(ok, (n_w - r) / (r - 1.0), np.nan)
        if immersion_factor_sigma is None:
            return n_g
        # dn_g/dr = (1 - n_w) / (r - 1)^2 ; dr/dI = 1 / (2 r n_w)
        dng_di = (1.0 - n_w) / (r - 1.0) ** 2 / (2.0 * r * n_w)
    return n_g, np.abs(dng_di) * np.asarray(immersion_factor_sigma, dtype=float)


def in_water_dn(dn_air, height_cm, attenuation_per_m, n2_factor, immersion_factor):
    """Forward model of the immersion experiment: in-water DN at water height z.

    y_DN(z) = y_DN(0+) * t_aw n_w^2 / I * exp(-(a + b) z)

    Parameters
    ----------
    dn_air : array_like
        In-air DN y_DN(0+) (any DN unit; output has the same unit).
    height_cm : array_like
        Water height above the camera, cm.
    attenuation_per_m : array_like
        Beam attenuation a + b of the water, m^-1 (pure water at 600 nm:
        a ~ 0.22, b ~ 0.002 m^-1).
    n2_factor : array_like
        t_aw n_w^2.
    immersion_factor : array_like
        I of the band.

    Returns
    -------
    numpy.ndarray broadcast over the inputs; fit_immersion_factor inverts it.
    """
    z_m = np.asarray(height_cm, dtype=float) / 100.0
    return (
        np.asarray(dn_air, dtype=float)
        * np.asarray(n2_factor, dtype=float)
        / np.asarray(immersion_factor, dtype=float)
        * np.exp(-np.asarray(attenuation_per_m, dtype=float) * z_m)
    )
