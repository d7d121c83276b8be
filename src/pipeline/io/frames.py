"""Read an experiment's raw frames once each, checked, and cut into lens band images."""

from __future__ import annotations

from collections import deque
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from itertools import islice

import numpy as np
import pandas as pd

from pipeline.io.bands import cut_region, split_bands, split_saturation
from pipeline.io.dataset import Dataset, check_md5
from pipeline.errors import InputError
from pipeline.io.rawio import RawFrame, read_raw


@dataclass
class LensImages:
    """One frame's band images (R, G, B) of one lens, plus a saturation map."""

    bands: dict[str, np.ndarray]
    saturated: dict[str, np.ndarray]   # True where any CFA site of the band pixel reached the white level


@dataclass
class DecodedFrame:
    row: pd.Series
    raw: RawFrame
    lenses: dict[str, LensImages]


#: raw pixels averaged in one band pixel (the G band is the mean of two sites)
SITES_PER_BAND_PIXEL = {"R": 1, "G": 2, "B": 1}


#: frames decoded ahead in one background thread while the caller reduces the current one, unless the
#: configuration says otherwise (``performance.decode_ahead_frames``, set for a job by
#: :func:`decode_ahead`). Reading the bytes, hashing them, LibRaw's unpacking and the band split release
#: the GIL for most of their time, so a one-thread job keeps a second core busy (when there is one) and
#: its wall time approaches the larger of decoding and reducing instead of their sum; each frame ahead
#: costs one decoded frame of memory (about 140 MB at 6912 x 3456).
DECODE_AHEAD_FRAMES = 1

_decode_ahead_frames: ContextVar[int] = ContextVar("decode_ahead_frames", default=DECODE_AHEAD_FRAMES)


@contextmanager
def decode_ahead(frames: int):
    """Within the block, :func:`iter_frames` decodes ``frames`` frames ahead (0: none, in the caller's thread).

    The stage runner sets it for each job from ``performance.decode_ahead_frames``, so that every
    stage reads the setting without each of its functions passing it on.

    Parameters
    ----------
    frames : int
        Frames decoded ahead in a background thread, >= 0.

    Yields
    ------
    None
        Control to the block, with the setting in force (restored on leaving it).

    Raises
    ------
    ValueError
        If ``frames`` is not an integer >= 0.
    """
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 0:
        raise ValueError(f"decode_ahead_frames must be an integer >= 0, not {frames!r}")
    token = _decode_ahead_frames.set(frames)
    try:
        yield
    finally:
        _decode_ahead_frames.reset(token)


def iter_frames(dataset: Dataset, experiment: str, frames: pd.DataFrame | None = None,
                lenses: list[str] | None = None, saturation_margin_dn: float = 1.0,
                progress: bool = False, decode_ahead_frames: int | None = None) -> "FrameStream":
    """Decode every frame of ``frames`` (default: the experiment's frames.csv) once, in order.

    Each file's checksum is compared with MD5SUMS from the bytes that were
    decoded; exposure time, ISO and time stamp must be in the tags. The next
    ``decode_ahead_frames`` frames (default: the setting of :func:`decode_ahead`, else
    :data:`DECODE_AHEAD_FRAMES`) are decoded in a background thread, the first of them from
    this call on (a stage may prepare its masks while the first frame decodes, and iterate
    later); a bad frame stops the iteration when its turn comes, with the same message.
    The stream is an iterator; :meth:`FrameStream.close` (or leaving it as a context manager)
    stops the decoding of frames not yet taken.

    Parameters
    ----------
    dataset : pipeline.io.dataset.Dataset
        The opened dataset (lens regions, MD5SUMS, frame tables).
    experiment : str
        The experiment's folder name, e.g. ``"dark"``.
    frames : pandas.DataFrame or None, optional
        Rows of the experiment's frames.csv to decode (a ``path`` column at least), in that order; ``None``
        (default) all of them.
    lenses : list[str] or None, optional
        The lenses to cut out; ``None`` (default) every lens of the dataset.
    saturation_margin_dn : float, default 1.0
        A band pixel is marked saturated where a CFA site reaches the white level less this, in DN.
    progress : bool, default False
        Show a progress bar on the terminal.
    decode_ahead_frames : int or None, optional
        Frames decoded ahead, overriding the setting of :func:`decode_ahead`.

    Returns
    -------
    FrameStream
        Iterator of :class:`DecodedFrame`: each frame's row, its :class:`~pipeline.io.rawio.RawFrame` and its
        :class:`LensImages` by lens.

    Raises
    ------
    pipeline.errors.InputError
        When the iteration reaches a frame that cannot be read, whose checksum differs from MD5SUMS, that lacks a
        required tag, or whose lens region does not fit it.
    """
    frames = dataset.frames(experiment) if frames is None else frames
    lenses = list(dataset.lenses) if lenses is None else lenses
    rows = iter([row for _, row in frames.iterrows()])
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(frames), unit="frame", desc=experiment, leave=False, disable=None)

    def decode(row) -> DecodedFrame:
        raw = read_raw(row["path"])
        check_md5(dataset, row["path"], raw.md5)
        out = {lens: lens_images(raw, dataset.lenses[lens], lens, saturation_margin_dn) for lens in lenses}
        return DecodedFrame(row=row, raw=raw, lenses=out)

    ahead = _decode_ahead_frames.get() if decode_ahead_frames is None else decode_ahead_frames
    return FrameStream(decode, rows, ahead, bar)


class FrameStream:
    """``decode(row)`` of each row in order, the next ``ahead_frames`` decoded in a background thread
    (submitted when the stream is made); what :func:`iter_frames` returns."""

    def __init__(self, decode, rows, ahead_frames: int, bar=None):
        self._decode, self._rows, self._bar = decode, rows, bar
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="decode") if ahead_frames >= 1 else None
        self._ahead = deque(self._pool.submit(decode, row) for row in islice(rows, ahead_frames)) \
            if self._pool is not None else deque()

    def __iter__(self) -> "FrameStream":
        return self

    def __next__(self) -> DecodedFrame:
        try:
            if self._pool is None:
                dec = self._decode(next(self._rows))
            else:
                if not self._ahead:
                    raise StopIteration
                dec = self._ahead.popleft().result()
                # the next frame starts decoding while the caller reduces this one
                nxt = next(self._rows, None)
                if nxt is not None:
                    self._ahead.append(self._pool.submit(self._decode, nxt))
        except BaseException:
            self.close()
            raise
        if self._bar is not None:
            self._bar.update()
        return dec

    def close(self) -> None:
        """Cancel the frames not yet decoding and wait for the one that is."""
        for future in self._ahead:
            future.cancel()
        self._ahead.clear()
        self._rows = iter(())
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> "FrameStream":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        if getattr(self, "_pool", None) is not None:
            self.close()


#: a band pixel is saturated where a CFA site reaches the white level less this (DN)
SATURATION_MARGIN_DN = 1.0


def lens_images(raw: RawFrame, region_span, lens: str, saturation_margin_dn: float = SATURATION_MARGIN_DN) -> LensImages:
    """One lens's band images of a decoded frame.

    Parameters
    ----------
    raw : pipeline.io.rawio.RawFrame
        The decoded frame.
    region_span : tuple[tuple[int, int], tuple[int, int]]
        The lens's ``(rows, cols)`` spans in the mosaic, each ``(start, stop)`` in mosaic pixels.
    lens : str
        The lens's name, for the error message.
    saturation_margin_dn : float, default :data:`SATURATION_MARGIN_DN`
        A band pixel is saturated where a CFA site reaches the frame's white level less this, in DN.

    Returns
    -------
    LensImages
        The lens's R, G, B float32 planes (raw DN, black level not subtracted) and their saturation maps.

    Raises
    ------
    pipeline.errors.InputError
        If the lens region does not fit the frame.
    """
    rows_span, cols_span = region_span
    try:
        region = cut_region(raw.cfa, rows_span, cols_span)
    except ValueError as exc:
        raise InputError(raw.path, f"lens '{lens}' region does not fit the frame ({exc})") from None
    return LensImages(
        bands=split_bands(region, raw.cfa_pattern),
        saturated=split_saturation(region, raw.cfa_pattern, raw.white_level - saturation_margin_dn),
    )
