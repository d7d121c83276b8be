"""Read an experiment's raw frames once each, checked, and cut into lens band images."""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from itertools import islice

import numpy as np
import pandas as pd

from pipeline.bands import cut_region, split_bands, split_saturation
from pipeline.dataset import Dataset, check_md5
from pipeline.errors import InputError
from pipeline.rawio import RawFrame, read_raw


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
                progress: bool = False, decode_ahead_frames: int | None = None) -> Iterator[DecodedFrame]:
    """Decode every frame of ``frames`` (default: the experiment's frames.csv) once, in order.

    Each file's checksum is compared with MD5SUMS from the bytes that were
    decoded; exposure time, ISO and time stamp must be in the tags. The next
    ``decode_ahead_frames`` frames (default: the setting of :func:`decode_ahead`, else
    :data:`DECODE_AHEAD_FRAMES`) are decoded in a background thread; a bad frame stops
    the iteration when its turn comes, with the same message.
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
    try:
        for dec in _decoded_in_order(decode, rows, ahead):
            if bar is not None:
                bar.update()
            yield dec
    finally:
        if bar is not None:
            bar.close()


def _decoded_in_order(decode, rows, ahead_frames: int) -> Iterator[DecodedFrame]:
    """``decode(row)`` of each row in order, the next ``ahead_frames`` decoded in a background thread."""
    if ahead_frames < 1:
        for row in rows:
            yield decode(row)
        return
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="decode") as pool:
        ahead = deque(pool.submit(decode, row) for row in islice(rows, ahead_frames))
        try:
            while ahead:
                dec = ahead.popleft().result()
                # the next frame starts decoding while the caller reduces this one
                nxt = next(rows, None)
                if nxt is not None:
                    ahead.append(pool.submit(decode, nxt))
                yield dec
        finally:
            for future in ahead:
                future.cancel()


#: a band pixel is saturated where a CFA site reaches the white level less this (DN)
SATURATION_MARGIN_DN = 1.0


def lens_images(raw: RawFrame, region_span, lens: str, saturation_margin_dn: float = SATURATION_MARGIN_DN) -> LensImages:
    """One lens's band images of a decoded frame; ``region_span`` is its (rows, cols) in the mosaic."""
    rows_span, cols_span = region_span
    try:
        region = cut_region(raw.cfa, rows_span, cols_span)
    except ValueError as exc:
        raise InputError(raw.path, f"lens '{lens}' region does not fit the frame ({exc})") from None
    return LensImages(
        bands=split_bands(region, raw.cfa_pattern),
        saturated=split_saturation(region, raw.cfa_pattern, raw.white_level - saturation_margin_dn),
    )
