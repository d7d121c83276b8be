"""Render a planar chessboard seen through a fisheye model, and the poses a lab would choose.

Board frame and pose conventions of :mod:`pipeline.geometry.chessboard`;
pixel and camera-frame conventions of :mod:`pipeline.geometry.scaramuzza`.
"""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.geometry.chessboard import Board, project_points, rotation_matrix
from pipeline.geometry.scaramuzza import FisheyeModel


def board_reflectance(model: FisheyeModel, board: Board, rvec, tvec, u, v, *,
                      white: float = 0.9, black: float = 0.05, background: float = 0.35,
                      outside: float = 0.0, half_fov_deg: float | None = None) -> np.ndarray:
    """Reflectance seen along the rays of pixel coordinates (u, v) (any shape).

    Each ray (model.cam2world) is intersected with the board plane: white or
    black squares, the white margin, ``background`` off the board or behind
    the camera, ``outside`` beyond the image circle (theta > half FOV).

    Parameters
    ----------
    model : FisheyeModel
        The camera model the pixel coordinates belong to.
    board : Board
        The chessboard (inner corners, square size in mm, margin).
    rvec : array_like
        Shape (3,): the board's rotation (Rodrigues vector, rad) in the camera frame.
    tvec : array_like
        Shape (3,): the board centre's position in the camera frame, mm.
    u : numpy.ndarray
        Pixel column coordinates (pixel centres at integers).
    v : numpy.ndarray
        Pixel row coordinates, same shape as ``u``.
    white : float, optional
        Reflectance of the white squares and margin; default 0.9.
    black : float, optional
        Reflectance of the black squares; default 0.05.
    background : float, optional
        Reflectance off the board; default 0.35.
    outside : float, optional
        Value beyond the image circle; default 0.
    half_fov_deg : float, optional
        The image circle's half field of view, degree; default None (the model's own; None there too: no circle).

    Returns
    -------
    numpy.ndarray
        The reflectance along each ray, dimensionless, shape of ``u``.
    """
    hfov = model.half_fov_deg if half_fov_deg is None else half_fov_deg
    R = rotation_matrix(rvec)
    t = np.asarray(tvec, float).ravel()
    normal = R[:, 2]
    n_dot_t = float(normal @ t)
    hx, hy = board.half_extent_mm()
    sq = board.square_mm
    cos_fov = np.cos(np.radians(hfov)) if hfov is not None else -2.0
    d = model.cam2world(u, v)
    denom = d @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = n_dot_t / denom
    hit = lam > 0
    p = np.where(hit[..., None], lam[..., None] * d, 0.0) - t
    bx = p @ R[:, 0]
    by = p @ R[:, 1]
    on_board = hit & (np.abs(bx) <= hx) & (np.abs(by) <= hy)
    pi = np.floor(bx / sq + (board.nx + 1) / 2)
    qi = np.floor(by / sq + (board.ny + 1) / 2)
    in_squares = (pi >= 0) & (pi <= board.nx) & (qi >= 0) & (qi <= board.ny)
    is_black = in_squares & ((pi + qi) % 2 == 0)
    val = np.where(on_board, np.where(is_black, black, white), background)
    return np.where(d[..., 2] < cos_fov, outside, val)


def render_chessboard(model: FisheyeModel, board: Board, rvec, tvec, *,
                      supersample: int = 4, white: float = 0.9, black: float = 0.05,
                      background: float = 0.35, outside: float = 0.0,
                      half_fov_deg: float | None = None,
                      chunk_rows: int | None = None):
    """Render the board into a band image by inverse mapping with supersampling.

    Every pixel is split into supersample x supersample sub-pixels; each
    sub-pixel's ray (model.cam2world) is intersected with the board plane and
    takes the reflectance there (white/black squares, white margin, grey
    ``background`` off the board or behind the camera, ``outside`` beyond the
    image circle theta > half FOV). The pixel value is the mean.

    Parameters
    ----------
    model : FisheyeModel
        The camera model; its ``shape`` (rows, cols) is the image's.
    board : Board
        The chessboard.
    rvec : array_like
        Shape (3,): the board's rotation (Rodrigues vector, rad) in the camera frame.
    tvec : array_like
        Shape (3,): the board centre's position in the camera frame, mm.
    supersample : int, optional
        Sub-pixels per side; default 4.
    white : float, optional
        Reflectance of the white squares and margin; default 0.9.
    black : float, optional
        Reflectance of the black squares; default 0.05.
    background : float, optional
        Reflectance off the board; default 0.35.
    outside : float, optional
        Value beyond the image circle; default 0.
    half_fov_deg : float, optional
        The image circle's half field of view, degree; default None (the model's).
    chunk_rows : int, optional
        Image rows rendered at once; default None (about 2 million sub-pixels at a time).

    Returns
    -------
    image : numpy.ndarray
        float64, shape (rows, cols): the mean reflectance of each pixel.
    corners : numpy.ndarray
        Shape (nx ny, 2): the true inner-corner pixel positions (u, v), OpenCV order.
    """
    rows, cols = model.shape
    ss = int(supersample)
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    if chunk_rows is None:
        chunk_rows = max(1, int(2_000_000 // (cols * ss * ss)))
    image = np.empty((rows, cols))
    u_sub = (np.arange(cols)[:, None] + offs[None, :]).ravel()  # cols*ss
    for r0 in range(0, rows, chunk_rows):
        r1 = min(rows, r0 + chunk_rows)
        v_sub = (np.arange(r0, r1)[:, None] + offs[None, :]).ravel()
        uu, vv = np.meshgrid(u_sub, v_sub)
        val = board_reflectance(model, board, rvec, tvec, uu, vv, white=white, black=black,
                                background=background, outside=outside, half_fov_deg=half_fov_deg)
        val = val.reshape(r1 - r0, ss, cols, ss).mean(axis=(1, 3))
        image[r0:r1] = val
    corners = project_points(model, board.corners_mm(), rvec, tvec)
    return image, corners


def look_rotation(direction, tilt_rad, tilt_azimuth, roll) -> np.ndarray:
    """Rotation whose z column is `direction` tilted by tilt_rad, rolled in-plane.

    Parameters
    ----------
    direction : numpy.ndarray
        Shape (3,): the direction the board's normal starts from (need not be unit length).
    tilt_rad : float
        Tilt away from ``direction``, rad.
    tilt_azimuth : float
        Azimuth of the tilt's axis about ``direction``, rad.
    roll : float
        In-plane rotation about the tilted z axis, rad.

    Returns
    -------
    numpy.ndarray
        Shape (3, 3): the rotation matrix, columns x, y, z.
    """
    z0 = direction / np.linalg.norm(direction)
    helper = np.array([0.0, 1.0, 0.0]) if abs(z0[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x0 = np.cross(helper, z0)
    x0 /= np.linalg.norm(x0)
    y0 = np.cross(z0, x0)
    axis = np.cos(tilt_azimuth) * x0 + np.sin(tilt_azimuth) * y0
    Rt = rotation_matrix(axis * tilt_rad)
    z = Rt @ z0
    x1 = Rt @ x0
    y1 = Rt @ y0
    x = np.cos(roll) * x1 + np.sin(roll) * y1
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def poses_covering_fov(n: int, half_fov_deg: float, rng=None, *, board: Board | None = None,
                       board_half_angle_deg: float | tuple[float, float] = (50.0, 20.0),
                       max_tilt_deg: float = 45.0,
                       edge_margin_deg: float = 1.5, model: FisheyeModel | None = None):
    """Poses whose board centres spread from the optical axis to the edge of the field.

    The i-th board centre sits at field angle ~ (i / (n-1)) * theta_max
    (jittered), theta_max chosen so that the board just fits inside the
    circle; azimuths are random; the distance makes the board's outline
    subtend ``board_half_angle_deg``; the board faces the camera with a
    random tilt (<= max_tilt_deg) and a random roll (0..360, so both
    180-degree orientations occur). A pose is kept only when every point of
    the board outline is at theta < half_fov - edge_margin_deg (board fully
    visible); when ``model`` is given the outline must also fall inside
    the image.

    Parameters
    ----------
    n : int
        Number of poses.
    half_fov_deg : float
        The lens's half field of view, degree.
    rng : int or numpy.random.Generator, optional
        Seed or generator (``numpy.random.default_rng``); default None (fresh entropy).
    board : Board, optional
        The chessboard; default ``Board()``.
    board_half_angle_deg : float or tuple of (float, float), optional
        Half-angle the board's half-diagonal subtends, degree; a pair (on the axis, at the edge) varies it over
        the poses: large boards near the axis constrain the focal scale through perspective, small ones reach the
        edge of the field. Default (50, 20).
    max_tilt_deg : float, optional
        Largest tilt of the board away from facing the camera, degree; default 45.
    edge_margin_deg : float, optional
        Margin of the board's outline inside the half field of view, degree; default 1.5.
    model : FisheyeModel, optional
        When given, the outline must also project inside its image; default None.

    Returns
    -------
    list of tuple of (numpy.ndarray, numpy.ndarray)
        Per pose, (rvec, tvec): rotation (Rodrigues vector, rad) and the board centre's position, mm.

    Raises
    ------
    RuntimeError
        When a fully visible board cannot be placed in 200 attempts.
    """
    rng = np.random.default_rng(rng)
    board = Board() if board is None else board
    hx, hy = board.half_extent_mm()
    half_diag = np.hypot(hx, hy)
    outline = board.outline_mm()
    alpha_axis, alpha_edge = np.broadcast_to(np.asarray(board_half_angle_deg, float), (2,))
    poses = []
    for i in range(n):
        frac = i / max(1, n - 1)
        alpha = alpha_axis + (alpha_edge - alpha_axis) * frac
        dist = half_diag / np.tan(np.radians(alpha))
        theta_max = half_fov_deg - edge_margin_deg - 0.8 * alpha
        for attempt in range(200):
            shrink = 1.0 - 0.01 * attempt  # move inwards if the board keeps clipping
            th = np.radians(max(0.0, theta_max * shrink * frac + rng.uniform(-2, 2)))
            ph = rng.uniform(-np.pi, np.pi)
            dvec = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
            tilt = np.radians(rng.uniform(0, max_tilt_deg))
            R = look_rotation(dvec, tilt, rng.uniform(0, 2 * np.pi), rng.uniform(0, 2 * np.pi))
            t = dvec * dist * rng.uniform(0.9, 1.1)
            pts = outline @ R.T + t
            theta = np.degrees(np.arctan2(np.hypot(pts[:, 0], pts[:, 1]), pts[:, 2]))
            if np.any(theta > half_fov_deg - edge_margin_deg):
                continue
            if model is not None:
                u, v = model.world2cam(pts)
                h, w = model.shape
                if not (np.all(np.isfinite(u)) and u.min() > 0 and v.min() > 0
                        and u.max() < w - 1 and v.max() < h - 1):
                    continue
            rvec = cv2.Rodrigues(R)[0].ravel()
            poses.append((rvec, t))
            break
        else:
            raise RuntimeError("could not place a fully visible board; reduce its size")
    return poses
