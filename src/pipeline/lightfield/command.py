"""``python -m pipeline lightfield``: radiance sphere grids to the light-field quantities, in the earth frame.

Per frame and band: the camera-frame grid's empty band between the lenses
filled (:mod:`~pipeline.lightfield.fill`), the earth's zenith found from the
frame's attitude (:mod:`~pipeline.lightfield.attitude`), the quantities and
their uncertainties (:mod:`~pipeline.lightfield.quantities`), and the grid
resampled into the earth frame for maps (each earth cell takes the camera cell
its centre falls in; the integrals are over the camera cells, never over the
resampled map).
"""

from __future__ import annotations

import os
import sys
import tempfile
from datetime import datetime, timezone
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import xarray as xr

from pipeline import __version__
from pipeline.bundle.apply import BandChain, apply_calibration, check_frame
from pipeline.io.artefact import model_effects
from pipeline.io.bands import BANDS
from pipeline.bundle.calibration import read_bundle
from pipeline.config import defaults
from pipeline.geometry.sphere import ZENITH_LENS
from pipeline.lightfield.bracket_closure import bracket_consistency, bracket_table
from pipeline.lightfield.grid import SphereGrids
from pipeline.lightfield.hdr import (EXPOSURE_TERMS, FLAG_SATURATED_EVERYWHERE, SphereBins, dynamic_range,
                                     exposure_maps, group_brackets, merge_exposures, pixel_sphere_cells,
                                     read_frames_table, split_lens)
from pipeline.stages.observations import table_to_dataset
from pipeline.io.rawio import read_raw, read_tags
from pipeline.errors import InputError
from pipeline.lightfield.attitude import (LEVEL, attitude_at, earth_to_camera_directions, earth_up_in_camera,
                                          read_attitude, solar_position)
from pipeline.lightfield.fill import fill_between_lenses
from pipeline.lightfield.grid import RADIANCE_UNITS, read_sphere_grids
from pipeline.lightfield.quadrature import GridEdges, cell_centre_directions
from pipeline.lightfield.sun_output import shortest_exposure_sun_centroid, sun_attitudes, sun_dataset
from pipeline.lightfield.quantities import COMPONENTS, INTEGRALS, QUANTITIES, WeightCache, light_field_quantities

__all__ = ["compute_light_field", "light_field_of_grids", "light_field_from_raw", "light_field_from_brackets",
           "write_light_field", "lightfield_command", "QUANTITY_ATTRS"]

_IRRADIANCE = "W m-2 nm-1"
#: per quantity: long name, units, CF standard name in air and in sea water (None: the table has none)
QUANTITY_ATTRS = {
    "E_d": ("downwelling plane irradiance (cosine-weighted integral of the upper hemisphere)", _IRRADIANCE,
            "downwelling_spectral_radiative_flux_in_air", "downwelling_spectral_radiative_flux_in_sea_water"),
    "E_u": ("upwelling plane irradiance (cosine-weighted integral of the lower hemisphere)", _IRRADIANCE,
            "upwelling_spectral_radiative_flux_in_air", "upwelling_spectral_radiative_flux_in_sea_water"),
    "E_0d": ("downwelling scalar irradiance (integral of the upper hemisphere)", _IRRADIANCE,
             None, "downwelling_spectral_spherical_irradiance_in_sea_water"),
    "E_0u": ("upwelling scalar irradiance (integral of the lower hemisphere)", _IRRADIANCE,
             None, "upwelling_spectral_spherical_irradiance_in_sea_water"),
    "E_0": ("scalar irradiance (integral of the whole sphere)", _IRRADIANCE,
            None, "omnidirectional_spectral_spherical_irradiance_in_sea_water"),
    "mu_d": ("average cosine of the downwelling light, E_d / E_0d", "1", None, None),
    "mu_u": ("average cosine of the upwelling light, E_u / E_0u", "1", None, None),
    "mu": ("average cosine of the light field, (E_d - E_u) / E_0", "1", None, None),
    "L_d": ("zenith radiance (mean over the cone about the zenith)", RADIANCE_UNITS,
            "downwelling_spectral_radiance_in_air", "downwelling_spectral_radiance_in_sea_water"),
    "L_u": ("nadir radiance (mean over the cone about the nadir)", RADIANCE_UNITS,
            "upwelling_spectral_radiance_in_air", "upwelling_spectral_radiance_in_sea_water"),
    "Q": ("Q factor, E_u / L_u", "sr", None, None),
}
_COMPONENT_TEXT = {
    "random": "random standard uncertainty (independent cell noise through the quadrature)",
    "systematic": "systematic standard uncertainty (terms common to the band, fully correlated between cells)",
    "fill_model": "standard uncertainty from the fill model of the cells no lens calibrates",
    "attitude": "standard uncertainty from the roll and pitch uncertainty (the grid rotated)",
    "quadrature": "quadrature error: difference from the same quadrature on the grid of half resolution",
}


def _frame_times_utc(grids, offset_h: float, needed_for: str) -> pd.DatetimeIndex:
    times = []
    for name, text in zip(grids.frame_names, grids.frame_times):
        if not text:
            raise InputError(name, f"the grid gives no frame_time, which {needed_for} needs")
        try:
            stamp = pd.Timestamp(text)
        except ValueError:
            raise InputError(name, f"frame_time {text!r} is not an ISO 8601 date and time") from None
        stamp = stamp.tz_convert("UTC") if stamp.tzinfo is not None else \
            (stamp - pd.Timedelta(hours=offset_h)).tz_localize("UTC")
        times.append(stamp)
    return pd.DatetimeIndex(times)


def compute_light_field(grid_paths, medium: str | None = None, attitude_path=None, site=None,
                        camera_utc_offset_h: float = 0.0, config: dict | None = None) -> xr.Dataset:
    """The light field of every frame and band of the grid files (see the module docstring and docs/light-field.md).

    Parameters
    ----------
    grid_paths : sequence of str or pathlib.Path
        The radiance sphere grid files.
    medium : str, optional
        "air" or "water"; the grids' own attribute when None.
    attitude_path : str or pathlib.Path, optional
        The attitude log (CSV, :func:`pipeline.lightfield.attitude.read_attitude`); level when None.
    site : tuple of float, optional
        (latitude_deg, longitude_deg[, altitude_m]): gives the solar position (pvlib) and each earth-frame
        azimuth relative to the sun.
    camera_utc_offset_h : float, default 0.0
        The camera clock minus UTC for frame times without an offset, hours.
    config : dict, optional
        The ``lightfield`` section of the configuration (default: the schema's defaults).

    Returns
    -------
    xarray.Dataset
        The quantities per frame and band with their uncertainty components, and the earth-frame grids.

    Raises
    ------
    InputError
        On bad grid files, attitude log or frame times.
    """
    cfg = config if config is not None else defaults()["lightfield"]
    return light_field_of_grids(read_sphere_grids(grid_paths, medium), attitude_path, site, camera_utc_offset_h, cfg)


def light_field_of_grids(grids, attitude_path=None, site=None, camera_utc_offset_h: float = 0.0, cfg: dict | None = None,
                         exposure_systematic=None, lower_bound=None, extra_maps: dict | None = None,
                         attitudes=None) -> xr.Dataset:
    """:func:`compute_light_field` on grids already read (:class:`~pipeline.lightfield.grid.SphereGrids`).

    Parameters
    ----------
    grids : SphereGrids
        The radiance sphere grids, W m-2 sr-1 nm-1.
    attitude_path : str or pathlib.Path, optional
        The attitude log (CSV, :func:`pipeline.lightfield.attitude.read_attitude`); level when None.
    site : tuple of float, optional
        (latitude_deg, longitude_deg[, altitude_m]): gives the solar position (pvlib) and each earth-frame
        azimuth relative to the sun.
    camera_utc_offset_h : float, default 0.0
        The camera clock minus UTC for frame times without an offset, hours.
    cfg : dict, optional
        The ``lightfield`` section of the configuration (default: the schema's defaults).
    exposure_systematic : numpy.ndarray, optional
        Shape ``(frame, band, exposure, zenith, azimuth)``: systematic sigmas (W m-2 sr-1 nm-1) each common to the
        cells of one exposure and independent between exposures (an HDR merge's per-exposure terms), beside the
        grids' band-common ``systematic_sigma``.
    lower_bound : numpy.ndarray, optional
        Shape ``(frame, band, zenith, azimuth)``, bool: cells whose value is a lower bound (saturated in every
        exposure), whose share of each integral is reported.
    extra_maps : dict, optional
        ``{name: (array (frame, band, zenith, azimuth), attrs)}``: camera-frame maps resampled into the earth frame
        as ``sphere_radiance`` is and added to the output under their names.
    attitudes : sequence of Attitude, optional
        Each frame's attitude, taking the place of the log.

    Returns
    -------
    xarray.Dataset
        The light field (as :func:`compute_light_field`).
    """
    cfg = cfg if cfg is not None else defaults()["lightfield"]
    medium = grids.medium or "air"
    n_f, n_b, n_z, n_a = grids.radiance.shape
    edges = GridEdges.regular(n_z, n_a)
    times = None
    if attitude_path is not None or site is not None:
        times = _frame_times_utc(grids, camera_utc_offset_h, "an attitude log" if attitude_path else "a site")
    if attitudes is not None:
        attitudes = list(attitudes)
    elif attitude_path is not None:
        attitudes = attitude_at(read_attitude(attitude_path), times, grids.frame_names)
    else:
        attitudes = [LEVEL] * n_f
    weights = WeightCache(float(cfg["radiance_cone_half_angle_deg"]), int(cfg["boundary_subcells"]))
    results = {k: np.full((n_f, n_b, len(QUANTITIES)), np.nan)
               for k in ("value", *COMPONENTS, "total", "filled_fraction", "filled_variance_fraction",
                         "lower_bound_fraction")}
    earth = {k: np.full((n_f, n_b, n_z, n_a), np.nan) for k in ("radiance", "random", "systematic", "model")}
    earth_flag = np.zeros((n_f, n_b, n_z, n_a), np.int8)
    extra_maps = extra_maps or {}
    extra_earth = {name: np.zeros_like(arr) for name, (arr, _) in extra_maps.items()}
    fallback = np.zeros((n_f, n_b), np.int32)
    earth_centres = cell_centre_directions(edges)
    cells = {}
    for f in range(n_f):
        # each earth cell's centre in the camera grid: the camera cell it falls in (once per attitude)
        if attitudes[f] not in cells:
            cam = earth_to_camera_directions(attitudes[f], earth_centres)
            cz = np.degrees(np.arccos(np.clip(cam[..., 2], -1, 1)))
            ca = np.degrees(np.arctan2(cam[..., 1], cam[..., 0])) % 360.0
            cells[attitudes[f]] = (np.clip((cz / (180.0 / n_z)).astype(int), 0, n_z - 1),
                                   np.clip((ca / (360.0 / n_a)).astype(int), 0, n_a - 1))
        iz, ia = cells[attitudes[f]]
        for b in range(n_b):
            filled = fill_between_lenses(grids.radiance[f, b], grids.random_sigma[f, b], grids.systematic_sigma[f, b],
                                         grids.zenith_deg, float(cfg["fill_fit_span_deg"]))
            res = light_field_quantities(filled, edges, attitudes[f], weights, float(cfg["attitude_step_deg"]),
                                         grids.centre_samples,
                                         None if exposure_systematic is None else exposure_systematic[f, b],
                                         None if lower_bound is None else lower_bound[f, b])
            for k in results:
                results[k][f, b] = res[k]
            fallback[f, b] = filled.fallback_cells
            earth["radiance"][f, b] = filled.radiance[iz, ia]
            earth["random"][f, b] = filled.random_sigma[iz, ia]
            earth["systematic"][f, b] = filled.systematic_sigma[iz, ia]
            earth["model"][f, b] = filled.model_sigma[iz, ia]
            earth_flag[f, b] = filled.flag[iz, ia]
            for name, (arr, _) in extra_maps.items():
                extra_earth[name][f, b] = arr[f, b][iz, ia]
    ds = _dataset(grids, medium, attitudes, times, site, attitude_path, results, earth, earth_flag, fallback, cfg,
                  edges)
    for name, (_, attrs) in extra_maps.items():
        ds[name] = (("frame", "band", "zenith", "azimuth"), extra_earth[name], attrs)
    return ds


def _attrs(long_name, units, **more):
    return {"long_name": long_name, "units": units, **more}


def _dataset(grids, medium, attitudes, times, site, attitude_path, results, earth, earth_flag, fallback, cfg, edges):
    dims4 = ("frame", "band", "zenith", "azimuth")
    data = {
        "sphere_radiance": (dims4, earth["radiance"], _attrs(
            "spectral radiance in the earth frame (measured and filled cells)", RADIANCE_UNITS,
            comment="upper hemisphere downwelling, lower upwelling radiance (no one CF standard name covers both); "
                    "each earth cell takes the camera cell its centre falls in")),
        "sphere_radiance_random_sigma": (dims4, earth["random"], _attrs("random standard uncertainty", RADIANCE_UNITS)),
        "sphere_radiance_systematic_sigma": (dims4, earth["systematic"],
                                             _attrs("systematic standard uncertainty (common to the band)",
                                                    RADIANCE_UNITS)),
        "sphere_radiance_fill_model_sigma": (dims4, earth["model"],
                                             _attrs("fill model standard uncertainty (0: measured cell)",
                                                    RADIANCE_UNITS)),
        "sphere_cell_flag": (dims4, earth_flag, {"long_name": "cell source", "flag_values": np.array([0, 1, 2], np.int8),
                                                 "flag_meanings": "measured filled empty"}),
        "fill_fallback_cells": (("frame", "band"), fallback, _attrs(
            "filled cells whose model sigma is the fallback half step (no smooth window of three calibrated rows "
            "beside the run, or an edge cell not positive)", "1")),
        "frame_file": ("frame", np.array(grids.frame_names, dtype=str), {"long_name": "raw frame (or grid file:index)"}),
        "grid_file": ("frame", np.array(grids.frame_files, dtype=str), {"long_name": "radiance grid file"}),
    }
    for name, unit_attr in (("roll", "roll"), ("pitch", "pitch"), ("heading", "heading")):
        data[f"{name}_deg"] = ("frame", np.array([getattr(a, f"{unit_attr}_deg") for a in attitudes]),
                               _attrs(f"camera {name}", "degree"))
        data[f"{name}_sigma_deg"] = ("frame", np.array([getattr(a, f"{unit_attr}_sigma_deg") for a in attitudes]),
                                     _attrs(f"standard uncertainty of the camera {name}", "degree"))
    tilt = [np.degrees(np.arccos(np.clip(earth_up_in_camera(a.roll_deg, a.pitch_deg)[2], -1, 1))) for a in attitudes]
    data["tilt_deg"] = ("frame", np.array(tilt), _attrs("angle between the grid's zenith and the zenith", "degree"))
    if times is not None:
        data["frame_time_utc"] = ("frame", np.array([t.isoformat() for t in times], dtype=str),
                                  {"long_name": "frame time (UTC)"})
    if site is not None:
        sz, sa = solar_position(times, *site)
        data["solar_zenith_deg"] = ("frame", sz, _attrs("apparent solar zenith angle (pvlib)", "degree"))
        data["solar_azimuth_deg"] = ("frame", sa, _attrs("solar azimuth from north towards east (pvlib)", "degree"))
        rel = (edges.azimuth_centres_deg[None, :] - sa[:, None]) % 360.0
        data["azimuth_from_sun_deg"] = (("frame", "azimuth"), rel,
                                        _attrs("earth-frame cell azimuth relative to the solar azimuth", "degree"))
    water = medium == "water"
    for q, (long_name, units, cf_air, cf_water) in QUANTITY_ATTRS.items():
        i = QUANTITIES.index(q)
        extra = {}
        cf = cf_water if water else cf_air
        if cf:
            extra["standard_name"] = cf
        data[q] = (("frame", "band"), results["value"][..., i], _attrs(long_name, units, **extra))
        for c in COMPONENTS:
            suffix = "quadrature_error" if c == "quadrature" else f"{c}_sigma"
            data[f"{q}_{suffix}"] = (("frame", "band"), results[c][..., i], _attrs(f"{q}: {_COMPONENT_TEXT[c]}", units))
        data[f"{q}_sigma"] = (("frame", "band"), results["total"][..., i],
                              _attrs(f"{q}: total standard uncertainty (root sum of squares of the components)", units))
        if q in INTEGRALS and np.isfinite(results["lower_bound_fraction"][..., i]).any():
            data[f"{q}_lower_bound_fraction"] = (("frame", "band"), results["lower_bound_fraction"][..., i], _attrs(
                f"{q}: share of the value from cells saturated in every exposure (lower bounds: the value is a "
                "lower bound where this is above 0)", "1"))
        if q in INTEGRALS:
            data[f"{q}_filled_fraction"] = (("frame", "band"), results["filled_fraction"][..., i],
                                            _attrs(f"{q}: share of the value from filled cells", "1"))
        data[f"{q}_filled_variance_fraction"] = (("frame", "band"), results["filled_variance_fraction"][..., i],
                                                 _attrs(f"{q}: fill model's share of the total variance", "1"))
    ds = xr.Dataset(data, coords={
        "frame": np.arange(len(attitudes)), "band": grids.bands,
        "zenith": ("zenith", edges.zenith_centres_deg, _attrs("earth-frame zenith angle of the cell centre", "degree")),
        "azimuth": ("azimuth", edges.azimuth_centres_deg,
                    _attrs("earth-frame azimuth of the cell centre, from north towards east" if attitude_path
                           else "azimuth of the cell centre in the grid's own frame (no attitude given)", "degree")),
    })
    ds.attrs.update({
        "Conventions": "CF-1.10", "title": "light field from radiance sphere grids",
        "pipeline_version": __version__, "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "medium": medium, "grid_files": ",".join(sorted(set(grids.frame_files))),
        "attitude": (f"from {attitude_path}: roll, pitch and heading interpolated to each frame's time; the grid "
                     "rotated into the earth frame (zenith up, azimuth from north towards east)") if attitude_path
        else "none given: the grid's zenith is taken as the zenith and its azimuth as the azimuth; no attitude "
             "uncertainty",
        "quadrature": "cell radiance constant over each cell; exact solid angles and cosine integrals per cell, cells "
                      f"the hemisphere's or cone's edge crosses divided into {int(cfg['boundary_subcells'])}^2 "
                      "sub-cells; the quadrature error is the difference from the grid of half resolution",
        "fill_model": "empty cells between calibrated cells of an azimuth column: linear interpolation of ln L in "
                      "zenith angle; model sigma L (z - z_a)(z_b - z) / 2 * max|(ln L)''| of quadratic fits over "
                      f"{float(cfg['fill_fit_span_deg']):g} degrees of calibrated rows on either side",
        "cell_values": "centre samples, turned into cell means by the local quadratic (the correction's size is "
                       "part of the quadrature error)" if grids.centre_samples else "cell means",
        "radiance_cone_half_angle_deg": float(cfg["radiance_cone_half_angle_deg"]),
        "attitude_step_deg": float(cfg["attitude_step_deg"]),
        "uncertainty": "random: independent per cell, averaged down by the quadrature; systematic: common to the "
                       "band, fully correlated (cancels in mu_d, mu_u, mu and Q when proportional to the radiance); "
                       "fill model: fully correlated between filled cells; attitude: derivative with respect to "
                       "roll and pitch; total: root sum of squares with the quadrature error",
    })
    if grids.absent_sigmas:
        ds.attrs["absent_uncertainty"] = (f"{', '.join(grids.absent_sigmas)} not in the grid file(s): taken as zero")
    if site is not None:
        ds.attrs["site"] = f"latitude {site[0]} deg, longitude {site[1]} deg" + (
            f", altitude {site[2]} m" if len(site) > 2 else "")
    return ds


def write_light_field(ds: xr.Dataset, out_path, overwrite: bool = False) -> Path:
    """Write the light field as NetCDF (atomically); an existing file only with ``overwrite``.

    Parameters
    ----------
    ds : xarray.Dataset
        The light field.
    out_path : str or pathlib.Path
        The NetCDF file to write.
    overwrite : bool, default False
        Replace an existing file.

    Returns
    -------
    pathlib.Path
        The file written.

    Raises
    ------
    InputError
        When the file exists and ``overwrite`` is False.
    """
    out = Path(out_path)
    if out.exists() and not overwrite:
        raise InputError(out, "exists (give --overwrite to replace it)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".part")
    ds.to_netcdf(tmp)
    os.replace(tmp, out)
    return out


def light_field_from_raw(bundle_path, raw_paths, medium: str | None = None, attitude_path=None, site=None,
                         camera_utc_offset_h: float = 0.0, grid_deg: float | None = None,
                         config: dict | None = None) -> xr.Dataset:
    """The light field of raw frames: ``apply`` with the calibration bundle makes their sphere grid (in a
    temporary file, without the per-pixel maps), then :func:`compute_light_field`.

    Parameters
    ----------
    bundle_path : str or pathlib.Path
        The calibration bundle.
    raw_paths : sequence of str or pathlib.Path
        The raw (DNG) frames.
    medium : str, optional
        "air" or "water" (air when None).
    attitude_path : str or pathlib.Path, optional
        The attitude log (CSV, :func:`pipeline.lightfield.attitude.read_attitude`); level when None.
    site : tuple of float, optional
        (latitude_deg, longitude_deg[, altitude_m]): gives the solar position (pvlib) and each earth-frame
        azimuth relative to the sun.
    camera_utc_offset_h : float, default 0.0
        The camera clock minus UTC for frame times without an offset, hours.
    grid_deg : float, optional
        Cell size of the sphere grid, degree (default: ``apply.grid_deg``).
    config : dict, optional
        The ``lightfield`` section of the configuration.

    Returns
    -------
    xarray.Dataset
        The light field, its attributes naming the bundle.
    """
    with tempfile.TemporaryDirectory(prefix="lightfield-") as tmp:
        grid = apply_calibration(bundle_path, raw_paths, medium or "air", Path(tmp) / "grid.nc", grid_deg,
                                 pixels=False)
        ds = compute_light_field([grid], medium, attitude_path, site, camera_utc_offset_h, config)
        ds.load()
    ds.attrs["grid_files"] = f"made by apply from {len(raw_paths)} raw frame(s) with the calibration {bundle_path}"
    ds.attrs["calibration_bundle"] = str(bundle_path)
    return ds


def _full_scale_dn(bundle, lenses) -> np.ndarray:
    """(lens, band) full scale of the response: the linearity stage's nonlinearity full scale, else its
    saturation level, else the white level less the bias (the signatures' scale only)."""
    out = np.full((len(lenses), len(BANDS)), np.nan)
    for i, lens in enumerate(lenses):
        for name in ("nonlinearity_full_scale_dn", "saturation_dn"):
            if name in bundle and not np.isfinite(out[i]).all():
                v = bundle[name].sel(lens=lens)
                v = np.broadcast_to(np.asarray(v.sel(band=list(BANDS)).values if "band" in v.dims else v.values,
                                               float), (len(BANDS),))
                out[i] = np.where(np.isfinite(out[i]), out[i], v)
    return np.where(np.isfinite(out), out, 16383.0 - 800.0)


def _with_sun_closure(ds: xr.Dataset, sun: xr.Dataset | None, attitude_from_sun: str | None, attitude_path,
                      n_brackets: int, cfg: dict) -> xr.Dataset:
    """The light field with the sun closure's variables and its summary attributes (what the attitude is, the
    largest angle over its sigma and what it names), or the note that the closure was not tested."""
    if sun is not None:
        ds = ds.merge(sun)
        source = (f"fitted from the sun ({attitude_from_sun})" if attitude_from_sun else
                  f"the log {attitude_path}" if attitude_path else "none: level, heading 0 assumed")
        ds.attrs["attitude_source"] = source
        found = int(np.sum(ds["sun_core_pixels"].values > 0))
        if attitude_from_sun:
            ds.attrs["attitude"] = (f"fitted from the sun's centroid against the solar position ({attitude_from_sun}: "
                                    + ("roll and pitch 0 assumed, heading fitted" if attitude_from_sun == "heading"
                                       else "heading and the tilt towards the sun fitted, the tilt across it 0 "
                                            "assumed") + "); the grid rotated into the earth frame")
            ds["azimuth"].attrs["long_name"] = "earth-frame azimuth of the cell centre, from north towards east"
            ds.attrs["sun_fit_dof"] = 1 if attitude_from_sun == "heading" else 0
            ds.attrs["sun_closure"] = (f"attitude fitted from the sun ({attitude_from_sun}, {ds.attrs['sun_fit_dof']} "
                                       "degree(s) of freedom left): the closure checks only what the fit leaves")
        else:
            worst = ds["sun_z"].values[np.isfinite(ds["sun_z"].values)]
            named = sorted({x for x in ds["sun_closure_named"].values if x})
            ds.attrs["sun_closure"] = (
                f"sun found in {found} of {n_brackets} bracket(s); attitude {source}; largest angle over its "
                f"sigma {float(worst.max()) if worst.size else float('nan'):.2f}"
                + (f"; beyond {float(cfg['sun_closure_z']):g} sigma, naming: {'; '.join(named)}" if named else
                   "; every component within its uncertainty"))
    else:
        ds.attrs["sun_closure"] = "no --site: the solar position is unknown, the sun closure not tested"
    return ds


def _with_bracket_descriptions(ds: xr.Dataset, dr, dr_pixels, info, snr: float) -> xr.Dataset:
    """The light field with what describes each bracket: the dynamic range of its merged cells and pixels, its
    exposures and its raw files."""
    ds["hdr_dynamic_range_decades"] = (("frame", "band"), np.array(dr), _attrs(
        "decades between the brightest unsaturated sphere cell and the faintest above its limit of detection "
        f"(radiance >= {snr:g} random sigma)", "1"))
    ds["hdr_pixel_dynamic_range_decades"] = (("frame", "band"), np.array(dr_pixels), _attrs(
        "the same over the merged band pixels of both lenses", "1"))
    ds["bracket_exposures_s"] = ("frame", np.array([" ".join(f"{float(r.exposure_s):g}" for r in frames)
                                                    for _, frames in info], dtype=str),
                                 {"long_name": "exposure times (s) merged in the bracket"})
    ds["bracket_files"] = ("frame", np.array([" ".join(Path(r.path).name for r in frames) for _, frames in info],
                                             dtype=str), {"long_name": "raw frames of the bracket"})
    ds["frame_file"] = ("frame", np.array([name for name, _ in info], dtype=str), {"long_name": "bracket"})
    return ds


def _with_bracket_consistency(ds: xr.Dataset, tables: list, effects, full: dict) -> xr.Dataset:
    """The light field with the bracket-consistency closure: the ``obs_bracket`` table, its residual test and
    the effects the model lacks that it ranks significant, or the note that it was not tested."""
    closure = pd.concat([t for t in tables if len(t)], ignore_index=True) if any(len(t) for t in tables) else None
    if closure is not None:
        obs = table_to_dataset(closure, "obs_bracket")
        obs["obs_bracket__value_dn"].attrs.update({"long_name": "ln(L_long / L_short) of an exposure pair",
                                                   "units": "1"})
        obs["obs_bracket__sigma_dn"].attrs.update({"long_name": "its standard uncertainty", "units": "1"})
        ds = ds.merge(obs)
        ranked, tests = bracket_consistency(closure, effects, full)
        test = tests.iloc[0]
        ds.attrs["bracket_consistency_chi2"] = float(test["chi2"])
        ds.attrs["bracket_consistency_dof"] = int(test["dof"])
        ds.attrs["bracket_consistency_rms_z"] = float(test["rms_z"])
        ds.attrs["bracket_consistency_p_value"] = float(test["p_value"])
        significant = [str(r["effect"]) for _, r in ranked.iterrows() if bool(r["significant"])] if len(ranked) else []
        ds.attrs["bracket_consistency_effects"] = ",".join(significant)
        ds.attrs["bracket_consistency"] = (
            f"{len(closure)} exposure-pair rows, chi2 {float(test['chi2']):.1f} on {int(test['dof'])} dof "
            f"(p {float(test['p_value']):.3g}); " + (
                f"significant missing effect(s): {', '.join(significant)}" if significant
                else "no missing effect significant: at the noise floor" if not bool(test["significant"])
                else "structure no catalogue effect explains"))
    else:
        ds.attrs["bracket_consistency"] = "no pixel measured in two exposures above the closure's SNR: not tested"
    return ds


def _merged_grids(merged_cells, n_exp: int, bundle_path, info, medium: str):
    """The brackets' merged sphere cells as sphere grids, the per-exposure systematic sigmas
    (bracket, band, exposure, zenith, azimuth), the HDR flag and the HDR variables of the output."""
    n_z, n_a = merged_cells[0].radiance.shape[-2:]
    exposure = np.zeros((len(merged_cells), len(BANDS), n_exp, n_z, n_a))
    for f, sph in enumerate(merged_cells):
        exposure[f, :, :sph.exposure_sigma.shape[0]] = np.moveaxis(sph.exposure_sigma, 0, 1)

    def stack(name):
        return np.stack([getattr(sph, name) for sph in merged_cells])
    flag = stack("flag")
    grids = SphereGrids(stack("radiance"), stack("random_sigma"), stack("common_sigma"),
                        (np.arange(n_z) + 0.5) * 180.0 / n_z, (np.arange(n_a) + 0.5) * 360.0 / n_a, list(BANDS),
                        [str(bundle_path)] * len(merged_cells), [name for name, _ in info],
                        [frames[0].time.isoformat() if frames[0].time else "" for _, frames in info], medium)
    extra = {
        "hdr_cell_flag": (flag, {"long_name": "HDR merge flag", "flag_values": np.array([0, FLAG_SATURATED_EVERYWHERE],
                                                                                        np.int8),
                                 "flag_meanings": "merged saturated_in_every_exposure"}),
        "hdr_lower_bound": (stack("lower_bound"), _attrs(
            "lower bound of the radiance of a cell saturated in every exposure (NaN elsewhere)", RADIANCE_UNITS)),
        "hdr_exposure_systematic_sigma": (np.sqrt(np.sum(exposure ** 2, axis=2)), _attrs(
            "root sum of squares of the per-exposure systematic sigmas (each common to one exposure's cells)",
            RADIANCE_UNITS)),
        "hdr_pixel_count": (stack("count").astype(float), _attrs("band pixels merged into the cell", "1")),
    }
    return grids, exposure, flag, extra


def _frame_tags(path) -> SimpleNamespace:
    """A raw file's tags without decoding its pixels; a file lacking a tag the chain needs stops with the
    reader's own line."""
    tags = read_tags(path)
    if any(tags.get(k) is None for k in ("exposure_s", "iso", "time")):
        read_raw(path)      # raises the one line that names the missing tag
    return SimpleNamespace(**tags)


def light_field_from_brackets(bundle_path, raw_paths, frames_table=None, medium: str | None = None,
                              attitude_path=None, site=None, camera_utc_offset_h: float = 0.0,
                              grid_deg: float | None = None, config: dict | None = None,
                              attitude_from_sun: str | None = None) -> xr.Dataset:
    """The light field of exposure brackets of raw frames (:mod:`pipeline.lightfield.hdr`).

    The frames are grouped by ``frames_table`` or by ``lightfield.bracket_window_s``, each bracket merged per
    pixel through the chain at each frame's exposure, binned onto the sphere grid and integrated (one output
    frame per bracket); the bracket-consistency closure (:mod:`pipeline.lightfield.bracket_closure`) as the
    ``obs_bracket`` table with its residual test and the ranking of the effects the model lacks. With ``site``:
    the sun's centroid in each bracket's shortest exposure against the solar position
    (:mod:`pipeline.lightfield.sun`, the ``sun_*`` variables and the ``obs_sun`` table). Bad input: InputError.

    Parameters
    ----------
    bundle_path, raw_paths, medium, attitude_path, site, camera_utc_offset_h, grid_deg
        As for :func:`light_field_from_raw`.
    frames_table : str or pathlib.Path, optional
        CSV with the columns file and bracket; the frames grouped by time when None.
    config : dict, optional
        The whole configuration (default: the schema's).
    attitude_from_sun : str, optional
        ``"heading"`` or ``"heading_tilt"``: the attitude fitted from the sun (needs ``site``, no log).

    Returns
    -------
    xarray.Dataset
        The light field, one frame per bracket, with the dynamic range, the ``obs_bracket`` table and, with a
        site, the sun closure.
    """
    if attitude_from_sun is not None and (site is None or attitude_path is not None):
        raise InputError(None, "--attitude-from-sun needs --site (the solar position at the frames' times) and "
                               "no --attitude log")
    full = config if config is not None else defaults()
    cfg = full["lightfield"]
    grid_deg = float(grid_deg if grid_deg is not None else full["apply"]["grid_deg"])
    medium = medium or "air"
    # the brackets are formed from the tags; each bracket's frames are decoded when it is merged (once each)
    frames = [_frame_tags(p) for p in raw_paths]
    table = read_frames_table(frames_table) if frames_table is not None else None
    brackets = group_brackets(frames, table, float(cfg["bracket_window_s"]), frames_table)
    bundle = read_bundle(bundle_path)
    effects = model_effects(bundle)
    media = [m for m in str(bundle.attrs.get("media", "air")).split(",") if m]
    if medium not in media:
        raise InputError(bundle_path, f"has no calibration for medium '{medium}' (media: {', '.join(media)})")
    for frame in frames:
        check_frame(frame, bundle, effects)
    lenses = [str(x) for x in bundle["lens"].values]
    zenith_lens = ZENITH_LENS if ZENITH_LENS in lenses else lenses[0]
    chains = {(lens, band): BandChain(bundle, lens, band, medium, effects) for lens in lenses for band in BANDS}
    cells = pixel_sphere_cells(bundle, lenses, medium, zenith_lens, grid_deg)
    full_scale = _full_scale_dn(bundle, lenses)
    snr = float(cfg["hdr_detection_snr"])
    n_exp = max(len(b.frames) for b in brackets)
    merged_cells, tables, dr, dr_pixels, info, centroids = [], [], [], [], [], []
    for br in brackets:
        raws = {f: read_raw(raw_paths[f]) for f in br.frames}
        terms = EXPOSURE_TERMS | ({"iso_gain"} if len({float(frames[i].iso) for i in br.frames}) > 1 else set())
        bins = SphereBins(len(BANDS), len(br.frames), grid_deg)
        extremes = [[] for _ in BANDS]      # per band, per lens: (brightest, faintest detected) merged pixel
        # one lens and band at a time: a bracket's maps of the full-size camera stay a few hundred MB
        for i, lens in enumerate(lenses):
            images = [split_lens(raws[f], bundle, lens) for f in br.frames]
            for b, band in enumerate(BANDS):
                maps = [exposure_maps(raws[f], bundle, chains, [lens], medium, effects, [band], {lens: img}, terms)
                        for f, img in zip(br.frames, images)]
                merged = merge_exposures(maps)
                bins.add(merged, cells[i:i + 1, b:b + 1], [b])
                tables.append(bracket_table(maps, br.name, [lens], full_scale[i:i + 1, b:b + 1],
                                            float(cfg["bracket_closure_min_snr"]),
                                            int(cfg["bracket_closure_signal_bins"]),
                                            float(cfg["bracket_closure_max_signal_fraction"]), [band]))
                values = merged.radiance.ravel()
                _, hi, lo = dynamic_range(values, np.hypot(merged.random_sigma, merged.fixed_sigma).ravel(), snr)
                if hi >= 0:
                    extremes[b].append((float(values[hi]), float(values[lo])))
                del maps, merged
            del images
        sphere = bins.result()
        merged_cells.append(sphere)
        dr.append([dynamic_range(sphere.radiance[b], sphere.random_sigma[b], snr, sphere.flag[b] > 0)[0]
                   for b in range(len(BANDS))])
        dr_pixels.append([float(np.log10(max(x[0] for x in e) / min(x[1] for x in e))) if e else float("nan")
                          for e in extremes])
        info.append((br.name, [frames[i] for i in br.frames]))
        if site is not None:
            shortest = raws[min(br.frames, key=lambda i: float(frames[i].exposure_s))]
            centroids.append(shortest_exposure_sun_centroid(shortest, bundle, chains, lenses, medium, effects,
                                                            zenith_lens, full_scale))
        del raws
    grids, exposure, flag, extra = _merged_grids(merged_cells, n_exp, bundle_path, info, medium)
    sun = None
    attitudes = None
    if site is not None:
        times = _frame_times_utc(grids, camera_utc_offset_h, "a site")
        solar = list(zip(*solar_position(times, *site)))
        logged = (attitude_at(read_attitude(attitude_path), times, grids.frame_names) if attitude_path is not None
                  else [LEVEL] * len(brackets))
        attitudes, fits = sun_attitudes(centroids, logged, solar, attitude_from_sun, grids.frame_names)
        sun = sun_dataset(centroids, attitudes, solar, grids.frame_names, float(cfg["sun_closure_z"]), fits)
    ds = light_field_of_grids(grids, attitude_path, site, camera_utc_offset_h, cfg, exposure, flag > 0, extra,
                              attitudes)
    ds = _with_sun_closure(ds, sun, attitude_from_sun, attitude_path, len(brackets), cfg)
    ds = _with_bracket_descriptions(ds, dr, dr_pixels, info, snr)
    ds = _with_bracket_consistency(ds, tables, effects, full)
    ds.attrs["title"] = "light field from exposure brackets merged into HDR sphere grids"
    ds.attrs["grid_files"] = f"made from {len(raw_paths)} raw frame(s) in {len(brackets)} bracket(s)"
    ds.attrs["calibration_bundle"] = str(bundle_path)
    ds.attrs["hdr"] = ("per band pixel, inverse-variance mean of the exposures where it is unsaturated and unflagged, "
                       "each through the chain at its own exposure; per-exposure systematic terms (shutter offset, "
                       "nonlinearity, dark model, black level) kept per exposure, band-common terms (R^-1, roll-off, "
                       "immersion factor) as the weighted mean of sigmas; cells with a pixel saturated in every "
                       "exposure flagged (hdr_cell_flag) with their lower bound")
    ds.attrs["bracket_grouping"] = (f"frames table {frames_table}" if frames_table is not None else
                                    f"frames within {float(cfg['bracket_window_s']):g} s of their bracket's first")
    return ds


def lightfield_command(args) -> int:
    """Run ``lightfield`` from parsed arguments; bad input prints one line and returns 1.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments of ``lightfield``.

    Returns
    -------
    int
        The exit status: 0 on success, 1 on bad input.
    """
    try:
        if Path(args.out).exists() and not args.overwrite:
            raise InputError(args.out, "exists (give --overwrite to replace it)")
        if args.grid_deg is not None and args.calibration is None:
            raise InputError(None, "--grid-deg applies to raw frames (--calibration); a grid file keeps its own cells")
        if (args.frames is not None or args.hdr) and args.calibration is None:
            raise InputError(None, "--frames and --hdr merge raw frames: they need --calibration")
        if args.frames is not None or args.hdr:
            ds = light_field_from_brackets(args.calibration, args.grids, args.frames, args.medium, args.attitude,
                                           args.site, args.camera_utc_offset_h, args.grid_deg,
                                           attitude_from_sun=args.attitude_from_sun)
        elif args.attitude_from_sun is not None:
            raise InputError(None, "--attitude-from-sun fits the sun in exposure brackets: it needs --calibration "
                                   "and --frames or --hdr")
        elif args.calibration is not None:
            ds = light_field_from_raw(args.calibration, args.grids, args.medium, args.attitude, args.site,
                                      args.camera_utc_offset_h, args.grid_deg)
        else:
            ds = compute_light_field(args.grids, args.medium, args.attitude, args.site, args.camera_utc_offset_h)
        out = write_light_field(ds, args.out, overwrite=args.overwrite)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"light field: {out}")
    return 0
