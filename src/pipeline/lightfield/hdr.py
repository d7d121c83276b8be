"""High dynamic range from exposure brackets: frames of one scene at several exposures merged per pixel and cell.

A natural scene spans five or six decades of radiance (the sun-adjacent sky
against dim directions), more than one exposure holds between its noise and
its saturation. A bracket is the frames of one scene at several exposures,
the camera still. Each frame goes through the measurement chain at its own
exposure (:class:`pipeline.bundle.apply.BandChain`); per band pixel the merged
radiance is the inverse-variance mean of the exposures where the pixel is
unsaturated and unflagged,

    L = sum_k w_k L_k / sum_k w_k,      w_k = 1 / (r_k^2 + e_k^2),

with r_k the pixel's independent random sigma in exposure k (shot, read and
dark noise) and e_k the systematic sigma of the terms that differ between
exposures (:data:`EXPOSURE_TERMS`: the shutter offset's relative error
sigma_dt / (t + dt), the nonlinearity's at the pixel's signal, the dark
model's offset over the exposure, the frame's own black level). Their
uncertainty goes forward by kind:

- random: sqrt(sum_k w_k^2 r_k^2) / sum_k w_k (independent between exposures
  and pixels: averages down);
- per exposure: e_k w_k / sum_k w_k, one term per exposure k, each common to
  every pixel of that frame and independent of the other exposures' (kept
  apart, so that the integrals carry each as one shared deviation);
- band-common (R^-1, roll-off, immersion factor, the ISO gain at the
  bracket's ISO): sum_k w_k c_k / sum_k w_k, the same deviation in every
  exposure, so a weighted mean of sigmas and not averaged down;
- fixed pattern (the flat field's noise, ``prnu``): the same pixel in every
  exposure, so again a weighted mean of sigmas, independent between pixels.

A pixel saturated in every exposure has no measurement; it is flagged and
gives a lower bound: the largest over the exposures of the chain's radiance of
its clipped reading (a clipped reading is below the light that would have
been read). On the sphere grid a cell is the mean of its merged pixels, as
``apply`` bins one frame (random: root sum of squares over the count; the
per-exposure and common terms: the mean of the pixels' sigmas, fully
correlated); a cell holding a pixel saturated in every exposure is flagged,
and its value (its merged pixels and the bounds of the saturated ones) is a
lower bound.

Dynamic range: the decades between the brightest unsaturated cell (or pixel)
and the faintest above its limit of detection (radiance at least
``lightfield.hdr_detection_snr`` times its random sigma).

Brackets: a frames table (CSV, columns ``file`` and ``bracket``; ``file`` the
raw file's name or its path relative to the table) names each frame's
bracket; without one, frames are grouped by time: sorted by their
DateTimeOriginal, a frame more than ``lightfield.bracket_window_s`` after its
bracket's first frame starts a new bracket.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.bundle.apply import BandChain
from pipeline.io.bands import BANDS
from pipeline.errors import InputError
from pipeline.io.frames import lens_images
from pipeline.geometry.sphere import grid_shape, sphere_cells, sphere_coordinates
from pipeline.radiometry import measurement as mm
from pipeline.radiometry.exposure import gain_from_iso

__all__ = ["EXPOSURE_TERMS", "FIXED_PATTERN_TERMS", "FLAG_SATURATED_EVERYWHERE", "Bracket", "read_frames_table",
           "group_brackets", "ExposureMaps", "exposure_maps", "split_lens", "Merged", "merge_exposures",
           "SphereMerged", "SphereBins", "merged_on_sphere", "pixel_sphere_cells", "dynamic_range"]

#: systematic terms of the chain that differ between the exposures of a bracket (independent between them)
EXPOSURE_TERMS = frozenset({"shutter_offset", "nonlinearity", "dark_model", "bias_drift"})
#: random terms fixed to a pixel (the same in every exposure)
FIXED_PATTERN_TERMS = frozenset({"prnu"})
#: flags that keep a pixel out of the merge in every exposure
_OFF = mm.FLAG_OUTSIDE_IMAGE_CIRCLE | mm.FLAG_BEYOND_CALIBRATED_ANGLE | mm.FLAG_HOT
#: sphere cell flag of the merged map: a pixel of the cell saturated in every exposure (the value a lower bound)
FLAG_SATURATED_EVERYWHERE = 4


@dataclass
class Bracket:
    """The frames of one scene at several exposures (indices into the caller's list, by exposure)."""

    name: str
    frames: list


def read_frames_table(path) -> dict[str, str]:
    """The frames table: {file name: bracket}; bad input: one line naming the file.

    Parameters
    ----------
    path : str or pathlib.Path
        The frames table (CSV, columns ``file`` and ``bracket``).

    Returns
    -------
    dict[str, str]
        The bracket of each raw file's name.

    Raises
    ------
    InputError
        When the file cannot be read, lacks a column, has an empty entry, or lists a file in two brackets.
    """
    path = Path(path)
    try:
        table = pd.read_csv(path, dtype=str, keep_default_na=False)
    except (OSError, ValueError, pd.errors.ParserError) as exc:
        raise InputError(path, f"cannot read the frames table as CSV ({exc.__class__.__name__})") from None
    missing = [c for c in ("file", "bracket") if c not in table.columns]
    if missing:
        raise InputError(path, f"frames table lacks the column(s) {', '.join(missing)} (needs file, bracket)")
    out = {}
    for i, (file, bracket) in enumerate(zip(table["file"], table["bracket"])):
        if not file.strip() or not bracket.strip():
            raise InputError(path, f"line {i + 2}: empty file or bracket")
        name = Path(file.strip()).name
        if name in out and out[name] != bracket.strip():
            raise InputError(path, f"line {i + 2}: {name} is listed in two brackets")
        out[name] = bracket.strip()
    return out


def group_brackets(frames, table: dict[str, str] | None = None, window_s: float = 5.0, source=None) -> list[Bracket]:
    """Group decoded frames (``path``, ``exposure_s``, ``time``, ``make``, ``model``, ``serial``, ``iso``)
    into brackets by the frames table or, without one, by time; each bracket's frames by exposure.

    One line for a frame the table does not list, a frame without a time (no table), a bracket with one
    exposure only, or a bracket mixing cameras.

    Parameters
    ----------
    frames : sequence
        The decoded frames (with ``path``, ``exposure_s`` in s, ``time``, ``make``, ``model``, ``serial``, ``iso``).
    table : dict[str, str], optional
        The frames table (:func:`read_frames_table`); grouping by time when None.
    window_s : float, default 5.0
        Without a table, a frame more than this many seconds after its bracket's first frame starts a new one.
    source : str or pathlib.Path, optional
        The frames table's path, named in the error messages.

    Returns
    -------
    list of Bracket
        The brackets, each its frames' indices by exposure.

    Raises
    ------
    InputError
        For a frame the table does not list, a frame without a time (no table), a bracket with one exposure only,
        or a bracket mixing cameras.
    """
    groups: dict[str, list[int]] = {}
    if table is not None:
        for i, f in enumerate(frames):
            name = Path(f.path).name
            if name not in table:
                raise InputError(source, f"the frames table does not list {name}")
            groups.setdefault(table[name], []).append(i)
    else:
        order = []
        for i, f in enumerate(frames):
            if f.time is None:
                raise InputError(f.path, "has no DateTimeOriginal: give a frames table (--frames) to bracket it")
            order.append((f.time, i))
        order.sort()
        start = None
        for when, i in order:
            if start is None or (when - start).total_seconds() > window_s:
                start = when
                groups[f"bracket-{len(groups) + 1:03d}"] = []
            groups[list(groups)[-1]].append(i)
    out = []
    for name, members in groups.items():
        cams = {(frames[i].make, frames[i].model, frames[i].serial) for i in members}
        if len(cams) > 1:
            raise InputError(frames[members[0]].path, f"bracket {name} mixes cameras "
                             f"({'; '.join(' '.join(str(x) for x in c) for c in sorted(cams, key=str))})")
        exposures = {round(float(frames[i].exposure_s), 12) for i in members}
        if len(exposures) < 2:
            raise InputError(frames[members[0]].path, f"bracket {name} has one exposure only "
                             f"({len(members)} frame(s) at {float(frames[members[0]].exposure_s):g} s): "
                             "an HDR merge needs at least two")
        out.append(Bracket(name, sorted(members, key=lambda i: (float(frames[i].exposure_s), i))))
    return out


@dataclass
class ExposureMaps:
    """One frame through the chain: per (lens, band, y, x) the radiance and its sigmas by kind, the DN
    signal above dark, and which pixels are usable (in the calibrated field, not hot) and saturated."""

    file: str
    exposure_s: float
    iso: float
    radiance: np.ndarray
    random_sigma: np.ndarray       # independent: shot, read, dark noise
    fixed_sigma: np.ndarray        # fixed to the pixel in every exposure (FIXED_PATTERN_TERMS)
    exposure_sigma: np.ndarray     # EXPOSURE_TERMS
    common_sigma: np.ndarray       # the other systematic terms (common to the bracket's exposures)
    signal_dn: np.ndarray          # DN above the dark level (before linearisation)
    usable: np.ndarray
    saturated: np.ndarray
    #: (lens, band): the noise model of a band pixel's signal s (DN above dark): variance read_var_dn2 +
    #: shot_dn * s (read noise and offset pattern; electrons' Poisson noise through the conversion gain)
    read_var_dn2: np.ndarray | None = None
    shot_dn: np.ndarray | None = None

    def predicted_snr(self, radiance) -> np.ndarray:
        """The signal-to-noise ratio this exposure would read for ``radiance`` (lens, band, y, x) by its noise
        model, the pixel's DN per radiance taken from the frame (a property of the chain, not of the noise).

        Parameters
        ----------
        radiance : numpy.ndarray
            Radiance, W m-2 sr-1 nm-1, shape ``(lens, band, y, x)``.

        Returns
        -------
        numpy.ndarray
            The predicted signal-to-noise ratio, of the same shape.
        """
        with np.errstate(invalid="ignore", divide="ignore"):
            per = self.signal_dn / self.radiance
            s = np.asarray(radiance) * per
            return s / np.sqrt(self.read_var_dn2[..., None, None] + self.shot_dn[..., None, None] * np.clip(s, 0, None))


def _sum(terms: dict, names, keep: bool, shape) -> np.ndarray:
    total = np.zeros(shape)
    for k, v in terms.items():
        if (k in names) == keep:
            total = total + np.asarray(v, float)
    return np.broadcast_to(total, shape)


def split_lens(raw, bundle, lens: str):
    """The band images of one lens of a decoded frame (:func:`pipeline.io.frames.lens_images`).

    Parameters
    ----------
    raw : RawFrame
        The decoded frame.
    bundle : xarray.Dataset
        The calibration bundle (its ``lens_region_px``).
    lens : str
        The lens.

    Returns
    -------
    LensImages
        The lens's band images.
    """
    span = bundle["lens_region_px"].sel(lens=lens).values
    return lens_images(raw, (tuple(span[0]), tuple(span[1])), lens)


def exposure_maps(raw, bundle, chains: dict, lenses, medium: str, effects, bands=BANDS, images: dict | None = None,
                  exposure_terms=EXPOSURE_TERMS) -> ExposureMaps:
    """A decoded frame through the chain of each of ``lenses`` and ``bands`` (``chains[(lens, band)]``:
    :class:`BandChain`); ``images`` {lens: band images} when already split (:func:`split_lens`).
    ``exposure_terms``: the systematic terms that differ between the bracket's exposures (a bracket at
    several ISOs adds ``iso_gain``). The maps are float32 (the chain's precision), the sigmas' sums in float64.

    Parameters
    ----------
    raw : RawFrame
        The decoded frame.
    bundle : xarray.Dataset
        The calibration bundle.
    chains : dict
        ``{(lens, band): BandChain}``.
    lenses : sequence of str
        The lenses.
    medium : str
        "air" or "water".
    effects : collection of str
        The effects the chain applies (unused here: each chain holds its own).
    bands : sequence of str, default BANDS
        The bands.
    images : dict, optional
        ``{lens: LensImages}`` already split.
    exposure_terms : frozenset of str, default EXPOSURE_TERMS
        The systematic terms that differ between the bracket's exposures.

    Returns
    -------
    ExposureMaps
        Per (lens, band, y, x) the radiance (W m-2 sr-1 nm-1) and its sigmas by kind, the signal (DN above dark), the usable
        and saturated masks; per (lens, band) the noise model (DN^2, DN).
    """
    frame = mm.FrameSettings(exposure_s=float(raw.exposure_s), iso=float(raw.iso))
    arrays = {k: [] for k in ("radiance", "random", "fixed", "exposure", "common", "signal", "usable", "saturated",
                              "read", "shot")}
    for lens in lenses:
        lens_bands = images[lens] if images is not None and lens in images else split_lens(raw, bundle, lens)
        per = {k: [] for k in arrays}
        for band in bands:
            chain: BandChain = chains[(lens, band)]
            m = chain(lens_bands, frame, source=raw.path)
            value = np.asarray(m.value, np.float32)
            shape = value.shape
            rnd, sy = m.random_var, m.systematic_var
            per["radiance"].append(value)
            per["random"].append(np.sqrt(_sum(rnd, FIXED_PATTERN_TERMS, False, shape)).astype(np.float32))
            per["fixed"].append(np.sqrt(_sum(rnd, FIXED_PATTERN_TERMS, True, shape)).astype(np.float32))
            per["exposure"].append(np.sqrt(_sum(sy, exposure_terms, True, shape)).astype(np.float32))
            per["common"].append(np.sqrt(_sum(sy, exposure_terms, False, shape)).astype(np.float32))
            dark, response, _ = chain.parameters(frame)
            factor = response.iso_gain_factor if "iso_gain" in chain.effects else 1.0
            per["read"].append(np.float64(dark.read_noise_dn ** 2 / dark.sites_per_pixel + dark.offset_pattern_dn ** 2))
            per["shot"].append(np.float64(response.conversion_gain_dn_per_e * gain_from_iso(frame.iso) * factor
                                          / dark.sites_per_pixel))
            unlit = lens_bands.bands[band][chain.unlit_corners()] if "bias_drift" in chain.effects else None
            per["signal"].append(np.asarray(mm.subtract_dark(mm.from_raw(lens_bands.bands[band]), dark, frame,
                                                             chain.effects, unlit).value, np.float32))
            flags = m.flags
            per["usable"].append(((flags & _OFF) == 0) & np.isfinite(chain.g["theta_deg"].values))
            per["saturated"].append((flags & mm.FLAG_SATURATED) != 0)
        for k in arrays:
            arrays[k].append(np.stack(per[k]))
    a = {k: np.stack(v) for k, v in arrays.items()}
    return ExposureMaps(str(raw.path), float(raw.exposure_s), float(raw.iso), a["radiance"], a["random"], a["fixed"],
                        a["exposure"], a["common"], a["signal"], a["usable"], a["saturated"], a["read"], a["shot"])


@dataclass
class Merged:
    """The merged pixel maps of one bracket, (lens, band, y, x); ``exposure_sigma`` (exposure, lens, band, y, x)."""

    radiance: np.ndarray            # NaN where no exposure measured the pixel
    random_sigma: np.ndarray
    fixed_sigma: np.ndarray
    exposure_sigma: np.ndarray
    common_sigma: np.ndarray
    n_exposures: np.ndarray         # exposures merged in the pixel
    saturated_everywhere: np.ndarray
    lower_bound: np.ndarray         # NaN but where saturated everywhere
    usable: np.ndarray


def _weight(m: ExposureMaps, usable: np.ndarray) -> np.ndarray:
    """w = 1 / (r^2 + e^2) where the exposure measured the pixel (usable, unsaturated, finite), else 0 (float64)."""
    var = np.square(m.random_sigma, dtype=float) + np.square(m.exposure_sigma, dtype=float)
    valid = usable & ~m.saturated & np.isfinite(m.radiance) & np.isfinite(var) & (var > 0)
    return np.where(valid, 1.0 / np.where(valid, var, 1.0), 0.0)


def merge_exposures(maps: list[ExposureMaps]) -> Merged:
    """Inverse-variance mean per pixel of the unsaturated, usable measurements (module docstring).

    Running sums over the exposures (two passes: the weights' total first), so that the memory is a few
    maps of one lens and band whatever the number of exposures.

    Parameters
    ----------
    maps : list of ExposureMaps
        The bracket's frames through the chain.

    Returns
    -------
    Merged
        The merged radiance (W m-2 sr-1 nm-1) and its sigmas by kind, per (lens, band, y, x), the number of exposures
        merged, the pixels saturated everywhere and their lower bounds.
    """
    usable = np.logical_and.reduce([m.usable for m in maps])
    shape = np.shape(maps[0].radiance)
    W = np.zeros(shape)
    for m in maps:
        W += _weight(m, usable)
    has = W > 0
    Wd = np.where(has, W, 1.0)
    sums = {name: np.zeros(shape) for name in ("radiance", "random", "fixed", "common")}
    exposure = np.zeros((len(maps),) + shape, np.float32)
    n_used = np.zeros(shape, np.int32)
    everywhere = usable.copy()
    bound = np.full(shape, -np.inf)
    for k, m in enumerate(maps):
        w = _weight(m, usable)
        used = w > 0
        n_used += used
        sums["radiance"] += w * np.where(used, m.radiance, 0.0)
        sums["random"] += np.square(w * np.where(used, m.random_sigma, 0.0))
        sums["fixed"] += w * np.where(used, m.fixed_sigma, 0.0)
        sums["common"] += w * np.where(used, m.common_sigma, 0.0)
        exposure[k] = w * np.where(used, m.exposure_sigma, 0.0) / Wd
        everywhere &= m.saturated
        bound = np.fmax(bound, np.where(m.saturated & np.isfinite(m.radiance), m.radiance, -np.inf))
    radiance = np.where(has, sums["radiance"] / Wd, np.nan)
    random_sigma = np.where(has, np.sqrt(sums["random"]) / Wd, np.nan)
    fixed = np.where(has, sums["fixed"] / Wd, np.nan)
    common = np.where(has, sums["common"] / Wd, np.nan)
    bound = np.where(everywhere & np.isfinite(bound), bound, np.nan)
    return Merged(radiance, random_sigma, fixed, exposure, common, n_used, everywhere, bound, usable)


@dataclass
class SphereMerged:
    """One bracket's merged map on the sphere grid, per (band, zenith, azimuth); ``exposure_sigma`` with
    the exposures first: (exposure, band, zenith, azimuth)."""

    radiance: np.ndarray
    random_sigma: np.ndarray
    exposure_sigma: np.ndarray
    common_sigma: np.ndarray
    count: np.ndarray
    flag: np.ndarray                # FLAG_SATURATED_EVERYWHERE or 0
    lower_bound: np.ndarray         # the cell's value where flagged (a lower bound), else NaN


def pixel_sphere_cells(bundle, lenses, medium: str, zenith_lens: str, grid_deg: float) -> np.ndarray:
    """(lens, band, y, x) sphere cell of every band pixel (-1 without a direction), by apply's convention.

    Parameters
    ----------
    bundle : xarray.Dataset
        The calibration bundle (its ``theta_deg`` and ``phi_deg`` maps).
    lenses : sequence of str
        The lenses.
    medium : str
        "air" or "water".
    zenith_lens : str
        The lens that looks at the zenith.
    grid_deg : float
        Cell size of the sphere grid, degree.

    Returns
    -------
    numpy.ndarray
        Cell index (int32), shape ``(lens, band, y, x)`` over R, G, B.
    """
    out = []
    for lens in lenses:
        per = []
        for band in BANDS:
            g = bundle.sel(lens=lens, medium=medium, band=band)
            z, a = sphere_coordinates(np.asarray(g["theta_deg"].values, float), np.asarray(g["phi_deg"].values, float),
                                      lens == zenith_lens)
            per.append(sphere_cells(z, a, grid_deg).reshape(np.shape(z)))
        out.append(np.stack(per))
    return np.stack(out)


class SphereBins:
    """Running per-cell sums of merged pixels, added a lens and band at a time (:func:`merged_on_sphere`)."""

    def __init__(self, n_bands: int, n_exposures: int, grid_deg: float):
        self.shape = grid_shape(grid_deg)
        n = self.shape[0] * self.shape[1]
        self.n = n
        self.sums = {name: np.zeros((n_bands, n)) for name in ("value", "random_var", "common")}
        self.exposure = np.zeros((n_exposures, n_bands, n))
        self.count = np.zeros((n_bands, n), np.int64)
        self.saturated = np.zeros((n_bands, n), np.int64)

    def add(self, merged: Merged, cells: np.ndarray, band_indices) -> None:
        """Add merged maps (lens, band, y, x) whose band axis holds the bands ``band_indices``; ``cells`` the
        sphere cell of each of their pixels (:func:`pixel_sphere_cells`, the same lens and band axes).

        Parameters
        ----------
        merged : Merged
            Merged maps, shape ``(lens, band, y, x)``.
        cells : numpy.ndarray
            The sphere cell of each pixel, same lens and band axes.
        band_indices : sequence of int
            The bins' band of each of the maps' bands.
        """
        n = self.n
        for j, b in enumerate(band_indices):
            c = cells[:, j].ravel()
            value = merged.radiance[:, j].ravel().astype(float)
            bound = merged.lower_bound[:, j].ravel().astype(float)
            good = merged.usable[:, j].ravel() & np.isfinite(value) & (c >= 0)
            sat = merged.saturated_everywhere[:, j].ravel() & np.isfinite(bound) & (c >= 0)
            used = good | sat
            v = np.where(good, value, np.where(sat, bound, 0.0))
            self.count[b] += np.bincount(c[used], minlength=n)
            self.saturated[b] += np.bincount(c[sat], minlength=n)
            self.sums["value"][b] += np.bincount(c[used], v[used], n)
            var = merged.random_sigma[:, j].ravel().astype(float) ** 2 + merged.fixed_sigma[:, j].ravel().astype(
                float) ** 2
            self.sums["random_var"][b] += np.bincount(c[good], var[good], n)
            self.sums["common"][b] += np.bincount(c[good], merged.common_sigma[:, j].ravel()[good].astype(float), n)
            for k in range(self.exposure.shape[0]):
                self.exposure[k, b] += np.bincount(c[good], merged.exposure_sigma[k, :, j].ravel()[good].astype(float),
                                                   n)

    def result(self) -> SphereMerged:
        """The bracket's merged map on the sphere: the cells' means and their sigmas.

        Returns
        -------
        SphereMerged
            Per (band, zenith, azimuth) the mean radiance (W m-2 sr-1 nm-1; NaN in an empty cell), its sigmas by kind, the
            count, the flag and the lower bound.
        """
        has = self.count > 0
        d = np.where(has, self.count, 1)
        radiance = np.where(has, self.sums["value"] / d, np.nan)
        flag = np.where(self.saturated > 0, FLAG_SATURATED_EVERYWHERE, 0).astype(np.int8)
        n_b = radiance.shape[0]
        shape = (n_b,) + self.shape
        return SphereMerged(radiance.reshape(shape), np.where(has, np.sqrt(self.sums["random_var"]) / d,
                                                               np.nan).reshape(shape),
                            (self.exposure / d[None]).reshape((self.exposure.shape[0],) + shape),
                            np.where(has, self.sums["common"] / d, np.nan).reshape(shape),
                            self.count.astype(np.int32).reshape(shape), flag.reshape(shape),
                            np.where(self.saturated > 0, radiance, np.nan).reshape(shape))


def merged_on_sphere(merged: Merged, cells: np.ndarray, grid_deg: float) -> SphereMerged:
    """Bin the merged pixels (lens, band, y, x; every band) onto the sphere grid (module docstring), both
    lenses together, per band.

    Parameters
    ----------
    merged : Merged
        The merged pixel maps, shape ``(lens, band, y, x)``, every band.
    cells : numpy.ndarray
        The sphere cell of each pixel (:func:`pixel_sphere_cells`).
    grid_deg : float
        Cell size, degree.

    Returns
    -------
    SphereMerged
        The merged map on the sphere grid (W m-2 sr-1 nm-1).
    """
    bins = SphereBins(merged.radiance.shape[1], merged.exposure_sigma.shape[0], grid_deg)
    bins.add(merged, cells, range(merged.radiance.shape[1]))
    return bins.result()


def dynamic_range(radiance, random_sigma, detection_snr: float, exclude=None) -> tuple[float, int, int]:
    """Decades between the brightest value and the faintest above its limit of detection.

    Parameters
    ----------
    radiance : numpy.ndarray
        Radiance (cells or pixels), W m-2 sr-1 nm-1.
    random_sigma : numpy.ndarray
        Its random standard uncertainty, same unit and shape.
    detection_snr : float
        A value is detected when it is at least this many random sigmas.
    exclude : numpy.ndarray, optional
        Boolean, same shape: values kept out (lower bounds).

    Returns
    -------
    decades : float
        log10 of the brightest over the faintest detected value; NaN when none is detected.
    brightest : int
        Flat index of the brightest, -1 when none.
    faintest : int
        Flat index of the faintest, -1 when none.
    """
    L = np.asarray(radiance, float).ravel()
    s = np.asarray(random_sigma, float).ravel()
    ok = np.isfinite(L) & np.isfinite(s) & (L > 0) & (L >= detection_snr * s)
    if exclude is not None:
        ok &= ~np.asarray(exclude, bool).ravel()
    if not ok.any():
        return float("nan"), -1, -1
    idx = np.flatnonzero(ok)
    hi, lo = idx[np.argmax(L[idx])], idx[np.argmin(L[idx])]
    return float(np.log10(L[hi] / L[lo])), int(hi), int(lo)
