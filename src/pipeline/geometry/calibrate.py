"""Scaramuzza (OCamCalib) calibration from detected chessboard corners.

Steps, as in Scaramuzza et al. (2006) and the OCamCalib toolbox:

1. Linear initialisation for a given principal point: per frame, the
   cross-product constraint ``u' (r21 X + r22 Y + t2) - v' (r11 X + r12 Y +
   t1) = 0`` gives r11, r12, r21, r22, t1, t2 up to scale (SVD);
   orthonormality gives r31, r32; then one joint linear least-squares
   problem gives the polynomial (a1 = 0) and every frame's t3. Sign
   ambiguities are resolved by requiring the projected board to lie in the
   direction of its pixels, t3 > 0 and a0 > 0.
2. Centre search: the linear solution's reprojection error on a grid of
   candidate centres around the image centre, refined by shrinking the grid.
3. Nonlinear refinement (scipy.optimize.least_squares) of all poses, the
   centre, the stretch and the polynomial, minimising reprojection error in
   pixels. Frames with too few corners, a failed initialisation or wild
   errors are dropped and reported.
4. Covariance of the model parameters: by default a leave-one-board-out
   jackknife, each leave-one-out fit redone in full
   (:func:`jackknife_refit_covariance`) up to a number of boards, beyond
   linearised at the solution with the outlier rules re-applied per
   left-out board (:func:`jackknife_rejection_covariance`),
   or the cluster-robust sandwich over the boards, or scaled by the reduced
   chi-square of the corner residuals (:func:`intrinsic_covariance`); its
   block of the centre, stretch and polynomial is that of the poses
   profiled out.

Internally the polynomial is written in rho / r_norm (r_norm = half the
image's short side) so that all coefficients are of similar size.

Stretch: A = [[c, d], [e, 1]]. Its antisymmetric part is a rotation about the
optical axis, which the board poses absorb; ``stretch="symmetric"`` therefore
fits c and d with e = d; ``"full"`` frees e as well (the rotation gauge is
then fixed only weakly by the solver); ``"none"`` keeps the identity;
``"auto"`` (the default) keeps "symmetric" only when a test over the boards
shows a stretch, else fits "none" on the same corners, with its own covariance
(:func:`select_stretch`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats
from scipy.optimize import least_squares

from .scaramuzza import FisheyeModel
from .theta_uncertainty import parameter_names

#: estimates of the model parameters' covariance (:func:`calibrate`'s ``covariance``)
COVARIANCE_ESTIMATES = ("board_jackknife", "board_clustered", "reduced_chi2")
#: stretch models a fit can use
STRETCH_MODELS = ("symmetric", "full", "none")
#: :func:`calibrate`'s ``stretch``: a model, or "auto" (chosen by :func:`select_stretch`)
STRETCH_CHOICES = ("auto",) + STRETCH_MODELS
#: the candidates of stretch "auto", nested, the most general last (:func:`select_stretch` says why not "full")
AUTO_STRETCH_CANDIDATES = ("none", "symmetric")
#: Penalty (pixels) for a point the model cannot project (outside its domain).
_UNPROJECTABLE_PX = 1.0e3


@dataclass
class CalibrationResult:
    """Fitted model, poses and errors. Frame-indexed lists follow the input order."""

    model: FisheyeModel
    poses: list                     # (rvec, tvec_mm) per frame, None for dropped frames
    frame_rms_px: np.ndarray        # RMS reprojection error per frame (NaN when dropped)
    mean_error_px: float            # mean Euclidean reprojection error over all used corners
    rms_error_px: float             # RMS Euclidean reprojection error
    residuals_px: np.ndarray        # (n, 2) projected - detected, used corners
    residual_rho_px: np.ndarray     # (n,) radial distance of each used corner from the centre
    used_frames: list               # indices of frames used in the final fit
    dropped: dict = field(default_factory=dict)  # frame index -> reason
    linear_centre: tuple = (np.nan, np.nan)      # centre chosen by the grid search
    n_points_dropped: int = 0                    # single outlier corners removed
    success: bool = True
    message: str = ""
    #: names of the model parameters the covariance is over (pipeline.geometry.theta_uncertainty.parameter_names)
    parameter_names: tuple = ()
    #: their covariance (units of the parameters: pixel, 1, pixel^(1-k)), board poses profiled out
    #: (estimated as calibrate's ``covariance`` says)
    parameter_covariance: np.ndarray | None = None
    #: sum of squared corner residuals over the degrees of freedom (px^2): the corner noise the covariance assumes
    reduced_chi2_px2: float = float("nan")
    n_dof: int = 0
    #: per input frame the indices of its corners the final fit used (None for a dropped frame)
    corners_used: list = field(default_factory=list)
    #: how the stretch model was chosen: {"criterion", "values" (candidate -> criterion), "chosen"}
    stretch_selection: dict = field(default_factory=dict)
    #: the covariance estimate used: "board_jackknife_refit", "board_jackknife_linearised_rejection",
    #: "board_clustered", "reduced_chi2" or "not computed"
    covariance_method: str = ""

    def residuals_vs_radius(self, n_bins: int = 10):
        """Mean residual norm of the used corners in radial bins from the centre.

        Parameters
        ----------
        n_bins : int, default 10
            Number of equal-width bins from 0 to the largest corner radius.

        Returns
        -------
        centres : numpy.ndarray
            Bin centres, radial distance from the principal point, pixels, shape ``(n_bins,)``.
        mean : numpy.ndarray
            Mean Euclidean reprojection error in each bin, pixels (NaN in an empty bin).
        counts : numpy.ndarray
            Number of corners in each bin.
        """
        r = self.residual_rho_px
        e = np.linalg.norm(self.residuals_px, axis=1)
        edges = np.linspace(0, r.max() if r.size else 1.0, n_bins + 1)
        idx = np.clip(np.digitize(r, edges) - 1, 0, n_bins - 1)
        counts = np.bincount(idx, minlength=n_bins)
        sums = np.bincount(idx, weights=e, minlength=n_bins)
        with np.errstate(invalid="ignore", divide="ignore"):
            return 0.5 * (edges[1:] + edges[:-1]), sums / counts, counts


# ----------------------------------------------------------------- rotations
def rodrigues(rvecs):
    """Rotation matrices (k, 3, 3) of rotation vectors (k, 3).

    Parameters
    ----------
    rvecs : numpy.ndarray
        Rotation vectors (axis times angle, radians), shape ``(k, 3)`` or ``(3,)``.

    Returns
    -------
    numpy.ndarray
        Rotation matrices, shape ``(k, 3, 3)``.
    """
    rvecs = np.atleast_2d(rvecs)
    th = np.linalg.norm(rvecs, axis=1)
    k = rvecs / np.where(th > 0, th, 1.0)[:, None]
    K = np.zeros((len(rvecs), 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -k[:, 2], k[:, 1]
    K[:, 1, 0], K[:, 1, 2] = k[:, 2], -k[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3)[None] + s * K + (1 - c) * K @ K


def _rotvec(R):
    """Rotation vector of a rotation matrix (robust through cv2)."""
    import cv2
    return cv2.Rodrigues(np.asarray(R, float))[0].ravel()


def _nearest_rotation(M):
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1, 1, -1]) @ Vt
    return R


# ------------------------------------------------------- linear initialisation
def _extrinsic_partial(up, vp, X, Y):
    """r11, r12, r21, r22, t1, t2 (scaled) candidates and r31/r32 for one frame."""
    M = np.stack([-vp * X, -vp * Y, up * X, up * Y, -vp, up], axis=1)
    _, _, Vt = np.linalg.svd(M, full_matrices=False)
    H = Vt[-1]
    r11, r12, r21, r22, t1, t2 = H
    # The board must lie in the direction of its pixels (lambda > 0).
    if np.sum(up * (r11 * X + r12 * Y + t1) + vp * (r21 * X + r22 * Y + t2)) < 0:
        H = -H
        r11, r12, r21, r22, t1, t2 = H
    A = (r12**2 + r22**2) - (r11**2 + r21**2)
    B = -(r11 * r12 + r21 * r22)
    p = 0.5 * (A + np.sqrt(A**2 + 4 * B**2))
    r31 = np.sqrt(max(p, 0.0))
    r32 = B / r31 if r31 > 1e-9 * np.abs(H).max() else np.sqrt(max(p - A, 0.0))
    scale = 1.0 / np.sqrt(r11**2 + r21**2 + r31**2)
    return H * scale, r31 * scale, r32 * scale


def _poly_rows(up, vp, X, Y, H, r31, r32, powers):
    r11, r12, r21, r22, t1, t2 = H
    rho = np.hypot(up, vp)
    Ai = r11 * X + r12 * Y + t1
    Bi = r21 * X + r22 * Y + t2
    Ci = r31 * X + r32 * Y
    P = rho[:, None] ** np.asarray(powers)[None, :]
    rows = np.concatenate([P * Bi[:, None], P * Ai[:, None]])
    t3col = np.concatenate([-vp, -up])
    rhs = np.concatenate([vp * Ci, up * Ci])
    return rows, t3col, rhs


def _linear_init(frames, centre, degree, r_norm):
    """Linear Scaramuzza solution for a centre; frames = [(uv, XY), ...] (normalised).

    Returns (b, poses) with b the normalised polynomial coefficients (b0, b2..bN)
    and poses [(R, t)] (t in board units), or None when it fails.
    """
    powers = [0] + list(range(2, degree + 1))
    parts = []
    for uv, XY in frames:
        up = (uv[:, 0] - centre[0]) / r_norm
        vp = (uv[:, 1] - centre[1]) / r_norm
        X, Y = XY[:, 0], XY[:, 1]
        H, r31, r32 = _extrinsic_partial(up, vp, X, Y)
        best = None
        for sgn in (1.0, -1.0):
            rows, t3col, rhs = _poly_rows(up, vp, X, Y, H, sgn * r31, sgn * r32, powers)
            M = np.concatenate([rows, t3col[:, None]], axis=1)
            sol, *_ = np.linalg.lstsq(M, rhs, rcond=None)
            res = np.linalg.norm(M @ sol - rhs)
            ok = sol[-1] > 0 and sol[0] > 0
            key = (not ok, res)
            if best is None or key < best[0]:
                best = (key, sgn, rows, t3col, rhs)
        parts.append((up, vp, X, Y, H, best[1] * r31, best[1] * r32, best[2], best[3], best[4]))
    # Joint system: shared polynomial, one t3 per frame. A frame's t3 column is nonzero only in its own
    # rows, so it is eliminated frame by frame (each frame's rows projected off its t3 column): the
    # polynomial is the least-squares solution of the projected rows, and each t3 follows from it; the same
    # solution as the whole block system's, at the cost of a system with the polynomial's columns alone.
    n_p = len(powers)
    projected, projected_rhs = [], []
    for *_, rows, t3col, rhs in parts:
        tt = t3col @ t3col
        projected.append(rows - np.outer(t3col, t3col @ rows) / tt)
        projected_rhs.append(rhs - t3col * ((t3col @ rhs) / tt))
    b_sol, *_ = np.linalg.lstsq(np.concatenate(projected), np.concatenate(projected_rhs), rcond=None)
    t3 = [(t3col @ (rhs - rows @ b_sol)) / (t3col @ t3col) for *_, rows, t3col, rhs in parts]
    sol = np.concatenate([b_sol, t3])
    b = sol[:n_p]
    if not np.all(np.isfinite(sol)) or b[0] <= 0:
        return None
    poses = []
    for i, (_up, _vp, _X, _Y, H, r31, r32, *_r) in enumerate(parts):
        r11, r12, r21, r22, t1, t2 = H
        r1 = np.array([r11, r21, r31])
        r2 = np.array([r12, r22, r32])
        R = _nearest_rotation(np.stack([r1, r2, np.cross(r1, r2)], axis=1))
        t = np.array([t1, t2, sol[n_p + i]])
        poses.append((R, t))
    return b, poses


def _b_to_poly(b, degree, r_norm):
    powers = [0] + list(range(2, degree + 1))
    poly = np.zeros(degree + 1)
    for k, bk in zip(powers, b):
        poly[k] = bk * r_norm ** (1 - k)
    return tuple(poly)


def _poly_to_b(poly, degree, r_norm):
    powers = [0] + list(range(2, degree + 1))
    return np.array([poly[k] / r_norm ** (1 - k) if k < len(poly) else 0.0 for k in powers])


def _project(model, R, t, XYZ):
    cam = XYZ @ R.T + t
    u, v = model.world2cam(cam)
    return np.stack([u, v], axis=-1)


def _linear_error(frames, centre, degree, r_norm, shape, L):
    out = _linear_init(frames, centre, degree, r_norm)
    if out is None:
        return np.inf, None
    b, poses = out
    model = FisheyeModel(_b_to_poly(b, degree, r_norm), centre[0], centre[1], shape=shape)
    cam = np.concatenate([np.concatenate([XY, np.zeros((len(XY), 1))], axis=1) @ R.T + t
                          for (_, XY), (R, t) in zip(frames, poses)])
    uv = np.concatenate([uv for uv, _ in frames])
    u, v = model.world2cam(cam)
    e = (u - uv[:, 0]) ** 2 + (v - uv[:, 1]) ** 2
    e = np.where(np.isfinite(e), e, _UNPROJECTABLE_PX**2)
    return float(np.sqrt(np.mean(e))), (b, poses)


def search_centre(frames, shape, degree, r_norm, L, *, half_width_frac: float = 0.1,
                  n_grid: int = 5, n_levels: int = 4):
    """Grid search of the principal point minimising the linear solution's error.

    Starting at the image centre, a ``n_grid`` x ``n_grid`` grid of candidate centres is searched, then a grid
    around the best candidate, its half width shrunk by ``3 / (n_grid - 1)`` at each of ``n_levels`` levels.

    Parameters
    ----------
    frames : list of tuple
        Per usable frame, (detected corners (u, v), pixels, shape ``(k, 2)``; planar board points in board units,
        shape ``(k, 2)``).
    shape : tuple of int
        (rows, cols) of the image.
    degree : int
        Polynomial degree N of f(rho).
    r_norm : float
        Radius (pixels) the polynomial's argument is divided by.
    L : float
        The board unit, mm.
    half_width_frac : float, default 0.1
        Half width of the first grid, as a fraction of the image's short side.
    n_grid : int, default 5
        Candidates per grid side.
    n_levels : int, default 4
        Number of refinements after the first grid.

    Returns
    -------
    centre : tuple of float
        The best principal point (xc, yc), pixels.
    error : float
        RMS reprojection error of the linear solution there, pixels (inf when no candidate initialised).
    solution : tuple or None
        The linear solution there: (normalised polynomial coefficients, per-frame (R, t) poses), or None.
    """
    h, w = shape
    best = ((w - 1) / 2.0, (h - 1) / 2.0)
    half = half_width_frac * min(h, w)
    best_err, best_sol = _linear_error(frames, best, degree, r_norm, shape, L)
    for _ in range(n_levels):
        cx0, cy0 = best
        for cy in np.linspace(cy0 - half, cy0 + half, n_grid):
            for cx in np.linspace(cx0 - half, cx0 + half, n_grid):
                err, sol = _linear_error(frames, (cx, cy), degree, r_norm, shape, L)
                if err < best_err:
                    best, best_err, best_sol = (cx, cy), err, sol
        half *= 3.0 / (n_grid - 1)
    return best, best_err, best_sol


# ------------------------------------------------------- nonlinear refinement
def _unpack(x, n_frames, degree, r_norm, shape, stretch):
    i = 0
    xc, yc = x[0], x[1]
    i = 2
    c, d, e = 1.0, 0.0, 0.0
    if stretch == "symmetric":
        c, d = x[2], x[3]
        e = d
        i = 4
    elif stretch == "full":
        c, d, e = x[2], x[3], x[4]
        i = 5
    n_b = degree  # b0, b2..bN
    b = x[i:i + n_b]
    i += n_b
    model = FisheyeModel(_b_to_poly(b, degree, r_norm), xc, yc, c, d, e, shape=shape)
    pose = x[i:].reshape(n_frames, 6)
    return model, pose, i


def _reprojection_functions(frames, degree, r_norm, shape, stretch, n_intr):
    """Residuals (projected - detected, px, flattened u, v per corner) and their Jacobian as functions of the
    refinement's parameter vector (centre, stretch, b0, b2..bN, then six pose parameters per frame) over the
    corners of ``frames`` [(uv, XY), ...]; with the frame index of every corner."""
    n_f = len(frames)
    uv_all = np.concatenate([uv for uv, _ in frames])
    counts = [len(uv) for uv, _ in frames]
    frame_of_pt = np.repeat(np.arange(n_f), counts)
    XYZ = np.concatenate([np.concatenate([XY, np.zeros((len(XY), 1))], axis=1)
                          for _, XY in frames])

    def residuals(x):
        model, pose, _ = _unpack(x, n_f, degree, r_norm, shape, stretch)
        Rs = rodrigues(pose[:, :3])[frame_of_pt]
        cam = np.einsum("nij,nj->ni", Rs, XYZ) + pose[frame_of_pt, 3:]
        u, v = model.world2cam(cam)
        r = np.stack([u - uv_all[:, 0], v - uv_all[:, 1]], axis=1)
        return np.nan_to_num(r, nan=_UNPROJECTABLE_PX).ravel()

    def jacobian(x):
        # Central differences, grouped: a pose parameter of every frame is
        # perturbed at once (each frame's residuals depend on its pose only).
        J = np.zeros((2 * len(uv_all), len(x)))
        rows_of_frame = np.repeat(frame_of_pt, 2)
        for j in range(n_intr):
            h = 1e-6 * max(1.0, abs(x[j]))
            xp, xm = x.copy(), x.copy()
            xp[j] += h
            xm[j] -= h
            J[:, j] = (residuals(xp) - residuals(xm)) / (2 * h)
        for k in range(6):
            cols = n_intr + 6 * np.arange(n_f) + k
            h = 1e-6 * np.maximum(1.0, np.abs(x[cols]))
            xp, xm = x.copy(), x.copy()
            xp[cols] += h
            xm[cols] -= h
            d = (residuals(xp) - residuals(xm)) / (2 * h[rows_of_frame])
            J[np.arange(len(d)), cols[rows_of_frame]] = d
        return J

    return residuals, jacobian, frame_of_pt


def _refine(frames, L, model0, poses0, degree, r_norm, stretch, max_nfev, with_jacobian=True):
    shape = model0.shape
    b0 = _poly_to_b(model0.poly, degree, r_norm)
    head = [model0.xc, model0.yc]
    if stretch == "symmetric":
        head += [model0.c, model0.d]
    elif stretch == "full":
        head += [model0.c, model0.d, model0.e]
    pose = np.concatenate([np.concatenate([_rotvec(R), t]) for R, t in poses0])
    x0 = np.concatenate([head, b0, pose])
    n_intr = len(head) + len(b0)
    residuals, jacobian, frame_of_pt = _reprojection_functions(frames, degree, r_norm, shape, stretch, n_intr)
    sol = least_squares(residuals, x0, jac=jacobian, method="lm", x_scale="jac",
                        max_nfev=max_nfev, xtol=1e-10, ftol=1e-10)
    model, pose, _ = _unpack(sol.x, len(frames), degree, r_norm, shape, stretch)
    res = sol.fun.reshape(-1, 2)
    poses = [(rodrigues(p[:3])[0], p[3:].copy()) for p in pose]
    return model, poses, res, frame_of_pt, sol, jacobian(sol.x) if with_jacobian else None, n_intr


def intrinsic_covariance(J: np.ndarray, residuals: np.ndarray, n_intrinsic: int,
                         groups: np.ndarray | None = None) -> tuple[np.ndarray, float, int]:
    """Covariance of the first ``n_intrinsic`` parameters of a least-squares fit, the rest profiled out.

    Without ``groups``: C = s^2 (J^T J)^-1 with s^2 = |r|^2 / (n - p) the
    reduced chi-square of the residuals (every corner coordinate one
    independent measurement of equal variance, estimated from the fit).

    With ``groups`` (one label per residual, e.g. the board frame): the
    cluster-robust (sandwich) covariance C = B^-1 M B^-1, B = J^T J,
    M = G / (G - 1) sum_g J_g^T r_g r_g^T J_g over the G groups: errors may be
    correlated within a group (a board's corners share its detection errors)
    but not between groups. At the solution J_g^T r_g vanishes for the
    group's own pose columns, so M is carried by the shared parameters.

    Either way the top-left block of the full inverse is the inverse of the
    Schur complement of the nuisance block: the covariance with the nuisance
    parameters (the board poses) re-fitted at every value of the others, to
    first order the same as marginalising them. Columns are scaled to unit
    norm before the inversion (centre in pixels, coefficients and poses in
    normalised units differ by orders of magnitude).

    Parameters
    ----------
    J : numpy.ndarray
        Jacobian of the residuals at the solution, shape ``(n, p)``, the intrinsic parameters' columns first.
    residuals : numpy.ndarray
        Residuals at the solution, pixels, shape ``(n,)``.
    n_intrinsic : int
        Number of leading columns whose covariance is returned.
    groups : numpy.ndarray, optional
        A cluster label per residual (e.g. the board); the reduced-chi-square form when None.

    Returns
    -------
    covariance : numpy.ndarray
        Covariance of the intrinsic parameters, in the units of the Jacobian's columns, shape
        ``(n_intrinsic, n_intrinsic)``.
    s2 : float
        Reduced chi-square of the residuals, pixel^2.
    dof : int
        Degrees of freedom n - p.

    Raises
    ------
    ValueError
        When J^T J is singular (a parameter the data do not constrain), a column of J is zero, or there are too
        few residuals or groups.
    """
    n, p = J.shape
    dof = n - p
    if dof <= 0:
        raise ValueError(f"{n} residuals for {p} parameters: no degrees of freedom for a covariance")
    s2 = float(residuals @ residuals) / dof
    norm = np.linalg.norm(J, axis=0)
    if not np.all(norm > 0):
        raise ValueError("a model parameter does not change the reprojection (zero Jacobian column)")
    Js = J / norm
    eig = np.linalg.eigvalsh(Js.T @ Js)
    if eig[0] <= 1e-12 * eig[-1]:
        raise ValueError(f"the normal matrix is singular (condition {eig[-1] / max(eig[0], 1e-300):.1e}): "
                         "a parameter combination is not constrained by the corners")
    bread = np.linalg.inv(Js.T @ Js)
    if groups is None:
        cov = s2 * bread
    else:
        labels = np.unique(groups)
        if labels.size < 2:
            raise ValueError("a cluster-robust covariance needs at least two groups")
        score = np.stack([Js[groups == g].T @ residuals[groups == g] for g in labels])
        meat = score.T @ score * labels.size / (labels.size - 1)
        cov = bread @ meat @ bread
    cov = cov / np.outer(norm, norm)
    return cov[:n_intrinsic, :n_intrinsic], s2, dof


def jackknife_covariance(J: np.ndarray, residuals: np.ndarray, n_intrinsic: int, groups: np.ndarray,
                         nuisance_group: np.ndarray) -> np.ndarray:
    """Leave-one-board-out jackknife covariance of the first ``n_intrinsic`` parameters of a least-squares fit.

    Each board g left out in turn, the fit is redone from the solution by one Gauss-Newton step without
    its rows (its own pose, ``nuisance_group == g``, then has no data and goes with them): since J^T r = 0 at
    the solution, the step is delta_g = (B - J_g^T J_g)^-1 J_g^T r_g over the remaining columns, B = J^T J.
    The jackknife covariance is (G - 1) / G sum_g (delta_g - mean)(delta_g - mean)^T.

    Against the cluster-robust sandwich (:func:`intrinsic_covariance` with ``groups``), which uses B^-1 for
    every board, each board's influence is here computed with that board out of the normal matrix: a board
    that carries much of the information about a parameter (a rim board, the only one near some azimuth)
    moves the fit far more when it is left out than its score under B^-1 says (its leverage; the sandwich is
    then low, as the CR3 correction of the sandwich also states). Measured on the tiny scale's 12 boards
    (docs/stages.md, "Uncertainty of the field angle"): the fitted centres' chi-square against the simulator's truth
    42.8 for 24 (sandwich) against 24.2 (this one, refitted in full; the one-step form here 23.9).

    Parameters
    ----------
    J : numpy.ndarray
        Jacobian of the residuals at the solution, shape ``(n, p)``, the intrinsic parameters' columns first.
    residuals : numpy.ndarray
        Residuals at the solution, pixels, shape ``(n,)``.
    n_intrinsic : int
        Number of leading (shared) columns whose covariance is returned.
    groups : numpy.ndarray
        The board of each residual row, shape ``(n,)``.
    nuisance_group : numpy.ndarray
        The board whose pose each column beyond ``n_intrinsic`` is, shape ``(p - n_intrinsic,)``.

    Returns
    -------
    numpy.ndarray
        Covariance of the intrinsic parameters, in the units of the Jacobian's columns, shape
        ``(n_intrinsic, n_intrinsic)``.

    Raises
    ------
    ValueError
        With fewer than three boards, a zero Jacobian column, or when a leave-one-out normal matrix is singular
        (a parameter only one board constrains).
    """
    labels = np.unique(groups)
    if labels.size < 3:
        raise ValueError("a jackknife over the boards needs at least three boards")
    norm = np.linalg.norm(J, axis=0)
    if not np.all(norm > 0):
        raise ValueError("a model parameter does not change the reprojection (zero Jacobian column)")
    Js = J / norm
    B = Js.T @ Js
    col_group = np.concatenate([np.full(n_intrinsic, -1), np.asarray(nuisance_group)])
    steps = []
    for g in labels:
        rows = groups == g
        keep = col_group != g
        Jg = Js[rows][:, keep]
        Bg = B[np.ix_(keep, keep)] - Jg.T @ Jg
        rhs = Jg.T @ residuals[rows]
        try:
            delta = np.linalg.solve(Bg, rhs)
        except np.linalg.LinAlgError:
            raise ValueError(f"without board {g} a parameter is not constrained: no jackknife") from None
        steps.append(delta[:n_intrinsic] / norm[:n_intrinsic])
    steps = np.array(steps)
    dev = steps - steps.mean(axis=0)
    return (labels.size - 1) / labels.size * dev.T @ dev


def _frame_rms_limit(rms: np.ndarray, outlier_factor: float, max_frame_rms_px: float | None) -> float:
    """The frame outlier rule's limit (px): ``outlier_factor`` times the median frame RMS, never below
    ``max_frame_rms_px`` when given."""
    limit = outlier_factor * float(np.median(rms))
    return limit if max_frame_rms_px is None else max(limit, max_frame_rms_px)


def jackknife_rejection_covariance(J: np.ndarray, residuals: np.ndarray, n_intrinsic: int, frame_of_pt: np.ndarray,
                                   *, outlier_factor: float, point_outlier_factor: float,
                                   max_frame_rms_px: float | None = None) -> np.ndarray:
    """Leave-one-board-out jackknife covariance with the outlier rules re-applied per left-out board, linearised.

    ``J`` and ``residuals`` (projected - detected, px; u, v per corner) are over EVERY corner of the G boards
    the fit used, those its corner rule rejected too, at the full fit's solution; ``frame_of_pt`` gives each
    corner's board (0..G-1), whose six pose columns follow the first ``n_intrinsic``. Each board g left out,
    the fit's path is followed on the linear model r + J delta from the solution: all corners of the other
    boards first, then, as :func:`calibrate` does after each fit, the worst board dropped when its RMS
    exceeds the frame rule's limit, else every corner whose error exceeds ``point_outlier_factor`` times the
    median error dropped, refitted (one linear least-squares solve from the solution, the rejected corners
    staying rejected) until nothing more is rejected. The covariance is (G - 1) / G sum_g (delta_g - mean)
    (delta_g - mean)^T over the intrinsic parts delta_g of the final steps.

    Why: :func:`jackknife_covariance` keeps the full fit's corners for every left-out board, while a fit
    without board g rejects its own (the median error moves, corners near the limit cross it, a corner the
    full fit rejected early stays in when its pull is gone): with heavy-tailed corner errors that choice is a
    share of the spread. Measured on the paper's close lens (11 boards, 26 of 528 corners rejected): the
    field-angle sigma of the one-step form 0.49-0.67 of the full refit's (:func:`jackknife_refit_covariance`),
    this one's within 30 % of it (docs/geometry-real-corners.md), at the cost of a few linear solves per
    board instead of a nonlinear fit. Without rejection (every corner within the limits) it is
    :func:`jackknife_covariance`. ValueError with fewer than three boards or when a leave-one-out system is
    singular.

    Parameters
    ----------
    J : numpy.ndarray
        Jacobian of the residuals over every corner, shape ``(2 m, p)``, rows u, v per corner.
    residuals : numpy.ndarray
        Projected minus detected positions, pixels, ``2 m`` values (u, v per corner).
    n_intrinsic : int
        Number of leading columns whose covariance is returned.
    frame_of_pt : numpy.ndarray
        The board (0..G-1) of each corner, shape ``(m,)``.
    outlier_factor : float
        The frame rule: a board whose RMS exceeds this times the median board RMS is dropped.
    point_outlier_factor : float
        The corner rule: a corner whose error exceeds this times the median corner error is dropped.
    max_frame_rms_px : float, optional
        An absolute limit on a board's RMS error, pixels.

    Returns
    -------
    numpy.ndarray
        Covariance of the intrinsic parameters, in the units of the Jacobian's columns, shape
        ``(n_intrinsic, n_intrinsic)``.

    Raises
    ------
    ValueError
        With fewer than three boards, a zero Jacobian column, or a singular leave-one-out system.
    """
    frame_of_pt = np.asarray(frame_of_pt)
    n_boards = int(frame_of_pt.max()) + 1 if frame_of_pt.size else 0
    if n_boards < 3:
        raise ValueError("a jackknife over the boards needs at least three boards")
    norm = np.linalg.norm(J, axis=0)
    if not np.all(norm > 0):
        raise ValueError("a model parameter does not change the reprojection (zero Jacobian column)")
    Js = J / norm
    r = np.asarray(residuals, float).reshape(-1, 2)
    Ju, Jv = Js[0::2], Js[1::2]
    col_board = np.concatenate([np.full(n_intrinsic, -1), np.repeat(np.arange(n_boards), 6)])
    steps = []
    for g in range(n_boards):
        active = frame_of_pt != g
        boards = [k for k in range(n_boards) if k != g]
        while True:
            cols = (col_board == -1) | np.isin(col_board, boards)
            rows = np.repeat(active, 2)
            A = Js[rows][:, cols]
            try:
                delta = np.linalg.solve(A.T @ A, -(A.T @ r.ravel()[rows]))
            except np.linalg.LinAlgError:
                raise ValueError(f"without board {g} a parameter is not constrained: no jackknife") from None
            pred = r + np.stack([Ju[:, cols] @ delta, Jv[:, cols] @ delta], axis=1)
            err = np.hypot(pred[:, 0], pred[:, 1])
            rms = np.array([np.sqrt(np.mean(err[active & (frame_of_pt == k)] ** 2)) for k in boards])
            bad = np.flatnonzero(rms > _frame_rms_limit(rms, outlier_factor, max_frame_rms_px))
            if bad.size:
                worst = boards.pop(int(bad[np.argmax(rms[bad])]))
                active &= frame_of_pt != worst
                continue
            bad_pts = active & (err > point_outlier_factor * np.median(err[active]))
            if not bad_pts.any():
                break
            active &= ~bad_pts
        steps.append(delta[:n_intrinsic] / norm[:n_intrinsic])
    steps = np.array(steps)
    dev = steps - steps.mean(axis=0)
    return (n_boards - 1) / n_boards * dev.T @ dev


def _intrinsic_vector(model: FisheyeModel, stretch: str, degree: int, r_norm: float) -> np.ndarray:
    """The fitted parameters of a model in the refinement's units: centre, stretch terms, b0, b2..bN."""
    head = {"symmetric": [model.c, model.d], "full": [model.c, model.d, model.e], "none": []}[stretch]
    return np.concatenate([[model.xc, model.yc], head, _poly_to_b(model.poly, degree, r_norm)])


def jackknife_refit_covariance(image_points, object_points, image_shape, used_frames, centre, *, stretch: str,
                               **options) -> np.ndarray:
    """Leave-one-board-out jackknife covariance of the intrinsic parameters, the whole fit redone per board.

    Each of the G boards the fit used (``used_frames``, indices into ``image_points``) is left out in turn
    and the calibration is run again on the other boards' detected corners: frame and corner outlier rules
    included (which corners a fit rejects is part of the estimate), initialised at ``centre`` (the full
    fit's principal point) instead of the centre grid search. The covariance is (G - 1) / G sum_g
    (p_g - mean)(p_g - mean)^T over the G refitted parameter vectors p_g, in the refinement's units (centre,
    stretch, b0, b2..bN; :func:`_to_model_units` converts). :func:`jackknife_covariance` takes one
    Gauss-Newton step from the full fit instead, with its corners: it misses the spread of the rejection
    and of fits that move beyond the linear range (measured on the paper's close lens, 11 boards, stretch
    "symmetric": the one-step sigma of the centre's column 0.54 times this one's;
    docs/geometry-real-corners.md). ValueError with fewer than three boards.

    Parameters
    ----------
    image_points : list
        Per frame, detected corners (u, v), pixels, shape ``(k, 2)``, or None.
    object_points : list of numpy.ndarray
        Per frame, board-frame corner positions, mm, shape ``(k, 3)``.
    image_shape : tuple of int
        (rows, cols) of the images.
    used_frames : list of int
        Indices of the frames the full fit used.
    centre : tuple of float
        The full fit's principal point (xc, yc), pixels.
    stretch : str
        The stretch model of the full fit (one of ``STRETCH_MODELS``).
    **options
        The other keyword arguments of the full fit (as :func:`calibrate` passes them; ``degree`` and
        ``min_frames`` are required).

    Returns
    -------
    numpy.ndarray
        Covariance of the intrinsic parameters in the refinement's units, square, one row per parameter.

    Raises
    ------
    ValueError
        With fewer than three boards, or when a leave-one-out fit fails.
    """
    used = list(used_frames)
    if len(used) < 3:
        raise ValueError("a jackknife over the boards needs at least three boards")
    r_norm = 0.5 * min(int(n) for n in image_shape)
    estimates = []
    for g in used:
        without = [None if k == g else uv for k, uv in enumerate(image_points)]
        fit = _calibrate_fixed(without, object_points, image_shape, stretch=stretch,
                               **{**options, "centre_guess": centre, "covariance": None,
                                  "min_frames": options["min_frames"] - 1})
        estimates.append(_intrinsic_vector(fit.model, stretch, options["degree"], r_norm))
    estimates = np.array(estimates)
    n = len(used)
    dev = estimates - estimates.mean(axis=0)
    return (n - 1) / n * dev.T @ dev


def _to_model_units(cov_x: np.ndarray, n_head: int, degree: int, r_norm: float) -> np.ndarray:
    """Covariance of (centre, stretch, b0, b2..bN) converted to the coefficients a_k = b_k r_norm^(1-k)."""
    powers = [0] + list(range(2, degree + 1))
    scale = np.concatenate([np.ones(n_head), [r_norm ** (1 - k) for k in powers]])
    return cov_x * np.outer(scale, scale)


def calibrate(image_points, object_points, image_shape, *, degree: int = 4,
              stretch: str = "auto", min_corners: int = 6, min_frames: int = 5,
              outlier_factor: float = 5.0, max_frame_rms_px: float | None = None,
              point_outlier_factor: float = 5.0,
              centre_half_width_frac: float = 0.1, max_nfev: int = 200,
              half_fov_deg: float | None = None,
              centre_guess: tuple[float, float] | None = None,
              covariance: str = "board_jackknife", jackknife_refit_max_boards: int = 0,
              stretch_significance: float = 0.05) -> CalibrationResult:
    """Calibrate a Scaramuzza model from chessboard corners seen in many frames.

    Parameters
    ----------
    image_points : list over frames of (k, 2) arrays of detected (u, v)
        pixels (pixel centres at integers), or None for frames where the
        board was not found.
    object_points : (k, 3) board-frame corner positions (mm, z = 0), shared
        by all frames, or a list with one array per frame.
    image_shape : (rows, cols) of the images.
    degree : polynomial degree N of f(rho) (a1 = 0).
    stretch : "symmetric" (fit c, d with e = d), "full", "none", or "auto":
        "symmetric" when a Wald test over the boards rejects no stretch at
        ``stretch_significance``, else "none" on the same corners
        (:func:`select_stretch`); the result's ``stretch_selection`` holds
        the test's values.
    min_corners : frames with fewer detected corners are dropped.
    min_frames : ValueError when fewer good frames remain.
    outlier_factor : a frame whose RMS error exceeds outlier_factor times
        the median frame RMS (and max_frame_rms_px when given) is dropped
        and the fit repeated.
    max_frame_rms_px : float, optional
        An absolute limit (pixels) on a frame's RMS reprojection error, on top of
        ``outlier_factor``; none when None.
    point_outlier_factor : single corners whose error exceeds this times the
        median corner error are dropped (a mislocated corner on a steeply
        tilted board) and the fit repeated; counted in ``n_points_dropped``.
    centre_half_width_frac : float, default 0.1
        Half width of the first grid of candidate principal points around the
        image centre, as a fraction of the image's short side.
    max_nfev : int, default 200
        Most function evaluations of the nonlinear refinement.
    half_fov_deg : stored in the returned model (e.g. from the image circle).
    centre_guess : a principal point already known to within a few pixels
        (e.g. another band's fit): the centre grid search is skipped and the
        linear initialisation is made at this centre (the nonlinear
        refinement still frees it).
    covariance : how the parameter covariance is estimated:
        ``"board_jackknife"`` (leave one board out: every leave-one-out fit
        redone in full, :func:`jackknife_refit_covariance`, up to
        ``jackknife_refit_max_boards`` boards; beyond, linearised with the
        outlier rules re-applied per board,
        :func:`jackknife_rejection_covariance`; the default 0 is the schema's,
        so a caller gets what the geometry stage does), ``"board_clustered"``
        (:func:`intrinsic_covariance` with the boards as clusters: the
        corners of one board may share errors, boards are independent) or
        ``"reduced_chi2"`` (every corner coordinate independent). The
        reduced chi-square is returned either way; the result's
        ``covariance_method`` says which was used.
    jackknife_refit_max_boards : int, default 0
        Most boards for which ``"board_jackknife"`` redoes every leave-one-out
        fit in full; with more boards the linearised form is used.
    stretch_significance : float, default 0.05
        Significance level of the Wald test of no stretch with ``stretch="auto"``.

    Returns
    -------
    CalibrationResult
        The fitted model, the boards' poses, the reprojection errors, the frames
        used and dropped, and the parameter covariance.

    Raises
    ------
    ValueError
        On an unknown ``covariance`` or ``stretch``, when fewer than ``min_frames``
        usable frames remain, or when the linear initialisation fails at every
        candidate centre.
    """
    if covariance not in COVARIANCE_ESTIMATES:
        raise ValueError(f"covariance must be one of {COVARIANCE_ESTIMATES}, got {covariance!r}")
    if stretch not in STRETCH_CHOICES:
        raise ValueError(f"stretch must be one of {STRETCH_CHOICES}, got {stretch!r}")
    options = dict(degree=degree, min_corners=min_corners, min_frames=min_frames, outlier_factor=outlier_factor,
                   max_frame_rms_px=max_frame_rms_px, point_outlier_factor=point_outlier_factor,
                   centre_half_width_frac=centre_half_width_frac, max_nfev=max_nfev, half_fov_deg=half_fov_deg,
                   centre_guess=centre_guess, covariance=covariance,
                   jackknife_refit_max_boards=jackknife_refit_max_boards)
    if stretch == "auto":
        return select_stretch(image_points, object_points, image_shape, stretch_significance=stretch_significance,
                              **options)
    return _calibrate_fixed(image_points, object_points, image_shape, stretch=stretch, **options)


def stretch_test(result: CalibrationResult) -> dict:
    """Evidence for a stretch in a fit with stretch "symmetric": a Wald test of c = 1, d = e = 0.

    W = delta^T C^-1 delta with delta = (c - 1, d) and C their block of the fit's parameter covariance. With
    a covariance over the boards (jackknife or clustered) C has G - 1 degrees of freedom (G boards) and
    W (G - p) / (p (G - 1)) follows F(p, G - p) under no stretch (Hotelling's T^2, p = 2); with the reduced
    chi-square W follows chi-square(p). The boards, not the corners, are the independent units: a corner
    criterion (BIC on the corner residuals as independent Gaussian) counts each board's shared error 48
    times and is carried by a few corners of the heavy tails (docs/geometry-real-corners.md).

    Parameters
    ----------
    result : CalibrationResult
        A fit with stretch "symmetric" and a parameter covariance.

    Returns
    -------
    dict
        ``"wald_statistic"`` (W, float), ``"p_value"`` (float), ``"n_boards"`` (G, int) and ``"reference"`` (the
        reference distribution, str).
    """
    names = list(result.parameter_names)
    at = [names.index("stretch_c"), names.index("stretch_d_and_e")]
    delta = np.array([result.model.c - 1.0, result.model.d])
    cov = result.parameter_covariance[np.ix_(at, at)]
    wald = float(delta @ np.linalg.solve(cov, delta))
    p, g = len(delta), len(result.used_frames)
    if result.covariance_method == "reduced_chi2":
        p_value, reference = float(stats.chi2.sf(wald, p)), f"chi-square({p})"
    else:
        p_value = float(stats.f.sf(wald * (g - p) / (p * (g - 1)), p, g - p))
        reference = f"Hotelling T^2 with F({p}, {g - p})"
    return {"wald_statistic": wald, "p_value": p_value, "n_boards": g, "reference": reference}


def select_stretch(image_points, object_points, image_shape, *, stretch_significance: float,
                   **options) -> CalibrationResult:
    """Calibrate with stretch "symmetric" kept only when the boards show it, else "none" on the same corners.

    The symmetric fit comes first, with the frame and corner outlier rules and the configured covariance;
    :func:`stretch_test` tests its stretch against the identity. Below ``stretch_significance`` the
    symmetric fit is returned; otherwise the fit is redone with stretch "none" (the same rules and
    covariance, initialised at the symmetric fit's centre), its covariance written over the symmetric fit's
    parameter names (zero for the stretch terms it holds fixed) so that every fit of a geometry artefact has
    the same parameters.

    The "none" fit states its own covariance. The symmetric fit's was stated before, to carry the stretch
    the test cannot exclude into theta; with the linearised jackknife made to follow the outlier rules
    (:func:`jackknife_rejection_covariance`) it states the paper's close lens's centre column 2.5 times the
    spread of a full leave-one-board-out refit of the "none" fit (its own: 1.02; the field angle 0.94-1.00
    against 0.87-1.46; docs/geometry-real-corners.md): the stretch-centre trade-off of a model that was
    not chosen. On simulated boards without stretch (medium scale, seed 3) the theta errors against the
    truth are consistent with the "none" fit's own covariance once the jackknife covariance's own
    sampling is counted (tests/geometry/test_geometry_theta_accuracy.py).
    ``stretch_selection`` holds the test, its values and the chosen model. "full" is no candidate: it adds
    to "symmetric" only a roll about the optical axis that the board poses absorb (the same reprojection,
    one parameter more, and a singular normal matrix).

    Parameters
    ----------
    image_points : list
        Per frame, detected corners (u, v), pixels, shape ``(k, 2)``, or None.
    object_points : numpy.ndarray or list of numpy.ndarray
        Board-frame corner positions, mm, shape ``(k, 3)``, shared or one per frame.
    image_shape : tuple of int
        (rows, cols) of the images.
    stretch_significance : float
        Significance level of the Wald test: the symmetric fit is kept when the p-value is below it.
    **options
        The other keyword arguments of :func:`calibrate`.

    Returns
    -------
    CalibrationResult
        The chosen fit, its ``stretch_selection`` holding the test.
    """
    general = AUTO_STRETCH_CANDIDATES[-1]
    first = _calibrate_fixed(image_points, object_points, image_shape, stretch=general, **options)
    test = stretch_test(first)
    selection = {"criterion": f"Wald test of no stretch ({test['reference']}, boards as the independent units)",
                 **test, "significance": float(stretch_significance)}
    if test["p_value"] < stretch_significance:
        return replace(first, stretch_selection={**selection, "chosen": general})
    chosen = AUTO_STRETCH_CANDIDATES[0]
    final = _calibrate_fixed(image_points, object_points, image_shape, stretch=chosen,
                             **{**options, "centre_guess": (first.model.xc, first.model.yc)})
    cov = final.parameter_covariance
    if cov is not None:
        cov = _embed_covariance(cov, final.parameter_names, first.parameter_names)
    return replace(final, parameter_names=first.parameter_names, parameter_covariance=cov,
                   linear_centre=first.linear_centre,
                   stretch_selection={**selection, "chosen": chosen})


def _embed_covariance(cov: np.ndarray, names, into) -> np.ndarray:
    """``cov`` over parameters ``names`` written over the parameters ``into`` (a superset): zero rows and
    columns for the parameters held fixed (the stretch terms of a fit without stretch)."""
    at = [list(into).index(n) for n in names]
    out = np.zeros((len(into), len(into)))
    out[np.ix_(at, at)] = cov
    return out


def _usable_frames(image_points, object_points, min_corners):
    """The frames a fit can use: each frame's finite corners and their board points in board units.

    Returns
    -------
    frames : list of (uv, XY) pairs, the image corners (px) and the planar board points divided by ``L``
    idx : the input index of each usable frame
    kept : the indices of each frame's corners that are used
    dropped : input index -> why the frame is not used
    L : the board unit (mm), the median absolute board coordinate
    """
    dropped = {}
    frames, idx, kept = [], [], []
    allpts = [np.asarray(o, float) for o in object_points if o is not None]
    L = float(np.median(np.abs(np.concatenate(allpts)[:, :2]))) or 1.0  # board unit, mm
    for i, (uv, obj) in enumerate(zip(image_points, object_points)):
        if uv is None:
            dropped[i] = "no corners detected"
            continue
        uv = np.asarray(uv, float).reshape(-1, 2)
        obj = np.asarray(obj, float).reshape(-1, 3)
        good = np.all(np.isfinite(uv), axis=1)
        if good.sum() < min_corners:
            dropped[i] = f"only {int(good.sum())} corners (< {min_corners})"
            continue
        if np.abs(obj[:, 2]).max() > 1e-9 * max(1.0, np.abs(obj).max()):
            raise ValueError("object_points must be planar with z = 0")
        frames.append((uv[good], obj[good, :2] / L))
        idx.append(i)
        kept.append(np.flatnonzero(good))
    return frames, idx, kept, dropped, L


def _calibrate_fixed(image_points, object_points, image_shape, *, degree, stretch, min_corners, min_frames,
                     outlier_factor, max_frame_rms_px, point_outlier_factor, centre_half_width_frac, max_nfev,
                     half_fov_deg, centre_guess, covariance, jackknife_refit_max_boards) -> CalibrationResult:
    """:func:`calibrate` with one stretch model; ``covariance=None`` skips the covariance (left None)."""
    n_in = len(image_points)
    if isinstance(object_points, np.ndarray) and object_points.ndim == 2:
        object_points = [object_points] * n_in
    frames, idx, kept, dropped, L = _usable_frames(image_points, object_points, min_corners)
    # every usable corner of each frame, those the corner rule will reject too (the rejection-aware jackknife)
    all_frames, all_kept = list(frames), list(kept)
    if len(frames) < min_frames:
        raise ValueError(f"only {len(frames)} usable frames (< min_frames={min_frames}); "
                         f"dropped: {dropped}")
    shape = tuple(int(n) for n in image_shape)
    r_norm = 0.5 * min(shape)

    if centre_guess is not None:
        centre = (float(centre_guess[0]), float(centre_guess[1]))
        lin_err, sol = _linear_error(frames, centre, degree, r_norm, shape, L)
    else:
        centre, lin_err, sol = search_centre(frames, shape, degree, r_norm, L,
                                             half_width_frac=centre_half_width_frac)
    if sol is None:
        raise ValueError("linear initialisation failed for every candidate centre")
    b, poses = sol
    model = FisheyeModel(_b_to_poly(b, degree, r_norm), centre[0], centre[1], shape=shape)

    n_points_dropped = 0
    # the board jackknife takes its Jacobian over every corner after the loop
    with_jacobian = covariance in ("board_clustered", "reduced_chi2")
    while True:
        model, poses, res, frame_of_pt, ls, jac, n_intr = _refine(frames, L, model, poses, degree,
                                                                  r_norm, stretch, max_nfev,
                                                                  with_jacobian=with_jacobian)
        err = np.linalg.norm(res, axis=1)
        rms = np.array([np.sqrt(np.mean(err[frame_of_pt == k] ** 2)) for k in range(len(frames))])
        limit = _frame_rms_limit(rms, outlier_factor, max_frame_rms_px)
        bad = np.nonzero(rms > limit)[0]
        if bad.size == 0:
            bad_pts = err > point_outlier_factor * np.median(err)
            if not bad_pts.any():
                break
            offsets = np.concatenate([[0], np.cumsum([len(uv) for uv, _ in frames])])
            new_frames = []
            for k, (uv, XY) in enumerate(frames):
                keep = ~bad_pts[offsets[k]:offsets[k + 1]]
                new_frames.append((uv[keep], XY[keep]))
                kept[k] = kept[k][keep]
            n_points_dropped += int(bad_pts.sum())
            frames = new_frames
            continue
        worst = int(bad[np.argmax(rms[bad])])  # drop one frame at a time
        dropped[idx[worst]] = f"reprojection RMS {rms[worst]:.2f} px > {limit:.2f} px"
        del frames[worst], idx[worst], poses[worst], kept[worst], all_frames[worst], all_kept[worst]
        if len(frames) < min_frames:
            raise ValueError(f"only {len(frames)} good frames (< min_frames={min_frames}) "
                             f"after dropping outliers; dropped: {dropped}")

    if half_fov_deg is not None:
        model = FisheyeModel(model.poly, model.xc, model.yc, model.c, model.d, model.e,
                             shape=shape, half_fov_deg=half_fov_deg)
    out_poses = [None] * n_in
    frame_rms = np.full(n_in, np.nan)
    corners_used = [None] * n_in
    for k, i in enumerate(idx):
        R, t = poses[k]
        out_poses[i] = (_rotvec(R), t * L)
        frame_rms[i] = rms[k]
        corners_used[i] = kept[k]
    names = parameter_names(stretch, degree)
    s2 = float(ls.fun @ ls.fun) / max(len(ls.fun) - len(ls.x), 1)
    dof = len(ls.fun) - len(ls.x)
    cov, method = None, "not computed"
    if covariance is not None:
        if covariance == "board_jackknife":
            # residuals and Jacobian over every corner of the used boards at the solution; the kept corners'
            # rows are those of the fit
            res_all, jac_all, frame_of_all = _reprojection_functions(all_frames, degree, r_norm, shape, stretch,
                                                                     n_intr)
            r_all, J_all = res_all(ls.x), jac_all(ls.x)
            in_fit = np.repeat(np.concatenate([np.isin(a, k) for a, k in zip(all_kept, kept)]), 2)
            jac = J_all[in_fit]
        groups = np.repeat(frame_of_pt, 2) if covariance == "board_clustered" else None
        cov_x, s2, dof = intrinsic_covariance(jac, ls.fun, n_intr, groups)
        method = covariance
        if covariance == "board_jackknife" and len(frames) <= jackknife_refit_max_boards:
            options = dict(degree=degree, min_corners=min_corners, min_frames=min_frames,
                           outlier_factor=outlier_factor, max_frame_rms_px=max_frame_rms_px,
                           point_outlier_factor=point_outlier_factor, centre_half_width_frac=centre_half_width_frac,
                           max_nfev=max_nfev, half_fov_deg=None, jackknife_refit_max_boards=jackknife_refit_max_boards)
            cov_x = jackknife_refit_covariance(image_points, object_points, image_shape, idx, (model.xc, model.yc),
                                               stretch=stretch, **options)
            method = "board_jackknife_refit"
        elif covariance == "board_jackknife":
            cov_x = jackknife_rejection_covariance(J_all, r_all, n_intr, frame_of_all, outlier_factor=outlier_factor,
                                                   point_outlier_factor=point_outlier_factor,
                                                   max_frame_rms_px=max_frame_rms_px)
            method = "board_jackknife_linearised_rejection"
        cov = _to_model_units(cov_x, n_intr - degree, degree, r_norm)
    uv_used = np.concatenate([uv for uv, _ in frames])
    x, y = model._sensor_xy(uv_used[:, 0], uv_used[:, 1])
    return CalibrationResult(
        model=model, poses=out_poses, frame_rms_px=frame_rms,
        mean_error_px=float(err.mean()), rms_error_px=float(np.sqrt(np.mean(err**2))),
        residuals_px=res, residual_rho_px=np.hypot(x, y), used_frames=list(idx),
        dropped=dropped, linear_centre=tuple(centre), n_points_dropped=n_points_dropped,
        success=bool(ls.success),
        message=str(ls.message), parameter_names=names, parameter_covariance=cov, reduced_chi2_px2=s2,
        n_dof=int(dof), corners_used=corners_used, stretch_selection={"criterion": "none (configured)",
                                                                       "values": {}, "chosen": stretch},
        covariance_method=method)
