"""Absolute spectral-radiance stage (Larouche et al. 2024, Sections 2.1, 2.6 and 3.5; Table 1, Fig. 7).

Per lens and band:

* the source spectrum (``absolute/source_spectrum.csv``, relative) is scaled
  so that its value at the reference wavelength (589 nm) equals the C-OPS
  reading (``absolute/source_reference.csv``), Section 2.6;
* its effective band radiance by Eq. (3), with the MEASURED peak-normalised
  response of the spectral artefact, linearly interpolated onto the
  spectrometer's wavelengths inside the measured range (400-700 nm) and zero
  outside it (unmeasured: with the simulator's default response this drops
  the B tail below 400 nm, about +0.9 % on B's L and R^-1);
* y_DN, Eq. (2): dark-subtracted mean DN in the ``absolute.mask_half_angle_deg``
  mask (geometry artefact, in air), divided by exposure time and ISO/100;
  when the lens's linearity artefact is given, each pixel of the mask goes
  through the measurement chain's ``linearise`` and ``normalise_exposure``
  (:func:`pipeline.radiometry.response.response_corrected`) with the effects
  that artefact fitted (nonlinearity, true exposure t + dt, gain ISO/100 f_ISO,
  and its flat field when it fitted ``prnu``),
  as ``apply`` does; the artefact's ``response_corrections`` attribute names
  them, and their fitted uncertainties are the budget's ``response`` term;
* R^-1 = L / y_DN, Eq. (9), and its uncertainty budget
  (:func:`pipeline.radiometry.absolute.absolute_calibration_budget`):
  spectrometer calibration lamp (manufacturer 9.1 % at 400 nm to 6.9 % at
  800 nm; by default, ``absolute.lamp_model: colour_temperature``, only its
  shape part that survives the rescaling at 589 nm, about 0.1-0.9 %; the
  paper's full counting, about 8 %, with ``lamp_model: profile``), reference
  reading (its ``uncertainty_rel``, 2.5 %), spectrometer noise
  (``radiance_std``), the user's named extra source terms
  (``absolute.extra_uncertainty``, none by default), and image statistics (the
  spread of the averaging region by default, as Section 3.5 says).  The
  reference reading dominates by default.  The spectral response's own
  uncertainty is left out, as in the paper (R^-1 x y_DN gives Eq. 3 back).

Dark level: the experiment's dark frames at the same setting, or the dark
artefact's model when there are none (:func:`pipeline.stages.spectral.dark_levels`).

Observation table (closure): frame level, one row per frame, lens and band
(signal and dark frames): ``value_dn`` the dark-corrected mask mean
(linearised when the nonlinearity was fitted), ``sigma_dn`` its temporal
noise, ``dn_per_s`` and ``dn_per_s_sigma`` the same through the response
corrections, one free level per group
``lens/band/kind/setting`` (``x_level``); covariates ``frame``, ``iso``,
``exposure_s``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.io.bands import BANDS
from pipeline.io.dataset import read_source_reference, read_source_spectrum
from pipeline.errors import InputError
from pipeline.radiometry.absolute import (absolute_calibration_budget, lamp_calibration_relative_sigma,
                                          lamp_colour_temperature_shape_nm)
from pipeline.stages.observations import table_to_dataset, with_corner_table
from pipeline.radiometry.measurement import FrameSettings
from pipeline.radiometry.response import flat_field_at, response_corrected, response_effects
from pipeline.radiometry.source import scale_to_reference
from pipeline.stages.spectral import frame_table, reduce_lens_central

STAGE = "absolute"
TERMS = ("lamp_calibration", "reference", "spectrometer_noise", "extra", "image", "response")


def extra_components(cfg: dict) -> dict[str, float]:
    """The user's named source-radiance uncertainties (``absolute.extra_uncertainty``), name -> relative sigma.

    Parameters
    ----------
    cfg : dict
        The ``absolute`` section of the configuration.

    Returns
    -------
    dict[str, float]
        Name -> relative standard uncertainty of the source radiance; empty when none is given.

    Raises
    ------
    pipeline.errors.InputError
        If a name is given twice.
    """
    out = {}
    for item in cfg.get("extra_uncertainty", []):
        if item["name"] in out:
            raise InputError(None, f"config absolute.extra_uncertainty: the name '{item['name']}' is given twice")
        out[item["name"]] = float(item["relative_sigma"])
    return out


def reference_reading(table: pd.DataFrame, path: Path, wavelength_nm: float,
                      tolerance_nm: float = 0.5) -> tuple[float, float]:
    """The reference radiance (W sr-1 m-2 nm-1) and its relative uncertainty at ``wavelength_nm``.

    Parameters
    ----------
    table : pandas.DataFrame
        The source reference readings (:func:`pipeline.io.dataset.read_source_reference`).
    path : pathlib.Path
        Their file, named in the errors.
    wavelength_nm : float
        The reference wavelength, nm (``absolute.reference_wavelength_nm``).
    tolerance_nm : float, default 0.5
        How far from it a reading may be, nm.

    Returns
    -------
    radiance : float
        The port's radiance at that wavelength, W sr-1 m-2 nm-1.
    relative_sigma : float
        Its relative standard uncertainty.

    Raises
    ------
    pipeline.errors.InputError
        If no reading, or more than one, lies within the tolerance.
    """
    hit = np.flatnonzero(np.abs(table["wavelength_nm"].to_numpy(float) - wavelength_nm) <= tolerance_nm)
    if hit.size == 0:
        raise InputError(path, f"no reading at {wavelength_nm:g} nm (needed to scale the source spectrum)")
    if hit.size > 1:
        raise InputError(path, f"more than one reading at {wavelength_nm:g} nm")
    row = table.iloc[hit[0]]
    return float(row["radiance_W_sr_m2_nm"]), float(row["uncertainty_rel"])


def check_spectrum(spectrum: pd.DataFrame, path: Path, reference_nm: float, response_nm: np.ndarray) -> None:
    """Check the source's relative spectrum before it is used: increasing wavelengths covering the reference and the response.

    Parameters
    ----------
    spectrum : pandas.DataFrame
        The relative spectrum (:func:`pipeline.io.dataset.read_source_spectrum`).
    path : pathlib.Path
        Its file, named in the errors.
    reference_nm : float
        The reference wavelength the spectrum is scaled at, nm.
    response_nm : numpy.ndarray
        The wavelengths of the measured spectral response, nm, ascending.

    Raises
    ------
    pipeline.errors.InputError
        If the wavelengths do not increase strictly, do not cover the reference wavelength or the response's
        range, or a radiance is negative.
    """
    wl = spectrum["wavelength_nm"].to_numpy(float)
    if np.any(np.diff(wl) <= 0):
        raise InputError(path, "wavelength_nm must increase strictly")
    if not (wl[0] <= reference_nm <= wl[-1]):
        raise InputError(path, f"does not cover the reference wavelength {reference_nm:g} nm")
    if wl[0] > response_nm[0] or wl[-1] < response_nm[-1]:
        raise InputError(path, f"covers {wl[0]:g}-{wl[-1]:g} nm, not the measured response range "
                               f"{response_nm[0]:g}-{response_nm[-1]:g} nm")
    if np.any(spectrum["radiance"].to_numpy(float) < 0):
        raise InputError(path, "radiance must not be negative")


def response_on_grid(wavelength_nm: np.ndarray, response_nm: np.ndarray, response: np.ndarray) -> np.ndarray:
    """Measured response linearly interpolated onto ``wavelength_nm``; zero outside its range.

    Parameters
    ----------
    wavelength_nm : numpy.ndarray
        The wavelengths to interpolate to, nm.
    response_nm : numpy.ndarray
        The wavelengths of the measured response, nm, ascending.
    response : numpy.ndarray
        The relative spectral response at ``response_nm``.

    Returns
    -------
    numpy.ndarray
        The response at ``wavelength_nm``, shape of ``wavelength_nm``.
    """
    return np.interp(wavelength_nm, response_nm, response, left=0.0, right=0.0)


def analyse_absolute(reduced: dict, darks: dict, spectral: dict[str, xr.Dataset], spectrum: pd.DataFrame,
                     spectrum_path: Path, reference: tuple[float, float], config: dict,
                     linearity: dict[str, xr.Dataset] | None = None) -> dict[str, xr.Dataset]:
    """R^-1 and its budget per lens and band.

    Parameters
    ----------
    reduced : dict
        What :func:`pipeline.stages.spectral.reduce_central` returned for the absolute frames.
    darks : dict
        What :func:`pipeline.stages.spectral.dark_levels` returned.
    spectral : dict[str, xarray.Dataset]
        Lens -> its spectral artefact (the relative spectral response).
    spectrum : pandas.DataFrame
        The source's relative spectrum (:func:`pipeline.io.dataset.read_source_spectrum`).
    spectrum_path : pathlib.Path
        Its file, named in the errors (its folder's frames.csv too).
    reference : tuple[float, float]
        The reference radiance (W sr-1 m-2 nm-1) and its relative uncertainty (:func:`reference_reading`).
    config : dict
        The run's configuration (section ``absolute``).
    linearity : dict[str, xarray.Dataset] or None, optional
        Lens -> its linearity artefact, which corrects y_DN through the chain's response steps.

    Returns
    -------
    dict[str, xarray.Dataset]
        Lens -> its absolute artefact: the inverse responsivity R^-1 (W sr-1 m-2 nm-1 s DN-1) with its
        uncertainty and budget by term, the effective band radiance (W sr-1 m-2 nm-1), the signal (DN s-1) and
        the frame table.

    Raises
    ------
    pipeline.errors.InputError
        If the mask saturates, a lens has no spectral artefact or no signal frames, the spectrum fails
        :func:`check_spectrum`, or the lamp settings are inconsistent.
    """
    cfg = config[STAGE]
    moments = reduced["moments"]
    linearity = linearity or {}
    fr = frame_table(reduced, darks, linearity)
    if fr[fr["kind"] == "signal"]["saturated"].any():
        raise InputError(spectrum_path.parent / "frames.csv", "saturated pixels in the averaging mask")
    wl = spectrum["wavelength_nm"].to_numpy(float)
    spec = spectrum["radiance"].to_numpy(float)
    spec_std = spectrum["radiance_std"].to_numpy(float)
    ref_value, ref_rel = reference
    if cfg["lamp_model"] == "profile":
        lamp = lamp_calibration_relative_sigma(wl, cfg["lamp_relative_sigma_400nm"], cfg["lamp_relative_sigma_800nm"])
    else:
        lamp = (cfg["lamp_relative_sigma_400nm"], cfg["lamp_relative_sigma_800nm"])
        try:
            lamp_colour_temperature_shape_nm(*lamp)
        except ValueError as exc:
            raise InputError(None, f"config absolute: {exc}") from None
    out = {}
    for lens in sorted({k[0] for k in moments}):
        if lens not in spectral:
            raise InputError(None, f"no spectral artefact for lens {lens}")
        sp = spectral[lens]
        lin = linearity.get(lens)
        resp_nm = sp["wavelength_nm"].values.astype(float)
        check_spectrum(spectrum, spectrum_path, cfg["reference_wavelength_nm"], resp_nm)
        rows = []
        for band in BANDS:
            keys = [k for k in moments if k[0] == lens and k[1] == band and k[2] == "signal"]
            if not keys:
                raise InputError(spectrum_path.parent / "frames.csv", f"no signal frames for lens {lens}")
            # Eq. (2) per setting through the chain's response steps, then the frame-weighted mean
            # over settings (usually one: ISO 100, 0.1 s)
            y, y_var_std, y_var_se, y_resp_sum, n_tot, n_mask = 0.0, 0.0, 0.0, 0.0, 0, 0
            for k in keys:
                mom = moments[k]
                d = darks[(lens, band, k[4], k[5])]
                mean_map = mom.mean()
                n_mask = mean_map.size
                frame = FrameSettings(exposure_s=k[5], iso=k[4])
                se_dn = np.sqrt(float(mom.variance().mean()) / n_mask / mom.n + d["sigma_dn"] ** 2)
                flat = flat_field_at(lin, band, reduced["masks"][(lens, band)])
                _, pixels = response_corrected(mean_map - d["level_dn"], lin, band, frame, flat_field=flat)
                _, mean = response_corrected(float(mean_map.mean()) - d["level_dn"], lin, band, frame, se_dn)
                y_k = float(np.mean(pixels.value))
                region_std = float(np.std(pixels.value, ddof=1))
                y += y_k * mom.n
                y_var_std += (region_std * mom.n) ** 2
                y_var_se += (float(mean.random_sigma) * mom.n) ** 2
                # the fitted response parameters are common to all settings: their errors add linearly
                y_resp_sum += float(mean.systematic_sigma) * mom.n
                n_tot += mom.n
            y /= n_tot
            # the signal frames' setting (frame-weighted): where the field scale closure evaluates the response
            # effects the model lacks against the field frames' (stages.field)
            t_mean = sum(k[5] * moments[k].n for k in keys) / n_tot
            iso_mean = sum(k[4] * moments[k].n for k in keys) / n_tot
            y_std = np.sqrt(y_var_std) / n_tot
            y_se = np.sqrt(y_var_se) / n_tot
            y_resp = y_resp_sum / n_tot
            y_sigma = y_std if cfg["image_sigma"] == "region_std" else y_se
            s = response_on_grid(wl, resp_nm, sp["response"].sel(band=band).values.astype(float))
            budget = absolute_calibration_budget(
                wl, spec, s, y, y_sigma, spectrum_noise_sigma=spec_std,
                reference_wavelength_nm=cfg["reference_wavelength_nm"], reference_value=ref_value,
                reference_sigma=ref_value * ref_rel, lamp_relative_sigma=lamp,
                lamp_reference_correlation=cfg["lamp_reference_correlation"], lamp_model=cfg["lamp_model"],
                extra_components=extra_components(cfg), response_relative_sigma=y_resp / y)
            rows.append({"band": band, "y": y, "y_sigma": y_sigma, "y_std": y_std, "y_se": y_se, "y_resp": y_resp,
                         "exposure_s": t_mean, "iso": iso_mean, "signal_dn": y * t_mean * iso_mean / 100.0,
                         "n_mask": n_mask, "n_frames": n_tot, "budget": budget,
                         "dark_dn": darks[(lens, band, keys[0][4], keys[0][5])]["level_dn"],
                         "dark_source": darks[(lens, band, keys[0][4], keys[0][5])]["source"]})
        scaled = scale_to_reference(wl, spec, cfg["reference_wavelength_nm"], ref_value, ref_value * ref_rel)["radiance"]
        out[lens] = _lens_dataset(rows, wl, scaled, ref_value, ref_rel, fr[fr["lens"] == lens].reset_index(drop=True),
                                  cfg)
        out[lens].attrs["response_corrections"] = ",".join(response_effects(lin))
        # the 'extra' term of the budget is the quadrature sum of these named components
        out[lens].attrs["extra_uncertainty"] = json.dumps(cfg.get("extra_uncertainty", []))
    return out


def _lens_dataset(rows, wl, scaled, ref_value, ref_rel, fr, cfg) -> xr.Dataset:
    def col(key):
        return np.array([r[key] for r in rows])

    def bud(key):
        return np.array([r["budget"][key] for r in rows])

    contrib = np.array([[r["budget"]["contributions"][t] for t in TERMS] for r in rows])
    ds = xr.Dataset(
        coords={"band": ("band", list(BANDS)), "term": ("term", list(TERMS)),
                "source_wavelength_nm": ("source_wavelength_nm", wl, {"long_name": "spectrometer wavelength", "units": "nm"})},
        data_vars={
            "effective_radiance": ("band", bud("effective_radiance"),
                                   {"long_name": "effective band radiance of the source, Eq. (3), measured response (Table 1)",
                                    "units": "W sr-1 m-2 nm-1"}),
            "effective_radiance_sigma": ("band", bud("effective_radiance_sigma"),
                                         {"long_name": "standard uncertainty of the effective band radiance", "units": "W sr-1 m-2 nm-1"}),
            "dn_per_s": ("band", col("y"), {"long_name": "dark-subtracted DN per second at ISO 100 in the mask, Eq. (2) with "
                                                         "the fitted response corrections (Table 1)",
                                            "units": "DN s-1"}),
            "dn_per_s_sigma": ("band", col("y_sigma"), {"long_name": f"uncertainty of dn_per_s used in the budget ({cfg['image_sigma']})",
                                                        "units": "DN s-1"}),
            "exposure_s": ("band", col("exposure_s"), {"long_name": "exposure time of the signal frames (frame-weighted "
                                                                   "mean over their settings)", "units": "s"}),
            "iso": ("band", col("iso"), {"long_name": "ISO of the signal frames (frame-weighted mean)", "units": "1"}),
            "signal_dn": ("band", col("signal_dn"), {"long_name": "dark-subtracted DN in the mask at the signal frames' "
                                                                 "setting (dn_per_s x exposure x ISO / 100)", "units": "DN"}),
            "dn_per_s_region_std": ("band", col("y_std"), {"long_name": "spatial spread of the frame-averaged image in the mask", "units": "DN s-1"}),
            "dn_per_s_standard_error": ("band", col("y_se"),
                                        {"long_name": "standard error of the mask mean (temporal noise and dark level)", "units": "DN s-1"}),
            "dn_per_s_response_sigma": ("band", col("y_resp"),
                                        {"long_name": "uncertainty of dn_per_s from the fitted response corrections "
                                                      "(attribute response_corrections)", "units": "DN s-1"}),
            "inverse_responsivity": ("band", bud("inverse_responsivity"),
                                     {"long_name": "calibration coefficient R^-1, Eq. (9) (Table 1)",
                                      "units": "W sr-1 m-2 nm-1 s DN-1"}),
            "inverse_responsivity_sigma": ("band", bud("inverse_responsivity_sigma"),
                                           {"long_name": "standard uncertainty of R^-1", "units": "W sr-1 m-2 nm-1 s DN-1"}),
            "relative_sigma": ("band", bud("relative_sigma"), {"long_name": "relative standard uncertainty of R^-1", "units": "1"}),
            "uncertainty_contribution": (("band", "term"), contrib,
                                         {"long_name": "relative standard uncertainty of each budget term", "units": "1"}),
            "dominant_term": ("band", np.array([r["budget"]["dominant"] for r in rows]).astype(str),
                              {"long_name": "largest term of the budget"}),
            "dark_level_dn": ("band", col("dark_dn"), {"long_name": "dark level subtracted in the mask", "units": "DN",
                                                      "source": ",".join(f"{r['band']}:{r['dark_source']}" for r in rows)}),
            "mask_n_pixels": ("band", col("n_mask"), {"long_name": "band pixels in the averaging mask", "units": "1"}),
            "n_frames": ("band", col("n_frames"), {"long_name": "signal frames averaged", "units": "1"}),
            "source_radiance": ("source_wavelength_nm", scaled,
                                {"long_name": "source spectrum scaled to the reference reading (Fig. 7)", "units": "W sr-1 m-2 nm-1"}),
            "reference_wavelength_nm": ((), float(cfg["reference_wavelength_nm"]), {"units": "nm"}),
            "reference_radiance": ((), ref_value, {"long_name": "reference radiometer reading", "units": "W sr-1 m-2 nm-1"}),
            "reference_relative_sigma": ((), ref_rel, {"units": "1"}),
            "mask_half_angle_deg": ((), float(cfg["mask_half_angle_deg"]), {"units": "degree"}),
            "rms_z": ((), fr.attrs.get("rms_z", np.nan),
                      {"long_name": "RMS of the noise-normalised frame residuals (1 at the noise floor)", "units": "1"}),
        },
    )
    return ds.merge(table_to_dataset(fr, "obs_frame"))


def compute(ctx) -> xr.Dataset:
    """The absolute artefact of one lens (the stage runner's contract).

    Parameters
    ----------
    ctx : pipeline.runner.workflow.StageContext
        The job: the lens's dataset, the configuration and the upstream ``geometry``, ``spectral`` and (when
        given) ``dark`` and ``linearity`` artefacts.

    Returns
    -------
    xarray.Dataset
        The lens's absolute artefact (:func:`analyse_absolute`) with its ``obs_corner`` table.
    """
    cfg = ctx.params
    root = ctx.dataset.root
    # sidecars first: bad input fails before any frame is decoded
    spectrum = read_source_spectrum(ctx.dataset)
    reference = reference_reading(read_source_reference(ctx.dataset), root / STAGE / "source_reference.csv",
                                  cfg["reference_wavelength_nm"])
    reduced, darks, corners = reduce_lens_central(ctx, STAGE)
    linearity = {ctx.lens: ctx.upstream["linearity"]} if "linearity" in ctx.upstream else {}
    arts = analyse_absolute(reduced, darks, {ctx.lens: ctx.upstream["spectral"]}, spectrum,
                            root / STAGE / "source_spectrum.csv", reference, ctx.config, linearity)
    return with_corner_table(arts[ctx.lens], corners.of_lens(ctx.lens))
