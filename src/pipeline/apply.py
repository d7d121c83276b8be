"""``apply``: raw frames to spectral radiance maps with uncertainty, per pixel and on the sphere.

Every band pixel of both lenses goes through the measurement chain of
:mod:`pipeline.radiometry.measurement` (the inverse of Eq. 4, Larouche et al.
2024, Section 2.1; Section 2.9: "pixel digital values were transformed into
calibrated spectral radiance using the inverse of Eq. (4)") with the
parameters of a calibration bundle (:mod:`pipeline.calibration`). The output
holds, per frame, lens and band: radiance (W sr-1 m-2 nm-1), its random and
systematic standard uncertainty, theta, phi, solid angle and a quality flag;
and the same binned onto a regular zenith/azimuth grid joining both lenses
into the full sphere (mean, spread and count of the pixels in each cell; NaN
where none falls).

Sphere convention: the lens named ``zenith_lens`` (default ``close``) looks
at the zenith, its pixel (theta, phi) is zenith angle theta and azimuth phi;
the other lens looks the opposite way (nadir): zenith angle 180 - theta and
azimuth -phi (mirrored, as a back-to-back lens sees its sensor's x axis
reversed), both mod 360.

A frame from another camera (make, model, serial), with an ISO or exposure
outside those the bundle was calibrated for, or for a medium the bundle
lacks, is refused with one line naming the file.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import xarray as xr

from pipeline.artefact import model_effects
from pipeline.bands import BANDS
from pipeline.calibration import band_parameters, calibrated_isos, read_bundle
from pipeline.config import defaults
from pipeline.errors import ImpossibleResult, InputError
from pipeline.frames import lens_images
from pipeline.radiometry import measurement as mm
from pipeline.rawio import read_raw

__all__ = ["apply_calibration", "check_frame", "sphere_coordinates", "bin_on_sphere", "add_apply_parser",
           "apply_command"]

#: flags that keep a pixel out of the sphere grid
EXCLUDED_FROM_GRID = (mm.FLAG_SATURATED | mm.FLAG_HOT | mm.FLAG_OUTSIDE_IMAGE_CIRCLE
                      | mm.FLAG_BEYOND_CALIBRATED_ANGLE)
ZENITH_LENS = "close"
SPHERE_CONVENTION = ("the {zenith} lens's optical axis is the zenith (zenith angle = theta, azimuth = phi); "
                     "the other lens looks at the nadir (zenith angle = 180 - theta, azimuth = -phi mod 360, mirrored); "
                     "theta, phi from the bundle's geometry maps (phi from the band image's +x towards +y)")


def check_frame(raw, bundle: xr.Dataset, effects) -> None:
    """Refuse a frame the bundle does not calibrate: another camera, ISO or exposure outside the calibrated range."""
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


def sphere_coordinates(theta_deg, phi_deg, looks_up: bool):
    """Zenith angle and azimuth (deg) of a lens pixel's direction, by the sphere convention of this module."""
    theta = np.asarray(theta_deg, float)
    phi = np.asarray(phi_deg, float)
    if looks_up:
        return theta, np.mod(phi, 360.0)
    return 180.0 - theta, np.mod(-phi, 360.0)


def bin_on_sphere(zenith_deg, azimuth_deg, values, grid_deg: float):
    """Mean, spread (standard deviation) and count of ``values`` per zenith/azimuth cell; NaN where empty.

    Every finite value falls into its cell (no nearest-pixel choice); the
    arrays returned have shape (180 / grid, 360 / grid).
    """
    n_z, n_a = int(round(180.0 / grid_deg)), int(round(360.0 / grid_deg))
    z = np.asarray(zenith_deg, float).ravel()
    a = np.asarray(azimuth_deg, float).ravel()
    v = np.asarray(values, float).ravel()
    ok = np.isfinite(z) & np.isfinite(a) & np.isfinite(v)
    iz = np.clip((z[ok] / grid_deg).astype(int), 0, n_z - 1)
    ia = np.clip((a[ok] / grid_deg).astype(int), 0, n_a - 1)
    cell = iz * n_a + ia
    count = np.bincount(cell, minlength=n_z * n_a).astype(float)
    total = np.bincount(cell, weights=v[ok], minlength=n_z * n_a)
    mean = np.where(count > 0, total / np.where(count > 0, count, 1), np.nan)
    dev = v[ok] - mean[cell]
    var = np.bincount(cell, weights=dev**2, minlength=n_z * n_a)
    spread = np.where(count > 1, np.sqrt(var / np.where(count > 1, count - 1, 1)), np.nan)
    shape = (n_z, n_a)
    return mean.reshape(shape), spread.reshape(shape), count.reshape(shape).astype(np.int32)


def _outside_circle(bundle: xr.Dataset, lens: str, medium: str, band: str, shape) -> np.ndarray:
    g = bundle.sel(lens=lens, medium=medium, band=band)
    y, x = np.indices(shape)
    r = np.hypot(x - float(g["circle_xc_px"]), y - float(g["circle_yc_px"]))
    theta = g["theta_deg"].values
    return (r > float(g["circle_radius_px"])) | ~np.isfinite(theta) | (theta > float(g["half_fov_deg"]))


def _frame_radiance(raw, bundle, medium, effects, negative_sigma):
    """Radiance, random and systematic sigma, flags of one decoded frame: arrays (lens, band, y, x)."""
    lenses = list(bundle["lens"].values)
    shape = bundle["theta_deg"].shape[-2:]
    out = {k: np.full((len(lenses), len(BANDS)) + shape, np.nan) for k in ("radiance", "random", "systematic")}
    flags = np.zeros((len(lenses), len(BANDS)) + shape, np.uint8)
    frame = mm.FrameSettings(exposure_s=float(raw.exposure_s), iso=float(raw.iso))
    for i, lens in enumerate(lenses):
        span = bundle["lens_region_px"].sel(lens=lens).values
        images = lens_images(raw, (tuple(span[0]), tuple(span[1])), lens)
        for j, band in enumerate(BANDS):
            image = images.bands[band]
            if image.shape != tuple(shape):
                raise InputError(raw.path, f"lens '{lens}' band image is {image.shape}, the calibration's {tuple(shape)}")
            dark, response, cal = band_parameters(bundle, lens, band, medium, frame, effects)
            theta = bundle["theta_deg"].sel(lens=lens, medium=medium, band=band).values.astype(float)
            theta = np.where(_outside_circle(bundle, lens, medium, band, shape), np.nan, theta)
            b = bundle.sel(lens=lens, band=band)
            m = mm.measure_band(image, frame, dark, response, cal, theta, medium, effects,
                                saturated=images.saturated[band],
                                hot_mask=b["hot_pixel_mask"].values if "hot_pixel_mask" in b else None,
                                flat_field=b["flat_field"].values if "flat_field" in b else None,
                                flat_field_sigma=b["flat_field_sigma"].values if "flat_field_sigma" in b else None,
                                prnu_sigma_rel=float(b["prnu_sigma_rel"]) if "prnu_sigma_rel" in b else 0.0,
                                phi_deg=bundle["phi_deg"].sel(lens=lens, medium=medium, band=band).values)
            inside = ~(m.flags & mm.FLAG_OUTSIDE_IMAGE_CIRCLE).astype(bool)
            good = inside & ~(m.flags & (mm.FLAG_SATURATED | mm.FLAG_HOT)).astype(bool) & np.isfinite(m.value)
            if good.any():
                mean = float(np.mean(m.value[good]))
                se = float(np.sqrt(np.sum(m.random_sigma[good] ** 2))) / good.sum()
                if mean < -negative_sigma * se:
                    raise ImpossibleResult(raw.path, f"lens {lens}, band {band}: mean radiance {mean:.3g} W sr-1 m-2 nm-1 "
                                                     f"over the image circle is {-mean / se:.1f} standard errors below "
                                                     "zero: the dark level or the calibration does not fit this frame")
            out["radiance"][i, j] = np.where(inside, m.value, np.nan)
            out["random"][i, j] = np.where(inside, m.random_sigma, np.nan)
            out["systematic"][i, j] = np.where(inside, m.systematic_sigma, np.nan)
            flags[i, j] = m.flags
    return out, flags


def _attrs(long_name, units, **extra):
    return {"long_name": long_name, "units": units, **extra}


def apply_calibration(bundle_path, raw_paths, medium: str, out_path, grid_deg: float | None = None, *,
                      overwrite: bool = False, zenith_lens: str = ZENITH_LENS, config: dict | None = None) -> Path:
    """Turn raw frames into radiance maps with the calibration bundle; write ``out_path`` (NetCDF).

    Returns the path written. Each frame is decoded once. The output is
    written to a temporary name and renamed; an existing ``out_path`` is
    replaced only with ``overwrite``.
    """
    config = config if config is not None else defaults()
    cfg = config["apply"]
    grid_deg = float(cfg["grid_deg"] if grid_deg is None else grid_deg)
    out_path = Path(out_path)
    if out_path.exists() and not overwrite:
        raise InputError(out_path, "exists; add --overwrite to replace it")
    bundle_path = Path(bundle_path)
    bundle = read_bundle(bundle_path)
    effects = model_effects(bundle)
    if medium not in _media(bundle):
        raise InputError(bundle_path, f"has no calibration for medium '{medium}' (media: {', '.join(_media(bundle))})")
    raw_paths = [Path(p) for p in raw_paths]
    if not raw_paths:
        raise InputError(None, "no raw frames to apply the calibration to")
    lenses = list(bundle["lens"].values)
    if zenith_lens not in lenses:
        zenith_lens = lenses[0]
    results, meta = [], []
    for path in raw_paths:
        raw = read_raw(path)
        check_frame(raw, bundle, effects)
        results.append(_frame_radiance(raw, bundle, medium, effects, float(cfg["negative_mean_sigma"])))
        meta.append((str(path), float(raw.exposure_s), float(raw.iso), raw.time.isoformat() if raw.time else ""))
    radiance = np.stack([r[0]["radiance"] for r in results])
    random = np.stack([r[0]["random"] for r in results])
    systematic = np.stack([r[0]["systematic"] for r in results])
    flags = np.stack([r[1] for r in results])
    geo = bundle[["theta_deg", "phi_deg", "solid_angle_sr"]].sel(medium=medium)
    zen = np.empty(geo["theta_deg"].shape)
    azi = np.empty_like(zen)
    for i, lens in enumerate(lenses):
        zen[i], azi[i] = sphere_coordinates(geo["theta_deg"].values[i], geo["phi_deg"].values[i], lens == zenith_lens)
    n_z, n_a = int(round(180.0 / grid_deg)), int(round(360.0 / grid_deg))
    grid = {k: np.full((len(raw_paths), len(BANDS), n_z, n_a), np.nan) for k in ("mean", "spread", "random", "systematic")}
    count = np.zeros((len(raw_paths), len(BANDS), n_z, n_a), np.int32)
    for f in range(len(raw_paths)):
        for j in range(len(BANDS)):
            use = (flags[f, :, j] & EXCLUDED_FROM_GRID) == 0
            val = np.where(use, radiance[f, :, j], np.nan)
            grid["mean"][f, j], grid["spread"][f, j], count[f, j] = bin_on_sphere(zen[:, j], azi[:, j], val, grid_deg)
            rnd, _, _ = bin_on_sphere(zen[:, j], azi[:, j], np.where(use, random[f, :, j] ** 2, np.nan), grid_deg)
            sy, _, _ = bin_on_sphere(zen[:, j], azi[:, j], np.where(use, systematic[f, :, j], np.nan), grid_deg)
            grid["random"][f, j] = np.sqrt(rnd / np.where(count[f, j] > 0, count[f, j], 1))
            grid["systematic"][f, j] = sy
    rad_units = "W sr-1 m-2 nm-1"
    convention = SPHERE_CONVENTION.format(zenith=zenith_lens)
    flag_values = np.array(list(mm.FLAG_MEANINGS.values()), np.uint8)
    ds = xr.Dataset(
        {
            "radiance": (("frame", "lens", "band", "y", "x"), radiance.astype(np.float32),
                         _attrs("effective spectral radiance of the band pixel, inverse of Eq. (4)", rad_units)),
            "radiance_random_sigma": (("frame", "lens", "band", "y", "x"), random.astype(np.float32),
                                      _attrs("random standard uncertainty (shot, read, dark noise), independent between "
                                             "pixels and frames", rad_units)),
            "radiance_systematic_sigma": (("frame", "lens", "band", "y", "x"), systematic.astype(np.float32),
                                          _attrs("systematic standard uncertainty (calibration terms), common to the "
                                                 "pixels of a band", rad_units)),
            "quality_flag": (("frame", "lens", "band", "y", "x"), flags,
                             {"long_name": "quality flag bits", "units": "1", "flag_masks": flag_values,
                              "flag_meanings": " ".join(mm.FLAG_MEANINGS)}),
            "theta_deg": (("lens", "band", "y", "x"), geo["theta_deg"].values,
                          _attrs("angle of the viewing direction from the lens's optical axis", "degree")),
            "phi_deg": (("lens", "band", "y", "x"), geo["phi_deg"].values,
                        _attrs("azimuth of the viewing direction about the lens's axis", "degree")),
            "solid_angle_sr": (("lens", "band", "y", "x"), geo["solid_angle_sr"].values,
                               _attrs("solid angle seen by the band pixel", "sr")),
            "zenith_deg": (("lens", "band", "y", "x"), zen, _attrs("zenith angle of the pixel's direction on the sphere", "degree",
                                                               convention=convention)),
            "azimuth_deg": (("lens", "band", "y", "x"), azi, _attrs("azimuth of the pixel's direction on the sphere", "degree",
                                                                convention=convention)),
            "sphere_radiance": (("frame", "band", "zenith", "azimuth"), grid["mean"],
                                _attrs("mean radiance of the unflagged pixels in the cell (NaN: no pixel)", rad_units)),
            "sphere_radiance_spread": (("frame", "band", "zenith", "azimuth"), grid["spread"],
                                       _attrs("standard deviation of the pixel radiances in the cell", rad_units)),
            "sphere_radiance_random_sigma": (("frame", "band", "zenith", "azimuth"), grid["random"],
                                             _attrs("random standard uncertainty of the cell mean", rad_units)),
            "sphere_radiance_systematic_sigma": (("frame", "band", "zenith", "azimuth"), grid["systematic"],
                                                 _attrs("systematic standard uncertainty of the cell mean", rad_units)),
            "sphere_count": (("frame", "band", "zenith", "azimuth"), count, _attrs("pixels binned into the cell", "1")),
            "frame_file": ("frame", np.array([m[0] for m in meta], dtype=str), {"long_name": "raw frame"}),
            "exposure_s": ("frame", np.array([m[1] for m in meta]), _attrs("exposure time (tag)", "s")),
            "iso": ("frame", np.array([m[2] for m in meta]), _attrs("ISO speed (tag)", "1")),
            "frame_time": ("frame", np.array([m[3] for m in meta], dtype=str), {"long_name": "DateTimeOriginal (tag)"}),
        },
        coords={
            "frame": np.arange(len(raw_paths)), "lens": lenses, "band": list(BANDS),
            "zenith": ("zenith", (np.arange(n_z) + 0.5) * grid_deg, _attrs("zenith angle of the cell centre", "degree")),
            "azimuth": ("azimuth", (np.arange(n_a) + 0.5) * grid_deg, _attrs("azimuth of the cell centre", "degree")),
        },
        attrs={
            "Conventions": "CF-1.10", "title": "spectral radiance from raw frames (Larouche et al. 2024, inverse of Eq. 4)",
            "medium": medium, "grid_deg": grid_deg, "sphere_convention": convention,
            "calibration_bundle": str(bundle_path), "calibration_created": bundle.attrs.get("created", ""),
            "camera_serial": bundle.attrs.get("camera_serial", ""), "model_effects": ",".join(effects),
            "uncertainty": "random: shot, read and dark noise of each pixel and frame, and the flat field's noise "
                           "(or PRNU where unmeasured) of each pixel; systematic: dark model, shutter offset, ISO gain, "
                           "nonlinearity, roll-off (and its azimuthal term), immersion factor and R^-1, common to a band",
        },
    )
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_name(f".{out_path.name}.tmp")
    # zlib level 1 with the byte shuffle: about as small as level 4 without it, and the write is most of
    # apply's time at the full scale (benchmarks/bench_apply.py)
    big = {name: {"zlib": True, "complevel": 1, "shuffle": True} for name, var in ds.data_vars.items()
           if var.dtype.kind in "fiu" and var.size > 1024}
    ds.to_netcdf(tmp, engine="netcdf4", encoding=big)
    os.replace(tmp, out_path)
    return out_path


# --------------------------------------------------------------------------- command line
def add_apply_parser(subparsers) -> argparse.ArgumentParser:
    """``apply --calibration BUNDLE [--medium air|water] RAW.dng... -o OUT.nc``."""
    p = subparsers.add_parser("apply", help="raw frames to radiance maps with a calibration bundle")
    p.add_argument("--calibration", required=True, help="calibration bundle (results/calibration/<serial>.nc)")
    p.add_argument("--medium", choices=("air", "water"), default="air")
    p.add_argument("raw", nargs="+", help="raw DNG frames of the calibrated camera")
    p.add_argument("-o", "--out", required=True, help="NetCDF file to write")
    p.add_argument("--grid-deg", type=float, default=None, help="zenith/azimuth cell size (default: apply.grid_deg)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    return p


def apply_command(args) -> int:
    """Run ``apply`` from parsed arguments; bad input prints one line and returns 1."""
    try:
        out = apply_calibration(args.calibration, args.raw, args.medium, args.out, args.grid_deg,
                                overwrite=args.overwrite)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"radiance: {out}")
    return 0
