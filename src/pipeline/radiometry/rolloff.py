"""Roll-off (relative illumination) g(theta): even polynomial fit and evaluation.

Larouche et al. (2024), Sections 2.4 and 3.3, Eq. (13):

    g(theta) = a0 + a2 theta^2 + a4 theta^4 + a6 theta^6 + a8 theta^8,
    theta in degrees from the optical axis.

Measurements: the source imaged every 5 deg from -80 to 80 deg in air and
every 2 deg from -70 to 70 deg in water, normalised by the curve's maximum;
the uncertainty of each point is the spread inside the 15-pixel averaging
region.  Coefficients are stored lowest order first, (a0, a2, a4, a6, a8),
for theta in degrees; internally the fit works in theta / theta_max so that
the normal equations stay well conditioned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "RolloffFit",
    "rolloff_design_matrix",
    "fit_rolloff",
    "evaluate_rolloff",
    "rolloff_on_image",
    "rolloff_slope",
    "normalise_rolloff",
]

N_COEFFICIENTS = 5  # a0, a2, a4, a6, a8
#: Powers of theta in Eq. (13), lowest first.
ROLLOFF_POWERS = tuple(2 * k for k in range(N_COEFFICIENTS))


def rolloff_design_matrix(theta_deg, scale_deg=1.0):
    """Design matrix of Eq. (13): columns (theta / scale)^(2k), k = 0..4.

    At theta = scale every column is 1.  g(theta) = A(theta) @ a for coefficients a of theta / scale.

    Parameters
    ----------
    theta_deg : array_like
        Field angles (degree).
    scale_deg : float, default 1.0
        Scale of the angles (degree); one of the order of the largest angle keeps least-squares fits well
        conditioned.

    Returns
    -------
    numpy.ndarray
        The design matrix (dimensionless): the shape of ``theta_deg`` plus a last axis of 5, e.g. (n, 5) for
        n angles.
    """
    u = np.asarray(theta_deg, dtype=float) / float(scale_deg)
    return u[..., None] ** np.asarray(ROLLOFF_POWERS)


@dataclass(frozen=True)
class RolloffFit:
    """Weighted least-squares fit of Eq. (13).

    Attributes
    ----------
    coefficients : (5,) a0..a8 for theta in degrees.
    covariance : (5, 5) their covariance.
    chi2 : weighted sum of squared residuals; dof = n - 5.
    reduced_chi2 : chi2 / dof (about 1 when the sigmas are right).
    residuals : data - model at each input theta (unit of the data).
    absolute_sigma : whether the covariance trusts the given sigmas (True)
        or was scaled by reduced_chi2 (False).
    """

    coefficients: np.ndarray
    covariance: np.ndarray
    chi2: float
    dof: int
    reduced_chi2: float
    residuals: np.ndarray
    absolute_sigma: bool

    def __call__(self, theta_deg, with_sigma=False):
        """g at theta (deg); with_sigma=True also returns its standard uncertainty."""
        return evaluate_rolloff(self.coefficients, theta_deg, self.covariance if with_sigma else None)


def fit_rolloff(theta_deg, relative_signal, sigma=None, absolute_sigma=None):
    """Fit g(theta) = sum a_2k theta^2k (k = 0..4) by weighted least squares.

    Parameters
    ----------
    theta_deg : (n,) field angles, deg (sign ignored: the model is even)
    relative_signal : (n,) relative illumination (dimensionless)
    sigma : (n,), optional
        Standard uncertainty of each point; weights 1 / sigma^2.
    absolute_sigma : bool, optional
        True: covariance = (A^T W A)^-1 (trust sigma).  False: scaled by the
        reduced chi-square.  Default: True when sigma is given, else False.

    Returns
    -------
    RolloffFit
    """
    theta = np.asarray(theta_deg, dtype=float).ravel()
    y = np.asarray(relative_signal, dtype=float).ravel()
    if theta.size != y.size:
        raise ValueError("theta_deg and relative_signal must have the same length")
    if theta.size <= N_COEFFICIENTS:
        raise ValueError("need more than 5 points to fit 5 coefficients with an error estimate")
    if sigma is None:
        s = np.ones_like(y)
        absolute_sigma = False if absolute_sigma is None else absolute_sigma
    else:
        s = np.broadcast_to(np.asarray(sigma, dtype=float), y.shape)
        if np.any(s <= 0):
            raise ValueError("sigma must be positive")
        absolute_sigma = True if absolute_sigma is None else absolute_sigma
    scale = max(np.max(np.abs(theta)), 1e-12)
    a = rolloff_design_matrix(theta, scale)
    aw = a / s[:, None]
    yw = y / s
    b, *_ = np.linalg.lstsq(aw, yw, rcond=None)
    # covariance from the SVD of the weighted design matrix (stable)
    _, sv, vt = np.linalg.svd(aw, full_matrices=False)
    cov_b = (vt.T / sv**2) @ vt
    resid = y - a @ b
    chi2 = float(np.sum((resid / s) ** 2))
    dof = theta.size - N_COEFFICIENTS
    red = chi2 / dof
    if not absolute_sigma:
        cov_b = cov_b * red
    d = scale ** (-2.0 * np.arange(N_COEFFICIENTS))
    coef = b * d
    cov = cov_b * np.outer(d, d)
    return RolloffFit(coef, cov, chi2, dof, red, resid, bool(absolute_sigma))


def evaluate_rolloff(coefficients, theta_deg, covariance=None):
    """g(theta) for coefficients (a0, a2, a4, a6, a8), theta in degrees.

    With ``covariance`` also returns the standard uncertainty of the
    prediction at each theta, sqrt(J C J^T) with J_k = theta^2k.

    Parameters
    ----------
    coefficients : array_like
        (a0, a2, a4, a6, a8) for theta in degrees, shape (5,) or with leading batch axes (..., 5).
    theta_deg : array_like
        Field angles (degree).
    covariance : array_like, optional
        Covariance of the coefficients, shape (5, 5).

    Returns
    -------
    g : numpy.ndarray
        Relative illumination at each theta (dimensionless).
    sigma : numpy.ndarray
        Its standard uncertainty (dimensionless); returned, as the second element of a tuple, only with
        ``covariance``.
    """
    c = np.asarray(coefficients, dtype=float)
    powers = rolloff_design_matrix(theta_deg)
    g = np.sum(powers * c, axis=-1) if c.ndim == 1 else np.einsum("...k,...k->...", powers, c)
    if covariance is None:
        return g
    cov = np.asarray(covariance, dtype=float)
    var = np.einsum("...i,ij,...j->...", powers, cov, powers)
    return g, np.sqrt(np.clip(var, 0.0, None))


def rolloff_on_image(coefficients, theta_deg, covariance=None):
    """:func:`evaluate_rolloff` of one set of coefficients on a large array of angles (a band image's theta).

    Horner's rule in u = theta^2, without the (..., 5) design matrix; the
    variance J C J^T = sum_k d_k u^k with d_k the sum of the covariance's
    k-th anti-diagonal (k = 0..8). The same values as :func:`evaluate_rolloff`
    to rounding (1e-15 relative in g, 1e-11 in its sigma on fitted curves).

    Parameters
    ----------
    coefficients : array_like
        (a0, a2, a4, a6, a8) for theta in degrees, shape (5,).
    theta_deg : array_like
        Field angles (degree), any shape.
    covariance : array_like, optional
        Covariance of the coefficients, shape (5, 5).

    Returns
    -------
    g : numpy.ndarray or float
        Relative illumination (dimensionless), shape of ``theta_deg`` (a scalar for a scalar theta).
    sigma : numpy.ndarray or float
        Its standard uncertainty; returned, as the second element of a tuple, only with ``covariance``.

    Raises
    ------
    ValueError
        When ``coefficients`` is not one set of five.
    """
    c = np.asarray(coefficients, dtype=float)
    if c.ndim != 1:
        raise ValueError("rolloff_on_image takes one set of coefficients (a0, a2, a4, a6, a8)")
    u = np.square(np.asarray(theta_deg, dtype=float))
    g = _horner(c, u)
    if covariance is None:
        return g[()]  # a scalar for a scalar theta
    cov = np.asarray(covariance, dtype=float)
    flipped = cov[::-1]
    d = np.array([np.trace(flipped, offset=k) for k in range(-(len(c) - 1), len(c))])
    var = _horner(d, u)
    np.clip(var, 0.0, None, out=var)
    return g[()], np.sqrt(var, out=var)[()]


def _horner(coefficients, u):
    """sum_k coefficients[k] u^k (lowest order first), in as few temporaries as the size of u."""
    out = np.full(np.shape(u), coefficients[-1], dtype=float)
    for a in coefficients[-2::-1]:
        out *= u
        out += a
    return out


def rolloff_slope(coefficients, theta_deg):
    """dg/dtheta of Eq. (13) in deg^-1: sum_k 2k a_2k theta^(2k - 1), theta in degrees.

    E.g. g = 1 - 1e-4 theta^2 has slope -2e-3 deg^-1 at 10 deg.

    Parameters
    ----------
    coefficients : array_like
        (a0, a2, a4, a6, a8) for theta in degrees, as stored; shape (5,) or (..., 5).
    theta_deg : array_like
        Field angles (degree).

    Returns
    -------
    numpy.ndarray
        dg/dtheta (degree-1) at each theta.
    """
    c = np.asarray(coefficients, dtype=float)
    t = np.asarray(theta_deg, dtype=float)
    # g' = theta * sum_k 2k a_2k theta^(2k - 2): the first four columns of Eq. (13)'s design matrix
    dc = np.asarray(ROLLOFF_POWERS[1:], dtype=float) * c[..., 1:]
    return t * np.sum(rolloff_design_matrix(t)[..., :-1] * dc, axis=-1)


def rolloff_slope_on_image(coefficients, theta_deg):
    """:func:`rolloff_slope` of one set of coefficients on a large array of angles, by Horner's rule in theta^2.

    g'(theta) = theta * sum_k 2k a_2k u^(k - 1) with u = theta^2 (deg^-1), without the design matrix.

    Parameters
    ----------
    coefficients : array_like
        (a0, a2, a4, a6, a8) for theta in degrees, shape (5,).
    theta_deg : array_like
        Field angles (degree), any shape.

    Returns
    -------
    numpy.ndarray or float
        dg/dtheta (degree-1), shape of ``theta_deg`` (a scalar for a scalar theta).

    Raises
    ------
    ValueError
        When ``coefficients`` is not one set of five.
    """
    c = np.asarray(coefficients, dtype=float)
    if c.ndim != 1:
        raise ValueError("rolloff_slope_on_image takes one set of coefficients (a0, a2, a4, a6, a8)")
    t = np.asarray(theta_deg, dtype=float)
    dc = np.asarray(ROLLOFF_POWERS[1:], dtype=float) * c[1:]
    out = _horner(dc, np.square(t))
    out *= t
    return out[()]


def normalise_rolloff(coefficients, covariance=None):
    """Divide by a0 so that g(0) = 1; propagate the covariance (first order).

    The normalised a0 is exactly 1 with zero variance.

    Parameters
    ----------
    coefficients : array_like
        (a0, a2, a4, a6, a8) for theta in degrees, shape (5,).
    covariance : array_like, optional
        Their covariance, shape (5, 5).

    Returns
    -------
    coefficients : numpy.ndarray
        The normalised coefficients, shape (5,).
    covariance : numpy.ndarray
        Their covariance, shape (5, 5); returned, as the second element of a tuple, only with ``covariance``.
    """
    c = np.asarray(coefficients, dtype=float)
    a0 = c[0]
    out = c / a0
    if covariance is None:
        return out
    jac = np.eye(N_COEFFICIENTS) / a0
    jac[:, 0] = -c / a0**2
    jac[0, :] = 0.0
    return out, jac @ np.asarray(covariance, dtype=float) @ jac.T
