"""Geometric calibration of a rectilinear (pinhole) lens with OpenCV, and its per-pixel maps.

An ordinary camera or a smartphone follows the pinhole model with Brown-Conrady
distortion as OpenCV writes it (``calibrateCamera``; the "camera calibration and
3D reconstruction" module): a ray with normalised coordinates (x, y) = (X/Z, Y/Z),
r^2 = x^2 + y^2, lands at

    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y
    u = fx x_d + cx,  v = fy y_d + cy

(pixel centres at integer u, v, as in :mod:`pipeline.geometry.maps`). A lens of
this kind sees less than 90 degrees off axis, which the model covers; the
fisheye lenses need :mod:`pipeline.geometry.scaramuzza` instead.

:func:`calibrate_pinhole` fits the intrinsics and distortion from detected
chessboard corners and returns their covariance (board poses profiled out,
from OpenCV's projection Jacobian at the solution, scaled by the corner
residual variance); :func:`pinhole_maps` gives theta, phi (degrees; phi =
atan2(y, x) as for the fisheye maps), the solid angle of every pixel (sr) and
the first-order standard uncertainty of theta from that covariance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: intrinsic parameters in the order of the covariance (k3 only when fitted)
PARAMETERS = ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3")


@dataclass
class PinholeModel:
    """Camera matrix and distortion of one band image (OpenCV conventions)."""

    fx: float
    fy: float
    cx: float
    cy: float
    dist: np.ndarray                 # k1, k2, p1, p2, k3
    shape: tuple[int, int]           # (rows, cols) of the band image
    meta: dict = field(default_factory=dict)

    @property
    def camera_matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def parameters(self) -> np.ndarray:
        """The model's parameters as one vector, in the order of ``PARAMETERS``.

        Returns
        -------
        numpy.ndarray
            (fx, fy, cx, cy) in pixels, then the distortion coefficients (dimensionless).
        """
        return np.concatenate([[self.fx, self.fy, self.cx, self.cy], np.asarray(self.dist, float)])

    @classmethod
    def from_parameters(cls, p, shape) -> PinholeModel:
        """The model of a parameter vector as :meth:`parameters` writes it.

        Parameters
        ----------
        p : array_like
            (fx, fy, cx, cy) in pixels, then the distortion coefficients.
        shape : tuple of int
            (rows, cols) of the band image.

        Returns
        -------
        PinholeModel
            The model.
        """
        p = np.asarray(p, float)
        return cls(p[0], p[1], p[2], p[3], p[4:].copy(), tuple(shape))

    def normalised(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised ray coordinates (x, y) of pixels (u, v) (OpenCV's undistortPoints).

        Parameters
        ----------
        u, v : numpy.ndarray
            Pixel coordinates (column, row; pixel centres at integers).

        Returns
        -------
        x : numpy.ndarray
            Normalised coordinate X/Z of each ray, of the shape of ``u``.
        y : numpy.ndarray
            Normalised coordinate Y/Z of each ray.
        """
        import cv2

        u = np.asarray(u, float)
        pts = np.stack([u.ravel(), np.asarray(v, float).ravel()], axis=-1).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        out = cv2.undistortPoints(pts, self.camera_matrix, np.asarray(self.dist, float), None, None, None, criteria)
        xy = out.reshape(-1, 2)
        return xy[:, 0].reshape(u.shape), xy[:, 1].reshape(u.shape)

    def theta_phi(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """Field angle theta and azimuth phi (degrees) of the rays that land on pixels (u, v).

        Parameters
        ----------
        u, v : numpy.ndarray
            Pixel coordinates (column, row; pixel centres at integers).

        Returns
        -------
        theta : numpy.ndarray
            Angle from the optical axis, degree.
        phi : numpy.ndarray
            Azimuth ``atan2(y, x)``, degree in (-180, 180].
        """
        x, y = self.normalised(u, v)
        return np.degrees(np.arctan(np.hypot(x, y))), np.degrees(np.arctan2(y, x))

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Pixels (u, v) of camera-frame points (N, 3) (OpenCV's projectPoints).

        Parameters
        ----------
        points_cam : numpy.ndarray
            Points in the camera frame (any length unit), shape ``(N, 3)``.

        Returns
        -------
        numpy.ndarray
            Pixel coordinates (u, v), shape ``(N, 2)``.
        """
        import cv2

        pts = np.asarray(points_cam, float).reshape(-1, 1, 3)
        uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.camera_matrix, np.asarray(self.dist, float))
        return uv.reshape(-1, 2)


@dataclass
class PinholeCalibration:
    model: PinholeModel
    rms_error_px: float
    mean_error_px: float
    used_frames: list[int]
    per_frame_rms_px: np.ndarray
    parameter_names: tuple[str, ...]
    parameter_covariance: np.ndarray
    residuals_px: np.ndarray
    reduced_chi2_px2: float


def calibrate_pinhole(image_points: list[np.ndarray | None], object_points_mm: np.ndarray,
                      shape: tuple[int, int], *, fit_k3: bool = False) -> PinholeCalibration:
    """Intrinsics and distortion of one band image from the chessboard corners of several frames.

    k3 is fixed at 0 unless ``fit_k3`` (a phone lens to 40 degrees needs k1, k2; k3 only trades against them).

    Parameters
    ----------
    image_points : list of numpy.ndarray or None
        Per frame the ``(N, 2)`` detected corners (u, v), pixels, or None (no board).
    object_points_mm : numpy.ndarray
        The board's ``(N, 3)`` corners in its own plane (z = 0), mm.
    shape : tuple of int
        (rows, cols) of the band image.
    fit_k3 : bool, default False
        Fit the sixth-order radial coefficient k3.

    Returns
    -------
    PinholeCalibration
        The model, the RMS and mean reprojection errors (pixels), the frames used, the per-frame RMS, the
        covariance of the intrinsic parameters (board poses profiled out, scaled by the reduced chi-square), the
        residuals and the reduced chi-square (pixel^2).

    Raises
    ------
    ValueError
        With fewer than three frames with a board.
    """
    import cv2

    used = [i for i, p in enumerate(image_points) if p is not None]
    if len(used) < 3:
        raise ValueError(f"only {len(used)} frames with a board; a pinhole calibration needs at least 3")
    obj = [np.asarray(object_points_mm, np.float32).reshape(-1, 1, 3) for _ in used]
    img = [np.asarray(image_points[i], np.float32).reshape(-1, 1, 2) for i in used]
    flags = 0 if fit_k3 else cv2.CALIB_FIX_K3
    h, w = shape
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, (int(w), int(h)), None, None, flags=flags)[:5]
    dist = np.asarray(dist, float).ravel()[:5]
    model = PinholeModel(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), dist, tuple(shape))
    names = PARAMETERS if fit_k3 else PARAMETERS[:8]
    n_int = len(names)
    blocks, residuals, per_frame = [], [], []
    for o, p, rvec, tvec in zip(obj, img, rvecs, tvecs):
        proj, jac = cv2.projectPoints(o, rvec, tvec, K, dist)
        res = (p - proj).reshape(-1, 2)
        residuals.append(res)
        per_frame.append(float(np.sqrt(np.mean(np.sum(res**2, axis=1)))))
        # jacobian columns: rvec (3), tvec (3), fx, fy, cx, cy, distortion (k1, k2, p1, p2, k3, ...)
        blocks.append((jac[:, :6], jac[:, 6:6 + n_int]))
    res_all = np.concatenate(residuals)
    n_pose = 6 * len(blocks)
    n_obs = 2 * res_all.shape[0]
    J = np.zeros((n_obs, n_int + n_pose))
    row = 0
    for k, (pose, intr) in enumerate(blocks):
        J[row:row + pose.shape[0], :n_int] = intr
        J[row:row + pose.shape[0], n_int + 6 * k:n_int + 6 * (k + 1)] = pose
        row += pose.shape[0]
    dof = max(n_obs - J.shape[1], 1)
    chi2 = float(np.sum(res_all**2)) / dof
    cov_full = chi2 * np.linalg.pinv(J.T @ J)
    return PinholeCalibration(model=model, rms_error_px=float(rms),
                              mean_error_px=float(np.mean(np.linalg.norm(res_all, axis=1))), used_frames=used,
                              per_frame_rms_px=np.array(per_frame), parameter_names=names,
                              parameter_covariance=cov_full[:n_int, :n_int], residuals_px=res_all,
                              reduced_chi2_px2=chi2)


def pinhole_maps(model: PinholeModel, covariance: np.ndarray | None = None,
                 parameter_names: tuple[str, ...] = PARAMETERS[:8], step_px: float = 0.5) -> dict[str, np.ndarray]:
    """theta_deg, phi_deg, solid_angle_sr and theta_deg_sigma at every band pixel centre.

    The solid angle is that of the pixel's square on the sky: dOmega = dx dy / (1 + x^2 + y^2)^(3/2)
    on the normalised plane, with dx dy the pixel's area mapped through the undistortion
    (central differences of ``step_px``). theta_deg_sigma: first-order propagation of
    ``covariance``, derivatives by central differences; NaN without a covariance.

    Parameters
    ----------
    model : PinholeModel
        The band image's model.
    covariance : numpy.ndarray, optional
        Covariance of the parameters named in ``parameter_names``, in their units.
    parameter_names : tuple of str, default ``PARAMETERS[:8]``
        The parameters the covariance is over, in its order.
    step_px : float, default 0.5
        Half step of the central differences of the pixel area, pixels.

    Returns
    -------
    dict[str, numpy.ndarray]
        ``"theta_deg"`` (degree), ``"phi_deg"`` (degree), ``"solid_angle_sr"`` (sr) and ``"theta_deg_sigma"``
        (degree), each of shape ``model.shape``.
    """
    rows, cols = model.shape
    v, u = np.mgrid[0:rows, 0:cols].astype(float)
    x, y = model.normalised(u, v)
    theta = np.degrees(np.arctan(np.hypot(x, y)))
    phi = np.degrees(np.arctan2(y, x))
    xu, yu = model.normalised(u + step_px, v)
    xl, yl = model.normalised(u - step_px, v)
    xd, yd = model.normalised(u, v + step_px)
    xt, yt = model.normalised(u, v - step_px)
    jac = np.abs((xu - xl) * (yd - yt) - (yu - yl) * (xd - xt)) / (2 * step_px) ** 2
    solid = jac / (1.0 + x * x + y * y) ** 1.5
    sigma = np.full(model.shape, np.nan)
    if covariance is not None:
        p0 = model.parameters()
        n = len(parameter_names)
        grads = np.zeros((n,) + model.shape)
        for k in range(n):
            h = 1e-6 * max(abs(p0[k]), 1.0)
            hi, lo = p0.copy(), p0.copy()
            hi[k] += h
            lo[k] -= h
            t_hi = PinholeModel.from_parameters(hi, model.shape).theta_phi(u, v)[0]
            t_lo = PinholeModel.from_parameters(lo, model.shape).theta_phi(u, v)[0]
            grads[k] = (t_hi - t_lo) / (2 * h)
        g = grads.reshape(n, -1)
        sigma = np.sqrt(np.maximum(np.einsum("ip,ij,jp->p", g, np.asarray(covariance), g), 0.0)).reshape(model.shape)
    return {"theta_deg": theta, "phi_deg": phi, "solid_angle_sr": solid, "theta_deg_sigma": sigma}
