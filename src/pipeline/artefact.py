"""Versioned NetCDF artefacts: one per stage and lens, with provenance.

Every artefact carries, as global attributes, the stage name, the schema
version of that stage's output, the pipeline version, the creation time, the
sha256 of the configuration subset the stage used and of every input file, and
the effects of the model it was fitted with (docs/design.md); their variables' units
are UDUNITS-2 units on disk (:mod:`pipeline.units`). Files are written to
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
from pipeline.units import decode_units, encode_units

#: schema version of each stage's output; bump when a stage's variables change meaning.
#: linearity 2: saturation found in the data (saturation_dn NaN when not reached, its lower bound,
#: the count of saturated settings); spectral 2 and absolute 2: frames corrected by the fitted
#: response (linearity artefact) and, for absolute, a 'response' term in the budget; immersion 2:
#: the same for its air and water frames; calibration 2: the per-pixel maps stored uncompressed and
#: contiguous (a band image of one lens and medium reads as one block), see pipeline.calibration;
#: calibration 3: the azimuthal roll-off term (amplitude, phase, their sigmas) and the flat field's per-pixel
#: uncertainty, which the chain applies; linearity 3: the flat field (map, its sigma, the ``flat`` rows) taken
#: on the linearised signal, the photon-transfer gain fitted with one zero-signal intercept per band, weights of
#: the model and (with ``bias_drift``) the frames' common offsets removed (``offset_var_dn2`` in ``obs_setting``);
#: absolute 3: the lamp term of R^-1's budget counts only the part
#: of the calibration lamp's error that survives the rescaling at 589 nm (absolute.lamp_model); field 2:
#: the stray_light covariate (sun seen, clear-sky direct beam, sun_glare_proxy) in the match-up table and,
#: with the effect in the model, the fitted sun glare; geometry 2: the covariance of the fitted model and
#: the theta uncertainty it gives (theta_deg_sigma per band pixel, a 1-D summary); calibration 5: the
#: linearity of version 3, the absolute budget of version 3, theta_deg_sigma, and apply's precomputed maps (see pipeline.calibration);
#: dark 2 and linearity 4: the bias drift's spread (bias_drift_dn and its interval, and the frame noise
#: it is removed from) weighted by the corners' own noise, its interval from the number of raw frames, not of
#: lens x band rows (the rows of one frame share its offset), see effects.catalogue.drift_sigma; calibration 6:
#: the dark and linearity of these versions; rolloff 2: the in-water closure predicts each water point from
#: the air fit and the immersion physics (``obs_water`` gains ``theta_air_deg``, ``theta_air_sigma_deg``,
#: ``deg_per_px_air``, ``water_factor``, ``air_prediction_sigma``; ``water_compression`` gives way to
#: ``water_closure_scale`` and its sigma); dark 3 and linearity 5: the lens region's ``projection``, the
#: frames' black-level reference (``bias_reference``: unlit corners, optically black pixels of the DNG, or
#: none, when ``bias_drift`` is not testable and ``bias_drift_dn`` is NaN), the dark's
#: ``optical_black_offset_dn`` and linearity's ``n_corner_sites`` in ``obs_frame``, the dark histograms' range
#: moved to a dark level outside the configured one, and with ``bias_drift`` the read and temporal noise
#: without the frames' common offsets (linearity: the flat field's noise too); calibration 7: those;
#: geometry 3: the ``projection`` attribute, and for a rectilinear region the pinhole fit's variables
#: (``pinhole_parameters`` and their covariance; no image circle), see stages.geometry_rectilinear;
#: calibration 8: a lens's ``projection`` and ``bias_reference``, the dark's ``optical_black_offset_dn``,
#: a rectilinear lens's geometry without the fisheye model's variables (NaN) and no image circle;
#: calibration 9: the per-pixel factors in apply's compact form (pixel_factor, pixel_flag, ...), see
#: pipeline.calibration; calibration 10: ``sphere_cell_in_block`` with a second spill value (the block's
#: cell count + 1) for the pixels inside the image circle, not hot, but off the grid (beyond the
#: calibrated field angle), so that apply takes its negative-mean sums from the grid's sums.
#: closure 1: the diagnostics' closure table
#: (``results/closure/residuals.nc``, one row per measurement of every experiment, pipeline.diagnostics).
#: rolloff 3: ``obs_setting`` gains the frames' ``exposure_s`` and ``iso`` (the cross-experiment closure turns
#: the on-axis DN into DN per second); closure 2: the cross-experiment tables (experiment ``closure``, levels
#: ``responsivity`` and ``dark_corners``, pipeline.cross_closure) among its rows; field 3: the match-up's
#: noise with the mask's pointing term (``sky_gradient``, ``mask_pointing_sigma``), see stages.field;
#: linearity 6: ``obs_frame`` and ``obs_setting`` gain the raw files' ``white_level_dn`` and the signal level
#: ``signal_fraction`` (predicted signal above black over the range between the black and the white level);
#: closure 3: the ``signal_fraction`` covariate (NaN where a table has none), scanned by the residual tests;
#: geometry 4: ``geometry_parameter_covariance`` (and from it ``theta_deg_sigma``) by default a leave-one-board-out
#: jackknife (attribute ``estimate`` ``board_jackknife``); rolloff 4: ``obs_setting`` and ``obs_water`` gain the
#: principal point's nuisance columns ``x_centre_1``, ``x_centre_2``, rows of kind ``centre_prior`` holding their
#: prior, and the spots' gradients of theta in the centre (``theta_centre_grad_*``, ``theta_sigma_deg``);
#: calibration 11: the bundle's ``theta_deg_sigma`` and field-angle variance from the jackknife covariance,
#: beside version 10's second spill cell; calibration 12: ``sphere_cell_count`` and ``sphere_checked_count``, the
#: pixels of each sphere cell and of apply's negative-mean check per lens, medium and band (apply counts none).
#: closure 4: the recorded diagnostics config gains ``closure_source_level_rel_sigma`` (the source's level between
#: the lenses' sessions, in quadrature on every responsivity row; default 0 leaves the rows as in version 3).
#: geometry 5: the image circle (``circle_*``, hence ``half_fov_deg``) fitted to the edge of the lit region of the
#: frames' maximum (``geometry.image_circle_lit_fraction``), no longer to its strongest edge (the boards' white
#: squares: radius up to 9.7 of 29 band px short on the tiny scale); calibration 13: that geometry;
#: rolloff 5: settings whose port spot cannot be measured (no light above the noise, the port beyond the lit field's edge)
#: dropped, counted in ``n_settings_dropped`` with their reasons.
#: linearity 7: ``obs_corner``, each lit frame's unlit-corner mean against the dark model's prediction there
#: with its noise and the frame's time stamp (pipeline.radiometry.unlit_corners; the same values as ``obs_frame``'s
#: ``corner_dn``, ``dark_corner_dn``, ``sigma_corner_dn``), for the dark-corner closure over every lit stage.
#: rolloff 6, spectral 3, absolute 4, immersion 3: ``obs_corner``, the same per-frame record of each lit (signal)
#: frame's unlit corners against the dark model, with the stage's own keys (rolloff: ``medium``, ``azimuth_deg``,
#: ``angle_deg``; spectral: ``wavelength_nm``; immersion: ``medium``, ``water_height_cm``), when the stage is given
#: the dark artefact; closure 5: ``closure/dark_corners`` holds the rows of every lit experiment (covariate
#: ``experiment``), not the linearity's alone.
#: closure 5 also: the field-angle table (level ``field_angle``, pipeline.field_angle_closure: the geometry
#: against the roll-off's rotation stage) among its rows, its prior rows of kind ``geometry_prior``; the
#: recorded diagnostics config gains ``closure_spot_centroid_sigma_px``.
#: dark 4: with ``bias_drift`` a setting's sigma leaves out the corners' noise that each frame's correction adds to
#: the frame (the corners' deviations from their setting mean sum to zero over its frames).
#: closure 6: ``source_experiment``, the experiment whose frames each row measures (a dark-corner row's lit
#: experiment, which ``experiment``, ``closure`` on those rows, cannot hold).
#: dark 5: ``fpn_corner_mean_dn``, the offset map averaged over the unlit corners (with the corner fraction it
#: was made with), so that a lit stage's corner prediction does not decompress the whole map.
#: rolloff 7: the spots' pixels through the linearity artefact's fitted nonlinearity and flat field, the
#: nonlinearity's uncertainty in ``rolloff_covariance`` (``rolloff_nonlinearity_shift``), ``response_corrections``.
#: rolloff 8: ``obs_setting`` gains the G spot centroid's standard uncertainty per axis (``spot_x_sigma_px``,
#: ``spot_y_sigma_px``: pixel noise, the frames' scatter through the cut, the grid's sampling) and its terms;
#: closure 7: the field-angle rows' noise is that uncertainty through the lens model's d a / d (u, v), no longer
#: ``closure_spot_centroid_sigma_px`` (gone from the recorded diagnostics config) times the degrees per pixel.
#: dark 6: with ``hot_pixels`` in the model, ``fpn_corner_mean_dn`` averages the corner pixels that are not hot
#: (attribute ``hot_pixels_excluded``); linearity 8, rolloff 9, spectral 4, absolute 5, immersion 4: each lit
#: frame's corner mean (``obs_corner``) leaves out the dark stage's hot pixels where the dark model does, so that
#: it is the level that model predicts (pipeline.radiometry.unlit_corners.corner_sites).
#: absolute 6: the signal frames' setting and level (``exposure_s``, ``iso``, ``signal_dn``), in the bundle (calibration
#: 14) as ``absolute_exposure_s``, ``absolute_iso``, ``absolute_signal_dn``; field 4: the field scale closure
#: (``obs_scale``: the camera/reference scale of each band against its prediction and its stated budget).
#: No version changed when the units on disk became UDUNITS-2 units (DN, electron and pixel as counts, the camera's
#: spelling in ``camera_units``, pipeline.units): the values and their meaning are the same, and read_artefact
#: gives a file of either spelling the same units.
ARTEFACT_VERSIONS = {"dark": 6, "linearity": 8, "geometry": 5, "rolloff": 9, "spectral": 4,
                     "absolute": 6, "immersion": 4, "calibration": 14, "field": 4, "closure": 7}

#: stages a calibration bundle is gathered from, in the order of the calibration chain
BUNDLE_STAGES = ("dark", "linearity", "geometry", "rolloff", "spectral", "absolute", "immersion")
#: without these a bundle gives no radiance: dark level, pixel directions, roll-off, R^-1
BUNDLE_REQUIRED_STAGES = ("dark", "linearity", "geometry", "rolloff", "absolute")


def sha256_file(path: str | Path, chunk: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def config_sha256(config_subset: dict) -> str:
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
    electron, pixel) kept in ``camera_units`` (:mod:`pipeline.units`).
    """
    path = Path(path)
    ds = encode_units(ds)   # a copy, its units spelled for UDUNITS-2 (pipeline.units)
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
    (:func:`pipeline.units.decode_units`).
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
    text = ds.attrs.get("model_effects", "")
    return [e for e in text.split(",") if e]
