"""The field angle's shift with the principal point: an error common to every pixel of a band image.

A fitted principal point (xc, yc) off the true one by delta_c moves the theta of every pixel by, to first
order, d theta / d c . delta_c (:func:`pipeline.geometry.theta_uncertainty.theta_gradient`): about
-|delta_c| cos(phi - phi_c) / (pixels per degree) away from the axis, the same delta_c for every
measurement taken on that band image. A quantity measured at many field angles (the roll-off's port
spots) therefore shares one centre error: a correlated term, not independent noise per point. Through a
slope g'(theta) it leaves g'(theta) cos(phi - phi_c), which looks like a decentred optic's
cos(phi - phi0) (``rolloff_azimuth``).

A fit that allows for it carries two nuisance parameters per band image, u = L^-1 delta_c with
L L^T = C_c the geometry artefact's covariance of (xc, yc), so that u ~ N(0, I) a priori: the columns are
the measurement's slope times d theta / d c . L (:func:`centre_columns`), and the prior is two
pseudo-measurements u_k = 0 +/- 1.
"""

from __future__ import annotations

import numpy as np

from .scaramuzza import FisheyeModel
from .theta_uncertainty import theta_gradient

#: the geometry artefact's names of the principal point in its parameter covariance
CENTRE_PARAMETERS = ("xc_px", "yc_px")


def centre_theta_gradient(model: FisheyeModel, u, v) -> np.ndarray:
    """Mean over the pixels (u, v) of d theta / d (xc, yc), degree per pixel: shape (2,).

    The mean is that of a quantity averaged over those pixels (a spot's theta is the mean of theta over
    its pixels); pixels on the axis itself (theta not differentiable in the centre) count as zero.

    Parameters
    ----------
    model : FisheyeModel
        The lens's geometric model, with the principal point (xc, yc) to differentiate against.
    u, v : numpy.ndarray
        Pixel coordinates of the pixels averaged over, pixels.

    Returns
    -------
    numpy.ndarray
        Mean d theta / d (xc, yc), degree per pixel, shape ``(2,)``.
    """
    g = theta_gradient(model, CENTRE_PARAMETERS, np.ravel(np.asarray(u, float)), np.ravel(np.asarray(v, float)))
    return np.nanmean(np.where(np.isfinite(g), g, 0.0), axis=1)


def centre_root(covariance: np.ndarray) -> np.ndarray:
    """L with L L^T = C for the 2 x 2 covariance of the centre (symmetric square root; negative
    eigenvalues of a numerically indefinite estimate are set to zero).

    Parameters
    ----------
    covariance : numpy.ndarray
        Covariance of (xc, yc), pixel^2: its upper-left 2 x 2 block is used.

    Returns
    -------
    numpy.ndarray
        The symmetric square root L, pixel, shape ``(2, 2)``.
    """
    c = np.asarray(covariance, float)[:2, :2]
    w, v = np.linalg.eigh(0.5 * (c + c.T))
    return v @ np.diag(np.sqrt(np.clip(w, 0.0, None))) @ v.T


def centre_columns(slope: np.ndarray, gradient: np.ndarray, root: np.ndarray) -> np.ndarray:
    """Columns of the whitened centre shift u in a fitted quantity y(theta): y' (theta) d theta / d c . L.

    Parameters
    ----------
    slope : numpy.ndarray
        dy / d theta at each measurement, units of y per degree, shape ``(n,)``.
    gradient : numpy.ndarray
        d theta / d (xc, yc) at each measurement, degree per pixel, shape ``(n, 2)``.
    root : numpy.ndarray
        L (:func:`centre_root`), pixel, shape ``(2, 2)``.

    Returns
    -------
    numpy.ndarray
        Design-matrix columns, units of y per unit of u, shape ``(n, 2)``.
    """
    return np.asarray(slope, float)[:, None] * (np.asarray(gradient, float) @ np.asarray(root, float))


def centre_variance(gradient: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """Variance of theta that the centre's covariance alone gives: g C_c g^T per row of ``gradient``.

    Parameters
    ----------
    gradient : numpy.ndarray
        d theta / d (xc, yc) per measurement, degree per pixel, shape ``(n, 2)``.
    covariance : numpy.ndarray
        Covariance of (xc, yc), pixel^2: its upper-left 2 x 2 block is used.

    Returns
    -------
    numpy.ndarray
        Variance of theta per measurement, degree^2, shape ``(n,)``.
    """
    g = np.asarray(gradient, float)
    c = np.asarray(covariance, float)[:2, :2]
    return np.einsum("ni,ij,nj->n", g, c, g)
