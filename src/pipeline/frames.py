"""Read an experiment's raw frames once each, checked, and cut into lens band images."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pandas as pd

from pipeline.bands import cut_region, split_bands
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


def iter_frames(dataset: Dataset, experiment: str, frames: pd.DataFrame | None = None,
                lenses: list[str] | None = None, saturation_margin_dn: float = 1.0,
                progress: bool = False) -> Iterator[DecodedFrame]:
    """Decode every frame of ``frames`` (default: the experiment's frames.csv) once.

    Each file's checksum is compared with MD5SUMS from the bytes that were
    decoded; exposure time, ISO and time stamp must be in the tags.
    """
    frames = dataset.frames(experiment) if frames is None else frames
    lenses = list(dataset.lenses) if lenses is None else lenses
    rows = frames.iterrows()
    if progress:
        from tqdm import tqdm

        rows = tqdm(rows, total=len(frames), unit="frame", desc=experiment, leave=False, disable=None)
    for _, row in rows:
        raw = read_raw(row["path"])
        check_md5(dataset, row["path"], raw.md5)
        out = {lens: lens_images(raw, dataset.lenses[lens], lens, saturation_margin_dn) for lens in lenses}
        yield DecodedFrame(row=row, raw=raw, lenses=out)


def lens_images(raw: RawFrame, region_span, lens: str, saturation_margin_dn: float = 1.0) -> LensImages:
    """One lens's band images of a decoded frame; ``region_span`` is its (rows, cols) in the mosaic."""
    rows_span, cols_span = region_span
    try:
        region = cut_region(raw.cfa, rows_span, cols_span)
    except ValueError as exc:
        raise InputError(raw.path, f"lens '{lens}' region does not fit the frame ({exc})") from None
    return LensImages(bands=split_bands(region, raw.cfa_pattern),
                      saturated=saturated_sites(region, raw.cfa_pattern, raw.white_level - saturation_margin_dn))


def saturated_sites(cfa, pattern: str, threshold_dn: float) -> dict[str, np.ndarray]:
    """{"R", "G", "B"}: True where any CFA site of the band pixel reads ``threshold_dn`` or more.

    Compared site by site on the mosaic's strided views (the band split's
    layout, :func:`pipeline.bands.split_bands`): one boolean plane per band,
    the two greens ORed, without a full-mosaic mask or a float copy.
    """
    cfa = np.asarray(cfa)
    h, w = cfa.shape[0] // 2 * 2, cfa.shape[1] // 2 * 2
    out: dict[str, np.ndarray] = {}
    for index, letter in enumerate(str(pattern).upper()):
        dy, dx = divmod(index, 2)
        site = cfa[dy:h:2, dx:w:2] >= threshold_dn
        if letter in out:
            out[letter] |= site
        else:
            out[letter] = site
    return out
