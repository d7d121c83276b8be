"""The dark model against the unlit corners of a lit frame (Larouche et al. 2024, Sections 2.8 and 3.7).

A fisheye's image circle fits inside its square lens region, so the region's corners are never lit
(:func:`pipeline.stats.moments.unlit_mask`, beyond ``bias.corner_min_radius_fraction`` of the half side); a
rectilinear region has none, and the sensor's optically black pixels stand in for them when the DNG
declares them. The mean of a lit frame there measures that frame's black level, which the dark model
predicts at the frame's ISO, exposure time and logged temperature:

    corner_dn = b0 + b1 (g - 1) + D g t  [+ (dB/dT + dD/dT g t) (T - T_ref)]  + mean of the fixed pattern

(:mod:`pipeline.radiometry.dark`; the fixed pattern is the dark artefact's ``fpn_map_dn`` averaged over the
same corner pixels, or its ``optical_black_offset_dn``). With ``hot_pixels`` in the dark model, its level is that
of the pixels that are not hot (the dark stage fits those, and the hot ones apart), so the corners' mean leaves
out the dark stage's hot pixels too (:func:`corner_sites`): a hot pixel in a corner adds its own rate times the
exposure, which no term of the model above holds (0.15 DN/s on the corners' mean of the default small dataset,
6.5 sigma at 33 ms in its dark-corner closure before they were left out). ``apply`` leaves them out of its
corners alike. The noise of the measured mean is the dark stage's
read noise at the frame's ISO over the square root of the raw sites averaged (a G band pixel averages two):
1.6 DN over sqrt(868) sites is 0.054 DN. The linearity stage corrects each frame's black level with it
(``bias_drift``); every lit stage records it per frame (its artefact's ``obs_corner`` table), and the
closure compares measurement and prediction over all experiments (:mod:`pipeline.diagnostics.cross_closure`,
``closure/dark_corners``).
"""

from __future__ import annotations

from collections.abc import Callable
from datetime import datetime, timezone

import numpy as np
import xarray as xr

from pipeline.io.bands import BANDS
from pipeline.io.frames import SITES_PER_BAND_PIXEL, LensImages
from pipeline.stats.moments import unlit_mask
from pipeline.radiometry.dark import band_value, dark_level_dn, temperature_shift_dn
from pipeline.io.rawio import RawFrame

__all__ = ["CORNER_COLUMNS", "FrameCorners", "corner_mean_dn", "corner_noise_dn", "corner_pattern_dn", "corner_pixels",
           "corner_sites", "frame_corner_records", "frame_time_s", "hot_pixels_left_out", "predicted_corner_dn"]

#: columns of a per-frame corner record (and of the stages' ``obs_corner`` tables, with the stage's own keys)
CORNER_COLUMNS = {"lens": ("lens region", None), "band": ("band", None),
                  "iso": ("ISO of the frame", "1"), "exposure_s": ("exposure time of the frame", "s"),
                  "temperature_c": ("logged temperature of the frame (NaN when not logged)", "degree_Celsius"),
                  "time_s": ("frame time stamp, seconds since 1970-01-01 on the camera clock read as UTC "
                             "(NaN when the frame has none)", "s"),
                  "corner_dn": ("mean raw DN of the frame's unlit corner pixels (or optically black pixels)", "DN"),
                  "n_corner_sites": ("raw sites averaged in corner_dn", "1"),
                  "dark_corner_dn": ("the dark model's prediction of corner_dn at the frame's ISO, exposure and "
                                     "temperature", "DN"),
                  "sigma_corner_dn": ("noise of corner_dn: read noise at the frame's ISO over sqrt(n_corner_sites)",
                                      "DN")}


def corner_pixels(shape: tuple[int, int], projection: str, min_radius_fraction: float) -> np.ndarray:
    """The band pixels of a lens region that are never lit (:func:`pipeline.stats.moments.unlit_mask`).

    Parameters
    ----------
    shape : tuple of int
        (rows, columns) of the lens region's band image (band pixels).
    projection : str
        The lens region's declared projection; ``"rectilinear"`` has no unlit pixels.
    min_radius_fraction : float
        Pixels beyond this fraction of the half side from the centre are corners
        (``bias.corner_min_radius_fraction``).

    Returns
    -------
    numpy.ndarray of bool
        True at the unlit band pixels, ``shape``.
    """
    return unlit_mask(shape, projection, min_radius_fraction)


def hot_pixels_left_out(dark: xr.Dataset) -> bool:
    """Whether the dark model is the level of the pixels that are not hot (``hot_pixels`` in its model: the
    dark stage fits those and flags the others in ``hot_pixel_mask``).

    Parameters
    ----------
    dark : xarray.Dataset
        The dark artefact of the lens.

    Returns
    -------
    bool
        True when the artefact's model has ``hot_pixels`` and it holds ``hot_pixel_mask``.
    """
    effects = str(dark.attrs.get("model_effects", "")).replace(",", " ").split()
    return "hot_pixels" in effects and "hot_pixel_mask" in dark


def corner_sites(dark: xr.Dataset, corners: np.ndarray) -> dict[str, np.ndarray]:
    """Per band, the corner pixels whose mean the dark model predicts: ``corners`` less the dark stage's hot
    pixels when its model leaves them out (:func:`hot_pixels_left_out`), else ``corners`` (module docstring).

    Parameters
    ----------
    dark : xarray.Dataset
        The dark artefact of the lens.
    corners : numpy.ndarray of bool
        The lens's unlit band pixels (:func:`corner_pixels`).

    Returns
    -------
    dict[str, numpy.ndarray]
        Band -> boolean mask of the corner pixels to average (``corners`` itself for a band whose corners
        would all be hot).
    """
    if not corners.any() or not hot_pixels_left_out(dark):
        return {band: corners for band in BANDS}
    out = {}
    for band in BANDS:
        keep = corners & (dark["hot_pixel_mask"].sel(band=band).values == 0)
        out[band] = keep if keep.any() else corners
    return out


def corner_mean_dn(band_image: np.ndarray, corners: np.ndarray, band: str, raw: RawFrame) -> tuple[float, int]:
    """A frame's black-level reference in one band: (mean DN, raw sites averaged).

    Its unlit corners (fisheye), else the sensor's optically black pixels when the DNG declares them,
    else none (NaN, 0).

    Parameters
    ----------
    band_image : numpy.ndarray
        The frame's band image of the lens (raw DN).
    corners : numpy.ndarray of bool
        The band's corner pixels (:func:`corner_sites`); none for a rectilinear region.
    band : str
        Band label (a G band pixel averages two raw sites).
    raw : pipeline.io.rawio.RawFrame
        The decoded frame (its optically black pixels' mean and count).

    Returns
    -------
    mean_dn : float
        Mean raw value of the reference pixels (DN); NaN without any.
    n_sites : int
        Raw sites averaged; 0 without any.
    """
    if corners.any():
        return float(band_image[corners].mean()), SITES_PER_BAND_PIXEL[band] * int(corners.sum())
    if raw.optical_black_dn is not None:
        return raw.optical_black_dn, raw.optical_black_count
    return np.nan, 0


def corner_pattern_dn(dark: xr.Dataset, band: str, corners: np.ndarray, min_radius_fraction: float | None = None) -> float:
    """The dark model's fixed pattern where :func:`corner_mean_dn` measures: its offset map averaged over the
    corner pixels, or the optically black pixels' offset in the dark frames, NaN without either.

    With the ``min_radius_fraction`` that made ``corners``, the dark stage's own average over the same pixels
    (``fpn_corner_mean_dn``, when it was made with that fraction and over the same pixels, :func:`corner_sites`)
    is read instead of the whole offset map
    (decompressing the map of one band at the full resolution costs about 0.1 s).

    Parameters
    ----------
    dark : xarray.Dataset
        The dark artefact of the lens.
    band : str
        Band label.
    corners : numpy.ndarray of bool
        The band's corner pixels.
    min_radius_fraction : float, optional
        The fraction that made ``corners``; None always averages the offset map.

    Returns
    -------
    float
        Mean fixed-pattern offset over the reference pixels (DN); NaN without either source.
    """
    stored = dark.get("fpn_corner_mean_dn")
    if (corners.any() and min_radius_fraction is not None and stored is not None
            and stored.attrs.get("corner_min_radius_fraction") == float(min_radius_fraction)
            and bool(stored.attrs.get("hot_pixels_excluded", 0)) == hot_pixels_left_out(dark)
            and np.isfinite(float(stored.sel(band=band)))):
        return float(stored.sel(band=band))
    if corners.any():
        return float(dark["fpn_map_dn"].sel(band=band).values[corners].mean())
    if "optical_black_offset_dn" in dark:
        return float(dark["optical_black_offset_dn"].sel(band=band))
    return np.nan


def predicted_corner_dn(dark: xr.Dataset, band: str, iso: float, exposure_s: float, corners: np.ndarray,
                        temperature_c: float | None = None, pattern_dn: float | None = None) -> float:
    """The dark model's prediction of :func:`corner_mean_dn` (module docstring), DN.

    The temperature term is added when the dark model has one and ``temperature_c`` is logged (finite).

    Parameters
    ----------
    dark : xarray.Dataset
        The dark artefact of the lens.
    band : str
        Band label.
    iso : float
        ISO setting of the frame.
    exposure_s : float
        Exposure time of the frame (s).
    corners : numpy.ndarray of bool
        The band's corner pixels.
    temperature_c : float, optional
        Logged sensor temperature (degree Celsius).
    pattern_dn : float, optional
        :func:`corner_pattern_dn` when the caller has it already (DN).

    Returns
    -------
    float
        Predicted mean of the reference pixels (DN).
    """
    pattern = corner_pattern_dn(dark, band, corners) if pattern_dn is None else pattern_dn
    value = dark_level_dn(dark, band, iso, exposure_s) + pattern
    if temperature_c is not None and np.isfinite(temperature_c):
        value += float(temperature_shift_dn(dark, iso, exposure_s, temperature_c))
    return value


def corner_noise_dn(dark: xr.Dataset, band: str, iso: float, n_sites: int) -> float:
    """Noise of a corner mean of ``n_sites`` raw sites: the dark stage's read noise of the band at the nearest
    ISO over sqrt(n_sites) (NaN without sites).

    Parameters
    ----------
    dark : xarray.Dataset
        The dark artefact of the lens (``read_noise_dn`` over its ``iso`` axis).
    band : str
        Band label.
    iso : float
        ISO setting of the frame.
    n_sites : int
        Raw sites averaged in the mean.

    Returns
    -------
    float
        Standard deviation of the mean (DN).
    """
    if not n_sites > 0:
        return np.nan
    by_iso = band_value(dark, "read_noise_dn", band)     # over the dark artefact's ISO axis
    isos = dark.indexes["iso"]
    exact = np.flatnonzero(isos.to_numpy() == iso)       # the frame's ISO on the axis: itself is the nearest
    read_dn = float(by_iso[exact[0] if exact.size else isos.get_indexer([iso], method="nearest")[0]])
    return read_dn / np.sqrt(n_sites)


def frame_time_s(raw: RawFrame) -> float:
    """The frame's time stamp in seconds since 1970-01-01, a stamp without time zone read as UTC; NaN without one.

    Parameters
    ----------
    raw : pipeline.io.rawio.RawFrame
        The decoded frame.

    Returns
    -------
    float
        Seconds since 1970-01-01 (s) on the camera clock.
    """
    stamp: datetime | None = raw.time
    if stamp is None:
        return np.nan
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=timezone.utc)
    return stamp.timestamp()


def frame_corner_records(lens: str, images: LensImages, raw: RawFrame, dark: xr.Dataset,
                         corners: dict[str, np.ndarray], temperature_c: float = np.nan,
                         pattern_dn: dict[str, float] | None = None, memo: dict | None = None) -> list[dict]:
    """One decoded frame's corner records, one per band (columns :data:`CORNER_COLUMNS`).

    Each holds the measured mean of the lens's unlit pixels, the dark model's prediction there at the frame's
    ISO, exposure time and temperature, and the noise of the mean.

    Parameters
    ----------
    lens : str
        Name of the lens.
    images : pipeline.io.frames.LensImages
        The frame's band images of the lens.
    raw : pipeline.io.rawio.RawFrame
        The decoded frame (ISO, exposure time, time stamp, optically black pixels).
    dark : xarray.Dataset
        The dark artefact of the lens.
    corners : dict[str, numpy.ndarray]
        Band -> the corner pixels (:func:`corner_sites` of :func:`corner_pixels`).
    temperature_c : float, default NaN
        Logged sensor temperature (degree Celsius); NaN when not logged.
    pattern_dn : dict[str, float], optional
        :func:`corner_pattern_dn` of each band when the caller has it already (DN).
    memo : dict, optional
        A dict the caller keeps for one ``dark`` and ``corners``, in which the prediction and the noise of
        each setting are kept (frames repeat their settings; the values are the same as computed afresh).

    Returns
    -------
    list of dict
        One record per band, keyed by the names of :data:`CORNER_COLUMNS`.
    """
    iso, exposure_s = float(raw.iso), round(float(raw.exposure_s), 9)
    time_s = frame_time_s(raw)
    logged = float(temperature_c) if np.isfinite(temperature_c) else None
    memo = {} if memo is None else memo
    out = []
    for band in BANDS:
        corner_dn, sites = corner_mean_dn(images.bands[band], corners[band], band, raw)
        pattern = None if pattern_dn is None else pattern_dn[band]
        key = ("dark", band, iso, exposure_s, logged, pattern)
        if key not in memo:
            memo[key] = predicted_corner_dn(dark, band, iso, exposure_s, corners[band], temperature_c,
                                            pattern_dn=pattern)
        noise_key = ("noise", band, iso, sites)
        if noise_key not in memo:
            memo[noise_key] = corner_noise_dn(dark, band, iso, sites)
        out.append({"lens": lens, "band": band, "iso": iso, "exposure_s": exposure_s,
                    "temperature_c": float(temperature_c), "time_s": time_s,
                    "corner_dn": corner_dn, "n_corner_sites": sites,
                    "dark_corner_dn": memo[key], "sigma_corner_dn": memo[noise_key]})
    return out


class FrameCorners:
    """The corner records of a stage's lit frames, as the frames are decoded (each frame read once, by the
    stage's own reduction): each lens's corner pixels found at its first frame, from ``projection(lens)``
    (the dataset's declared projection of the lens region) and ``min_radius_fraction``
    (``bias.corner_min_radius_fraction``). A lens without a dark artefact in ``dark`` records nothing."""

    def __init__(self, dark: dict[str, xr.Dataset] | None, projection: Callable[[str], str],
                 min_radius_fraction: float):
        self.dark = dict(dark or {})
        self.projection = projection
        self.min_radius_fraction = float(min_radius_fraction)
        self.corners: dict[str, dict[str, np.ndarray]] = {}      # lens -> band -> corner pixels (corner_sites)
        # per lens and band, :func:`corner_pattern_dn` once at the lens's first frame (the upstream artefacts
        # are opened lazily: the dark artefact's offset map, 36 MB at the full resolution, stays on disk)
        self.pattern_dn: dict[str, dict[str, float]] = {}
        self.records: list[dict] = []
        self.memo: dict[str, dict] = {}     # lens -> the dark model's values per setting (frame_corner_records)

    @classmethod
    def of_upstream(cls, lens: str, upstream: dict, projection: Callable[[str], str], bias_config: dict):
        """A stage's recorder for ``lens``: its dark artefact from the stage's ``upstream`` (none: nothing
        recorded), the corners by ``bias.corner_min_radius_fraction``.

        Parameters
        ----------
        lens : str
            Name of the lens.
        upstream : dict[str, xarray.Dataset]
            The stage's upstream artefacts by stage name (``dark`` used when present).
        projection : callable
            Lens name -> the dataset's declared projection of its region.
        bias_config : dict
            The configuration's ``bias`` section.

        Returns
        -------
        FrameCorners
            The recorder.
        """
        return cls({lens: upstream["dark"]} if "dark" in upstream else None, projection,
                   bias_config["corner_min_radius_fraction"])

    def add(self, lens: str, images: LensImages, raw: RawFrame, temperature_c: float = np.nan, **keys) -> None:
        """Record one frame of ``lens``; ``keys`` (the stage's own: ``file_index``, ``medium``...) go on each row.

        Nothing is recorded for a lens without a dark artefact.

        Parameters
        ----------
        lens : str
            Name of the lens.
        images : pipeline.io.frames.LensImages
            The frame's band images of the lens.
        raw : pipeline.io.rawio.RawFrame
            The decoded frame.
        temperature_c : float, default NaN
            Logged sensor temperature (degree Celsius); NaN when not logged.
        **keys
            Further columns of each record.
        """
        if lens not in self.dark:
            return
        if lens not in self.corners:
            self.corners[lens] = corner_sites(self.dark[lens], corner_pixels(images.bands["G"].shape,
                                                                             self.projection(lens),
                                                                             self.min_radius_fraction))
            self.pattern_dn[lens] = {band: corner_pattern_dn(self.dark[lens], band, self.corners[lens][band],
                                                             self.min_radius_fraction) for band in BANDS}
        for record in frame_corner_records(lens, images, raw, self.dark[lens], self.corners[lens], temperature_c,
                                           self.pattern_dn[lens], memo=self.memo.setdefault(lens, {})):
            self.records.append({**record, **keys})

    def of_lens(self, lens: str) -> list[dict]:
        """The records of one lens.

        Parameters
        ----------
        lens : str
            Name of the lens.

        Returns
        -------
        list of dict
            Its records, in the order the frames were added.
        """
        return [r for r in self.records if r["lens"] == lens]
