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

    Parameters
    ----------
    cfa : array_like
        The raw Bayer mosaic, 2-D (rows, columns), in DN.
    rows : tuple[int, int]
        First (even) and one-past-last row of the region, in mosaic pixels.
    cols : tuple[int, int]
        First (even) and one-past-last column of the region, in mosaic pixels.

    Returns
    -------
    numpy.ndarray
        A view of the region of ``cfa``, shape ``(rows[1] - rows[0], cols[1] - cols[0])``.

    Raises
    ------
    ValueError
        If ``cfa`` is not 2-D, or a span is not a pair of integers, is outside the mosaic or starts on an odd
    row or column (which would change the Bayer phase).
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
    given; into ``out`` (boolean, the window's shape) when given.

    Parameters
    ----------
    cfa : array_like
        The raw Bayer mosaic (or a lens's region of it), 2-D, in DN.
    pattern : str
        The 2x2 Bayer cell read row-major, e.g. ``"RGGB"``.
    band : str
        ``"R"``, ``"G"`` or ``"B"``.
    threshold_dn : float
        The raw value (DN) at or above which a CFA site counts as saturated.
    window : tuple[slice, slice] or None, optional
        Rows and columns of the band plane to test; ``None`` (default) the whole plane.
    out : numpy.ndarray or None, optional
        Boolean array of the window's shape to write into.

    Returns
    -------
    numpy.ndarray
        Boolean, shape of the band plane (``(rows // 2, cols // 2)``) or of ``window``: True where any of the
        band pixel's sites is at or above the threshold (all False if the mosaic's integer type cannot reach it).
    """
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

    Parameters
    ----------
    cfa : array_like
        The raw Bayer mosaic, 2-D, in DN.
    pattern : str
        The 2x2 Bayer cell read row-major, e.g. ``"RGGB"``.
    threshold_dn : float
        The raw value (DN) at or above which a CFA site counts as saturated (the white level less a margin).

    Returns
    -------
    dict[str, numpy.ndarray]
        Band -> boolean plane of shape ``(rows // 2, cols // 2)``.
    """
    return {b: band_saturation(cfa, pattern, b, threshold_dn) for b in BANDS}


def band_plane(cfa, pattern: str, band: str, window=None, out=None) -> np.ndarray:
    """One float32 plane of :func:`split_bands` (G the mean of its two sites), on ``window`` ((row slice,
    column slice) of the plane) when given; into ``out`` (float32, the window's shape) when given. The same
    operations in the same order either way, so the same numbers.

    Parameters
    ----------
    cfa : array_like
        The raw Bayer mosaic (or a lens's region of it), 2-D, in DN.
    pattern : str
        The 2x2 Bayer cell read row-major, e.g. ``"RGGB"``.
    band : str
        ``"R"``, ``"G"`` or ``"B"``.
    window : tuple[slice, slice] or None, optional
        Rows and columns of the band plane to make; ``None`` (default) the whole plane.
    out : numpy.ndarray or None, optional
        float32 array of the window's shape to write into.

    Returns
    -------
    numpy.ndarray
        float32, shape ``(rows // 2, cols // 2)`` or that of ``window``: the band's raw values in DN (black
        level not subtracted).
    """
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

    An odd trailing row or column is dropped.

    Parameters
    ----------
    cfa : array_like
        The raw Bayer mosaic, 2-D, in DN.
    pattern : str
        The 2x2 cell read row-major, e.g. "RGGB", "BGGR", "GRBG", "GBRG".

    Returns
    -------
    dict[str, numpy.ndarray]
        Band -> float32 plane of raw values in DN, shape ``(rows // 2, cols // 2)``.

    Raises
    ------
    ValueError
        If ``cfa`` is not 2-D or holds no whole 2x2 cell, or ``pattern`` is not a Bayer pattern.
    """
    return {b: band_plane(cfa, pattern, b) for b in BANDS}
