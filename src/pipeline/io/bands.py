"""Cut lens regions out of a Bayer mosaic and split it into R, G, B planes.

No demosaicing: each output pixel is one 2x2 Bayer cell, so the planes have
half the mosaic's rows and columns.  G is the mean of the cell's two greens.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BANDS", "cut_region", "split_bands", "split_saturation", "band_plane", "band_saturation"]

BANDS = ("R", "G", "B")


def _check_range(name: str, span, size: int) -> tuple[int, int]:
    try:
        start, stop = (int(v) for v in span)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a (start, stop) pair of integers, got {span!r}") from None
    if not 0 <= start < stop <= size:
        raise ValueError(f"{name} [{start}, {stop}) is outside the mosaic's 0..{size}")
    if start % 2:
        raise ValueError(f"{name} start {start} is odd: it would change the Bayer phase")
    return start, stop


def cut_region(cfa, rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
    """The mosaic's [rows[0], rows[1]) x [cols[0], cols[1]) region (a view).

    Raises ValueError when the region is out of range or starts on an odd row
    or column (which would change the Bayer phase).
    """
    cfa = np.asarray(cfa)
    if cfa.ndim != 2:
        raise ValueError(f"cfa must be 2-D, got shape {cfa.shape}")
    r0, r1 = _check_range("rows", rows, cfa.shape[0])
    c0, c1 = _check_range("cols", cols, cfa.shape[1])
    return cfa[r0:r1, c0:c1]


def _sites(cfa, pattern: str) -> dict[str, list[np.ndarray]]:
    """The views of each colour's CFA sites (no copy), after the checks both splits share."""
    cfa = np.asarray(cfa)
    if cfa.ndim != 2:
        raise ValueError(f"cfa must be 2-D, got shape {cfa.shape}")
    pattern = str(pattern).upper()
    if len(pattern) != 4 or sorted(pattern) != ["B", "G", "G", "R"]:
        raise ValueError(f"pattern must be a 2x2 Bayer pattern like 'RGGB', got {pattern!r}")
    h, w = cfa.shape[0] // 2 * 2, cfa.shape[1] // 2 * 2
    if h == 0 or w == 0:
        raise ValueError(f"cfa of shape {cfa.shape} holds no complete 2x2 cell")
    sites: dict[str, list[np.ndarray]] = {}
    for index, letter in enumerate(pattern):
        dy, dx = divmod(index, 2)
        sites.setdefault(letter, []).append(cfa[dy:h:2, dx:w:2])
    return sites


def _window(view: np.ndarray, window) -> np.ndarray:
    return view if window is None else view[window]


def _integer_threshold(cfa: np.ndarray, threshold_dn: float):
    """The threshold for an integer mosaic, rounded up to an integer (the same test for integer values);
    None when no value of the type reaches it."""
    if not np.issubdtype(cfa.dtype, np.integer):
        return threshold_dn
    info = np.iinfo(cfa.dtype)
    limit = int(np.ceil(threshold_dn))
    if limit > info.max:
        return None
    return cfa.dtype.type(max(limit, info.min))


def band_saturation(cfa, pattern: str, band: str, threshold_dn: float, window=None, out=None) -> np.ndarray:
    """One band of :func:`split_saturation`, on ``window`` ((row slice, column slice) of the band plane) when
    given; into ``out`` (boolean, the window's shape) when given."""
    cfa = np.asarray(cfa)
    sites = [_window(v, window) for v in _sites(cfa, pattern)[band]]
    limit = _integer_threshold(cfa, threshold_dn)
    if out is None:
        out = np.empty(sites[0].shape, bool)
    if limit is None:
        out[...] = False
        return out
    np.greater_equal(sites[0], limit, out=out)
    for v in sites[1:]:
        out |= v >= limit
    return out


def split_saturation(cfa, pattern: str, threshold_dn: float) -> dict[str, np.ndarray]:
    """Boolean {"R", "G", "B"} planes: True where any CFA site of the band pixel is at or above ``threshold_dn``.

    Compares the integer mosaic's site views with the threshold rounded up to
    an integer (the same test for integer values), so no float plane is made.
    """
    return {b: band_saturation(cfa, pattern, b, threshold_dn) for b in BANDS}


def band_plane(cfa, pattern: str, band: str, window=None, out=None) -> np.ndarray:
    """One float32 plane of :func:`split_bands` (G the mean of its two sites), on ``window`` ((row slice,
    column slice) of the plane) when given; into ``out`` (float32, the window's shape) when given. The same
    operations in the same order either way, so the same numbers."""
    sites = [_window(v, window) for v in _sites(cfa, pattern)[band]]
    if out is None:
        out = np.empty(sites[0].shape, np.float32)
    np.copyto(out, sites[0], casting="unsafe")
    if len(sites) > 1:
        out += sites[1]
        out *= np.float32(0.5)
    return out


def split_bands(cfa, pattern: str) -> dict[str, np.ndarray]:
    """Split a Bayer mosaic into {"R", "G", "B"} float32 planes (rows//2, cols//2).

    ``pattern`` is the 2x2 cell row-major, e.g. "RGGB", "BGGR", "GRBG", "GBRG".
    An odd trailing row or column is dropped.
    """
    return {b: band_plane(cfa, pattern, b) for b in BANDS}
