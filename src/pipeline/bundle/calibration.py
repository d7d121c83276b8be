"""The calibration bundle: everything ``apply`` needs, gathered from the stage artefacts into one file.

One NetCDF file per camera (``results/calibration/<serial>.nc``) with a
``lens`` dimension, so that it opens in xarray as one Dataset: the dark model
and hot-pixel mask (Section 2.8), the linearity stage's conversion gain,
shutter offset, per-ISO gain factors, nonlinearity, saturation level and flat
field (Section 2.2), the geometry maps theta, phi and solid angle per medium
and band with the fitted model (Section 2.3) and the standard uncertainty of
theta per band pixel (``theta_deg_sigma``, from the fit's covariance), the roll-off with its
covariance and calibrated field angle (Section 2.4, Eq. 13), effective
wavelengths and responses (Section 2.5, Eq. 8), R^-1 with its budget
(Section 2.6, Eq. 9), the immersion factors (Section 2.7, Eq. 11), and the
noise-equivalent radiance and limit of detection (Section 3.8). It is a
versioned artefact (``artefact = calibration``, its version in :data:`pipeline.io.artefact.ARTEFACT_VERSIONS`,
what each version changed in docs/changelog.md; older files are refused with a line asking to
rebuild), which also holds the absolute experiment's signal setting and level
(``absolute_exposure_s``, ``absolute_iso``, ``absolute_signal_dn``), which the field scale closure
evaluates the missing response effects against, the sha256 of the lab's input files by experiment
(``lab_input_sha256``, which ``compare`` reads for the inputs two calibrations share), the read
noise's sampling uncertainty (``read_noise_dn_sigma``), and carries the sha256 of every artefact it came from,
the model's effects and the camera's make, model and serial number.

A rectilinear lens (dataset.yaml ``projection: rectilinear``; the geometry
stage's pinhole fit, :mod:`pipeline.stages.geometry_rectilinear`) brings the
same theta, phi, solid-angle and theta-sigma maps; it has no image circle (its
circle variables are NaN, the fisheye model's ``poly`` and stretch NaN too, and
no pixel is flagged outside the image circle), and its field ends where the
roll-off's measurements end (``calibrated_field_angle_deg``, the flag beyond
the calibrated field angle). A bundle may hold lenses of both kinds.

:func:`band_parameters` turns the bundle back into the small parameter
objects of :mod:`pipeline.radiometry.measurement`, so ``apply`` and the NER
use the same chain.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
import xarray as xr

from pipeline.io.artefact import BUNDLE_REQUIRED_STAGES, BUNDLE_STAGES, model_effects, read_artefact, sha256_file, write_artefact
from pipeline.io.bands import BANDS
from pipeline.config import defaults, stage_params
from pipeline.io.dataset import SIDECARS
from pipeline.effects.optics import AZIMUTH_THETA_REF_DEG
from pipeline.entry import exit_on_input_error, setup_log
from pipeline.errors import InputError
from pipeline.io.frames import SITES_PER_BAND_PIXEL
from pipeline.geometry.sphere import ZENITH_LENS, grid_shape, sphere_cells, sphere_coordinates
from pipeline.radiometry import measurement as mm
from pipeline.radiometry.dark import check_dark_iso

__all__ = ["BUNDLE_STAGES", "REQUIRED_STAGES", "STATIC_OFF_GRID", "FACTOR_EFFECTS", "factor_effects",
           "sphere_blocks", "sphere_counts", "build_bundle", "read_bundle", "band_parameters", "dark_parameters",
           "calibrated_isos", "outside_image_circle", "noise_equivalent_radiance", "build_bundle_script", "lab_inputs"]

#: stages a bundle is gathered from (in the order of the calibration chain) and those it cannot lack
BUNDLE_STAGES, REQUIRED_STAGES = BUNDLE_STAGES, BUNDLE_REQUIRED_STAGES
GEOMETRY_SCALARS = ("xc_px", "yc_px", "stretch_c", "stretch_d", "stretch_e", "half_fov_deg",
                    "circle_xc_px", "circle_yc_px", "circle_radius_px")


def _relative(path: Path, root: Path) -> str:
    try:
        return os.path.relpath(Path(path).resolve(), root.resolve())
    except ValueError:
        return str(path)


def _stack(per_lens: dict[str, xr.DataArray | xr.Dataset], lenses: list[str]):
    parts = [per_lens[lens] for lens in lenses]
    # a variable one kind of lens has and the other lacks (the fisheye model's poly and stretch for a
    # rectilinear lens): NaN of the same shape where it is missing
    for part in parts:
        for other in parts:
            for name in set(other.data_vars) - set(part.data_vars):
                part[name] = xr.full_like(other[name], np.nan, dtype=float)
    return xr.concat(parts, dim="lens", join="exact").assign_coords(lens=lenses)


def _dark_part(ds: xr.Dataset) -> xr.Dataset:
    keep = ["bias_dn", "bias_dn_sigma", "bias_per_gain_dn", "bias_per_gain_dn_sigma", "dark_current_dn_per_s",
            "dark_current_dn_per_s_sigma", "read_noise_dn", "hot_pixel_mask", "temperature_bias_dn_per_c",
            "temperature_dark_dn_per_s_per_c", "temperature_reference_c", "optical_black_offset_dn"]
    out = ds[[v for v in keep if v in ds]].drop_vars(["setting", "hist_bin"], errors="ignore")
    if "obs_setting__n_used" in ds:
        out["read_noise_dn_sigma"] = _read_noise_sigma(ds)
    out["offset_pattern_dn"] = ds["fpn_map_dn"].std(("y", "x")).assign_attrs(
        long_name="spatial spread of the pixel offsets about the dark model's level (ISO 100, shortest exposure)",
        units="DN")
    out["calibrated_exposure_s_min"] = ((), float(ds["setting_exposure_s"].min()),
                                        {"long_name": "shortest exposure of the dark model", "units": "s"})
    out["calibrated_exposure_s_max"] = ((), float(ds["setting_exposure_s"].max()),
                                        {"long_name": "longest exposure of the dark model", "units": "s"})
    return out.rename({"iso": "dark_iso"})


def _read_noise_sigma(ds: xr.Dataset) -> xr.DataArray:
    """Sampling uncertainty of the dark artefact's read noise (band, iso): the temporal variance of n_used
    pixels over n_frames frames has n_used (n_frames - 1) degrees of freedom, its square root a relative
    standard error 1 / sqrt(2 n_used (n_frames - 1)) (Gaussian noise); NaN where a setting has one frame."""
    read = ds["read_noise_dn"]
    sigma = np.full(read.shape, np.nan)
    band = ds["obs_setting__band"].values.astype(str)
    iso = ds["obs_setting__iso"].values.astype(float)
    exposure = ds["obs_setting__exposure_s"].values.astype(float)
    dof = ds["obs_setting__n_used"].values.astype(float) * (ds["obs_setting__n_frames"].values.astype(float) - 1.0)
    for i, b in enumerate(read["band"].values.astype(str)):
        for k, value in enumerate(read["iso"].values.astype(float)):
            rows = np.flatnonzero((band == b) & (iso == value))
            if rows.size:
                # read_noise_dn is the temporal noise of the iso's shortest exposure
                row = rows[np.argmin(exposure[rows])]
                if dof[row] > 0:
                    sigma[i, k] = float(read.values[i, k]) / np.sqrt(2.0 * dof[row])
    return xr.DataArray(sigma, dims=read.dims, coords=read.coords, attrs={
        "long_name": "standard error of read_noise_dn from its pixels and frames (Gaussian sampling)", "units": "DN"})


def lab_inputs(artefact_inputs: list[dict[str, str]]) -> dict[str, str]:
    """The lab files behind stage artefacts, from their input_sha256 dicts.

    The dataset's own files and the instrument sidecars are kept by name, and each experiment's raw frames (of all
    the artefacts) as one digest ``<experiment>/frames``, the sha256 of their sorted ``name sha256`` lines; upstream
    artefacts (``.nc``) are left out.

    Parameters
    ----------
    artefact_inputs : list of dict[str, str]
        Each artefact's ``input_sha256``: {input file relative to the dataset: sha256}.

    Returns
    -------
    dict[str, str]
        {file or ``<experiment>/frames``: sha256}, sorted by name.
    """
    sidecars = {f"{experiment}/{name}" for experiment, names in SIDECARS.items() for name in names}
    out, frames = {}, {}
    for inputs in artefact_inputs:
        for name, digest in inputs.items():
            if name.endswith(".nc"):
                continue
            if name in sidecars or "/" not in name:
                out[name] = digest
            else:
                frames.setdefault(name.split("/", 1)[0], set()).add(f"{name} {digest}")
    for experiment, lines in frames.items():
        out[f"{experiment}/frames"] = hashlib.sha256("\n".join(sorted(lines)).encode()).hexdigest()
    return dict(sorted(out.items()))


def _linearity_part(ds: xr.Dataset) -> xr.Dataset:
    out = xr.Dataset()
    for name in ("conversion_gain_dn_per_e", "conversion_gain_dn_per_e_sigma", "saturation_dn",
                 "nonlinearity_full_scale_dn"):
        if name in ds:
            out[name] = ds[name]
    scalar = {"shutter_offset": ("shutter_offset_s", "s"), "nonlinearity": ("nonlinearity_beta", "1")}
    for effect, (name, units) in scalar.items():
        if f"effect_{effect}" in ds:
            out[name] = ((), float(ds[f"effect_{effect}"].values[0]), {"long_name": f"fitted {effect}", "units": units})
            out[f"{name}_sigma"] = ((), float(ds[f"effect_{effect}_sigma"].values[0]), {"units": units})
    if "effect_iso_gain" in ds:
        isos = ds["effect_iso_gain_iso"].values.astype(float)
        out = out.assign_coords(gain_iso=("gain_iso", isos, {"long_name": "ISO of the fitted gain factor", "units": "1"}))
        out["iso_gain_factor"] = ("gain_iso", 1.0 + ds["effect_iso_gain"].values,
                                  {"long_name": "true gain over ISO/100 (1 at the lowest ISO)", "units": "1"})
        out["iso_gain_factor_sigma"] = ("gain_iso", ds["effect_iso_gain_sigma"].values, {"units": "1"})
    if "flat_field" in ds:
        out["flat_field"] = ds["flat_field"]
    if "flat_field_sigma" in ds:
        out["flat_field_sigma"] = ds["flat_field_sigma"]
    if "effect_prnu" in ds:
        # the linearity stage fits sigma_rel^2 (effects.catalogue.Prnu)
        out["prnu_sigma_rel"] = ((), float(np.sqrt(max(float(ds["effect_prnu"].values[0]), 0.0))),
                                 {"long_name": "pixel response non-uniformity, relative spread", "units": "1"})
    return out


def _geometry_part(ds: xr.Dataset) -> xr.Dataset:
    # theta_deg_sigma: the fit's theta uncertainty (geometry artefact 2); a geometry written from known optics
    # (tests) has none
    # a rectilinear lens (pinhole fit) has no fisheye polynomial nor stretch: _stack fills them with NaN
    # beside a fisheye lens
    sigma = ["theta_deg_sigma"] if "theta_deg_sigma" in ds else []
    return ds[[v for v in ("theta_deg", "phi_deg", "solid_angle_sr", "poly", *GEOMETRY_SCALARS, *sigma) if v in ds]]


def _rolloff_part(ds: xr.Dataset) -> xr.Dataset:
    out = ds[["rolloff_coefficients", "rolloff_covariance"]]
    kind = ds["obs_setting__kind"].values.astype(str)
    used = ds["obs_setting__used"].values.astype(bool)
    medium = ds["obs_setting__medium"].values.astype(str)
    theta = np.abs(ds["obs_setting__theta_deg"].values.astype(float))
    spots = [(kind == "spot") & used & (medium == m) for m in ds["medium"].values]
    reach = [float(np.nanmax(theta[s])) if np.any(s & np.isfinite(theta)) else np.nan for s in spots]
    out["calibrated_field_angle_deg"] = ("medium", np.array(reach),
                                         {"long_name": "largest field angle the roll-off was measured at", "units": "degree"})
    if "effect_rolloff_azimuth" in ds:
        # the polynomial is the even part; the odd term 1 + A (theta / theta_ref) cos(phi - phi0) goes with it
        for name, var, units in (("rolloff_azimuth_amplitude", "effect_rolloff_azimuth", "1"),
                                 ("rolloff_azimuth_phi0_deg", "effect_rolloff_azimuth_phi0_deg", "degree")):
            out[name] = ((), float(np.ravel(ds[var].values)[0]), {"long_name": f"fitted {var[7:]}", "units": units})
            out[f"{name}_sigma"] = ((), float(np.ravel(ds[f"{var}_sigma"].values)[0]), {"units": units})
    return out


def _spectral_part(ds: xr.Dataset) -> xr.Dataset:
    keep = ["effective_wavelength_nm", "effective_wavelength_nm_sigma", "bandwidth_nm", "half_bandwidth_nm", "response"]
    return ds[[v for v in keep if v in ds]]


def _absolute_part(ds: xr.Dataset) -> xr.Dataset:
    out = ds[["inverse_responsivity", "inverse_responsivity_sigma", "relative_sigma", "uncertainty_contribution",
              "exposure_s", "iso", "signal_dn"]]
    return out.rename({"relative_sigma": "inverse_responsivity_relative_sigma", "exposure_s": "absolute_exposure_s",
                       "iso": "absolute_iso", "signal_dn": "absolute_signal_dn"})


def _immersion_part(ds: xr.Dataset) -> xr.Dataset:
    return ds[["immersion_factor", "immersion_factor_sigma"]]


PARTS = {"dark": _dark_part, "linearity": _linearity_part, "geometry": _geometry_part, "rolloff": _rolloff_part,
         "spectral": _spectral_part, "absolute": _absolute_part, "immersion": _immersion_part}


def calibrated_isos(bundle: xr.Dataset, effects) -> np.ndarray:
    """ISOs a frame may have: those of the dark model, and with ``iso_gain`` only those with a gain factor.

    Parameters
    ----------
    bundle : xarray.Dataset
        The calibration bundle.
    effects : collection of str
        The effects of the bundle's model.

    Returns
    -------
    numpy.ndarray
        The ISOs (float).
    """
    isos = bundle["dark_iso"].values.astype(float)
    if "iso_gain" in effects and "gain_iso" in bundle.coords:
        allowed = set(bundle["gain_iso"].values.astype(float)) | {float(isos.min())}
        isos = np.array([i for i in isos if i in allowed])
    return isos


def _number(b: xr.Dataset, name: str, default: float = 0.0, **sel) -> float:
    """A scalar of the bundle's lens selection ``b`` (at ``sel``), or ``default`` when the bundle has none."""
    if name not in b:
        return default
    value = b[name].sel(**sel) if sel else b[name]
    return float(value)


def dark_parameters(bundle: xr.Dataset, lens: str, band: str, frame: mm.FrameSettings) -> mm.DarkModel:
    """The dark model of one lens and band at a frame's setting; one line when the bundle's dark model was
    measured at one ISO (no gain sweep) and the frame is at another.

    Parameters
    ----------
    bundle : xarray.Dataset
        The calibration bundle.
    lens : str
        The lens.
    band : str
        The band (R, G or B).
    frame : FrameSettings
        The frame's exposure time (s) and ISO.

    Returns
    -------
    DarkModel
        Bias (DN), dark current (DN s-1), their temperature terms, read noise and offset pattern (DN), with their
        sigmas.

    Raises
    ------
    InputError
        When the dark model was measured at one ISO and the frame is at another.
    """
    b = bundle.sel(lens=lens)

    def num(name, default=0.0, **sel):
        return _number(b, name, default, **sel)

    check_dark_iso(b, frame.iso, iso_coord="dark_iso")
    read = b["read_noise_dn"].sel(band=band).sel(dark_iso=frame.iso, method="nearest")
    return mm.DarkModel(
        bias_dn=num("bias_dn", band=band), bias_dn_sigma=num("bias_dn_sigma", band=band),
        bias_per_gain_dn=num("bias_per_gain_dn", band=band), bias_per_gain_dn_sigma=num("bias_per_gain_dn_sigma", band=band),
        dark_current_dn_per_s=num("dark_current_dn_per_s"), dark_current_dn_per_s_sigma=num("dark_current_dn_per_s_sigma"),
        temperature_bias_dn_per_c=num("temperature_bias_dn_per_c"),
        temperature_dark_dn_per_s_per_c=num("temperature_dark_dn_per_s_per_c"),
        temperature_reference_c=num("temperature_reference_c", float("nan")),
        read_noise_dn=float(read), offset_pattern_dn=num("offset_pattern_dn", band=band),
        sites_per_pixel=SITES_PER_BAND_PIXEL[band])


def band_parameters(bundle: xr.Dataset, lens: str, band: str, medium: str, frame: mm.FrameSettings,
                    effects) -> tuple[mm.DarkModel, mm.ResponseModel, mm.BandCalibration]:
    """The measurement chain's parameter objects for one lens, band, medium and frame setting.

    Parameters
    ----------
    bundle : xarray.Dataset
        The calibration bundle.
    lens : str
        The lens.
    band : str
        The band (R, G or B).
    medium : str
        "air" or "water".
    frame : FrameSettings
        The frame's exposure time (s) and ISO.
    effects : collection of str
        The effects of the bundle's model.

    Returns
    -------
    dark : DarkModel
        The dark model (:func:`dark_parameters`).
    response : ResponseModel
        Conversion gain (DN per electron), shutter offset (s), ISO gain factor, nonlinearity, full scale and
        saturation (DN), with their sigmas.
    calibration : BandCalibration
        Roll-off coefficients and covariance, calibrated field angle (degree), inverse responsivity R^-1
        (W m-2 sr-1 nm-1 per DN s-1) and its relative sigma, immersion factor (1 in air) and azimuthal roll-off.
    """
    b = bundle.sel(lens=lens)

    def num(name, default=0.0, **sel):
        return _number(b, name, default, **sel)

    dark = dark_parameters(bundle, lens, band, frame)
    factor, factor_sigma = 1.0, 0.0
    if "iso_gain_factor" in b and float(frame.iso) in set(b["gain_iso"].values.astype(float)):
        factor = num("iso_gain_factor", gain_iso=float(frame.iso))
        factor_sigma = num("iso_gain_factor_sigma", gain_iso=float(frame.iso))
    response = mm.ResponseModel(
        conversion_gain_dn_per_e=num("conversion_gain_dn_per_e"),
        shutter_offset_s=num("shutter_offset_s"), shutter_offset_s_sigma=num("shutter_offset_s_sigma"),
        iso_gain_factor=factor, iso_gain_factor_sigma=factor_sigma,
        nonlinearity_beta=num("nonlinearity_beta"), nonlinearity_beta_sigma=num("nonlinearity_beta_sigma"),
        full_scale_dn=num("nonlinearity_full_scale_dn", float("nan")), saturation_dn=num("saturation_dn", float("nan")))
    immersion, immersion_sigma = 1.0, 0.0
    if medium == "water":
        immersion, immersion_sigma = num("immersion_factor", band=band), num("immersion_factor_sigma", band=band)
    calibration = mm.BandCalibration(
        rolloff_coefficients=b["rolloff_coefficients"].sel(medium=medium, band=band).values.astype(float),
        rolloff_covariance=b["rolloff_covariance"].sel(medium=medium, band=band).values.astype(float),
        calibrated_field_angle_deg=num("calibrated_field_angle_deg", float("inf"), medium=medium),
        inverse_responsivity=num("inverse_responsivity", band=band),
        inverse_responsivity_relative_sigma=num("inverse_responsivity_relative_sigma", band=band),
        immersion_factor=immersion, immersion_factor_sigma=immersion_sigma,
        rolloff_azimuth_amplitude=num("rolloff_azimuth_amplitude"),
        rolloff_azimuth_amplitude_sigma=num("rolloff_azimuth_amplitude_sigma"),
        rolloff_azimuth_phi0_deg=num("rolloff_azimuth_phi0_deg"),
        rolloff_azimuth_phi0_deg_sigma=num("rolloff_azimuth_phi0_deg_sigma"),
        rolloff_azimuth_theta_ref_deg=AZIMUTH_THETA_REF_DEG)
    return dark, response, calibration


def outside_image_circle(g: xr.Dataset, theta: np.ndarray, rows: slice, cols: slice, shape) -> np.ndarray:
    """Pixels of the crop ``rows, cols`` of a band image (full ``shape``) outside the image circle or the half FOV.

    ``g`` is the bundle at one lens, medium and band (circle centre and radius, half field of view). A
    rectilinear lens has no image circle (radius NaN): only pixels without a field angle are outside.

    Parameters
    ----------
    g : xarray.Dataset
        The bundle at one lens, medium and band (circle centre and radius, pixels; half field of view, degree).
    theta : numpy.ndarray
        The crop's field angles, degree (NaN without a direction).
    rows : slice
        The crop's rows in the band image.
    cols : slice
        The crop's columns in the band image.
    shape : tuple of int
        (rows, cols) of the whole band image.

    Returns
    -------
    numpy.ndarray
        Boolean, of the crop's shape: True outside.
    """
    if not np.isfinite(float(g["circle_radius_px"])):
        return ~np.isfinite(theta)
    y = np.arange(shape[0])[rows]
    x = np.arange(shape[1])[cols]
    r = np.hypot(x[None, :] - float(g["circle_xc_px"]), y[:, None] - float(g["circle_yc_px"]))
    return (r > float(g["circle_radius_px"])) | ~np.isfinite(theta) | (theta > float(g["half_fov_deg"]))


#: frame-independent flags that keep a pixel off the sphere grid (apply adds the frame's saturation)
STATIC_OFF_GRID = mm.FLAG_HOT | mm.FLAG_OUTSIDE_IMAGE_CIRCLE | mm.FLAG_BEYOND_CALIBRATED_ANGLE
#: the effects the stored per-pixel factors depend on (apply's chain and band_radiance check them)
FACTOR_EFFECTS = ("hot_pixels", "prnu", "rolloff_azimuth")


def factor_effects(effects) -> str:
    """The effects of ``effects`` that the bundle's ``pixel_factor`` depends on, comma-separated.

    Parameters
    ----------
    effects : iterable of str
        The effects of the model.

    Returns
    -------
    str
        Those among ``FACTOR_EFFECTS``, comma-separated, in that order.
    """
    return ",".join(e for e in FACTOR_EFFECTS if e in tuple(effects))


def sphere_blocks(cells: np.ndarray, flags: np.ndarray, block_rows: int):
    """The sphere cells of a band image (y, x) per block of ``block_rows`` rows, in the form apply bins them.

    Off the grid, a pixel takes its block's number of cells n (its spill cell: no direction, or a hot pixel) or
    n + 1 (a second spill: inside the image circle and not hot, but off the grid, i.e. beyond the calibrated field
    angle; such pixels enter apply's negative-mean check, which takes every unflagged pixel inside the circle, but
    not the grid).

    Parameters
    ----------
    cells : numpy.ndarray
        The sphere cell of every pixel of a band image, shape ``(y, x)`` (-1 off the grid).
    flags : numpy.ndarray
        Each pixel's frame-independent flags (``pipeline.radiometry.measurement`` FLAG bits), shape ``(y, x)``.
    block_rows : int
        Rows per block.

    Returns
    -------
    index : numpy.ndarray
        Shape ``(y, x)``, uint16 (uint32 where a block spans 65,534 cells or more): the pixel's cell less its
        block's first cell where it is on the grid, else n or n + 1.
    first : numpy.ndarray
        Per block its first cell (int32).
    n_cells : numpy.ndarray
        Per block its number of cells (int32).
    columns : numpy.ndarray
        Per block ``[start, stop)`` of the columns that reach inside the image circle (start = stop for a block
        wholly outside it), int32, shape ``(n_blocks, 2)``.
    """
    shape = cells.shape
    starts = range(0, shape[0], block_rows)
    first = np.zeros(len(starts), np.int32)
    n_cells = np.zeros(len(starts), np.int32)
    columns = np.zeros((len(starts), 2), np.int32)
    # each row's first and last column inside the image circle (a row wholly outside: first > last)
    inside = (flags & mm.FLAG_OUTSIDE_IMAGE_CIRCLE) == 0
    row_first = np.where(inside.any(axis=1), inside.argmax(axis=1), shape[1])
    row_last = shape[1] - 1 - inside[:, ::-1].argmax(axis=1)
    # as uint32 the -1 of a pixel off the grid is the largest value: a block's first cell is the minimum
    unsigned = np.asarray(cells, np.int32).view(np.uint32)
    for b, r0 in enumerate(starts):
        r = slice(r0, min(r0 + block_rows, shape[0]))
        lo, last = int(unsigned[r].min()), int(cells[r].max())
        first[b], n_cells[b] = (lo, last - lo + 1) if last >= 0 else (0, 0)
        c0, c1 = int(row_first[r].min()), int(row_last[r][row_first[r] < shape[1]].max(initial=-1)) + 1
        columns[b] = (c0, max(c0, c1))
    dtype = np.uint16 if n_cells.max(initial=0) + 1 < np.iinfo(np.uint16).max else np.uint32
    index = np.empty(shape, dtype)
    # off the grid but counted by the negative-mean check: inside the circle, not hot
    checked = (flags & (mm.FLAG_OUTSIDE_IMAGE_CIRCLE | mm.FLAG_HOT)) == 0
    checked &= np.asarray(cells) < 0
    for b, r0 in enumerate(starts):
        r = slice(r0, min(r0 + block_rows, shape[0]))
        np.minimum(unsigned[r] - np.uint32(first[b]), np.uint32(n_cells[b]), out=index[r], casting="unsafe")
        np.copyto(index[r], dtype(n_cells[b] + 1), where=checked[r])
    return index, first, n_cells, columns


def sphere_counts(cells: np.ndarray, flags: np.ndarray, n_cells: int) -> tuple[np.ndarray, int]:
    """The pixels of a band image on each sphere cell and those the negative-mean check takes.

    The check's pixels are those on the grid and those inside the image circle, not hot, off the grid (beyond the
    calibrated field angle): :func:`sphere_blocks`'s cells and its second spill. What a frame's flags
    (saturation, a value that is not finite) keep off, ``apply`` takes away from these.

    Parameters
    ----------
    cells : numpy.ndarray
        The sphere cell of every pixel of a band image, shape ``(y, x)`` (-1 off the grid).
    flags : numpy.ndarray
        Each pixel's frame-independent flags (``pipeline.radiometry.measurement`` FLAG bits), shape ``(y, x)``.
    n_cells : int
        The number of cells of the grid.

    Returns
    -------
    count : numpy.ndarray
        The pixels on each cell, int32, shape ``(n_cells,)``.
    checked : int
        The number of pixels the negative-mean check takes.
    """
    cells = np.asarray(cells).ravel()
    on = cells >= 0
    count = np.bincount(cells[on], minlength=n_cells).astype(np.int32)
    spill = (np.asarray(flags).ravel() & (mm.FLAG_OUTSIDE_IMAGE_CIRCLE | mm.FLAG_HOT)) == 0
    spill &= ~on
    return count, int(np.count_nonzero(on)) + int(np.count_nonzero(spill))


def _pixel_factors(bundle: xr.Dataset, effects, grid_deg: float, block_rows: int) -> xr.Dataset:
    """What depends only on lens, medium and band, per band pixel, in the compact form the chain uses.

    The chain's :func:`~pipeline.radiometry.measurement.pixel_factors` of
    every pixel, computed by the chain's own functions (in float32, the
    chain's type for band images): ``pixel_factor`` = 1 / (F g(theta, phi))
    (the flat field F only with ``prnu``), ``pixel_systematic_relative_variance``
    the sum of the roll-off's relative variances (``rolloff``, ``field_angle``,
    ``rolloff_azimuth``; the chain adds them in quadrature per pixel),
    ``pixel_flag`` the geometry flags with the hot-pixel mask folded in
    (``hot_pixels``), ``pixel_random_relative_variance`` the flat field's
    relative variance (``prnu``; per lens and band); and the cell of every
    pixel on the default sphere grid (``apply.grid_deg``, the
    :mod:`pipeline.geometry.sphere` convention; off the grid where no direction or a
    frame-independent flag keeps it off) per block of ``apply.block_rows`` rows
    (:func:`sphere_blocks`). ``apply`` reads these for its medium instead of
    evaluating them on every call.
    """
    lenses, media = list(bundle["lens"].values), list(bundle["medium"].values)
    # apply's choice: the default zenith lens, or the first lens of a camera without one (a phone's only lens)
    zenith_lens = ZENITH_LENS if ZENITH_LENS in lenses else lenses[0]
    shape = bundle["theta_deg"].shape
    dims = bundle["theta_deg"].dims
    per_band = tuple(shape[dims.index(d)] for d in ("lens", "band", "y", "x"))
    inverse = np.empty(shape, np.float32)
    rel = np.empty(shape, np.float32)
    flags = np.empty(shape, np.uint8)
    blocks = {}
    n_grid = int(np.prod(grid_shape(grid_deg)))
    counts = np.zeros((len(lenses), len(media), len(BANDS), n_grid), np.int32)
    checked = np.zeros((len(lenses), len(media), len(BANDS)), np.int64)
    flat = "prnu" in effects and "flat_field" in bundle
    random_rel = np.empty(per_band, np.float32) if flat else None
    frame = mm.FrameSettings(exposure_s=1.0, iso=float(bundle["dark_iso"].values.min()))
    for i, lens in enumerate(lenses):
        b_lens = bundle.sel(lens=lens)
        for k, medium in enumerate(media):
            for j, band in enumerate(BANDS):
                g = bundle.sel(lens=lens, medium=medium, band=band)
                b = b_lens.sel(band=band)
                at = {"lens": i, "medium": k, "band": j}
                index = tuple(at.get(d, slice(None)) for d in dims)
                theta = g["theta_deg"].values.astype(float)
                phi = g["phi_deg"].values
                theta = np.where(outside_image_circle(g, theta, slice(None), slice(None), theta.shape), np.nan, theta)
                cal = band_parameters(bundle, lens, band, medium, frame, effects)[2]
                sigma = g["theta_deg_sigma"].values if "theta_deg_sigma" in g else None
                r = mm.rolloff_map(theta, cal, phi, effects, np.float32, theta_deg_sigma=sigma)
                f = mm.pixel_factors(r, effects, hot_mask=b["hot_pixel_mask"].values if "hot_pixel_mask" in b else None,
                                     flat_field=b["flat_field"].values if flat else None,
                                     flat_field_sigma=b["flat_field_sigma"].values
                                     if flat and "flat_field_sigma" in b else None,
                                     prnu_sigma_rel=float(b["prnu_sigma_rel"]) if "prnu_sigma_rel" in b else 0.0,
                                     sites=SITES_PER_BAND_PIXEL[band])
                inverse[index], flags[index] = f.inverse, f.flags
                terms = list(f.systematic_rel.values())
                rel[index] = np.sum(terms, axis=0, dtype=np.float32) if terms else 0.0
                if flat and k == 0:
                    random_rel[i, j] = f.random_rel["prnu"]
                zen, azi = sphere_coordinates(g["theta_deg"].values, phi, lens == zenith_lens)
                cells = np.where((f.flags & STATIC_OFF_GRID) != 0, -1, sphere_cells(zen, azi, grid_deg))
                blocks[i, k, j] = index, sphere_blocks(cells, f.flags, block_rows)
                counts[i, k, j], checked[i, k, j] = sphere_counts(cells, f.flags, n_grid)
    # one index type for all (uint16 unless a block spans 65,535 cells or more)
    dtype = np.result_type(*(b[1][0].dtype for b in blocks.values()))
    cell_index = np.empty(shape, dtype)
    n_blocks = len(next(iter(blocks.values()))[1][1])
    block_dims = ("lens", "medium", "band", "block")
    per_block = {name: np.empty((len(lenses), len(media), len(BANDS), n_blocks) + extra, np.int32)
                 for name, extra in (("first", ()), ("n_cells", ()), ("columns", (2,)))}
    for at, (index, (cell, first, n_cells, columns)) in blocks.items():
        cell_index[index] = cell
        per_block["first"][at], per_block["n_cells"][at], per_block["columns"][at] = first, n_cells, columns
    used = factor_effects(effects)
    out = xr.Dataset({
        "pixel_factor": (dims, inverse, {
            "long_name": "the chain's frame-independent factor 1 / (F g(theta, phi)): roll-off (Eq. 13) and, with "
                         "prnu, flat field; NaN without a direction", "units": "1", "effects": used}),
        "pixel_systematic_relative_variance": (dims, rel, {
            "long_name": "relative variance of the roll-off factor: the sum of the terms rolloff (coefficient "
                         "covariance), field_angle (theta_deg_sigma) and rolloff_azimuth", "units": "1",
            "effects": used}),
        "pixel_flag": (dims, flags, {
            "long_name": "frame-independent quality flag bits: outside the image circle, beyond the calibrated "
                         "field angle, hot pixel (hot_pixels)", "units": "1",
            "flag_masks": np.array([mm.FLAG_OUTSIDE_IMAGE_CIRCLE, mm.FLAG_BEYOND_CALIBRATED_ANGLE, mm.FLAG_HOT],
                                   np.uint8),
            "flag_meanings": "outside_image_circle beyond_calibrated_angle hot_pixel", "effects": used}),
        "sphere_cell_in_block": (dims, cell_index, {
            "long_name": "cell of the pixel's direction on the sphere grid (row-major zenith, azimuth) less its "
                         "block's first cell (sphere_block_first_cell); sphere_block_n_cells: off the grid (no "
                         "direction, or a hot pixel); sphere_block_n_cells + 1: off the grid but inside the image "
                         "circle and not hot (beyond the calibrated field angle)", "units": "1",
            "grid_deg": float(grid_deg), "zenith_lens": zenith_lens, "block_rows": int(block_rows),
            "effects": used}),
        "sphere_block_first_cell": (block_dims, per_block["first"], {
            "long_name": "first sphere cell of each block of block_rows rows", "units": "1"}),
        "sphere_block_n_cells": (block_dims, per_block["n_cells"], {
            "long_name": "sphere cells a block spans (also its spill index: pixels off the grid)", "units": "1"}),
        "sphere_cell_count": (("lens", "medium", "band", "sphere_cell"), counts, {
            "long_name": "band pixels on each sphere cell (row-major zenith, azimuth) before a frame's flags "
                         "(saturation) keep some off", "units": "1", "grid_deg": float(grid_deg),
            "zenith_lens": zenith_lens}),
        "sphere_checked_count": (("lens", "medium", "band"), checked, {
            "long_name": "band pixels the negative-mean check takes before a frame's flags keep some off: on the "
                         "grid, or inside the image circle, not hot, beyond the calibrated field angle",
            "units": "1"}),
        "sphere_block_columns": (block_dims + ("bound",), per_block["columns"], {
            "long_name": "columns of each block that reach inside the image circle, [start, stop)",
            "units": "pixel"}),
    })
    if flat:
        out["pixel_random_relative_variance"] = (("lens", "band", "y", "x"), random_rel, {
            "long_name": "relative variance of the flat field 1 / F (random term prnu: its measurement noise, or "
                         "the PRNU where unmeasured)", "units": "1", "effects": used})
    return out


def noise_equivalent_radiance(dark: mm.DarkModel, response: mm.ResponseModel, calibration: mm.BandCalibration,
                              frame: mm.FrameSettings, effects, snr: float = 1.0) -> float:
    """Radiance on the optical axis whose signal is ``snr`` times its random noise (Section 3.8).

    The chain's random variance of a dark-corrected signal s (DN) is a + b s
    (read noise, dark electrons and offset pattern; shot noise), read off the
    chain itself at s = 0 and s = 1; s = (snr^2 b + sqrt(snr^4 b^2 + 4 snr^2 a)) / 2
    solves s = snr sqrt(a + b s); the radiance follows through the chain's
    exposure, gain and R^-1 steps (roll-off 1 and flat field 1 on the axis).

    Parameters
    ----------
    dark : DarkModel
        The band's dark model.
    response : ResponseModel
        The band's response model.
    calibration : BandCalibration
        The band's calibration (its R^-1).
    frame : FrameSettings
        The frame's exposure time (s) and ISO.
    effects : collection of str
        The effects of the model.
    snr : float, default 1.0
        The signal-to-noise ratio of the radiance sought.

    Returns
    -------
    float
        The radiance, W m-2 sr-1 nm-1.
    """
    def variance(signal_dn):
        m = mm.subtract_dark(mm.from_raw(np.zeros(1)), dark, frame, effects)
        m = mm.Measured(value=np.array([signal_dn], float), units="DN", random_var=m.random_var)
        return float(mm.add_shot_noise(m, dark, response, frame, effects).random_sigma[0] ** 2)

    a = variance(0.0)
    b = variance(1.0) - a
    s = 0.5 * (snr**2 * b + np.sqrt(snr**4 * b**2 + 4.0 * snr**2 * a))
    m = mm.normalise_exposure(mm.Measured(value=np.array([s]), units="DN"), response, frame, effects)
    return float(mm.to_radiance(m, calibration).value[0])


def _noise_floor(bundle: xr.Dataset, effects, cfg: dict) -> xr.Dataset:
    frame = mm.FrameSettings(exposure_s=float(cfg["noise_equivalent_exposure_s"]), iso=float(cfg["noise_equivalent_iso"]))
    lenses, bands = list(bundle["lens"].values), list(BANDS)
    ner = np.full((len(lenses), len(bands)), np.nan)
    lod = np.full_like(ner, np.nan)
    for i, lens in enumerate(lenses):
        for j, band in enumerate(bands):
            dark, response, cal = band_parameters(bundle, lens, band, "air", frame, effects)
            ner[i, j] = noise_equivalent_radiance(dark, response, cal, frame, effects, 1.0)
            lod[i, j] = noise_equivalent_radiance(dark, response, cal, frame, effects, float(cfg["detection_snr"]))
    at = f"ISO {frame.iso:g}, {frame.exposure_s:g} s, one band pixel on the optical axis, in air"
    return xr.Dataset({
        "noise_equivalent_radiance": (("lens", "band"), ner, {
            "long_name": f"radiance at SNR 1 ({at}; Section 3.8)", "units": "W sr-1 m-2 nm-1",
            "iso": frame.iso, "exposure_s": frame.exposure_s}),
        "limit_of_detection": (("lens", "band"), lod, {
            "long_name": f"radiance at SNR {cfg['detection_snr']:g} ({at}; Section 3.8)", "units": "W sr-1 m-2 nm-1",
            "iso": frame.iso, "exposure_s": frame.exposure_s, "snr": float(cfg["detection_snr"])}),
    }, coords={"lens": lenses, "band": bands})


class _ReadPart(NamedTuple):
    """What :func:`build_bundle` takes from one stage artefact."""

    sha256: str
    effects: list
    input_sha256: str
    projection: str
    bias_reference: str
    part: xr.Dataset


#: artefacts build_bundle has read in this process, (resolved path, stage) -> (file identity, what it took): a
#: process that builds many bundles from the same upstream artefacts (a bundle per simulated lab session with
#: one camera's dark, linearity, geometry and roll-off) reads and hashes each of them once. The identity is
#: (inode, size, mtime in ns): the stages replace an artefact by renaming a new file into place, a new inode.
_READ_CACHE: dict[tuple[str, str], tuple[tuple[int, int, int], _ReadPart]] = {}
#: what the cache holds at most: entries, and the in-memory size of one part (bytes; at the full scale the
#: per-pixel maps are hundreds of MB, read once by the workflow's single bundle job: not kept)
_READ_CACHE_ENTRIES, _READ_CACHE_PART_BYTES = 32, 32 << 20


def _read_part(path: str | Path, stage: str) -> _ReadPart:
    """The artefact's sha256, model effects, lab-input hashes, projection, bias reference and bundle part (the
    cached read while the file is the same file; the caller copies the part before changing it)."""
    if not Path(path).is_file():
        return _read_uncached(path, stage)      # read_artefact says what is wrong with the path, in one line
    stat = os.stat(path)
    identity = (stat.st_ino, stat.st_size, stat.st_mtime_ns)
    key = (str(Path(path).resolve()), stage)
    hit = _READ_CACHE.get(key)
    if hit is not None and hit[0] == identity:
        return hit[1]
    read = _read_uncached(path, stage)
    if read.part.nbytes <= _READ_CACHE_PART_BYTES:
        _READ_CACHE.pop(key, None)
        while len(_READ_CACHE) >= _READ_CACHE_ENTRIES:
            _READ_CACHE.pop(next(iter(_READ_CACHE)))          # the oldest first
        _READ_CACHE[key] = (identity, read)
    return read


def _read_uncached(path: str | Path, stage: str) -> _ReadPart:
    ds = read_artefact(path, stage)
    return _ReadPart(sha256_file(path), model_effects(ds), ds.attrs.get("input_sha256", "{}"),
                     str(ds.attrs.get("projection", "fisheye")), str(ds.attrs.get("bias_reference", "unlit corners")),
                     PARTS[stage](ds))


def build_bundle(artefacts: dict[str, dict[str, str | Path]], out_path: str | Path, camera: dict,
                 lens_regions: dict[str, dict], config: dict | None = None) -> xr.Dataset:
    """Gather the stage artefacts into the calibration bundle at ``out_path``.

    Every lens needs the stages of :data:`REQUIRED_STAGES`; spectral and immersion are taken when present (without
    immersion the bundle has no water). All artefacts must have been fitted with the same model. Bad input (an
    artefact missing, lenses or models that differ, no lens regions): InputError.

    Parameters
    ----------
    artefacts : dict[str, dict[str, str or pathlib.Path]]
        {stage: {lens: artefact path}}.
    out_path : str or pathlib.Path
        The bundle to write (NetCDF), under the results folder's ``calibration/``.
    camera : dict
        dataset.yaml's ``camera`` section (make, model, serial).
    lens_regions : dict[str, dict]
        dataset.yaml's ``lenses`` section ({lens: {rows: [r0, r1], cols: [c0, c1]}}, raw mosaic pixels).
    config : dict, optional
        The configuration (default: the schema's defaults).

    Returns
    -------
    xarray.Dataset
        The bundle as written.
    """
    config = config if config is not None else defaults()
    out_path = Path(out_path)
    results_root = out_path.parent.parent
    missing = [s for s in REQUIRED_STAGES if not artefacts.get(s)]
    if missing:
        raise InputError(out_path, f"the calibration bundle needs the {', '.join(missing)} artefact(s)")
    lenses = sorted(artefacts["dark"])
    effects, first, inputs, geometry_inputs, lab = None, None, {}, {}, []
    projection = {lens: "fisheye" for lens in lenses}
    bias_reference = {lens: "unlit corners" for lens in lenses}
    parts: dict[str, dict[str, xr.Dataset]] = {}
    for stage in BUNDLE_STAGES:
        paths = artefacts.get(stage) or {}
        if not paths:
            continue
        if sorted(paths) != lenses:
            raise InputError(out_path, f"the {stage} artefacts are for lenses {sorted(paths)}, the dark ones for {lenses}")
        parts[stage] = {}
        for lens in lenses:
            read = _read_part(paths[lens], stage)
            found = list(read.effects)
            if effects is None:
                effects, first = found, paths[lens]
            elif found != effects:
                raise InputError(paths[lens], f"was fitted with the model [{', '.join(found)}], {first} with "
                                              f"[{', '.join(effects)}]: rerun the stages with one model")
            inputs[_relative(paths[lens], results_root)] = read.sha256
            lab.append(json.loads(read.input_sha256))
            if stage == "geometry":
                geometry_inputs[_relative(paths[lens], results_root)] = inputs[_relative(paths[lens], results_root)]
            if stage == "geometry":
                projection[lens] = read.projection
            if stage == "dark":
                bias_reference[lens] = read.bias_reference
            parts[stage][lens] = read.part.copy(deep=True)    # _stack adds variables to it: the cache's stays whole
    if "geometry" in parts and "rolloff" in parts:
        # only the media the geometry has maps for (a rectilinear region calibrated in air only; its roll-off
        # artefact may list water without measurements): an outer join would add them with NaN maps
        for lens in lenses:
            have = list(parts["geometry"][lens]["medium"].values)
            part = parts["rolloff"][lens]
            parts["rolloff"][lens] = part.sel(medium=[m for m in part["medium"].values if m in have])
    merged, stages = [], list(parts)
    for stage in stages:
        # each stage's per-lens parts let go as soon as they are stacked: the lenses' maps are not held twice
        # (at the full resolution the per-lens parts and the stacked copy together were 1.1 GB of the peak)
        try:
            merged.append(_stack(parts.pop(stage), lenses))
        except ValueError as exc:
            raise InputError(out_path, f"the {stage} artefacts of the lenses do not line up ({exc})") from None
    bundle = xr.merge(merged, compat="override", combine_attrs="drop_conflicts")
    del merged
    bundle.attrs = {}
    for lens in lenses:
        for band in BANDS:
            value = float(bundle["inverse_responsivity"].sel(lens=lens, band=band))
            mm.check_inverse_responsivity(value, f"of lens {lens}, band {band} ")
    bundle["lens"].attrs.update(long_name="lens of the camera (dataset.yaml lenses)")
    bundle["projection"] = ("lens", np.array([projection[lens] for lens in lenses], dtype=str), {
        "long_name": "projection of the lens region (fisheye: image circle and fisheye model; rectilinear: "
                     "pinhole fit, no image circle)"})
    bundle["bias_reference"] = ("lens", np.array([bias_reference[lens] for lens in lenses], dtype=str), {
        "long_name": "what measures each frame's black level with bias_drift (unlit corners, optically black "
                     "pixels, none)"})
    media = ["air"] + (["water"] if "immersion" in stages else [])
    bundle = bundle.merge(_noise_floor(bundle, effects, config["calibration"]))
    try:
        span = np.array([[lens_regions[lens]["rows"], lens_regions[lens]["cols"]] for lens in lenses], dtype=int)
    except (KeyError, TypeError, ValueError):
        raise InputError(out_path, f"lens regions (dataset.yaml lenses) are needed for lenses {lenses}") from None
    bundle["lens_region_px"] = (("lens", "axis", "bound"), span,
                                {"long_name": "lens region of the raw mosaic: rows then columns, [start, stop)",
                                 "units": "pixel"})
    apply_cfg = config.get("apply") or defaults()["apply"]
    bundle = bundle.merge(_pixel_factors(bundle, effects, float(apply_cfg["grid_deg"]), int(apply_cfg["block_rows"])))
    bundle.attrs.update({
        "title": "calibration bundle of a RAW camera as a radiometer (Larouche et al. 2024)",
        "camera_make": str(camera.get("make", "")), "camera_model": str(camera.get("model", "")),
        "camera_serial": str(camera.get("serial", "")),
        "media": ",".join(media), "stages": ",".join(stages),
        # what names the per-pixel geometry maps (theta, phi, solid angle) in an apply output without them
        "geometry_sha256": json.dumps(geometry_inputs, sort_keys=True),
        # the lab files the artefacts were made from (pipeline.bundle.calibration.lab_inputs): what two bundles share
        "lab_input_sha256": json.dumps(lab_inputs(lab), sort_keys=True),
    })
    # the per-pixel maps uncompressed and contiguous: apply reads one lens, band and medium of them
    # as one block, where decompressing them cost it seconds at the full resolution
    maps = {name: {"zlib": False, "contiguous": True} for name, var in bundle.data_vars.items()
            if var.dims[-2:] == ("y", "x") or name == "sphere_cell_count"}
    write_artefact(bundle, out_path, stage="calibration", inputs=inputs,
                   config_subset=stage_params(config, "calibration"), effects=list(effects), encoding=maps)
    return bundle


def read_bundle(path: str | Path, *, load: bool = True) -> xr.Dataset:
    """Open a calibration bundle, refusing another artefact or an unknown version.

    Parameters
    ----------
    path : str or pathlib.Path
        The bundle (NetCDF).
    load : bool, default True
        Load the variables into memory; False leaves them on disk (read when selected; the caller closes the
        Dataset).

    Returns
    -------
    xarray.Dataset
        The bundle.
    """
    return read_artefact(path, "calibration", load=load)


def build_bundle_script(smk) -> None:
    """Entry point of the ``calibration`` rule's thin script: the stage artefacts of both lenses -> the bundle.

    Parameters
    ----------
    smk : snakemake.script.Snakemake
        The rule's ``snakemake`` object (inputs per stage, output ``bundle``, params ``camera`` and ``config``, log).
    """
    setup_log(smk.log[0] if smk.log else None)
    artefacts = {}
    for stage in BUNDLE_STAGES:
        if stage in smk.input.keys():
            paths = smk.input[stage]
            paths = [paths] if isinstance(paths, (str, Path)) else list(paths)
            artefacts[stage] = {Path(p).stem: str(p) for p in paths}
    exit_on_input_error(build_bundle, artefacts, smk.output.bundle, smk.params.camera["camera"],
                        smk.params.camera["lenses"], smk.params.config)
