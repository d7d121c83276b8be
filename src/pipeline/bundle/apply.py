"""``apply``: raw frames to spectral radiance maps with uncertainty, per pixel and on the sphere.

Every band pixel of both lenses goes through the measurement chain of
:mod:`pipeline.radiometry.measurement` (the inverse of Eq. 4, Larouche et al.
2024, Section 2.1; Section 2.9: "pixel digital values were transformed into
calibrated spectral radiance using the inverse of Eq. (4)") with the
parameters of a calibration bundle (:mod:`pipeline.bundle.calibration`). The output
holds, per frame, lens and band: radiance (W sr-1 m-2 nm-1), its random and
systematic standard uncertainty, theta, phi, solid angle and a quality flag;
and the same binned onto a regular zenith/azimuth grid joining both lenses
into the full sphere (mean, spread and count of the pixels in each cell; NaN
where none falls). With ``pixels=False`` (``--no-pixels``) only the sphere
grid is written. :func:`band_radiance` is the chain on one band image of one
lens (or a window of it), for any caller.

Sphere convention: the lens named ``zenith_lens`` (default ``close``) looks
at the zenith, its pixel (theta, phi) is zenith angle theta and azimuth phi;
the other lens looks the opposite way (nadir): zenith angle 180 - theta and
azimuth -phi (mirrored, as a back-to-back lens sees its sensor's x axis
reversed), both mod 360.

A rectilinear lens (a phone or an ordinary camera, bundle ``projection``)
has no image circle and no unlit corners: every pixel with a field angle is
measured, those beyond the roll-off's calibrated field angle are flagged, and
on the sphere grid it covers only its field (NaN elsewhere). With
``bias_drift`` in the model each frame's black level is then the mean of the
frame's optically black pixels (DNG ActiveArea/MaskedAreas) less the dark
stage's ``optical_black_offset_dn`` (their level above the region's dark
level); a frame without them keeps the dark model's bias, and the output's
``bias_drift_note`` says that the bias drift was not corrected.

A frame from another camera (make, model, serial), with an ISO or exposure
outside those the bundle was calibrated for, or for a medium the bundle
lacks, is refused with one line naming the file.
"""

from __future__ import annotations

import os
import queue
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import xarray as xr
from scipy import sparse

from pipeline.io.artefact import mapped_variables, model_effects
from pipeline.io.bands import BANDS, band_plane, band_saturation, cut_region
from pipeline.bundle.calibration import (STATIC_OFF_GRID, band_parameters, calibrated_isos, factor_effects,
                                  outside_image_circle, read_bundle, sphere_blocks, sphere_counts)
from pipeline.config import defaults
from pipeline.errors import ImpossibleResult, InputError
from pipeline.io.frames import SATURATION_MARGIN_DN, lens_images
from pipeline.geometry.sphere import ZENITH_LENS, grid_shape, sphere_cells, sphere_coordinates
from pipeline.stats.moments import corner_mask
from pipeline.radiometry import measurement as mm
from pipeline.io.rawio import read_raw
from pipeline.io.units import encode_units

__all__ = ["apply_calibration", "band_radiance", "BandChain", "check_frame", "sphere_coordinates", "sphere_directions", "bin_on_sphere",
           "apply_command"]

#: flags that keep a pixel out of the sphere grid
EXCLUDED_FROM_GRID = mm.FLAG_SATURATED | STATIC_OFF_GRID
SPHERE_CONVENTION = ("the {zenith} lens's optical axis is the zenith (zenith angle = theta, azimuth = phi); "
                     "the other lens looks at the nadir (zenith angle = 180 - theta, azimuth = -phi mod 360, mirrored); "
                     "theta, phi from the bundle's geometry maps (phi from the band image's +x towards +y)")


def check_frame(raw, bundle: xr.Dataset, effects) -> None:
    """Refuse a frame the bundle does not calibrate: another camera, ISO or exposure outside the calibrated range.

    Parameters
    ----------
    raw : RawFrame
        The decoded frame (its camera tags, ISO and exposure time in s).
    bundle : xarray.Dataset
        The calibration bundle.
    effects : collection of str
        The effects of the bundle's model.

    Raises
    ------
    InputError
        When the frame is from another camera, at an ISO the bundle does not calibrate, or its exposure time is
        outside the calibrated range.
    """
    for key, tag in (("make", "make"), ("model", "model"), ("serial", "serial")):
        want = bundle.attrs.get(f"camera_{key}", "")
        got = getattr(raw, tag)
        if want and got is not None and str(got) != want:
            raise InputError(raw.path, f"is from camera {key} '{got}', the calibration is for '{want}'")
        if want and got is None and key != "serial":
            raise InputError(raw.path, f"has no camera {key} tag; the calibration is for '{want}'")
    isos = calibrated_isos(bundle, effects)
    if not np.any(np.isclose(isos, raw.iso)):
        raise InputError(raw.path, f"ISO {raw.iso:g} is not a calibrated ISO ({', '.join(f'{i:g}' for i in isos)})")
    t0 = float(bundle["calibrated_exposure_s_min"].min())
    t1 = float(bundle["calibrated_exposure_s_max"].max())
    if not t0 <= raw.exposure_s <= t1:
        raise InputError(raw.path, f"exposure {raw.exposure_s:g} s is outside the calibrated range {t0:g} to {t1:g} s")


def _media(bundle: xr.Dataset) -> list[str]:
    return [m for m in bundle.attrs.get("media", "air").split(",") if m]


@lru_cache(maxsize=1)
def _default_negative_sigma() -> float:
    return float(defaults()["apply"]["negative_mean_sigma"])


@lru_cache(maxsize=1)
def _default_corner_fraction() -> float:
    return float(defaults()["bias"]["corner_min_radius_fraction"])


@lru_cache(maxsize=8)
def _unlit_corners(shape: tuple[int, int], fraction: float) -> np.ndarray:
    """The unlit corner pixels of a lens region's band image (the dark and linearity stages' corners)."""
    return corner_mask(shape, fraction)


def _projection(bundle: xr.Dataset, lens: str) -> str:
    return str(bundle["projection"].sel(lens=lens).values) if "projection" in bundle else "fisheye"


def optical_black_level(raw, bundle: xr.Dataset, lens: str, band: str) -> tuple[float, float] | None:
    """The black level (DN) of a band pixel of ``lens`` in this frame from its optically black pixels, and its variance.

    The optically black pixels' mean (:attr:`pipeline.io.rawio.RawFrame.optical_black_dn`) less the dark
    stage's ``optical_black_offset_dn`` (their mean less the region's dark level in the dark frames); the
    variance is the standard error of that mean squared (their sample variance over their number; the
    offset's own error, from the dark frames, is about 0.01 DN and not propagated). None when the frame
    declares no optically black pixels or the bundle has no offset for them.

    Parameters
    ----------
    raw : RawFrame
        The decoded frame.
    bundle : xarray.Dataset
        The calibration bundle.
    lens : str
        The lens.
    band : str
        The band (R, G or B).

    Returns
    -------
    tuple of float or None
        (black level, DN; its variance, DN^2), or None.
    """
    if raw.optical_black_dn is None or raw.optical_black_count < 2 or "optical_black_offset_dn" not in bundle:
        return None
    offset = float(bundle["optical_black_offset_dn"].sel(lens=lens, band=band))
    if not np.isfinite(offset):
        return None
    var = float(raw.optical_black_var_dn2 or 0.0) / raw.optical_black_count
    return float(raw.optical_black_dn) - offset, var


def _crop(b: xr.Dataset, name: str, rows: slice, cols: slice):
    return b[name].isel(y=rows, x=cols).values if name in b else None


def _stored_factors(g: xr.Dataset, b: xr.Dataset, rows: slice, cols: slice, effects) -> mm.PixelFactors | None:
    """The bundle's per-pixel factors of the crop (:func:`pipeline.bundle.calibration.build_bundle`), when made for ``effects``.

    ``g`` the bundle at one lens, medium and band, ``b`` at that lens and band (the flat field's term).
    """
    if "pixel_factor" not in g or str(g["pixel_factor"].attrs.get("effects", "")) != factor_effects(effects):
        return None
    random = ({"prnu": _crop(b, "pixel_random_relative_variance", rows, cols)}
              if "pixel_random_relative_variance" in b else {})
    return mm.PixelFactors(inverse=_crop(g, "pixel_factor", rows, cols),
                           systematic_rel={"rolloff": _crop(g, "pixel_systematic_relative_variance", rows, cols)},
                           random_rel=random, flags=_crop(g, "pixel_flag", rows, cols))


def band_radiance(images, bundle: xr.Dataset, lens: str, band: str, medium: str, effects,
                  frame: mm.FrameSettings, window=None, *, negative_sigma: float | None = None,
                  source=None, out=None, scratch=None, frame_black=None) -> mm.Measured:
    """The measurement chain on one band image of one lens: raw DN to radiance with its uncertainty.

    With ``window`` only that crop of the band image runs (and the same crop of theta, the hot-pixel mask and the
    flat field), and the result has the crop's shape; each pixel's result is the one of the whole image. Pixels
    outside the image circle (or beyond the half field of view) have no direction: NaN, flagged
    :data:`~pipeline.radiometry.measurement.FLAG_OUTSIDE_IMAGE_CIRCLE`. With ``bias_drift`` the frame's black level
    comes from the unlit corners of a fisheye lens, or for a rectilinear lens from ``frame_black`` (without it the
    dark model's bias).

    Parameters
    ----------
    images : LensImages
        What :func:`pipeline.io.frames.lens_images` returns for ``lens``.
    bundle : xarray.Dataset
        The calibration bundle.
    lens : str
        The lens.
    band : str
        The band (R, G or B).
    medium : str
        "air" or "water".
    effects : collection of str
        The effects of the bundle's model.
    frame : FrameSettings
        The frame's exposure time (s) and ISO.
    window : tuple of slice, optional
        ``(row_slice, col_slice)`` of the band image; the whole image when None.
    negative_sigma : float, optional
        A mean radiance over the unflagged pixels inside the circle more than this many standard errors below
        zero raises; default ``apply.negative_mean_sigma``.
    source : str or pathlib.Path, optional
        Names the frame in the messages.
    out : tuple of numpy.ndarray, optional
        Three arrays of the crop's shape (e.g. slots of the output maps) where the radiance and its random and
        systematic sigma are evaluated (:meth:`~pipeline.radiometry.measurement.Measured.evaluate_into`).
    scratch : numpy.ndarray, optional
        One more such array, for the sums on the way.
    frame_black : tuple of float, optional
        The frame's black level and its variance (DN, DN^2; :func:`optical_black_level`).

    Returns
    -------
    Measured
        The radiance (W m-2 sr-1 nm-1) with its random and systematic variance terms and the pixels' flags.

    Raises
    ------
    ImpossibleResult
        When the mean radiance is significantly negative.
    """
    return BandChain(bundle, lens, band, medium, effects)(images, frame, window, negative_sigma=negative_sigma,
                                                          source=source, out=out, scratch=scratch,
                                                          frame_black=frame_black)


class BandChain:
    """:func:`band_radiance` of one lens, band and medium of a bundle, for many frames.

    The bundle's selections for the band (about 2.5 ms each on a bundle of some hundred variables) are
    made once, and the chain's parameter objects (:func:`pipeline.bundle.calibration.band_parameters`, 7 ms)
    once per ISO, the one frame setting they depend on: a stage that puts every frame through the chain
    (the field's 31 frames x 3 bands) pays them once per band instead of once per frame and band.
    """

    def __init__(self, bundle: xr.Dataset, lens: str, band: str, medium: str, effects):
        self.bundle, self.lens, self.band, self.medium = bundle, lens, band, medium
        self.effects = tuple(effects)
        self.g = bundle.sel(lens=lens, medium=medium, band=band)
        self.b = bundle.sel(lens=lens, band=band)
        self.shape = tuple(self.g["theta_deg" if "theta_deg" in self.g else "pixel_factor"].shape)
        self.projection = _projection(bundle, lens)
        self._parameters: dict[float, tuple] = {}
        self._unlit: np.ndarray | None = None

    def parameters(self, frame: mm.FrameSettings) -> tuple[mm.DarkModel, mm.ResponseModel, mm.BandCalibration]:
        """:func:`pipeline.bundle.calibration.band_parameters` at the frame's ISO.

        Parameters
        ----------
        frame : FrameSettings
            The frame's exposure time (s) and ISO.

        Returns
        -------
        dark : DarkModel
            The dark model.
        response : ResponseModel
            The response model.
        calibration : BandCalibration
            The band's calibration.
        """
        key = float(frame.iso)
        if key not in self._parameters:
            self._parameters[key] = band_parameters(self.bundle, self.lens, self.band, self.medium, frame,
                                                    self.effects)
        return self._parameters[key]

    def unlit_corners(self) -> np.ndarray:
        """The unlit corner pixels of the band image that tell a frame's black level (``bias_drift``): those
        of the dark and linearity stages, less the hot pixels when ``hot_pixels`` is in the model.

        Returns
        -------
        numpy.ndarray
            Boolean mask of the band image's shape.
        """
        if self._unlit is None:
            corners = _unlit_corners(self.shape, _default_corner_fraction())
            hot = _crop(self.b, "hot_pixel_mask", slice(None), slice(None))
            if hot is not None and "hot_pixels" in self.effects:
                corners = corners & ~(np.asarray(hot) > 0)
            self._unlit = corners
        return self._unlit

    def __call__(self, images, frame: mm.FrameSettings, window=None, *, negative_sigma: float | None = None,
                 source=None, out=None, scratch=None, frame_black=None) -> mm.Measured:
        """:func:`band_radiance` of this lens, band and medium on one frame's ``images``."""
        lens, band, medium, effects, g, b, shape = (self.lens, self.band, self.medium, self.effects, self.g, self.b,
                                                    self.shape)
        image = images.bands[band]
        if image.shape != tuple(shape):
            raise InputError(source, f"lens '{lens}' band image is {image.shape}, the calibration's {tuple(shape)}")
        rows, cols = (slice(None), slice(None)) if window is None else window
        rows = slice(*rows.indices(shape[0]))
        cols = slice(*cols.indices(shape[1]))
        factors = _stored_factors(g, b, rows, cols, effects)
        theta = phi = rolloff = None
        if factors is None:
            theta = np.asarray(_crop(g, "theta_deg", rows, cols), dtype=float)
            theta = np.where(outside_image_circle(g, theta, rows, cols, shape), np.nan, theta)
            phi = _crop(g, "phi_deg", rows, cols)
        dark, response, cal = self.parameters(frame)
        if factors is None:
            rolloff = mm.rolloff_map(theta, cal, phi, effects, np.result_type(np.float32, image.dtype),
                                     theta_deg_sigma=_crop(g, "theta_deg_sigma", rows, cols))
        unlit = None
        if "bias_drift" in effects and self.projection != "rectilinear":
            # the frame's own black level from the unlit corners of the whole band image (not only the crop)
            unlit = image[self.unlit_corners()]
        m = mm.measure_band(image[rows, cols], frame, dark, response, cal, theta, medium, effects, unlit_dn=unlit,
                            saturated=images.saturated[band][rows, cols],
                            hot_mask=_crop(b, "hot_pixel_mask", rows, cols),
                            flat_field=_crop(b, "flat_field", rows, cols),
                            flat_field_sigma=_crop(b, "flat_field_sigma", rows, cols),
                            prnu_sigma_rel=float(b["prnu_sigma_rel"]) if "prnu_sigma_rel" in b else 0.0,
                            phi_deg=phi, rolloff=rolloff, factors=factors,
                            frame_black_dn=frame_black if self.projection == "rectilinear" else None)
        if out is not None:
            m.evaluate_into(*out, scratch=scratch)
        if negative_sigma is None:
            negative_sigma = _default_negative_sigma()
        good = (m.flags & (mm.FLAG_OUTSIDE_IMAGE_CIRCLE | mm.FLAG_SATURATED | mm.FLAG_HOT)) == 0
        good &= np.isfinite(m.value)
        n_good = int(np.count_nonzero(good))
        if n_good:
            # sums over the good pixels in float64 (the chain may run in float32)
            mean = float(np.sum(m.value, where=good, dtype=float)) / n_good
            sigma = m.random_sigma
            fits = scratch is not None and scratch.shape == sigma.shape and scratch.dtype == sigma.dtype
            se = float(np.sqrt(np.sum(np.square(sigma, out=scratch if fits else None), where=good, dtype=float))) / n_good
            if mean < -negative_sigma * se:
                raise ImpossibleResult(source, f"lens {lens}, band {band}: mean radiance {mean:.3g} W sr-1 m-2 nm-1 "
                                               f"over the image circle is {-mean / se:.1f} standard errors below "
                                               "zero: the dark level or the calibration does not fit this frame")
        return m


class _CellSums:
    """Running per-cell sums of pixel values (count, sum, sum of squares and of ``extra`` quantities).

    :meth:`add` takes the pixels of one block (any shape) at a time, so a
    band image is binned while its rows are still in the cache; every pixel
    is counted with ``np.bincount``, those that do not enter (cell < 0, value
    not finite, ``excluded``) go to one more cell, dropped at the end. The
    sums are float64; ``squared[k]`` squares the k-th extra quantity first.
    """

    def __init__(self, n_cells: int, n_extra: int = 0, squared=()):
        self.n_cells = n_cells
        self.squared = tuple(squared) + (False,) * (n_extra - len(squared))
        self.count = np.zeros(n_cells + 1)
        self.sums = np.zeros((2 + n_extra, n_cells + 1))

    def add(self, cell, value, extra=(), excluded=None) -> None:
        v = np.asarray(value).ravel()
        cell = np.asarray(cell).ravel()
        out = ~np.isfinite(v)
        out |= cell < 0
        if excluded is not None:
            out |= np.asarray(excluded).ravel()
        index = cell.astype(np.int32)
        np.copyto(index, self.n_cells, where=out)
        n = self.n_cells + 1
        self.count += np.bincount(index, minlength=n)
        cells = _cell_indicator(index, n)
        w = v.astype(float)  # a NaN goes to the spill cell only
        self.sums[0] += cells @ w
        np.square(w, out=w)
        self.sums[1] += cells @ w
        for k, x in enumerate(extra):
            np.copyto(w, np.asarray(x).ravel())
            if self.squared[k]:
                np.square(w, out=w)
            self.sums[2 + k] += cells @ w

    def merge(self, other: "_CellSums") -> "_CellSums":
        self.count += other.count
        self.sums += other.sums
        return self

    def result(self):
        """Mean, spread (standard deviation, NaN below 2 pixels), count (int32) and the extras' means per cell.

        The spread in one pass, from the sum of squares less n mean^2 (a float32 value squares exactly in
        float64; the cancellation leaves about 1e-8 of the mean in the spread of a cell of equal values).
        """
        count, sums = self.count[:self.n_cells], self.sums[:, :self.n_cells]
        has = count > 0
        per = np.where(has, count, 1)
        mean = np.where(has, sums[0] / per, np.nan)
        var = sums[1] - count * np.square(np.where(has, mean, 0.0))
        np.clip(var, 0.0, None, out=var)
        spread = np.where(count > 1, np.sqrt(var / np.where(count > 1, count - 1, 1)), np.nan)
        means = [np.where(has, sums[2 + k] / per, np.nan) for k in range(len(sums) - 2)]
        return mean, spread, count.astype(np.int32), means


def _bin_cells(cells, values, n_cells: int, extra=(), excluded=None, squared=()):
    """Mean, spread and count per cell of ``values`` (a list of arrays, e.g. one per lens, with their ``cells``).

    A value enters where its cell is >= 0, it is finite and (with
    ``excluded``, a list of boolean arrays like ``values``) not excluded;
    ``extra`` (a list of such lists) are averaged over the same pixels of
    each cell, squared first where ``squared[k]`` (:class:`_CellSums`).
    """
    sums = _CellSums(n_cells, len(extra), squared)
    for i, (cell, v) in enumerate(zip(cells, values)):
        sums.add(cell, v, [x[i] for x in extra], None if excluded is None else excluded[i])
    return sums.result()


@dataclass(frozen=True)
class _BandPlan:
    """What the chain needs of one band of one lens for every frame of an ``apply`` call.

    ``factors`` the hot-pixel flags, flat field and roll-off taken together
    (:class:`pipeline.radiometry.measurement.PixelFactors`, the bundle's ``pixel_*`` maps),
    ``corners`` the unlit corners whose mean is the frame's black level with ``bias_drift``
    (fisheye lenses; else None).
    """

    factors: mm.PixelFactors
    corners: np.ndarray | None
    #: per block of rows: its (rows, columns) (all columns with the pixel maps; else those that reach inside
    #: the image circle; blocks wholly outside it left out), its first cell, its number of cells n and
    #: every pixel's cell less the first (a view of the bundle's ``sphere_cell_in_block``: n, the block's
    #: spill cell, where no direction or a frame-independent flag keeps the pixel off the grid)
    blocks: list


def _band_plan(factors: mm.PixelFactors, cells, corners: bool, block_rows: int, pixels: bool) -> _BandPlan:
    """The :class:`_BandPlan` of one band image from its ``factors`` and ``cells`` (:func:`sphere_blocks`).

    ``corners``: the frame's black level from the unlit corners (``bias_drift``, fisheye lens).
    """
    shape = factors.inverse.shape
    unlit = None
    if corners:
        # the frame's own black level from the unlit corners of the whole band image, less the hot pixels
        unlit = _unlit_corners(tuple(shape), _default_corner_fraction()) & ((factors.flags & mm.FLAG_HOT) == 0)
    index, first, n_cells, columns = cells
    blocks = []
    for b, r0 in enumerate(range(0, shape[0], block_rows)):
        r = slice(r0, min(r0 + block_rows, shape[0]))
        c = slice(0, shape[1])
        if not pixels:
            # the grid alone: only the block's columns that reach inside the image circle (the pixels
            # outside it neither enter the grid nor the negative-mean check)
            c0, c1 = (int(v) for v in columns[b])
            if c1 <= c0:
                continue
            c = slice(c0, c1)
        blocks.append(((r, c), int(first[b]), int(n_cells[b]), index[r, c]))
    return _BandPlan(factors=factors, corners=unlit, blocks=blocks)


def _lens_plans(maps: dict, i: int, cells, corners: bool, block_rows: int, pixels: bool) -> dict:
    """The :class:`_BandPlan` of every band of lens ``i`` ({band: plan}) from the bundle's maps of the medium.

    ``maps``: the bundle's ``pixel_*`` variables at the medium, (lens, band, y, x); ``cells`` per band.
    """
    plans = {}
    for j, band in enumerate(BANDS):
        random = maps.get("pixel_random_relative_variance")
        factors = mm.PixelFactors(inverse=maps["pixel_factor"][i, j],
                                  systematic_rel={"rolloff": maps["pixel_systematic_relative_variance"][i, j]},
                                  random_rel={} if random is None else {"prnu": random[i, j]},
                                  flags=maps["pixel_flag"][i, j] if "pixel_flag" in maps else None)
        plans[band] = _band_plan(factors, cells[j], corners, block_rows, pixels)
    return plans


#: a weight of 1 per pixel and the column pointers 0, 1, ..., n of the largest block binned so far (read-only;
#: a block's are their first entries)
_UNIT_COLUMNS = (np.ones(0), np.arange(1, dtype=np.int32))


def _unit_columns(size: int) -> tuple[np.ndarray, np.ndarray]:
    """A weight of 1 for each of ``size`` pixels and the column pointers 0, 1, ..., size (read-only views)."""
    global _UNIT_COLUMNS
    ones, pointers = _UNIT_COLUMNS
    if ones.size < size:
        ones, pointers = np.ones(size), np.arange(size + 1, dtype=np.int32)
        ones.flags.writeable = pointers.flags.writeable = False
        _UNIT_COLUMNS = (ones, pointers)   # another thread's larger pair may replace it: both stay valid
    return ones[:size], pointers[:size + 1]


def _cell_indicator(cell, n_cells: int):
    """The n_cells x pixels matrix with a 1 at (cell of the pixel, pixel): times a pixel quantity, its sums per cell.

    ``cell`` (np.int32, every value below ``n_cells``). The product runs through the pixels in their order,
    as ``np.bincount`` does, so the sums are bincount's to the bit; unlike ``np.bincount`` it releases the
    GIL, so the two lenses' blocks are binned side by side (two threads of 250 blocks of 110,000 pixels,
    four sums each: 0.16 s instead of 0.34 s with ``np.bincount``; one such thread alone 0.15 s against
    0.16 s; scipy 1.17, this machine, 2026-12-03).
    """
    ones, pointers = _unit_columns(cell.size)
    return sparse.csc_array((ones, cell, pointers), shape=(n_cells, cell.size), copy=False)


class _LensSums:
    """The sphere-grid sums of one lens of a frame, per band: count, sum and sum of squares of the radiance,
    sum of the random sigma squared and of the systematic sigma (:class:`_CellSums`, float64); and per band
    the negative-mean check's count, sum of the radiance and of its random variance over every unflagged
    pixel inside the image circle (the grid's pixels and those of the blocks' second spill cell).

    Each block of a band image is binned while it is in the cache, with
    ``np.bincount`` over the block's own range of cells (the pixels of a cell
    summed in the order :func:`_bin_cells` sums them); the pixels a frame's
    flags keep off (saturated, not finite) go to the block's spill cell.
    The counts are not binned: ``counts`` gives per band the pixels of each
    cell and of the check (:func:`~pipeline.bundle.calibration.sphere_counts`, from
    the bundle), less those the frame's flags keep off, counted per block.
    """

    def __init__(self, n_cells: int, counts):
        self.bands = [_CellSums(n_cells, 2, squared=(True, False)) for _ in counts]
        #: per band: [pixels, sum of the radiance, sum of its random variance] of the negative-mean check
        self.checked = [[int(checked), 0.0, 0.0] for _, checked in counts]
        # the pixels of each cell and of the check before the frame's flags (sphere_counts), less those
        # flags when a block is added
        for total, (count, _) in zip(self.bands, counts):
            total.count[:n_cells] = count

    def add_block(self, band: int, first: int, n: int, index, value, rnd, sy, excluded, at, wide,
                  check: bool = True) -> bool:
        """Bin one block (``first``, ``n``, ``index``: :attr:`_BandPlan.blocks`); ``excluded`` kept off.

        ``excluded``: None when no pixel of the block is, else a boolean map of the block. ``at``
        (np.int32) and ``wide`` (float64): buffers of at least the block's size.
        With ``check``, returns False (nothing added) when a value or its random sigma is not finite
        where the pixel is not excluded: the caller then excludes the non-finite values and adds the
        block again (``check=False``: a non-finite random sigma of a finite value then enters its cell).
        """
        size = index.size
        at = at[:size]
        np.copyto(at.reshape(index.shape), index)
        if excluded is not None:
            # the pixels a frame's flags keep off (saturated, not finite) into the block's spill cell n
            np.copyto(at, n, where=excluded.reshape(-1))
        m = n + 2
        cells = _cell_indicator(at, m)
        w = wide[:size]
        np.copyto(w, value.reshape(-1))
        s0 = cells @ w
        np.square(w, out=w)
        s1 = cells @ w
        np.square(rnd.reshape(-1), out=w, dtype=float)
        s2 = cells @ w
        # a non-finite value that was not excluded would make its cell's sums non-finite (a float32 value
        # squared is finite in float64): checked on the cells, not the pixels
        if check and not np.isfinite(s1[:n].sum() + s1[n + 1] + s2[:n].sum() + s2[n + 1]):
            return False
        np.copyto(w, sy.reshape(-1))
        s3 = cells @ w
        cells = slice(first, first + n)
        total = self.bands[band]
        checked = self.checked[band]
        if excluded is not None:
            # the pixels counted on their cells (or by the check) that the frame's flags keep off
            off = np.bincount(index.reshape(-1)[excluded.reshape(-1)], minlength=m)
            total.count[cells] -= off[:n]
            checked[0] -= int(off[n + 1])
        total.sums[0, cells] += s0[:n]
        total.sums[1, cells] += s1[:n]
        total.sums[2, cells] += s2[:n]
        total.sums[3, cells] += s3[:n]
        checked[1] += float(s0[:n].sum() + s0[n + 1])
        checked[2] += float(s2[:n].sum() + s2[n + 1])
        return True


def _lens_radiance(raw, bundle, lens, medium, effects, frame, negative_sigma, plans, block_rows, sums, maps=None,
                   parameters=None, band_done=None):
    """One lens of a decoded frame through the chain, a block of ``block_rows`` rows of a band image at a time.

    ``plans`` the lens's :class:`_BandPlan` per band. With ``maps``
    ({name: (band, y, x) array}: ``radiance``, ``random``, ``systematic``
    float32, ``flags`` uint8) each block is evaluated straight into them;
    into ``sums`` (a :class:`_LensSums`) each block is binned onto the sphere
    grid while it is in the cache. Each pixel's result is the one of the
    chain on the whole image. A mean radiance over the unflagged pixels inside
    the circle more than ``negative_sigma`` standard errors below zero raises
    :class:`~pipeline.errors.ImpossibleResult`, as :func:`band_radiance` does
    (its sums are the grid's, with the blocks' second spill cell: the pixels
    inside the circle that are off the grid only beyond the calibrated field angle).
    ``parameters``: a dict that keeps the chain's parameter objects of each
    lens, band and frame setting for the next frames of the call.
    ``band_done(j)`` is called when band ``j`` is through (its maps complete, its check passed).
    """
    parameters = {} if parameters is None else parameters
    span = bundle["lens_region_px"].sel(lens=lens).values
    span = (tuple(span[0]), tuple(span[1]))
    rectilinear = _projection(bundle, lens) == "rectilinear"
    images = region = None
    if "bias_drift" in effects and not rectilinear:
        # the frame's black level from the unlit corners of each whole band image: the band split first
        images = lens_images(raw, span, lens)
        shape = images.bands[BANDS[0]].shape
    else:
        # each block's band pixels split from the mosaic's rows into a block buffer (the same numbers as
        # the whole band image's; no full-size float32 planes to allocate and fill)
        try:
            region = cut_region(raw.cfa, *span)
        except ValueError as exc:
            raise InputError(raw.path, f"lens '{lens}' region does not fit the frame ({exc})") from None
        shape = (region.shape[0] // 2, region.shape[1] // 2)
        white = raw.white_level - SATURATION_MARGIN_DN
    if tuple(plans[BANDS[0]].factors.inverse.shape) != tuple(shape):
        raise InputError(raw.path, f"lens '{lens}' band image is {shape}, the calibration's "
                                   f"{tuple(plans[BANDS[0]].factors.inverse.shape)}")
    rows = max(1, min(int(block_rows), shape[0]))
    # per block: the chain's three results (unless written into maps) and one scratch for its sums of variances
    block = {name: np.empty(rows * shape[1], np.float32) for name in ("radiance", "random", "systematic", "scratch")}
    block["sums"] = np.empty(rows * shape[1])
    block["at"] = np.empty(rows * shape[1], np.int32)
    block["image"] = np.empty(rows * shape[1], np.float32)
    block["saturated"] = np.empty(rows * shape[1], bool)
    for j, band in enumerate(BANDS):
        plan = plans[band]
        if images is not None:
            image, saturated = images.bands[band], images.saturated[band]
        key = (lens, band, frame)
        if key not in parameters:
            parameters[key] = band_parameters(bundle, lens, band, medium, frame, effects)
        dark, response, cal = parameters[key]
        black = None
        if "bias_drift" in effects:
            if rectilinear:
                black = optical_black_level(raw, bundle, lens, band)
            elif plan.corners is not None:
                unlit = np.asarray(image[plan.corners], dtype=float)
                # subtract_dark's level and variance from the unlit pixels, taken once for the blocks
                black = (float(unlit.mean()), float(unlit.var(ddof=1) / unlit.size)) if unlit.size > 1 else None
        for window, first, n, index in plan.blocks:
            if images is not None:
                dn, sat = image[window], saturated[window]
            else:
                size = index.size
                dn = band_plane(region, raw.cfa_pattern, band, window, block["image"][:size].reshape(index.shape))
                sat = band_saturation(region, raw.cfa_pattern, band, white, window,
                                      block["saturated"][:size].reshape(index.shape))
            m = mm.measure_band(dn, frame, dark, response, cal, None, medium, effects, saturated=sat,
                                factors=plan.factors.window(window), frame_black_dn=black)
            if maps is not None:
                value, rnd, sy = (maps[name][j][window] for name in ("radiance", "random", "systematic"))
                np.copyto(maps["flags"][j][window], m.flags)
                scratch = block["scratch"][:value.size].reshape(value.shape)
            else:
                value, rnd, sy, scratch = (block[name][:index.size].reshape(index.shape)
                                           for name in ("radiance", "random", "systematic", "scratch"))
            m.evaluate_into(value, rnd, sy, scratch=scratch)
            # the frame's flags that keep a pixel off the grid and out of the negative-mean check (the
            # frame-independent ones are in the block's index)
            excluded = (m.flags & mm.FLAG_SATURATED) != 0
            args = (j, first, n, index, value, rnd, sy)
            if not sums.add_block(*args, excluded if excluded.any() else None, block["at"], block["sums"]):
                excluded |= ~np.isfinite(value)
                sums.add_block(*args, excluded, block["at"], block["sums"], check=False)
            del m
        n_good, total, total_var = sums.checked[j]
        if n_good:
            mean, se = total / n_good, np.sqrt(total_var) / n_good
            if mean < -negative_sigma * se:
                raise ImpossibleResult(raw.path, f"lens {lens}, band {band}: mean radiance {mean:.3g} W sr-1 m-2 "
                                                 f"nm-1 over the image circle is {-mean / se:.1f} standard errors "
                                                 "below zero: the dark level or the calibration does not fit this "
                                                 "frame")
        if band_done is not None:
            band_done(j)


def bin_on_sphere(zenith_deg, azimuth_deg, values, grid_deg: float):
    """Mean, spread (standard deviation) and count of ``values`` per zenith/azimuth cell; NaN where empty.

    Every finite value falls into its cell (no nearest-pixel choice).

    Parameters
    ----------
    zenith_deg : numpy.ndarray
        Zenith angle of each value's direction, degree.
    azimuth_deg : numpy.ndarray
        Azimuth of each value's direction, degree in [0, 360).
    values : numpy.ndarray
        The values (e.g. radiance), same shape.
    grid_deg : float
        Cell size, degree.

    Returns
    -------
    mean : numpy.ndarray
        Mean per cell, in the unit of ``values``, shape ``(180 / grid_deg, 360 / grid_deg)``.
    spread : numpy.ndarray
        Standard deviation per cell, same unit and shape.
    count : numpy.ndarray
        Number of values per cell, same shape.
    """
    shape = (int(round(180.0 / grid_deg)), int(round(360.0 / grid_deg)))
    cell = sphere_cells(zenith_deg, azimuth_deg, grid_deg)
    mean, spread, count, _ = _bin_cells([cell], [values], shape[0] * shape[1])
    return mean.reshape(shape), spread.reshape(shape), count.reshape(shape)


def _pixel_directions(maps, lenses, zenith_lens, grid_deg, block_rows):
    """The sphere cells of every band pixel per block ([lens][band]: :func:`~pipeline.bundle.calibration.sphere_blocks`)
    and the pixels of each cell and of the negative-mean check ([lens][band]: :func:`~pipeline.bundle.calibration.sphere_counts`).

    ``maps`` the bundle's maps at the medium ((lens, band, y, x)): its ``sphere_cell_in_block`` and
    ``sphere_block_*`` when made for this grid, zenith lens and block size, else the cells from
    ``theta_deg`` and ``phi_deg`` and ``pixel_flag``.
    """
    cells, counts = [], []
    stored = "sphere_cell_in_block" in maps
    n_cells = int(np.prod(grid_shape(grid_deg)))
    for i, lens in enumerate(lenses):
        cells.append([])
        counts.append([])
        for j in range(len(BANDS)):
            if not stored:
                z, a = sphere_coordinates(maps["theta_deg"][i, j], maps["phi_deg"][i, j], lens == zenith_lens)
            if stored:
                cells[i].append(tuple(maps[name][i, j] for name in ("sphere_cell_in_block", "sphere_block_first_cell",
                                                                     "sphere_block_n_cells", "sphere_block_columns")))
                counts[i].append((maps["sphere_cell_count"][i, j], int(maps["sphere_checked_count"][i, j])))
            else:
                flags = maps["pixel_flag"][i, j]
                cell = np.where((flags & STATIC_OFF_GRID) != 0, -1, sphere_cells(z, a, grid_deg))
                cells[i].append(sphere_blocks(cell, flags, block_rows))
                counts[i].append(sphere_counts(cell, flags, n_cells))
    return cells, counts


def sphere_directions(ds: xr.Dataset) -> tuple[xr.DataArray, xr.DataArray]:
    """Zenith angle and azimuth of every band pixel of an ``apply`` output with its pixel geometry.

    From its ``theta_deg`` and ``phi_deg`` by its ``sphere_convention`` (the lens ``zenith_lens`` looks at the
    zenith; :func:`~pipeline.geometry.sphere.sphere_coordinates`).

    Parameters
    ----------
    ds : xarray.Dataset
        An ``apply`` output written with the pixel geometry.

    Returns
    -------
    zenith : xarray.DataArray
        Zenith angle, degree, float32, dims (lens, band, y, x).
    azimuth : xarray.DataArray
        Azimuth, degree in [0, 360), float32, dims (lens, band, y, x).

    Raises
    ------
    InputError
        When the output has no ``theta_deg``.
    """
    if "theta_deg" not in ds:
        raise InputError(ds.encoding.get("source"), "has no theta_deg: written without the pixel geometry")
    zenith_lens = str(ds.attrs["zenith_lens"])
    zen, azi = [], []
    for lens in ds["lens"].values:
        z, a = sphere_coordinates(ds["theta_deg"].sel(lens=lens).values, ds["phi_deg"].sel(lens=lens).values,
                                  str(lens) == zenith_lens)
        zen.append(np.array(z, copy=True))
        azi.append(np.asarray(a))
    dims, coords = ds["theta_deg"].dims, ds["theta_deg"].coords
    convention = ds.attrs["sphere_convention"]
    return (xr.DataArray(np.stack(zen), coords, dims, "zenith_deg",
                         _attrs("zenith angle of the pixel's direction on the sphere", "degree", convention=convention)),
            xr.DataArray(np.stack(azi), coords, dims, "azimuth_deg",
                         _attrs("azimuth of the pixel's direction on the sphere", "degree", convention=convention)))


def _attrs(long_name, units, **extra):
    return {"long_name": long_name, "units": units, **extra}


_RADIANCE_UNITS = "W sr-1 m-2 nm-1"
#: the per-pixel variables of an ``apply`` output: name -> (key of the lens maps or the bundle's geometry map,
#: NetCDF type, long_name, units); the maps of the frames have dims (frame, lens, band, y, x), the geometry
#: (lens, band, y, x)
PIXEL_MAPS = {
    "radiance": ("radiance", "f4", "effective spectral radiance of the band pixel, inverse of Eq. (4)", _RADIANCE_UNITS),
    "radiance_random_sigma": ("random", "f4", "random standard uncertainty (shot, read, dark noise), independent "
                              "between pixels and frames", _RADIANCE_UNITS),
    "radiance_systematic_sigma": ("systematic", "f4", "systematic standard uncertainty (calibration terms), common "
                                  "to the pixels of a band", _RADIANCE_UNITS),
    "quality_flag": ("flags", "u1", "quality flag bits", "1"),
}
PIXEL_GEOMETRY = {
    "theta_deg": ("theta_deg", "f4", "angle of the viewing direction from the lens's optical axis", "degree"),
    "phi_deg": ("phi_deg", "f4", "azimuth of the viewing direction about the lens's axis", "degree"),
    "solid_angle_sr": ("solid_angle_sr", "f4", "solid angle seen by the band pixel", "sr"),
}


class _PixelMapFile:
    """The per-pixel maps of an ``apply`` output, written as they are made (the rest follows with xarray).

    Made before the first frame is decoded, so that the geometry maps (the
    bundle's, memory-mapped: one lens's bands are one contiguous slab there)
    go to the file while the frame decodes, and each band's maps of a frame
    as soon as its lens's chain is through it, beside the chains: no copy of
    any map (xarray's writer copied the bundle's geometry views, 215 MB at the
    full resolution, whose first touch in numpy's huge pages cost 1.3 to 1.8 s
    of kernel time), and one frame's maps in memory, not every frame's. Every
    variable uncompressed and contiguous (compressing them,
    zlib level 1, was most of apply's time at the full scale, 9 of 22 s, for
    a file half the size; --no-pixels when size matters), the fill mode off
    (each byte written once), the float maps with the ``_FillValue`` NaN that
    xarray gives them. Only the calling thread touches the file.
    """

    def __init__(self, path: Path, n_frames: int, lenses, shape, geometry: bool):
        import netCDF4

        path.parent.mkdir(parents=True, exist_ok=True)
        self.ds = netCDF4.Dataset(str(path), "w", format="NETCDF4")
        self.ds.set_fill_off()
        self.ds.set_auto_maskandscale(False)   # the arrays as they are: no NaN scan, no masked copy
        for dim, size in zip(("frame", "lens", "band", "y", "x"), (n_frames, len(lenses), len(BANDS), *shape)):
            self.ds.createDimension(dim, size)
        flag_values = np.array(list(mm.FLAG_MEANINGS.values()), np.uint8)
        self.maps = {}
        for variables, dims in ((PIXEL_MAPS, ("frame", "lens", "band", "y", "x")),
                                (PIXEL_GEOMETRY if geometry else {}, ("lens", "band", "y", "x"))):
            for name, (key, kind, long_name, units) in variables.items():
                fill = {"fill_value": np.float32(np.nan)} if kind == "f4" else {}
                var = self.ds.createVariable(name, kind, dims, contiguous=True, **fill)
                var.setncatts({"long_name": long_name, "units": units})
                if name == "quality_flag":
                    var.setncatts({"flag_masks": flag_values, "flag_meanings": " ".join(mm.FLAG_MEANINGS)})
                self.maps[key] = var

    def write_geometry(self, maps: dict, key: str, lens: int) -> None:
        """One geometry map (``key``: theta, phi or solid angle, :data:`PIXEL_GEOMETRY`) of every band pixel of
        lens number ``lens`` (``maps``: the bundle's at the medium, (lens, band, y, x))."""
        self.maps[key][lens] = np.asarray(maps[key][lens], np.float32)

    def write_band(self, frame: int, lens: int, band: int, lens_maps: dict) -> None:
        """One band's maps of one lens and frame (``lens_maps``: {key: (band, y, x) array}, :data:`PIXEL_MAPS`' keys)."""
        for key, _, _, _ in PIXEL_MAPS.values():
            self.maps[key][frame, lens, band] = lens_maps[key][band]

    def close(self) -> None:
        if self.ds.isopen():
            self.ds.close()


def apply_calibration(bundle_path, raw_paths, medium: str, out_path, grid_deg: float | None = None, *,
                      overwrite: bool = False, zenith_lens: str = ZENITH_LENS, config: dict | None = None,
                      pixels: bool = True, pixel_geometry: bool = True) -> Path:
    """Turn raw frames into radiance maps with the calibration bundle; write ``out_path`` (NetCDF).

    Each frame is decoded once. The sphere grid is always written; the per-pixel maps (radiance, uncertainties,
    flags and the geometry of every band pixel of both lenses) only with ``pixels``. The output is written to a
    temporary name and renamed. Each pixel's zenith angle and azimuth on the sphere are not stored (theta and phi
    by the output's ``sphere_convention``): :func:`sphere_directions` gives them.

    Parameters
    ----------
    bundle_path : str or pathlib.Path
        The calibration bundle.
    raw_paths : sequence of str or pathlib.Path
        The raw (DNG) frames.
    medium : str
        "air" or "water".
    out_path : str or pathlib.Path
        The NetCDF file to write.
    grid_deg : float, optional
        Cell size of the sphere grid, degree (default: ``apply.grid_deg``).
    overwrite : bool, default False
        Replace an existing ``out_path``.
    zenith_lens : str, default ZENITH_LENS
        The lens that looks at the zenith.
    config : dict, optional
        The configuration (default: the schema's defaults).
    pixels : bool, default True
        Write the per-pixel maps besides the sphere grid.
    pixel_geometry : bool, default True
        With the pixel maps, write the geometry maps (theta, phi, solid angle); False leaves them out and names
        them in the bundle (attribute ``pixel_geometry``, with the sha256 of the geometry artefacts they came
        from, ``geometry_sha256``).

    Returns
    -------
    pathlib.Path
        The file written (radiance in W m-2 sr-1 nm-1).

    Raises
    ------
    InputError
        When ``out_path`` exists without ``overwrite``, no frames are given, or a frame or the bundle is refused.
    """
    out_path = Path(out_path)
    if out_path.exists() and not overwrite:
        raise InputError(out_path, "exists; add --overwrite to replace it")
    raw_paths = [Path(p) for p in raw_paths]
    if not raw_paths:
        raise InputError(None, "no raw frames to apply the calibration to")
    bundle_path = Path(bundle_path)
    # two threads for two cores (a third would bin the three bands at once: more memory at the peak, no
    # core to run it on): the lenses' chains side by side (then the bands' binning), the decode of the next
    # frame (of the first while this thread reads the configuration and the bundle) and the pixels'
    # directions queued with them (numpy, rawpy and the NetCDF reads release the GIL)
    with ThreadPoolExecutor(max_workers=2) as pool:
        decoding = pool.submit(read_raw, raw_paths[0], checksums=False)
        try:
            # the schema's defaults are validated on the first call of a process (20 to 40 ms): beside the decode
            cfg = (config if config is not None else defaults())["apply"]
            grid_deg = float(cfg["grid_deg"] if grid_deg is None else grid_deg)
        except BaseException:
            decoding.cancel()
            raise
        return _apply_frames(pool, decoding, bundle_path, raw_paths, medium, out_path, grid_deg, cfg, zenith_lens,
                             pixels, pixel_geometry)


def _apply_frames(pool, decoding, bundle_path, raw_paths, medium, out_path, grid_deg, cfg, zenith_lens, pixels,
                  pixel_geometry=True):
    """:func:`apply_calibration` once the arguments are checked; ``decoding`` the future of the first frame."""
    with read_bundle(bundle_path, load=False) as on_disk:
        effects = model_effects(on_disk)
        if medium not in _media(on_disk):
            raise InputError(bundle_path, f"has no calibration for medium '{medium}' (media: {', '.join(_media(on_disk))})")
        if "pixel_factor" not in on_disk or str(on_disk["pixel_factor"].attrs.get("effects", "")) != factor_effects(
                effects):
            raise InputError(bundle_path, "has no per-pixel factors for its model's effects: rebuild the bundle")
        lenses = list(on_disk["lens"].values)
        if zenith_lens not in lenses:
            zenith_lens = lenses[0]
        # the bundle's sphere cells when made for this grid, zenith lens and block size; theta and phi then
        # only for the pixel maps
        block_rows = int(cfg["block_rows"])
        geometry = pixels and pixel_geometry
        cell_attrs = on_disk["sphere_cell_in_block"].attrs
        stored_cells = (np.isclose(float(cell_attrs.get("grid_deg", np.nan)), grid_deg)
                        and cell_attrs.get("zenith_lens") == zenith_lens
                        and int(cell_attrs.get("block_rows", -1)) == block_rows)
        # of the per-pixel maps only those of this medium that the chain needs (the compact factors, the
        # cells), the geometry only for the pixel maps (or cells on another grid); each read as one hyperslab
        # the frame-independent flags only for the pixel maps, the unlit corners (bias_drift) or cells on
        # another grid: the stored cells keep the flagged pixels off the grid and out of the negative-mean check
        flags = pixels or "bias_drift" in effects or not stored_cells
        names = ["pixel_factor", "pixel_systematic_relative_variance"] + (["pixel_flag"] if flags else []) \
            + [n for n in ("pixel_random_relative_variance",) if n in on_disk] \
            + (["sphere_cell_in_block", "sphere_block_first_cell", "sphere_block_n_cells", "sphere_block_columns",
                "sphere_cell_count", "sphere_checked_count"] if stored_cells else []) \
            + (["theta_deg", "phi_deg"] if geometry or not stored_cells else []) \
            + (["solid_angle_sr"] if geometry else [])
        at = {"medium": list(on_disk["medium"].values).index(medium)}
        # the per-pixel maps memory-mapped where stored contiguous (the chain touches the page cache's pages;
        # no copy into fresh memory), the others read through NetCDF
        mapped = mapped_variables(bundle_path, on_disk, [n for n in names if on_disk[n].dims[-2:] == ("y", "x")
                                                         or n == "sphere_cell_count"])
        maps = {}
        for name in names:
            var = on_disk[name].variable
            if name in mapped:
                var = xr.Variable(var.dims, mapped[name])
            var = var.isel({d: k for d, k in at.items() if d in var.dims})
            maps[name] = var.transpose("lens", "band", *(d for d in var.dims if d not in ("lens", "band"))).values
        # the small variables (parameters, scalars, per-band tables) loaded whole, at this medium
        bundle = on_disk.drop_vars([n for n, v in on_disk.data_vars.items() if {"y", "block", "sphere_cell"} & set(v.dims)]).sel(
            medium=[medium]).load()
    # the cell of every band pixel, once per lens and band (not per frame), beside the first frame's chain
    directions = pool.submit(_pixel_directions, maps, lenses, zenith_lens, grid_deg, block_rows)
    tmp = out_path.with_name(f".{out_path.name}.tmp")
    pixel_file = None
    try:
        if pixels:
            # the per-pixel maps' file made now: the geometry maps go into it while the first frame decodes
            # (_frames_into), each frame's maps band by band as the chains make them
            pixel_file = _PixelMapFile(tmp, len(raw_paths), lenses, maps["pixel_factor"].shape[-2:], geometry)
        return _frames_into(pool, decoding, raw_paths, bundle, bundle_path, maps, lenses, medium, effects, cfg,
                            grid_deg, zenith_lens, block_rows, directions, pixel_file, geometry, out_path, tmp)
    except BaseException:
        if pixel_file is not None:
            pixel_file.close()
        tmp.unlink(missing_ok=True)
        raise


def _frames_into(pool, decoding, raw_paths, bundle, bundle_path, maps, lenses, medium, effects, cfg, grid_deg,
                 zenith_lens, block_rows, directions, pixel_file, geometry, out_path, tmp) -> Path:
    """:func:`apply_calibration`'s frames through the chain into ``tmp`` (the pixel maps already in
    ``pixel_file`` when given), the sphere grid and the frames' tags after them; renamed to ``out_path``."""
    pixels = pixel_file is not None
    n_z, n_a = grid_shape(grid_deg)
    grid = {k: np.full((len(raw_paths), len(BANDS), n_z, n_a), np.nan) for k in ("mean", "spread", "random", "systematic")}
    count = np.zeros((len(raw_paths), len(BANDS), n_z, n_a), np.int32)
    meta = []
    rectilinear = [lens for lens in lenses if _projection(bundle, lens) == "rectilinear"]
    uncorrected = []   # (frame, lens) whose bias drift the model has and no optically black pixels measure
    # one frame's pixel maps per lens (only with pixels: the sphere grid is binned block by block), written
    # to the file once the lens is through the chain and used again for the next frame
    shape = (len(BANDS),) + maps["pixel_factor"].shape[-2:]
    lens_maps = [None] * len(lenses) if not pixels else [
        {"radiance": np.empty(shape, np.float32), "random": np.empty(shape, np.float32),
         "systematic": np.empty(shape, np.float32), "flags": np.empty(shape, np.uint8)} for _ in lenses]
    cells, counts = directions.result()
    # the geometry maps (one lens's map at a time) while the first frame decodes, the rest once its lenses'
    # chains are under way
    geometry_maps = [(key, i) for key in PIXEL_GEOMETRY for i in range(len(lenses))] if pixels and geometry else []
    while geometry_maps and not decoding.done():
        pixel_file.write_geometry(maps, *geometry_maps.pop(0))
    # what does not depend on the frame, once per call for every frame: each block's cells, the unlit corners
    negative_sigma = float(cfg["negative_mean_sigma"])
    corners = {lens: "bias_drift" in effects and lens not in rectilinear for lens in lenses}
    plans = [_lens_plans(maps, i, cells[i], corners[lens], block_rows, pixels) for i, lens in enumerate(lenses)]
    parameters = {}  # the chain's parameter objects per lens, band and frame setting
    for f, path in enumerate(raw_paths):
        raw = decoding.result()
        decoding = pool.submit(read_raw, raw_paths[f + 1], checksums=False) if f + 1 < len(raw_paths) else None
        check_frame(raw, bundle, effects)
        frame = mm.FrameSettings(exposure_s=float(raw.exposure_s), iso=float(raw.iso))
        sums = [_LensSums(n_z * n_a, counts[i]) for i in range(len(lenses))]
        # the lenses side by side (numpy releases the GIL in its array operations), each binning its own sums
        # each band's maps go to the file as soon as its lens's chain is through it, beside the chains (this
        # thread alone writes the file: the NetCDF library is not thread-safe); a chain that fails says so
        through = queue.SimpleQueue()
        jobs = [pool.submit(_lens_radiance, raw, bundle, lens, medium, effects, frame, negative_sigma, plans[i],
                            block_rows, sums[i], lens_maps[i], parameters,
                            (lambda j, i=i: through.put((i, j))) if pixels else None)
                for i, lens in enumerate(lenses)]
        for job in jobs:
            job.add_done_callback(lambda job: through.put(None) if job.exception() is not None else None)
        while geometry_maps:
            pixel_file.write_geometry(maps, *geometry_maps.pop(0))
        for _ in range(len(lenses) * len(BANDS) if pixels else 0):
            done = through.get()
            if done is None:
                break   # a lens's chain failed: raised below
            pixel_file.write_band(f, *done, lens_maps[done[0]])
        for job in jobs:
            job.result()
        meta.append((str(path), float(raw.exposure_s), float(raw.iso), raw.time.isoformat() if raw.time else ""))
        if "bias_drift" in effects:
            uncorrected += [(path.name, lens) for lens in rectilinear
                            if optical_black_level(raw, bundle, lens, BANDS[0]) is None]
        del raw
        for j in range(len(BANDS)):
            total = sums[0].bands[j]
            for other in sums[1:]:
                total.merge(other.bands[j])
            mean, spread, n, (rnd, sy) = total.result()
            grid["mean"][f, j], grid["spread"][f, j] = mean.reshape(n_z, n_a), spread.reshape(n_z, n_a)
            count[f, j] = n.reshape(n_z, n_a)
            grid["random"][f, j] = np.sqrt(rnd / np.where(n > 0, n, 1)).reshape(n_z, n_a)
            grid["systematic"][f, j] = sy.reshape(n_z, n_a)
    del lens_maps
    if pixels:
        pixel_file.close()
    ds = _sphere_grid_dataset(grid, count, meta, lenses, grid_deg)
    ds.attrs.update(_sphere_grid_attrs(bundle, bundle_path, lenses, medium, effects, grid_deg, zenith_lens, pixels,
                                       geometry, rectilinear, uncorrected))
    _write_sphere_grid(ds, cfg, tmp, out_path, pixels)
    return out_path


def _sphere_grid_dataset(grid: dict, count: np.ndarray, meta: list, lenses, grid_deg: float) -> xr.Dataset:
    """The frames' sphere grids (mean, spread, random and systematic sigma, count per frame, band and cell) and
    the frames' tags as a dataset, without its global attributes."""
    n_z, n_a = count.shape[-2:]
    rad_units = _RADIANCE_UNITS
    cell_dims = ("frame", "band", "zenith", "azimuth")
    return xr.Dataset(
        {
            "sphere_radiance": (cell_dims, grid["mean"],
                                _attrs("mean radiance of the unflagged pixels in the cell (NaN: no pixel)", rad_units)),
            "sphere_radiance_spread": (cell_dims, grid["spread"],
                                       _attrs("standard deviation of the pixel radiances in the cell", rad_units)),
            "sphere_radiance_random_sigma": (cell_dims, grid["random"],
                                             _attrs("random standard uncertainty of the cell mean", rad_units)),
            "sphere_radiance_systematic_sigma": (cell_dims, grid["systematic"],
                                                 _attrs("systematic standard uncertainty of the cell mean", rad_units)),
            "sphere_count": (cell_dims, count, _attrs("pixels binned into the cell", "1")),
            "frame_file": ("frame", np.array([m[0] for m in meta], dtype=str), {"long_name": "raw frame"}),
            "exposure_s": ("frame", np.array([m[1] for m in meta]), _attrs("exposure time (tag)", "s")),
            "iso": ("frame", np.array([m[2] for m in meta]), _attrs("ISO speed (tag)", "1")),
            "frame_time": ("frame", np.array([m[3] for m in meta], dtype=str), {"long_name": "DateTimeOriginal (tag)"}),
        },
        coords={
            "frame": np.arange(len(meta)), "lens": lenses, "band": list(BANDS),
            "zenith": ("zenith", (np.arange(n_z) + 0.5) * grid_deg, _attrs("zenith angle of the cell centre", "degree")),
            "azimuth": ("azimuth", (np.arange(n_a) + 0.5) * grid_deg, _attrs("azimuth of the cell centre", "degree")),
        },
    )


def _sphere_grid_attrs(bundle, bundle_path, lenses, medium, effects, grid_deg, zenith_lens, pixels, geometry,
                       rectilinear, uncorrected) -> dict:
    """The global attributes of :func:`apply_calibration`'s file: the calibration it used, the sphere's
    convention, the uncertainty's terms, where the pixel geometry is, and how each lens's black level was had."""
    attrs = {
        "Conventions": "CF-1.10", "title": "spectral radiance from raw frames (Larouche et al. 2024, inverse of Eq. 4)",
        "medium": medium, "grid_deg": grid_deg, "sphere_convention": SPHERE_CONVENTION.format(zenith=zenith_lens),
        "zenith_lens": zenith_lens, "pixel_maps": int(pixels),
        "calibration_bundle": str(bundle_path), "calibration_created": bundle.attrs.get("created", ""),
        "camera_serial": bundle.attrs.get("camera_serial", ""), "model_effects": ",".join(effects),
        "uncertainty": "random: shot, read and dark noise of each pixel and frame, and the flat field's noise "
                       "(or PRNU where unmeasured) of each pixel; systematic: dark model, shutter offset, ISO gain, "
                       "nonlinearity, roll-off (and its azimuthal term), immersion factor and R^-1, common to a band",
    }
    if pixels:
        attrs["pixel_map_precision"] = (
            "radiance and its sigmas float32 (the chain runs in float32; against float64 on the full-resolution "
            "benchmark frame the radiance differs by at most 2.4e-5 of its random sigma); geometry float32 as "
            "in the calibration bundle; the sphere grid float64")
    if pixels and geometry:
        # zenith and azimuth are theta and phi by the convention (one subtraction and sign): not written twice
        attrs["sphere_directions"] = (
            "zenith and azimuth of each band pixel follow from theta_deg and phi_deg by sphere_convention "
            "(pipeline.bundle.apply.sphere_directions(ds)); not stored, as they hold no more than theta and phi")
    if pixels and not geometry:
        # the geometry maps stay in the bundle: named there, with the hashes of the artefacts they came from
        attrs["pixel_geometry"] = (
            f"not in this file: theta_deg, phi_deg and solid_angle_sr of every band pixel are the calibration "
            f"bundle's (dims lens, medium, band, y, x) at medium '{medium}', the same y, x as the pixel maps; "
            "zenith and azimuth follow from theta and phi by sphere_convention")
        attrs["geometry_sha256"] = str(bundle.attrs.get("geometry_sha256", "{}"))
    attrs["black_level"] = "; ".join(
        f"{lens}: " + ("the dark model's bias (bias_drift not in the model)" if "bias_drift" not in effects
                       else "each frame's optically black pixels" if lens in rectilinear
                       else "each frame's unlit corners") for lens in lenses)
    if uncorrected:
        attrs["bias_drift_note"] = (
            "bias drift not corrected (the dark model's bias used) for "
            + ", ".join(f"{name} lens {lens}" for name, lens in uncorrected)
            + ": the frame declares no optically black pixels (DNG ActiveArea/MaskedAreas) or the calibration "
              "has no optical_black_offset_dn")
    return attrs


def _write_sphere_grid(ds: xr.Dataset, cfg: dict, tmp: Path, out_path: Path, pixels: bool) -> None:
    """The sphere grid into ``tmp`` (beside the pixel maps already there, or a new file), then renamed to
    ``out_path``."""
    # the sphere grid: uncompressed by default (zlib level 1 with the byte shuffle: a smaller file for more CPU,
    # measured in docs/performance.md); apply.sphere_zlib_level > 0 compresses it, with the shuffle
    level = int(cfg["sphere_zlib_level"])
    big = {name: ({"zlib": True, "complevel": level, "shuffle": True} if level else {"zlib": False})
           for name, var in ds.data_vars.items() if var.dtype.kind in "fiu" and var.size > 1024}
    # beside the pixel maps already written (_PixelMapFile), or a new file with the sphere grid only
    tmp.parent.mkdir(parents=True, exist_ok=True)
    _write_unfilled(encode_units(ds), tmp, big, mode="a" if pixels else "w")
    os.replace(tmp, out_path)


def _write_unfilled(ds: xr.Dataset, path: Path, encoding: dict, mode: str = "w") -> None:
    """``ds.to_netcdf(path, mode, engine="netcdf4", encoding=encoding)`` with the NetCDF fill mode off.

    In fill mode (the library's default, which ``to_netcdf`` keeps) the HDF5 layer writes the fill value
    into every contiguous variable when it is created and the data over it after: every byte of the pixel
    maps went into the page cache twice (1,196 MB for a 598 MB file at the full resolution). Every variable
    here is written whole, so no fill is needed; the file and what xarray reads from it are the same.
    """
    store = xr.backends.NetCDF4DataStore.open(str(path), mode=mode, format="NETCDF4")
    try:
        store.ds.set_fill_off()
        ds.dump_to_store(store, encoding=encoding)
    finally:
        store.close()


# --------------------------------------------------------------------------- command line
def apply_command(args) -> int:
    """Run ``apply`` from parsed arguments; bad input prints one line and returns 1.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments of ``apply``.

    Returns
    -------
    int
        The exit status: 0 on success, 1 on bad input.
    """
    try:
        out = apply_calibration(args.calibration, args.raw, args.medium, args.out, args.grid_deg,
                                overwrite=args.overwrite, pixels=args.pixels,
                                pixel_geometry=getattr(args, "pixel_geometry", True))
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"radiance: {out}")
    return 0
