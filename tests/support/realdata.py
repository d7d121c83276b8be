"""Real sensor data for the tests: where it lives, and statistics taken from its files with plain numpy.

The EMVA1288 Reference Set 001 (a Basler 12-bit CCD, (c) 2011 Basler AG, Dr. Marco Grimm, CC BY-SA 3.0,
from the public repository EMVA1288/datasets) lives beside the checkout in ``../shared/realdata`` (relative to
the repository root), or in the folder the environment variable ``PIPELINE_REALDATA`` names. A test that uses
it skips with one line when it is absent.

The statistics here are the EMVA1288 standard's own, taken from the PNG files directly (never through the
pipeline): per exposure step, the mean of the two frames and the variance of their difference over two.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

#: the environment variable naming the folder that holds the real data sets
REALDATA_ENV = "PIPELINE_REALDATA"
#: the default folder: beside the checkout (repository root / .. / shared / realdata)
REALDATA_DEFAULT = Path(__file__).resolve().parents[2].parent / "shared" / "realdata"
EMVA1288_SET = "emva1288-set001"
EMVA1288_DESCRIPTOR = "EMVA1288_Data.txt"


def realdata_folder() -> Path:
    return Path(os.environ.get(REALDATA_ENV) or REALDATA_DEFAULT)


def emva1288_descriptor_or_skip() -> Path:
    """The set's descriptor, or the test skipped with one line saying where it was looked for."""
    path = realdata_folder() / EMVA1288_SET / EMVA1288_DESCRIPTOR
    if not path.is_file():
        pytest.skip(f"EMVA1288 reference set absent: no {path} (set {REALDATA_ENV} to the folder holding "
                    f"{EMVA1288_SET}/)")
    return path


def realdata_image(path: Path) -> np.ndarray:
    """One PNG of the set as float64 values (DN)."""
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64)


@dataclass
class Emva1288Statistics:
    """Per exposure step (the descriptor's pairs, in order) the EMVA1288 quantities from the PNGs."""

    exposure_s: np.ndarray          # of each step
    photons_per_pixel: np.ndarray   # of each bright step
    bright_mean_dn: np.ndarray      # mean of the two bright frames
    bright_var_dn2: np.ndarray      # variance of their difference / 2 (temporal variance of one pixel)
    dark_mean_dn: np.ndarray        # mean of the two dark frames
    dark_var_dn2: np.ndarray        # the dark temporal variance of one pixel
    dark_frame_exposure_s: np.ndarray   # every dark frame (the pairs and the stack)
    dark_frame_mean_dn: np.ndarray      # each dark frame's mean over all its pixels


def emva1288_statistics(frames) -> Emva1288Statistics:
    """The pair statistics of the steps (blocks of two frames) and every dark frame's mean.

    ``frames`` are the descriptor's images (:func:`pipeline.scaffold.read_emva1288_descriptor`, which only
    parses the text); the stack blocks (more than two frames) give dark frame means only.
    """
    blocks: dict = {}
    for f in frames:
        blocks.setdefault((f.kind, f.step), []).append(f)
    out = {k: [] for k in ("t", "p", "bm", "bv", "dm", "dv")}
    dark_t, dark_m = [], []
    for (kind, _), items in blocks.items():
        if kind == "dark":
            for f in items:
                dark_t.append(f.exposure_s)
                dark_m.append(realdata_image(f.image).mean())
    for (kind, step), items in sorted(blocks.items(), key=lambda kv: kv[0][1]):
        if kind != "signal" or len(items) != 2:
            continue
        dark = blocks[("dark", step)]
        if len(dark) != 2 or dark[0].exposure_s != items[0].exposure_s:
            raise ValueError(f"bright step {step} has no dark pair at its exposure")
        a, b = (realdata_image(f.image) for f in items)
        da, db = (realdata_image(f.image) for f in dark)
        out["t"].append(items[0].exposure_s)
        out["p"].append(items[0].photons_per_pixel)
        out["bm"].append(0.5 * (a.mean() + b.mean()))
        out["bv"].append(0.5 * np.var(a - b))
        out["dm"].append(0.5 * (da.mean() + db.mean()))
        out["dv"].append(0.5 * np.var(da - db))
    arr = {k: np.array(v) for k, v in out.items()}
    return Emva1288Statistics(arr["t"], arr["p"], arr["bm"], arr["bv"], arr["dm"], arr["dv"],
                              np.array(dark_t), np.array(dark_m))
