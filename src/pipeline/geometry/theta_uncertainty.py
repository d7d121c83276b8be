"""Uncertainty of the field angle theta from the covariance of a fitted Scaramuzza model.

The calibration (:func:`pipeline.geometry.calibrate.calibrate`) gives the
covariance C of the model parameters p: the principal point (xc, yc), the
stretch terms and the coefficients a0, a2, ..., aN of f(rho) (Eq. 5-6 of
Larouche et al. 2024), the board poses profiled out (see
:func:`pipeline.geometry.calibrate.intrinsic_covariance`). A pixel's theta
follows from Eq. (7), tan(theta) = rho / f(rho), with rho = |A^-1 (u - xc,
v - yc)|; to first order its variance is g C g^T with g = d theta / d p, and
two pixels' thetas covary as g_1 C g_2^T.

The gradient is analytic in the polynomial coefficients,
d theta / d a_k = -rho^(k+1) / (rho^2 + f^2), and through rho for the centre
and stretch, d theta / d q = (f - rho f') / (rho^2 + f^2) d rho / d q, with
d rho / d q analytic for the centre and by central differences of the affine
map of Eq. (6) for the stretch terms. On the axis itself (rho = 0) theta is
not differentiable in the centre (it is a distance); the 1-D summary gives
there the limit from off the axis, the first-order sigma of theta in one
direction.

Parameter names (the order of the covariance): ``xc_px``, ``yc_px``, then
``stretch_c`` and ``stretch_d_and_e`` (stretch "symmetric": e = d),
``stretch_c``, ``stretch_d``, ``stretch_e`` ("full") or none ("none"), then
``a0``, ``a2``, ..., ``aN`` (pixel^(1-k)).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .scaramuzza import FisheyeModel

#: central-difference step of the stretch terms (dimensionless): rho is smooth in them
_STRETCH_STEP = 1.0e-6
#: radial distance (pixel) standing for the axis in the 1-D summary: theta is a distance there
_AXIS_RHO_PX = 1.0e-3
#: rows of a band image whose gradients are held at once (memory: n_params x rows x cols doubles)
_ROWS_PER_BLOCK = 64


def parameter_names(stretch: str, degree: int) -> tuple[str, ...]:
    """Names of the fitted model parameters, in the order of their covariance.

    Parameters
    ----------
    stretch : str
        Stretch model of the fit: "symmetric", "full" or "none".
    degree : int
        Polynomial degree N of f(rho).

    Returns
    -------
    tuple of str
        ``("xc_px", "yc_px", <stretch terms>, "a0", "a2", ..., "aN")``.
    """
    head = {"symmetric": ("stretch_c", "stretch_d_and_e"), "full": ("stretch_c", "stretch_d", "stretch_e"),
            "none": ()}[stretch]
    return ("xc_px", "yc_px", *head, "a0", *(f"a{k}" for k in range(2, degree + 1)))


def shifted_model(model: FisheyeModel, name: str, h: float) -> FisheyeModel:
    """``model`` with parameter ``name`` (of :func:`parameter_names`) moved by ``h``.

    Parameters
    ----------
    model : FisheyeModel
        The lens's geometric model.
    name : str
        A parameter name of :func:`parameter_names`.
    h : float
        Shift, in the parameter's unit (pixels for the centre and a_k's own units for coefficients).

    Returns
    -------
    FisheyeModel
        The shifted model.

    Raises
    ------
    ValueError
        On an unknown parameter name.
    """
    if name.startswith("a") and name[1:].isdigit():
        k = int(name[1:])
        poly = list(model.poly) + [0.0] * max(0, k + 1 - len(model.poly))
        poly[k] += h
        return replace(model, poly=tuple(poly))
    if name == "xc_px":
        return replace(model, xc=model.xc + h)
    if name == "yc_px":
        return replace(model, yc=model.yc + h)
    if name == "stretch_c":
        return replace(model, c=model.c + h)
    if name == "stretch_d":
        return replace(model, d=model.d + h)
    if name == "stretch_e":
        return replace(model, e=model.e + h)
    if name == "stretch_d_and_e":
        return replace(model, d=model.d + h, e=model.e + h)
    raise ValueError(f"unknown geometric parameter {name!r}")


def theta_gradient(model: FisheyeModel, names, u, v) -> np.ndarray:
    """d theta / d p (degree per unit of each parameter), shape ``(len(names), *u.shape)``.

    Parameters
    ----------
    model : FisheyeModel
        The lens's geometric model.
    names : sequence of str
        Parameters (of :func:`parameter_names`) to differentiate against.
    u, v : numpy.ndarray
        Pixel coordinates (broadcast together).

    Returns
    -------
    numpy.ndarray
        d theta / d p, degree per unit of each parameter, shape ``(len(names), *u.shape)``.
    """
    u, v = np.broadcast_arrays(np.asarray(u, float), np.asarray(v, float))
    x, y = model._sensor_xy(u, v)
    rho = np.hypot(x, y)
    f = model.f(rho)
    q = rho**2 + f**2
    dtheta_drho = (f - rho * model.df(rho)) / q
    out = np.empty((len(names),) + u.shape)
    for i, name in enumerate(names):
        if name.startswith("a") and name[1:].isdigit():
            out[i] = -rho ** (int(name[1:]) + 1) / q
            continue
        if name in ("xc_px", "yc_px"):
            # [u - xc, v - yc] = A [x', y']: d(x', y') / d xc = -A^-1 e_1, / d yc = -A^-1 e_2
            det = model.c - model.d * model.e
            dx, dy = ((-1.0 / det, model.e / det) if name == "xc_px" else (model.d / det, -model.c / det))
            out[i] = dtheta_drho * (x * dx + y * dy) / np.where(rho > 0, rho, np.inf)
            continue
        h = _STRETCH_STEP
        rp = np.hypot(*shifted_model(model, name, h)._sensor_xy(u, v))
        rm = np.hypot(*shifted_model(model, name, -h)._sensor_xy(u, v))
        out[i] = dtheta_drho * (rp - rm) / (2 * h)
    return np.degrees(out)


def theta_covariance(model: FisheyeModel, names, covariance, u, v) -> np.ndarray:
    """Covariance (degree^2) of theta between the pixels (u, v) (1-D arrays of k points): (k, k).

    Parameters
    ----------
    model : FisheyeModel
        The lens's geometric model.
    names : sequence of str
        Parameters (of :func:`parameter_names`) to differentiate against.
    covariance : numpy.ndarray
        Covariance of the parameters ``names``, in their units, shape ``(len(names), len(names))``.
    u, v : numpy.ndarray
        Pixel coordinates of the k points.

    Returns
    -------
    numpy.ndarray
        Covariance of theta between the points, degree^2, shape ``(k, k)``.
    """
    g = theta_gradient(model, names, np.ravel(u), np.ravel(v))
    return g.T @ np.asarray(covariance, float) @ g


def theta_sigma_map(model: FisheyeModel, names, covariance, shape=None) -> np.ndarray:
    """Standard uncertainty (degree) of theta at every pixel centre of an image (float32).

    Parameters
    ----------
    model : FisheyeModel
        The lens's geometric model.
    names : sequence of str
        Parameters (of :func:`parameter_names`) to differentiate against.
    covariance : numpy.ndarray
        Covariance of the parameters ``names``, in their units, shape ``(len(names), len(names))``.
    shape : tuple of int, optional
        (rows, cols) of the image; ``model.shape`` when None.

    Returns
    -------
    numpy.ndarray
        Standard uncertainty of theta, degree, float32, shape ``(rows, cols)``.
    """
    rows, cols = model.shape if shape is None else shape
    cov = np.asarray(covariance, float)
    out = np.empty((rows, cols), np.float32)
    u_row = np.arange(cols, dtype=float)
    for r0 in range(0, rows, _ROWS_PER_BLOCK):
        r1 = min(rows, r0 + _ROWS_PER_BLOCK)
        v, u = np.meshgrid(np.arange(r0, r1, dtype=float), u_row, indexing="ij")
        g = theta_gradient(model, names, u, v).reshape(len(names), -1)
        var = np.sum(g * (cov @ g), axis=0).reshape(r1 - r0, cols)
        out[r0:r1] = np.sqrt(np.maximum(var, 0.0))
    return out


def theta_sigma_at_field_angles(model: FisheyeModel, names, covariance, theta_deg, n_azimuth: int = 36) -> np.ndarray:
    """RMS over ``n_azimuth`` azimuths of sigma(theta) (degree) where the model puts each theta.

    NaN beyond the model's half field of view (when it has one) or its domain.
    At theta = 0 the limit from off the axis (``_AXIS_RHO_PX``, see the module docstring).

    Parameters
    ----------
    model : FisheyeModel
        The lens's geometric model.
    names : sequence of str
        Parameters (of :func:`parameter_names`) to differentiate against.
    covariance : numpy.ndarray
        Covariance of the parameters ``names``, in their units, shape ``(len(names), len(names))``.
    theta_deg : numpy.ndarray
        Field angles, degree.
    n_azimuth : int, default 36
        Azimuths averaged over.

    Returns
    -------
    numpy.ndarray
        RMS standard uncertainty of theta at each field angle, degree, of the shape of ``theta_deg``.
    """
    theta_deg = np.asarray(theta_deg, float)
    rho = np.maximum(model.rho_of_theta(np.radians(theta_deg)), _AXIS_RHO_PX)
    phi = np.linspace(0.0, 2 * np.pi, int(n_azimuth), endpoint=False)
    xs, ys = rho[:, None] * np.cos(phi)[None], rho[:, None] * np.sin(phi)[None]
    u = model.c * xs + model.d * ys + model.xc
    v = model.e * xs + ys + model.yc
    g = theta_gradient(model, names, u, v)
    var = np.einsum("i...,ij,j...->...", g, np.asarray(covariance, float), g)
    out = np.sqrt(np.mean(var, axis=1))
    if model.half_fov_deg is not None:
        out = np.where(theta_deg <= model.half_fov_deg, out, np.nan)
    return np.where(np.isfinite(rho), out, np.nan)
