"""Detect the inner corners of a chessboard in a band image.

Orientation rule (matches :mod:`pipeline.geometry.chessboard`): corners are
returned row by row, ``nx`` per row (OpenCV order for patternSize (nx, ny)),
such that

1. the grid is right-handed in the image: with u to the right and v down,
   ``cross(c[1] - c[0], c[nx] - c[0]) > 0`` (a board seen from its front);
2. the square enclosed by the first four corners (c[0], c[1], c[nx],
   c[nx+1]) is *dark* -- on the rendered board square (1, 1) is black.

With ``nx + ny`` odd the squares at the two ends of the grid have opposite
colours, so rule 2 resolves the 180-degree ambiguity; with ``nx + ny`` even
the board is symmetric and the result's ``ambiguous`` flag is set. When
``nx == ny`` the transposed orderings are also considered.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import map_coordinates

#: Detection is run on an image upsampled to at least this many pixels (short side).
MIN_DETECT_SIZE_PX = 800
#: Largest upsampling factor.
MAX_UPSAMPLE = 4
#: Band pixels added to every side of a crop beyond its margin in squares, so
#: that a board of tiny squares keeps a few pixels of context.
CROP_PAD_PX = 4


@dataclass
class CornerResult:
    """Detected corners (nx*ny, 2) as (u, v) in band pixels, or None and a reason."""

    corners: np.ndarray | None
    method: str
    ambiguous: bool = False
    message: str = ""

    @property
    def found(self) -> bool:
        return self.corners is not None


def to_uint8(image, low_pct: float = 0.5, high_pct: float = 99.5) -> np.ndarray:
    """Stretch a float image between two percentiles to 0..255 uint8.

    Parameters
    ----------
    image : numpy.ndarray
        Float image; NaN pixels are set to the low percentile.
    low_pct : float, default 0.5
        Percentile mapped to 0.
    high_pct : float, default 99.5
        Percentile mapped to 255.

    Returns
    -------
    numpy.ndarray
        uint8 image of the same shape.
    """
    img = np.asarray(image, dtype=float)
    finite = img[np.isfinite(img)]
    lo, hi = np.percentile(finite, [low_pct, high_pct]) if finite.size else (0.0, 1.0)
    if hi <= lo:
        hi = lo + 1.0
    out = np.clip((np.nan_to_num(img, nan=lo) - lo) / (hi - lo), 0, 1) * 255
    return np.round(out).astype(np.uint8)


def upsample_factor(shape) -> int:
    """Integer upsampling that brings an image's short side to ``MIN_DETECT_SIZE_PX``, at most ``MAX_UPSAMPLE``.

    Parameters
    ----------
    shape : tuple of int
        (rows, cols) of the band image.

    Returns
    -------
    int
        The factor, 1 for images already large enough.
    """
    return int(min(MAX_UPSAMPLE, max(1, np.ceil(MIN_DETECT_SIZE_PX / min(shape)))))


def _scale_back(pts, k):
    # Edge-preserving scaling: u_band + 0.5 = (u_up + 0.5) / k.
    return (pts + 0.5) / k - 0.5


def _candidates(img8, nx, ny):
    """Yield (corners in img8 pixels, method): sector-based detector, then classic."""
    flags_sb = [cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE,
                cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_NORMALIZE_IMAGE]
    for fl in flags_sb:
        ok, pts = cv2.findChessboardCornersSB(img8, (nx, ny), flags=fl)
        if ok and pts is not None and len(pts) == nx * ny:
            yield pts.reshape(-1, 2).astype(float), "findChessboardCornersSB"
    ok, pts = cv2.findChessboardCorners(
        img8, (nx, ny),
        flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if ok and pts is not None and len(pts) == nx * ny:
        pts = pts.reshape(-1, 1, 2).astype(np.float32)
        # Window about a quarter of the smallest spacing between neighbours.
        d = np.linalg.norm(np.diff(pts.reshape(ny, nx, 2), axis=1), axis=-1).min()
        win = int(max(2, min(11, d / 4)))
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
        pts = cv2.cornerSubPix(img8, pts, (win, win), (-1, -1), crit)
        yield pts.reshape(-1, 2).astype(float), "findChessboardCorners+cornerSubPix"


def _rough_candidates(img8, nx, ny):
    """Yield corners in img8 pixels without sub-pixel refinement (to locate a board only)."""
    ok, pts = cv2.findChessboardCornersSB(img8, (nx, ny),
                                          flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if ok and pts is not None and len(pts) == nx * ny:
        yield pts.reshape(-1, 2).astype(float)
    ok, pts = cv2.findChessboardCorners(img8, (nx, ny),
                                        flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if ok and pts is not None and len(pts) == nx * ny:
        yield pts.reshape(-1, 2).astype(float)


#: Largest ratio of neighbouring corner spacings along a grid line; fisheye
#: distortion changes the spacing slowly, a skipped or extra corner doubles it.
MAX_SPACING_RATIO = 1.6


def validate_grid(corners, image, nx: int, ny: int) -> str:
    """Empty string when corners form a plausible chessboard grid, else the reason.

    Checks that spacings along rows and columns vary smoothly and that the
    squares enclosed by the corners alternate dark / bright.

    Parameters
    ----------
    corners : numpy.ndarray
        Candidate corners (u, v), band pixels, shape ``(nx * ny, 2)``, row by row.
    image : numpy.ndarray
        Band image (float, e.g. DN), shape ``(rows, cols)``.
    nx, ny : int
        Inner corners per board row and per board column.

    Returns
    -------
    str
        Empty when the grid is plausible, else the reason ("corners collapse", "irregular corner spacing" or
        "squares do not alternate dark/bright").
    """
    g = np.asarray(corners, float).reshape(ny, nx, 2)
    for axis in (0, 1):
        d = np.linalg.norm(np.diff(g, axis=axis), axis=-1)
        if np.any(d < 0.5):
            return "corners collapse"
        if d.shape[axis] > 1:
            r = np.diff(np.log(d), axis=axis)
            if np.abs(r).max() > np.log(MAX_SPACING_RATIO):
                return "irregular corner spacing"
    if nx < 2 or ny < 2:
        return ""
    centres = 0.25 * (g[:-1, :-1] + g[1:, :-1] + g[:-1, 1:] + g[1:, 1:])
    vals = map_coordinates(np.asarray(image, float),
                           [centres[..., 1].ravel(), centres[..., 0].ravel()],
                           order=1, mode="nearest").reshape(centres.shape[:2])
    parity = (np.add.outer(np.arange(ny - 1), np.arange(nx - 1)) % 2).astype(bool)
    a, b = vals[parity], vals[~parity]
    if a.size == 0 or b.size == 0:
        return ""
    if not (a.min() > b.max() or b.min() > a.max()):
        return "squares do not alternate dark/bright"
    return ""


def _orderings(nx, ny):
    """Index arrays of the grid symmetries that keep the (ny, nx) layout."""
    idx = np.arange(nx * ny).reshape(ny, nx)
    cands = [idx, idx[::-1, ::-1], idx[::-1, :], idx[:, ::-1]]
    if nx == ny:
        cands += [c.T for c in cands]
    return [c.ravel() for c in cands]


def orient_corners(corners, image, nx: int, ny: int):
    """Reorder detected corners by the module's orientation rule.

    Parameters
    ----------
    corners : numpy.ndarray
        Detected corners (u, v), band pixels, shape ``(nx * ny, 2)``.
    image : numpy.ndarray
        Band image (float, e.g. DN), shape ``(rows, cols)``.
    nx, ny : int
        Inner corners per board row and per board column.

    Returns
    -------
    corners : numpy.ndarray
        The corners reordered, shape ``(nx * ny, 2)``.
    ambiguous : bool
        True when the board is symmetric (``nx + ny`` even) and the 180-degree ambiguity stays.
    """
    img = np.asarray(image, dtype=float)
    best = None
    for order in _orderings(nx, ny):
        g = corners[order].reshape(ny, nx, 2)
        a = g[0, 1] - g[0, 0]
        b = g[1, 0] - g[0, 0]
        if a[0] * b[1] - a[1] * b[0] <= 0:
            continue
        c_first = g[:2, :2].reshape(-1, 2).mean(axis=0)   # square (1, 1) on the board
        c_next = g[:2, 1:3].reshape(-1, 2).mean(axis=0)   # its neighbour (2, 1)
        vals = map_coordinates(img, [[c_first[1], c_next[1]], [c_first[0], c_next[0]]],
                               order=1, mode="nearest")
        score = vals[1] - vals[0]  # first square dark, its neighbour bright
        if best is None or score > best[0]:
            best = (score, order)
    if best is None:  # should not happen: reversal flips handedness for nx != ny
        return corners, True
    _, order = best
    # Symmetric boards: the last square has the same colour as the first.
    ambiguous = (nx + ny) % 2 == 0
    return corners[order], ambiguous


def detect_corners(image, nx: int, ny: int, *, upsample: int | None = None) -> CornerResult:
    """Find the (nx, ny) inner corners of a chessboard in a float band image.

    The image is stretched to uint8, upsampled (cubic) for small images so
    that the detectors see squares of several pixels, searched with
    ``findChessboardCornersSB`` (exhaustive + accuracy) and then with
    ``findChessboardCorners`` + ``cornerSubPix``. Corners are returned in
    band pixel coordinates (pixel centres at integers), ordered by the
    module's orientation rule. When no board is found the result has
    ``corners=None`` and a message (nothing is raised).

    Parameters
    ----------
    image : numpy.ndarray
        Band image (float, e.g. DN), shape ``(rows, cols)``.
    nx, ny : int
        Inner corners per board row and per board column.
    upsample : int, optional
        Upsampling factor; :func:`upsample_factor` of the image when None.

    Returns
    -------
    CornerResult
        The corners (u, v), band pixels, shape ``(nx * ny, 2)``, the detector that found them and the ambiguity
        flag; or ``corners=None`` and the reasons.
    """
    img = np.asarray(image, dtype=float)
    k = upsample_factor(img.shape) if upsample is None else int(upsample)
    img8 = to_uint8(img)
    if k > 1:
        img8 = cv2.resize(img8, (img.shape[1] * k, img.shape[0] * k),
                          interpolation=cv2.INTER_CUBIC)
    reasons = []
    for pts, method in _candidates(img8, nx, ny):
        pts = _scale_back(pts, k)
        why = validate_grid(pts, img, nx, ny)
        if why:
            reasons.append(f"{method}: {why}")
            continue
        pts, ambiguous = orient_corners(pts, img, nx, ny)
        return CornerResult(pts, method, ambiguous=ambiguous)
    msg = f"no {nx}x{ny} chessboard found" + (f" ({'; '.join(reasons)})" if reasons else "")
    return CornerResult(None, "none", message=msg)


def detect_in_crop(image, seed, nx: int, ny: int, *, upsample: int, margin_px: float) -> CornerResult:
    """Detect the board in the crop of ``image`` around ``seed`` corners (band px) plus ``margin_px``.

    The crop is searched exactly as :func:`detect_corners` searches a whole
    image, at the upsampling ``upsample`` the whole image would get, and the
    corners come back in the whole image's band pixel coordinates.

    Parameters
    ----------
    image : numpy.ndarray
        Band image (float, e.g. DN), shape ``(rows, cols)``.
    seed : numpy.ndarray
        Approximate corners (u, v), band pixels, shape ``(k, 2)``.
    nx, ny : int
        Inner corners per board row and per board column.
    upsample : int
        Upsampling factor of the search.
    margin_px : float
        Band pixels added around the seed corners' bounding box.

    Returns
    -------
    CornerResult
        As :func:`detect_corners`, corners in the whole image's band pixel coordinates.
    """
    img = np.asarray(image)
    seed = np.asarray(seed, float)
    h, w = img.shape
    c0 = max(0, int(np.floor(seed[:, 0].min() - margin_px)))
    c1 = min(w, int(np.ceil(seed[:, 0].max() + margin_px)) + 1)
    r0 = max(0, int(np.floor(seed[:, 1].min() - margin_px)))
    r1 = min(h, int(np.ceil(seed[:, 1].max() + margin_px)) + 1)
    res = detect_corners(img[r0:r1, c0:c1], nx, ny, upsample=upsample)
    if res.found:
        res.corners = res.corners + np.array([c0, r0], float)
    return res


def corner_spacing_px(corners, nx: int, ny: int) -> float:
    """Median distance between neighbouring corners along the rows (band px): about one square.

    Parameters
    ----------
    corners : numpy.ndarray
        Corners (u, v), band pixels, shape ``(nx * ny, 2)``, row by row.
    nx, ny : int
        Inner corners per board row and per board column.

    Returns
    -------
    float
        Median spacing, band pixels.
    """
    g = np.asarray(corners, float).reshape(ny, nx, 2)
    return float(np.median(np.linalg.norm(np.diff(g, axis=1), axis=-1)))


def locate_board(image, nx: int, ny: int, coarse_size_px: int) -> np.ndarray | None:
    """Approximate corners (band px) from a search on the image resampled to ``coarse_size_px`` (short side).

    Area averaging when the image shrinks, cubic when it grows; the
    detectors run without their sub-pixel refinement, which the crop search
    does. Returns None when no plausible grid is found there.

    Parameters
    ----------
    image : numpy.ndarray
        Band image (float, e.g. DN), shape ``(rows, cols)``.
    nx, ny : int
        Inner corners per board row and per board column.
    coarse_size_px : int
        Short side of the resampled image, pixels.

    Returns
    -------
    numpy.ndarray or None
        Approximate corners (u, v), band pixels, shape ``(nx * ny, 2)``, or None.
    """
    img = np.asarray(image, dtype=float)
    s = float(coarse_size_px) / min(img.shape)
    img8 = to_uint8(img)
    size = (max(1, round(img.shape[1] * s)), max(1, round(img.shape[0] * s)))
    small = cv2.resize(img8, size, interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_CUBIC)
    sx, sy = size[0] / img.shape[1], size[1] / img.shape[0]
    for pts in _rough_candidates(small, nx, ny):
        pts = (pts + 0.5) / np.array([sx, sy]) - 0.5
        if not validate_grid(pts, img, nx, ny):
            return pts
    return None


def detect_corners_coarse_to_fine(image, nx: int, ny: int, *, coarse_size_px: int,
                                  margin_squares: float) -> CornerResult:
    """:func:`detect_corners`, first locating the board on a resampled image, then searching its crop.

    The board is located by :func:`locate_board` on the image resampled to
    ``coarse_size_px`` (short side); the corners are then found by
    :func:`detect_in_crop` at the full search's upsampling in the crop that
    holds them plus ``margin_squares`` squares. The crop holds a fraction
    of the image, so the search costs that fraction of a whole-image one.
    When the coarse search finds nothing, or the crop search fails, or the
    whole-image search would run at no more pixels than the coarse one, the
    whole image is searched (:func:`detect_corners`).

    Parameters
    ----------
    image : numpy.ndarray
        Band image (float, e.g. DN), shape ``(rows, cols)``.
    nx, ny : int
        Inner corners per board row and per board column.
    coarse_size_px : int
        Short side of the resampled image of the coarse search, pixels.
    margin_squares : float
        Margin of the crop around the located board, in squares.

    Returns
    -------
    CornerResult
        As :func:`detect_corners`.
    """
    img = np.asarray(image, dtype=float)
    k = upsample_factor(img.shape)
    if coarse_size_px >= k * min(img.shape):
        return detect_corners(img, nx, ny, upsample=k)
    seed = locate_board(img, nx, ny, coarse_size_px)
    if seed is not None:
        margin = margin_squares * corner_spacing_px(seed, nx, ny) + CROP_PAD_PX
        res = detect_in_crop(img, seed, nx, ny, upsample=k, margin_px=margin)
        if res.found:
            return res
    return detect_corners(img, nx, ny, upsample=k)
