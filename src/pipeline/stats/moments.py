"""Streaming reductions: running per-pixel sums, never a stack of frames in memory."""

from __future__ import annotations

import threading

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
        """Add one frame to the per-pixel sums.

        Parameters
        ----------
        image : numpy.ndarray
            The frame (e.g. a band image in DN), of the same shape as the frames added before.
        """
        image = np.asarray(image)
        if self.s1 is None:
            self.shift = float(np.mean(image, dtype=np.float64))
            self.s1 = np.zeros(image.shape, dtype=np.float64)
            self.s2 = np.zeros(image.shape, dtype=np.float64)
        # one float64 temporary, squared in place (the same values as (x - shift) and its square)
        d = np.subtract(image, self.shift, dtype=np.float64)
        self.s1 += d
        np.multiply(d, d, out=d)
        self.s2 += d
        self.n += 1

    def mean(self) -> np.ndarray:
        """Per-pixel mean of the frames added.

        Returns
        -------
        numpy.ndarray
            float64, the frames' shape and unit.
        """
        return self.s1 / self.n + self.shift

    def variance(self) -> np.ndarray:
        """Unbiased per-pixel temporal variance (zeros when only one frame).

        Returns
        -------
        numpy.ndarray
            float64, the frames' shape, in their unit squared (e.g. DN^2); never negative.
        """
        if self.n < 2:
            return np.zeros_like(self.s1)
        m = self.s1 / self.n
        return np.maximum((self.s2 - self.n * m * m) / (self.n - 1), 0.0)


_SCRATCH = threading.local()


def _scratch_maps(shape) -> tuple[np.ndarray, np.ndarray]:
    """Two float64 maps of ``shape`` for :meth:`RunningPearson.add`, one pair per thread, kept for the next
    call: a fresh 24 MB temporary per band image cost its page faults again (the profile of a
    full-resolution linearity job: 0.76 s for the first touch of 18 such maps, 0.04 s each). The pair
    stays allocated for the thread's life (48 MB at 1728 x 1728)."""
    maps = getattr(_SCRATCH, "maps", None)
    if maps is None or maps[0].shape != tuple(shape):
        maps = _SCRATCH.maps = (np.empty(shape), np.empty(shape))
    return maps


class RunningPearson:
    """Per-pixel Pearson correlation of pixel values y against a scalar x, streaming.

    Samples where ``valid`` is False (e.g. saturated pixels) are left out of
    that pixel's sums. Only the sums that involve y are kept per pixel (three
    float64 maps): x is one scalar per sample, so each pixel's count and sums of
    x and x^2 follow exactly from the list of x and, per sample, the pixels it
    left out (one bit per pixel, kept only for samples that left any out),
    added up in the same order as the y sums when ``r`` is asked for; when no
    sample left a pixel out they are three numbers, not maps.
    """

    def __init__(self):
        self.xs: list[float] = []
        self.left_out: list[np.ndarray | None] = []    # per sample: packed bits of the invalid pixels, or None
        self.shape = None
        self.sy = self.syy = self.sxy = None

    def add(self, x: float, y: np.ndarray, valid: np.ndarray | None = None) -> None:
        """Add one sample: the scalar ``x`` and the pixel values ``y`` it goes with.

        Parameters
        ----------
        x : float
            The sample's abscissa (e.g. exposure time, s, or a setting's relative signal).
        y : numpy.ndarray
            The pixel values (e.g. DN), of the same shape as the samples added before.
        valid : numpy.ndarray, optional
            Boolean, shape of ``y``: False leaves that pixel's value out of its sums (e.g. saturated); default None
            (all valid).
        """
        y = np.asarray(y)
        if self.sy is None:
            self.shape = y.shape
            self.sy, self.syy, self.sxy = (np.zeros(y.shape) for _ in range(3))
        t, u = _scratch_maps(y.shape)
        x = float(x)
        if valid is None or valid.all():
            packed = None
            np.copyto(t, y)                            # y in float64, cast as it is copied
        else:
            packed = np.packbits(~valid, axis=None)
            np.multiply(y, valid, out=t, dtype=np.float64)    # y where valid, else 0
        self.sy += t
        self.sxy += np.multiply(t, x, out=u)
        np.multiply(t, y, out=t, dtype=np.float64)
        self.syy += t
        self.xs.append(x)
        self.left_out.append(packed)

    def _x_sums(self):
        """Per pixel: count, sum of x and sum of x^2 over the samples it was valid in (numbers when every
        pixel was valid in every sample)."""
        if all(packed is None for packed in self.left_out):
            n = sx = sxx = 0.0
            for x in self.xs:
                n += 1.0
                sx += x
                sxx += x * x
            return n, sx, sxx
        n, sx, sxx = (np.zeros(self.shape) for _ in range(3))
        size = int(np.prod(self.shape))
        for x, packed in zip(self.xs, self.left_out):
            if packed is None:
                n += 1.0
                sx += x
                sxx += x * x
            else:   # added where the sample was valid, in the same order as the y sums
                keep = (np.unpackbits(packed, count=size) == 0).reshape(self.shape)
                np.add(n, 1.0, out=n, where=keep)
                np.add(sx, x, out=sx, where=keep)
                np.add(sxx, x * x, out=sxx, where=keep)
        return n, sx, sxx

    def r(self, dtype=np.float64) -> np.ndarray:
        """The per-pixel r (NaN where a pixel has fewer than 3 valid samples or no spread), in ``dtype``.

        Parameters
        ----------
        dtype : numpy.dtype, optional
            The result's float type; default ``numpy.float64``.

        Returns
        -------
        numpy.ndarray
            Pearson's r of y against x per pixel, dimensionless, the samples' shape.
        """
        count, sx, sxx = self._x_sums()
        n = np.maximum(count, 1)
        cxx = sxx - sx**2 / n
        t = np.square(self.sy)                         # the y terms in place, one map at a time
        t /= n
        cyy = np.subtract(self.syy, t, out=t)
        cxy = np.multiply(sx, self.sy)
        cxy /= n
        np.subtract(self.sxy, cxy, out=cxy)
        denom = np.multiply(cxx, cyy, out=cyy)
        np.maximum(denom, 0.0, out=denom)
        np.sqrt(denom, out=denom)
        r = np.full(self.shape, np.nan, dtype=dtype)
        with np.errstate(invalid="ignore", divide="ignore"):
            np.divide(cxy, denom, out=r, where=denom > 0, casting="same_kind")
        r[np.broadcast_to(count < 3, self.shape)] = np.nan
        return r


def radius_map(shape: tuple[int, int], centre_xy: tuple[float, float]) -> np.ndarray:
    """Distance (pixels) of every pixel centre from ``centre_xy`` (x = column, y = row).

    Parameters
    ----------
    shape : tuple of (int, int)
        (rows, columns) of the image.
    centre_xy : tuple of (float, float)
        The centre (column, row), pixels, pixel centres at integers.

    Returns
    -------
    numpy.ndarray
        float64, shape ``shape``: the distance, pixels.
    """
    y = np.arange(shape[0], dtype=np.float64)[:, None]
    x = np.arange(shape[1], dtype=np.float64)[None, :]
    return np.hypot(x - centre_xy[0], y - centre_xy[1])


def corner_mask(shape: tuple[int, int], min_radius_fraction: float) -> np.ndarray:
    """Unlit corner pixels: farther from the region centre than ``min_radius_fraction`` of half its side.

    A fisheye image circle fits inside the square lens region, so pixels beyond the inscribed circle
    (fraction >= 1) are never lit.

    Parameters
    ----------
    shape : tuple of (int, int)
        (rows, columns) of the region's band image.
    min_radius_fraction : float
        The radius beyond which pixels count as corners, as a fraction of half the shorter side.

    Returns
    -------
    numpy.ndarray
        Boolean, shape ``shape``: True on the corner pixels.
    """
    h, w = shape
    r = radius_map(shape, ((w - 1) / 2, (h - 1) / 2))
    return r > min_radius_fraction * min(h, w) / 2


def unlit_mask(shape: tuple[int, int], projection: str, min_radius_fraction: float) -> np.ndarray:
    """The band pixels of a lens region that are never lit.

    A fisheye's corners (:func:`corner_mask`), none for a rectilinear region (an ordinary camera is lit to its
    edges).

    Parameters
    ----------
    shape : tuple of (int, int)
        (rows, columns) of the region's band image.
    projection : str
        The lens region's projection: ``rectilinear``, or any other (a fisheye).
    min_radius_fraction : float
        For a fisheye, the corners' radius as a fraction of half the shorter side (:func:`corner_mask`).

    Returns
    -------
    numpy.ndarray
        Boolean, shape ``shape``: True on the pixels never lit.
    """
    if projection == "rectilinear":
        return np.zeros(shape, dtype=bool)
    return corner_mask(shape, min_radius_fraction)


def histogram_counts(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """``np.histogram(values, bins=edges)[0]`` for edges of (nearly) equal steps, without sorting the values.

    Bins [e_i, e_i+1), the last one closed, values outside ignored, as numpy's. numpy sorts the values for
    edges given as an array (0.12 s for 3 million at the real camera's band-image size); here each value's
    bin is guessed from the mean step and corrected against the edges themselves (one bin at most, for
    equal steps to rounding, as ``np.arange`` makes them; other edges go to numpy): about half the time.

    Parameters
    ----------
    values : numpy.ndarray
        The values, any shape (flattened).
    edges : numpy.ndarray
        Shape (bins + 1,): increasing bin edges, in the values' unit.

    Returns
    -------
    numpy.ndarray
        Shape (bins,): the count of values in each bin (integers).
    """
    edges = np.asarray(edges, dtype=float)
    n = len(edges) - 1
    v = np.asarray(values, dtype=float).ravel()
    v = v[(v >= edges[0]) & (v <= edges[-1])]
    step = (edges[-1] - edges[0]) / n
    if not np.allclose(np.diff(edges), step, rtol=1e-9, atol=0.0):
        return np.histogram(v, bins=edges)[0]     # not equal steps: numpy's search
    index = np.minimum(((v - edges[0]) / step).astype(np.intp), n - 1)
    index -= v < edges[index]
    index += (v >= edges[index + 1]) & (index < n - 1)
    return np.bincount(index, minlength=n)
