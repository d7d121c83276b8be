"""Radiance sphere grids in: ``apply``'s sphere-grid format, or the same made by other software or by hand.

What a grid file needs (NetCDF, docs/light-field.md):

- ``sphere_radiance`` with dims (frame, band, zenith, azimuth) (``frame`` and
  ``band`` may be absent: one frame, one band), units of spectral radiance
  (any that convert to W m-2 sr-1 nm-1, such as uW cm-2 sr-1 nm-1), NaN where
  no lens measured;
- coordinates ``zenith`` and ``azimuth`` (degree) at the cell centres of a
  regular grid covering the sphere: zenith (i + 1/2) 180 / n, azimuth
  (j + 1/2) 360 / m;
- optionally ``sphere_radiance_random_sigma`` (independent from cell to cell)
  and ``sphere_radiance_systematic_sigma`` (common to every cell of a band,
  fully correlated), in radiance units (zero when absent, and the output says
  so); ``frame_time`` (ISO 8601, camera clock) when an attitude log or a site
  is given; the global attribute ``medium`` (air or water); the global
  attribute ``cell_values``: ``mean`` (each value the mean over its cell, as
  ``apply`` writes, recognised by its ``sphere_count``) or ``centre`` (the
  value at the cell centre, the default for other grids).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import xarray as xr

from pipeline.errors import InputError

__all__ = ["RADIANCE_UNITS", "SphereGrids", "read_sphere_grids", "GRID_VARIABLES"]

RADIANCE_UNITS = "W m-2 sr-1 nm-1"
GRID_VARIABLES = ("sphere_radiance", "sphere_radiance_random_sigma", "sphere_radiance_systematic_sigma")


@dataclass
class SphereGrids:
    """The frames of one or more grid files, in W m-2 sr-1 nm-1, dims (frame, band, zenith, azimuth)."""

    radiance: np.ndarray
    random_sigma: np.ndarray
    systematic_sigma: np.ndarray
    zenith_deg: np.ndarray
    azimuth_deg: np.ndarray
    bands: list
    frame_files: list            # the grid file of each frame
    frame_names: list            # the raw frame (``frame_file``) where the grid names it, else file:index
    frame_times: list            # ISO 8601 strings ('' where unknown)
    medium: str | None
    centre_samples: bool = False
    absent_sigmas: list = field(default_factory=list)


def _radiance_scale(units: str, path: Path, name: str) -> float:
    """Factor to W m-2 sr-1 nm-1 of a variable's units; bad units: one line."""
    import cf_units

    try:
        unit = cf_units.Unit(units)
    except ValueError:
        raise InputError(path, f"variable {name!r} has units {units!r}, which are not units "
                         f"(needs spectral radiance, e.g. {RADIANCE_UNITS})") from None
    target = cf_units.Unit(RADIANCE_UNITS)
    # udunits takes the steradian as dimensionless: a radiance must name it (sr-1) to be one
    if not unit.is_convertible(target) or "sr" not in units:
        raise InputError(path, f"variable {name!r} has units {units!r}, not spectral radiance "
                         f"(needs units convertible to {RADIANCE_UNITS})")
    return float(unit.convert(1.0, target))


def _centres(values, n_span: float, path: Path, name: str) -> np.ndarray:
    v = np.asarray(values, float)
    n = v.size
    expected = (np.arange(n) + 0.5) * n_span / max(n, 1)
    if n < 2 or not np.allclose(v, expected, rtol=0, atol=1e-6 * n_span / n):
        raise InputError(path, f"coordinate {name!r} is not the cell centres of a regular grid from 0 to "
                         f"{n_span:g} degrees ((i + 0.5) * {n_span:g} / n)")
    return v


def _one(path: Path) -> tuple[xr.Dataset, dict]:
    try:
        ds = xr.open_dataset(path)
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except (OSError, ValueError) as exc:
        raise InputError(path, f"cannot read as NetCDF ({exc.__class__.__name__})") from None
    if "sphere_radiance" not in ds:
        raise InputError(path, "lacks the variable 'sphere_radiance' (radiance on the zenith/azimuth grid, "
                         "dims (frame, band, zenith, azimuth))")
    rad = ds["sphere_radiance"]
    extra = set(rad.dims) - {"frame", "band", "zenith", "azimuth"}
    if not {"zenith", "azimuth"} <= set(rad.dims) or extra:
        raise InputError(path, f"'sphere_radiance' has dims {rad.dims}; needs (frame, band, zenith, azimuth), "
                         "frame and band optional")
    for coord in ("zenith", "azimuth"):
        if coord not in ds.coords:
            raise InputError(path, f"lacks the coordinate {coord!r} (cell centres, degree)")
        units = str(ds[coord].attrs.get("units", ""))
        if units not in ("degree", "degrees", "deg") and units != "":
            raise InputError(path, f"coordinate {coord!r} has units {units!r}; needs degree")
        if units == "":
            raise InputError(path, f"coordinate {coord!r} has no units; needs units = 'degree'")
    info = {"zenith": _centres(ds["zenith"].values, 180.0, path, "zenith"),
            "azimuth": _centres(ds["azimuth"].values, 360.0, path, "azimuth")}
    return ds, info


def _array(ds: xr.Dataset, name: str, path: Path) -> np.ndarray | None:
    if name not in ds:
        return None
    var = ds[name]
    if set(var.dims) != set(ds["sphere_radiance"].dims):
        raise InputError(path, f"variable {name!r} has dims {var.dims}, not those of 'sphere_radiance'")
    if "units" not in var.attrs:
        raise InputError(path, f"variable {name!r} has no units (needs spectral radiance, e.g. {RADIANCE_UNITS})")
    scale = _radiance_scale(str(var.attrs["units"]), path, name)
    for dim in ("frame", "band"):
        if dim not in var.dims:
            var = var.expand_dims(dim)
    values = var.transpose("frame", "band", "zenith", "azimuth").values.astype(float) * scale
    if np.isinf(values).any():
        raise InputError(path, f"variable {name!r} holds infinite values")
    return values


def read_sphere_grids(paths, medium: str | None = None) -> SphereGrids:
    """Read and check the grid files (frames concatenated in the order given); bad input: one line.

    Parameters
    ----------
    paths : sequence of str or pathlib.Path
        The grid files (NetCDF as ``apply`` writes them, or made by hand).
    medium : str, optional
        The medium given on the command line ("air" or "water"), checked against the files'.

    Returns
    -------
    SphereGrids
        Radiance and its sigmas (W m-2 sr-1 nm-1, dims frame, band, zenith, azimuth), the cell centres (degree)
        and the frames' files, names and times.

    Raises
    ------
    InputError
        When a file cannot be read or checked, the grids or bands differ between files, or the media disagree.
    """
    parts = []
    for p in paths:
        path = Path(p)
        ds, info = _one(path)
        with ds:
            arrays = {name: _array(ds, name, path) for name in GRID_VARIABLES}
            rad = arrays["sphere_radiance"]
            bands = [str(b) for b in ds["band"].values] if "band" in ds["sphere_radiance"].dims and "band" in ds.coords \
                else [str(i) for i in range(rad.shape[1])]
            n_frames = rad.shape[0]
            files = [str(v) for v in ds["frame_file"].values] if "frame_file" in ds else \
                [f"{path.name}:{i}" for i in range(n_frames)]
            times = [str(v) for v in ds["frame_time"].values] if "frame_time" in ds else [""] * n_frames
            grid_medium = str(ds.attrs["medium"]) if "medium" in ds.attrs else None
            cell_values = str(ds.attrs.get("cell_values", "mean" if "sphere_count" in ds else "centre"))
        if cell_values not in ("mean", "centre"):
            raise InputError(path, f"attribute cell_values = {cell_values!r}; needs mean or centre")
        if grid_medium is not None and grid_medium not in ("air", "water"):
            raise InputError(path, f"attribute medium = {grid_medium!r}; needs air or water")
        if medium is not None and grid_medium is not None and grid_medium != medium:
            raise InputError(path, f"the grid is for medium {grid_medium!r}, but --medium {medium} was given")
        parts.append((path, info, arrays, bands, files, times, grid_medium, cell_values == "centre"))
    first = parts[0]
    for path, info, _, bands, *_ in parts[1:]:
        if info["zenith"].size != first[1]["zenith"].size or info["azimuth"].size != first[1]["azimuth"].size:
            raise InputError(path, f"its grid ({info['zenith'].size} x {info['azimuth'].size} cells) differs from "
                             f"{first[0]}'s ({first[1]['zenith'].size} x {first[1]['azimuth'].size})")
        if bands != first[3]:
            raise InputError(path, f"its bands {bands} differ from {first[0]}'s {first[3]}")
    media = {p[6] for p in parts if p[6] is not None}
    if len(media) > 1:
        raise InputError(parts[-1][0], f"grids of different media ({', '.join(sorted(media))}) given together")
    absent = sorted({name for p in parts for name in GRID_VARIABLES[1:] if p[2][name] is None})

    def stack(name):
        return np.concatenate([p[2][name] if p[2][name] is not None else np.zeros_like(p[2]["sphere_radiance"])
                               for p in parts], axis=0)
    return SphereGrids(stack("sphere_radiance"), stack("sphere_radiance_random_sigma"),
                       stack("sphere_radiance_systematic_sigma"), first[1]["zenith"], first[1]["azimuth"], first[3],
                       [str(p[0]) for p in parts for _ in p[4]], [f for p in parts for f in p[4]],
                       [t for p in parts for t in p[5]], medium or (media.pop() if media else None),
                       any(p[7] for p in parts), absent)
