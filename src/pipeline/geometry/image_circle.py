"""Image circle of a fisheye lens and the half field of view it implies.

Method (after Section 3.2 of Larouche et al. 2024, which used Canny edges and
a circular Hough transform from scikit-image): block-average the image down
to about ``coarse_size`` pixels, keep the lit pixels (above ``lit_fraction``
of the way from the dark to the bright level, 1st and 99th percentiles),
Canny edges of that lit mask, circular Hough transform for a first centre and
radius; then, at full resolution, the edge is located along many radial
profiles as the outermost lit sample, refined to the sub-pixel crossing of
the level half-way between the lit pixels just inside it and the dark
outside, and a least-squares (algebraic, then geometric) circle fit of those
points gives the centre and radius. The half FOV is the model's theta at that
radius, averaged over azimuths.

Why the lit mask and the local level: the image is often the maximum over
chessboard frames, where the union of the white squares (reflectance 0.9) is
a far stronger edge than the rim of the image circle, seen there on the grey
wall (0.35) dimmed by the roll-off. Canny edges of the image itself gave the
Hough transform that union (tiny-scale seeds: radius up to 9.7 px short of
29 px), and a half level taken from the median 2 to 3 px inside the coarse
circle sat above the dim rim. Over the tiny scale's geometry maxima (30 seeds,
all lab effects) the dimmest rim pixel is 0.165 of the 1st-to-99th percentile
range above the dark level, the brightest pixel outside 0.014 (hot pixels,
stray light): the default ``lit_fraction`` 0.05 is about their geometric mean,
a factor 3 from each.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates
from scipy.optimize import least_squares

from pipeline.stats.moments import radius_map

from .scaramuzza import FisheyeModel

#: Short side (pixels) of the image the coarse Hough search runs on.
COARSE_SIZE_PX = 128
#: Number of radial profiles used to locate the edge at full resolution.
N_PROFILES = 360
#: A pixel is lit above this fraction of the way from the dark (1st percentile) to the bright
#: (99th percentile) level (module docstring; the geometry stage passes ``geometry.image_circle_lit_fraction``).
LIT_FRACTION = 0.05
#: The local inside level of a profile: median of its samples this far (pixels) inside its outermost lit sample.
INSIDE_BAND_PX = (1.0, 3.0)


@dataclass
class ImageCircle:
    """Circle centre (u, v) and radius in pixels (pixel centres at integers)."""

    xc: float
    yc: float
    radius: float
    rms_px: float        # RMS distance of the edge points from the fitted circle
    n_points: int


def _block_mean(img, k):
    h, w = (img.shape[0] // k) * k, (img.shape[1] // k) * k
    return img[:h, :w].reshape(h // k, k, w // k, k).mean(axis=(1, 3))


def _coarse_circle(img, lit_fraction: float = LIT_FRACTION):
    from skimage.feature import canny
    from skimage.transform import hough_circle

    k = max(1, int(min(img.shape) // COARSE_SIZE_PX))
    small = _block_mean(img, k)
    lo, hi = np.percentile(small, [1, 99])
    lit = (small - lo) > lit_fraction * max(hi - lo, 1e-12)
    edges = canny(lit.astype(float), sigma=1.0)
    if edges.sum() < 10:
        raise ValueError("no edges found: is the image bright inside the circle?")
    rmin = int(0.2 * min(small.shape))
    rmax = int(0.75 * max(small.shape))
    radii = np.arange(rmin, rmax + 1)
    acc = hough_circle(edges, radii)
    # The strongest circle is the largest vote over all radii and centres
    # (one argmax; a per-radius peak search would only rank the same maximum
    # among lower local peaks).
    ir, cy, cx = np.unravel_index(int(np.argmax(acc)), acc.shape)
    # Coarse pixel centres: fine coordinate = k * coarse + (k - 1) / 2.
    return k * cx + (k - 1) / 2.0, k * cy + (k - 1) / 2.0, k * float(radii[ir]), k


def _fit_circle(x, y):
    """Algebraic (Kasa) fit then geometric least squares; returns xc, yc, r, rms."""
    A = np.stack([x, y, np.ones_like(x)], axis=1)
    b = x**2 + y**2
    (p, q, s), *_ = np.linalg.lstsq(A, b, rcond=None)
    xc, yc = p / 2, q / 2
    r = np.sqrt(s + xc**2 + yc**2)

    def res(par):
        return np.hypot(x - par[0], y - par[1]) - par[2]

    sol = least_squares(res, [xc, yc, r], loss="soft_l1", f_scale=1.0)
    rms = float(np.sqrt(np.mean(sol.fun**2)))
    return float(sol.x[0]), float(sol.x[1]), float(sol.x[2]), rms


def find_image_circle(image, *, n_profiles: int = N_PROFILES, window_frac: float = 0.08,
                      lit_fraction: float = LIT_FRACTION) -> ImageCircle:
    """Centre and radius (pixels) of the bright image circle in a band image.

    Parameters
    ----------
    image : numpy.ndarray
        Band image, DN, shape ``(rows, cols)``: one frame or the maximum over frames.
    n_profiles : int, default N_PROFILES
        Number of radial profiles, evenly spread in azimuth.
    window_frac : float, default 0.08
        Half-length of each radial profile as a fraction of the coarse radius.
    lit_fraction : float, default LIT_FRACTION
        The lit level (module docstring).

    Returns
    -------
    ImageCircle
        Centre (u, v) and radius, pixels, the RMS distance of the edge points from the circle and their number.

    Raises
    ------
    ValueError
        When fewer than 10 profiles give an edge point.
    """
    img = np.asarray(image, dtype=float)
    cx, cy, r0, k = _coarse_circle(img, lit_fraction)
    lo, hi = np.percentile(img, [1, 99])
    lit_step = lit_fraction * max(hi - lo, 1e-12)
    half = max(3.0 * k, window_frac * r0) + INSIDE_BAND_PX[1]
    step = 0.25
    s = np.arange(r0 - half, r0 + half + step / 2, step)  # 0.25 px steps
    az = np.linspace(0, 2 * np.pi, n_profiles, endpoint=False)
    xs = cx + np.cos(az)[:, None] * s[None, :]
    ys = cy + np.sin(az)[:, None] * s[None, :]
    prof = map_coordinates(img, [ys, xs], order=1, mode="nearest")
    outside = np.median(prof[:, -len(s) // 8:], axis=1)
    lit = prof - outside[:, None] > lit_step
    inner = int(round(INSIDE_BAND_PX[0] / step)), int(round(INSIDE_BAND_PX[1] / step))
    pts_x, pts_y = [], []
    for i in range(n_profiles):
        idx = np.nonzero(lit[i])[0]
        if idx.size == 0 or idx[-1] < inner[1] or idx[-1] >= len(s) - len(s) // 8:
            continue  # no lit sample, or the edge too near an end of the profile to tell inside from outside
        last = idx[-1]
        inside = float(np.median(prof[i, last - inner[1]:last - inner[0] + 1]))
        level = 0.5 * (inside + outside[i])
        above = prof[i, last - inner[1]:] >= level
        cross = np.nonzero(above[:-1] & ~above[1:])[0]
        if inside - outside[i] <= lit_step or cross.size == 0:
            continue
        j = last - inner[1] + cross[-1]
        f0, f1 = prof[i, j] - level, prof[i, j + 1] - level
        rr = s[j] + (s[j + 1] - s[j]) * f0 / (f0 - f1)
        pts_x.append(cx + np.cos(az[i]) * rr)
        pts_y.append(cy + np.sin(az[i]) * rr)
    if len(pts_x) < 10:
        raise ValueError("too few edge points to fit the image circle")
    xc, yc, r, rms = _fit_circle(np.array(pts_x), np.array(pts_y))
    return ImageCircle(xc, yc, r, rms, len(pts_x))


def outside_lit_fraction(image, circle: ImageCircle, dark_level_dn: float, *, rim_margin: float = 0.05,
                         min_snr: float = 5.0) -> float:
    """How lit the region outside ``circle`` is, as a fraction of the inside, above the dark level.

    Median of the band pixels farther than (1 + ``rim_margin``) radius from the centre,
    less ``dark_level_dn``, over the median of those within (1 - ``rim_margin``) radius,
    less the same. A fisheye's corners are never lit (docs/dataset-format.md): about 0. A frame
    lit everywhere (an ordinary camera, or a circle fitted to noise) gives about 1;
    NaN when the circle leaves no pixel outside it, or when the inside is lit by less
    than ``min_snr`` times the pixel noise outside (robust: 1.4826 MAD), i.e. not at all.

    Parameters
    ----------
    image : numpy.ndarray
        Band image, DN, shape ``(rows, cols)``.
    circle : ImageCircle
        The image circle.
    dark_level_dn : float
        Dark level subtracted from both medians, DN.
    rim_margin : float, default 0.05
        Fraction of the radius left out on either side of the circle.
    min_snr : float, default 5.0
        Least ratio of the inside's lit level to the outside's pixel noise.

    Returns
    -------
    float
        The fraction (dimensionless), or NaN.
    """
    img = np.asarray(image, dtype=float)
    r = radius_map(img.shape, (circle.xc, circle.yc))
    outside = img[r > (1 + rim_margin) * circle.radius]
    inside = img[r < (1 - rim_margin) * circle.radius]
    if outside.size == 0 or inside.size == 0:
        return float("nan")
    lit_inside = float(np.median(inside)) - dark_level_dn
    noise = 1.4826 * float(np.median(np.abs(outside - np.median(outside))))
    if lit_inside <= min_snr * noise or lit_inside <= 0:
        return float("nan")
    return (float(np.median(outside)) - dark_level_dn) / lit_inside


def half_fov_from_circle(model: FisheyeModel, circle: ImageCircle, n_azimuths: int = 36) -> float:
    """Half field of view (degrees): model theta on the circle, averaged over azimuths.

    Parameters
    ----------
    model : FisheyeModel
        The lens's geometric model.
    circle : ImageCircle
        The image circle, pixels.
    n_azimuths : int, default 36
        Points on the circle averaged over.

    Returns
    -------
    float
        Half field of view, degree.
    """
    az = np.linspace(0, 2 * np.pi, n_azimuths, endpoint=False)
    theta, _ = model.theta_phi(circle.xc + circle.radius * np.cos(az),
                               circle.yc + circle.radius * np.sin(az))
    return float(np.mean(theta))
