"""Versioned NetCDF artefacts: one per stage and lens, with provenance.

Every artefact carries, as global attributes, the stage name, the schema
version of that stage's output, the pipeline version, the creation time, the
sha256 of the configuration subset the stage used and of every input file, and
the effects of the model it was fitted with (docs/design.md); their variables' units
are UDUNITS-2 units on disk (:mod:`pipeline.io.units`). Files are written to
a temporary name and renamed, so a failed stage never leaves a half-written
artefact.
"""

from __future__ import annotations

import hashlib
import json
import os
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import xarray as xr

from pipeline import __version__
from pipeline.errors import ArtefactError
from pipeline.io.units import decode_units, encode_units

#: schema version of each stage's output; bump when a stage's variables change meaning, and say what changed
#: in docs/changelog.md (the history of every version is there)
ARTEFACT_VERSIONS = {"dark": 7, "linearity": 9, "geometry": 5, "rolloff": 9, "spectral": 4,
                     "absolute": 6, "immersion": 4, "calibration": 14, "field": 4, "closure": 7}

#: stages a calibration bundle is gathered from, in the order of the calibration chain
BUNDLE_STAGES = ("dark", "linearity", "geometry", "rolloff", "spectral", "absolute", "immersion")
#: without these a bundle gives no radiance: dark level, pixel directions, roll-off, R^-1
BUNDLE_REQUIRED_STAGES = ("dark", "linearity", "geometry", "rolloff", "absolute")


def sha256_file(path: str | Path, chunk: int = 1 << 22) -> str:
    """The sha256 digest of a file's bytes, read in blocks (the provenance of an artefact's inputs).

    Parameters
    ----------
    path : str or pathlib.Path
        The file to hash.
    chunk : int, default 4194304
        Bytes read at a time (4 MiB), which bounds the memory used for a large raw frame.

    Returns
    -------
    str
        The digest as 64 lowercase hexadecimal characters.
    """
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def config_sha256(config_subset: dict) -> str:
    """The sha256 digest of a configuration subset, as its keys-sorted JSON text.

    Parameters
    ----------
    config_subset : dict
        The configuration values a stage used; values JSON cannot write are written as their ``str``.

    Returns
    -------
    str
        The digest as 64 lowercase hexadecimal characters: equal for equal subsets whatever their keys' order.
    """
    text = json.dumps(config_subset, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


#: zlib level of the artefacts' larger variables: 1 writes the full-resolution maps in half the time of 4
#: for files 2 to 3 % larger (the linearity artefact of one lens 1.55 s and 47.1 MB against 3.05 s and
#: 46.2 MB, the geometry's 2.74 s and 95.3 MB against 4.58 s and 92.1 MB; reading them is as fast)
ARTEFACT_COMPRESSION_LEVEL = 1


def write_artefact(ds: xr.Dataset, path: str | Path, *, stage: str, inputs: dict[str, str],
                   config_subset: dict, effects: list[str], encoding: dict | None = None) -> Path:
    """Write ``ds`` with the provenance attributes; ``inputs`` maps file name -> sha256.

    Variables larger than 1024 values are stored zlib-compressed (level
    :data:`ARTEFACT_COMPRESSION_LEVEL`) unless ``encoding`` names them
    (netCDF4 encodings by variable) or their own encoding says ``zlib: False``
    (a stage's map that compresses too little to pay for it). Every ``units``
    is written spelled for UDUNITS-2, the camera's counting units (DN,
    electron, pixel) kept in ``camera_units`` (:mod:`pipeline.io.units`).

    Parameters
    ----------
    ds : xarray.Dataset
        The stage's output; not modified (the units are spelled for UDUNITS-2 in a copy).
    path : str or pathlib.Path
        The artefact's file; its folder is made if missing, an existing file replaced.
    stage : str
        The stage's name, a key of :data:`ARTEFACT_VERSIONS` (its schema version is written with it).
    inputs : dict[str, str]
        Input file name -> sha256 of its bytes (:func:`sha256_file`).
    config_subset : dict
        The configuration values the stage used, written as JSON text and as their digest
        (:func:`config_sha256`).
    effects : list[str]
        The names of the model's effects the stage fitted, written comma-separated in ``model_effects``.
    encoding : dict or None, optional
        netCDF4 encodings by variable name, overriding the default compression.

    Returns
    -------
    pathlib.Path
        The path written.
    """
    path = Path(path)
    ds = encode_units(ds)   # a copy, its units spelled for UDUNITS-2 (pipeline.io.units)
    ds.attrs.update({
        "Conventions": "CF-1.10",
        "artefact": stage,
        "artefact_version": ARTEFACT_VERSIONS[stage],
        "pipeline_version": __version__,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "config_sha256": config_sha256(config_subset),
        "config": json.dumps(config_subset, sort_keys=True, default=str),
        "input_sha256": json.dumps(inputs, sort_keys=True),
        "model_effects": ",".join(effects),
    })
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    default = {name: {"zlib": True, "complevel": ARTEFACT_COMPRESSION_LEVEL} for name, var in ds.data_vars.items()
               if var.dtype.kind in "fiub" and var.size > 1024 and var.encoding.get("zlib", True) is not False}
    encoding = {**default, **(encoding or {})}
    ds.to_netcdf(tmp, engine="netcdf4", encoding=encoding)
    os.replace(tmp, path)
    return path


def read_artefact(path: str | Path, stage: str, *, load: bool = True, load_below_bytes: int = 0) -> xr.Dataset:
    """Open a stage's artefact, refusing an unknown stage or version.

    Loaded into memory (and the file closed) by default; with ``load=False``
    the variables stay on disk until read and the caller closes the Dataset,
    except those of at most ``load_below_bytes`` bytes, read at once (the
    model parameters and tables a stage reads again at every frame; a
    variable left on disk is read and decompressed again at each access).
    The variables' units are those the stage wrote, in the camera's notation
    (:func:`pipeline.io.units.decode_units`).

    Parameters
    ----------
    path : str or pathlib.Path
        The artefact's file.
    stage : str
        The stage that must have written it, a key of :data:`ARTEFACT_VERSIONS`.
    load : bool, default True
        Read every variable into memory and close the file.
    load_below_bytes : int, default 0
        With ``load=False``, the size in bytes up to which a variable is read at once.

    Returns
    -------
    xarray.Dataset
        The artefact, its units in the camera's notation; with ``load=False`` still open on its file.

    Raises
    ------
    pipeline.errors.ArtefactError
        If the file is missing or not a readable NetCDF file, or was written by another stage or at another
        schema version than the supported one.
    """
    path = Path(path)
    if not path.exists():
        raise ArtefactError(path, f"{stage} artefact is missing; run the '{stage}' stage first")
    try:
        ds = xr.open_dataset(path, engine="netcdf4")
    except (OSError, ValueError) as exc:
        raise ArtefactError(path, f"not a readable NetCDF artefact ({exc.__class__.__name__})") from None
    try:
        found = ds.attrs.get("artefact")
        if found != stage:
            raise ArtefactError(path, f"is a '{found}' artefact, expected '{stage}'")
        version = int(ds.attrs.get("artefact_version", -1))
        if version != ARTEFACT_VERSIONS[stage]:
            raise ArtefactError(path, f"{stage} artefact version {version} is not the supported version "
                                      f"{ARTEFACT_VERSIONS[stage]}; rerun the '{stage}' stage")
        decode_units(ds)
        try:
            if load:
                ds.load()
            else:
                for var in ds.variables.values():
                    if var.nbytes <= load_below_bytes:
                        var.load()
        except (OSError, ValueError, RuntimeError) as exc:
            raise ArtefactError(path, f"not a readable NetCDF artefact ({exc.__class__.__name__})") from None
    except BaseException:
        ds.close()
        raise
    if load:
        ds.close()
    return ds


def mapped_variables(path: str | Path, ds: xr.Dataset, names) -> dict[str, np.ndarray]:
    """An artefact's variables ``names`` memory-mapped from its file, read-only, in their dims on disk.

    A variable is mapped only where its bytes on disk are its values: stored contiguous and
    uncompressed (the calibration bundle writes its per-pixel maps so), allocated, and decoded by
    xarray as stored (no scale or offset; no fill value, or NaN for a float variable, so that masking
    changes nothing); the others are left out (the caller reads them through NetCDF). ``ds`` is the
    file opened lazily (:func:`read_artefact` with ``load=False``), for the decoding. Mapping instead
    of reading saves copying the maps into fresh memory: ``apply`` then touches the page cache's pages
    where its chain uses them (179 MB of the full-resolution bundle with ``--no-pixels``).

    Parameters
    ----------
    path : str or pathlib.Path
        The artefact's file (a NetCDF-4, i.e. HDF5, file).
    ds : xarray.Dataset
        The same file opened lazily, whose variables give the dtypes, shapes and decoding to check against.
    names : iterable of str
        The variables to map.

    Returns
    -------
    dict[str, numpy.ndarray]
        Variable name -> a read-only array mapped on the file's bytes, for those of ``names`` that can be mapped;
        empty if h5py is not installed, the file has a user block or cannot be opened by HDF5.
    """
    try:
        import h5py
    except ImportError:  # an install without it reads the maps through NetCDF
        return {}
    out = {}
    try:
        with h5py.File(path, "r") as f:
            if f.userblock_size:
                return {}
            for name in names:
                var = ds[name].variable
                d = f.get(name)
                if d is None or not isinstance(d, h5py.Dataset) or d.chunks is not None or d.compression is not None \
                        or d.id.get_create_plist().get_nfilters() or d.dtype != var.dtype or d.shape != var.shape \
                        or d.dtype.kind not in "fiu":
                    continue
                enc = var.encoding
                if any(k in enc or k in var.attrs for k in ("scale_factor", "add_offset")):
                    continue
                fills = [enc.get(k, var.attrs.get(k)) for k in ("_FillValue", "missing_value")]
                if any(v is not None and not (d.dtype.kind == "f" and np.all(np.isnan(v))) for v in fills):
                    continue
                offset = d.id.get_offset()
                if offset is None or d.size == 0:
                    continue
                out[name] = np.memmap(path, dtype=d.dtype, mode="r", offset=offset, shape=d.shape).view(np.ndarray)
    except OSError:
        return {}
    return out


def read_artefact_mapped(path: str | Path, stage: str, *, lenses=None) -> xr.Dataset:
    """An artefact in memory with its file closed, its maps (variables over ``y`` and ``x``) memory-mapped
    where :func:`mapped_variables` can (their pages read when touched), every other variable read.

    ``lenses`` (default all) keeps those lenses, as a slice of the lens axis when they are adjacent in it
    (a view of the mapped maps; otherwise the maps are copied). The field stage reads of the calibration
    bundle's two lenses and media its lens's maps in air, a crop of them at every frame and the whole of
    them once: reading its lens whole (0.5 GB at the full resolution) cost it more than the crops.

    Parameters
    ----------
    path : str or pathlib.Path
        The artefact's file.
    stage : str
        The stage that must have written it (checked as by :func:`read_artefact`).
    lenses : sequence of str or None, optional
        The lenses to keep, by their labels on the ``lens`` axis; lenses absent from the file are ignored.
        ``None`` (default) keeps all.

    Returns
    -------
    xarray.Dataset
        The artefact, closed on its file, its ``(..., y, x)`` maps memory-mapped where possible.

    Raises
    ------
    pipeline.errors.ArtefactError
        As :func:`read_artefact`, and if a variable cannot be read.
    """
    with read_artefact(path, stage, load=False) as on_disk:
        names = [n for n, v in on_disk.data_vars.items() if v.dims[-2:] == ("y", "x")]
        mapped = mapped_variables(path, on_disk, names)
        ds = on_disk.assign({name: xr.Variable(on_disk[name].dims, array, on_disk[name].attrs)
                             for name, array in mapped.items()})
        if lenses is not None:
            present = list(on_disk["lens"].values)
            at = [present.index(lens) for lens in lenses if lens in present]
            adjacent = bool(at) and at == list(range(at[0], at[0] + len(at)))
            ds = ds.isel(lens=slice(at[0], at[0] + len(at)) if adjacent else at)
        try:
            ds = ds.load()
        except (OSError, ValueError, RuntimeError) as exc:
            raise ArtefactError(path, f"not a readable NetCDF artefact ({exc.__class__.__name__})") from None
    return ds


def model_effects(ds: xr.Dataset) -> list[str]:
    """The names of the model effects an artefact was fitted with, from its ``model_effects`` attribute.

    Parameters
    ----------
    ds : xarray.Dataset
        An artefact written by :func:`write_artefact`.

    Returns
    -------
    list[str]
        The effects' names in the order written; empty if the attribute is missing or empty.
    """
    text = ds.attrs.get("model_effects", "")
    return [e for e in text.split(",") if e]
