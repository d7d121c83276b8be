"""Streaming reductions: running per-pixel sums, never a stack of frames in memory."""

from __future__ import annotations

import numpy as np


class RunningMoments:
    """Per-pixel count, sum and sum of squares of frames added one at a time.

    Values are shifted by the first frame's mean before squaring so that the
    variance of 800-ADU dark frames keeps its precision in float64.
    """

    def __init__(self):
        self.n = 0
        self.shift = None
        self.s1 = None
        self.s2 = None

    def add(self, image: np.ndarray) -> None:
        x = np.asarray(image, dtype=np.float64)
        if self.s1 is None:
            self.shift = float(np.mean(x))
            self.s1 = np.zeros_like(x)
            self.s2 = np.zeros_like(x)
        d = x - self.shift
        self.s1 += d
        self.s2 += d * d
        self.n += 1

    def mean(self) -> np.ndarray:
        return self.s1 / self.n + self.shift

    def variance(self) -> np.ndarray:
        """Unbiased per-pixel temporal variance (zeros when only one frame)."""
        if self.n < 2:
            return np.zeros_like(self.s1)
        m = self.s1 / self.n
        return np.maximum((self.s2 - self.n * m * m) / (self.n - 1), 0.0)


class RunningPearson:
    """Per-pixel Pearson correlation of pixel values y against a scalar x, streaming.

    Samples where ``valid`` is False (e.g. saturated pixels) are left out of
    that pixel's sums.
    """

    def __init__(self):
        self.n = self.sx = self.sy = self.sxx = self.syy = self.sxy = None

    def add(self, x: float, y: np.ndarray, valid: np.ndarray | None = None) -> None:
        y = np.asarray(y, dtype=np.float64)
        w = np.ones_like(y) if valid is None else valid.astype(np.float64)
        if self.n is None:
            self.n, self.sx, self.sy, self.sxx, self.syy, self.sxy = (np.zeros_like(y) for _ in range(6))
        yw = y * w
        self.n += w
        self.sx += w * x
        self.sy += yw
        self.sxx += w * x * x
        self.syy += yw * y
        self.sxy += yw * x

    def r(self) -> np.ndarray:
        n = np.maximum(self.n, 1)
        cxx = self.sxx - self.sx**2 / n
        cyy = self.syy - self.sy**2 / n
        cxy = self.sxy - self.sx * self.sy / n
        denom = np.sqrt(np.maximum(cxx * cyy, 0.0))
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.where(denom > 0, cxy / denom, np.nan)
        r[self.n < 3] = np.nan
        return r


def radius_map(shape: tuple[int, int], centre_xy: tuple[float, float]) -> np.ndarray:
    """Distance (pixels) of every pixel centre from ``centre_xy`` (x = column, y = row)."""
    y, x = np.indices(shape, dtype=np.float64)
    return np.hypot(x - centre_xy[0], y - centre_xy[1])


def corner_mask(shape: tuple[int, int], min_radius_fraction: float) -> np.ndarray:
    """Unlit corner pixels: farther from the region centre than ``min_radius_fraction`` of half its side.

    A fisheye image circle fits inside the square lens region, so pixels
    beyond the inscribed circle (fraction >= 1) are never lit.
    """
    h, w = shape
    r = radius_map(shape, ((w - 1) / 2, (h - 1) / 2))
    return r > min_radius_fraction * min(h, w) / 2


def unlit_mask(shape: tuple[int, int], projection: str, min_radius_fraction: float) -> np.ndarray:
    """The band pixels of a lens region that are never lit: a fisheye's corners (:func:`corner_mask`),
    none for a rectilinear region (an ordinary camera is lit to its edges)."""
    if projection == "rectilinear":
        return np.zeros(shape, dtype=bool)
    return corner_mask(shape, min_radius_fraction)
