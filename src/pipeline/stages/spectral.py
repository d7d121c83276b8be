"""Relative spectral response stage (Larouche et al. 2024, Sections 2.5 and 3.4; Fig. 6).

Streams the spectral experiment's frames once per lens and reduces them to:

* per wavelength and band, the dark-corrected mean DN inside a small mask
  around the optical axis (``spectral.mask_half_angle_deg`` of the geometry
  artefact's in-air theta map, grown to ``spectral.mask_min_pixels`` band pixels
  nearest the axis when the image is too coarse), averaged over the frames;
* the response r = DN / photodiode signal, divided by its peak value
  (:func:`pipeline.radiometry.spectral.peak_normalise_response`), with the
  covariance that the shared peak induces;
* the effective wavelength (Eq. 8) and the bandwidth int S dlambda (trapezoid)
  with half bandwidth, uncertainties propagated linearly from the response
  covariance (:func:`pipeline.radiometry.spectral.band_statistics`).

Dark correction: the experiment's own dark frames at the same ISO and
exposure (mean of their mask pixels, which also removes the fixed pattern);
when the experiment has none, the dark artefact's model
(:func:`pipeline.stages.dark.dark_level_dn`) plus its fixed pattern in the mask.

Response corrections: when the lens's linearity artefact is given, each
setting's dark-corrected signal goes through the measurement chain's
``linearise`` and ``normalise_exposure`` (its mask pixels also through
``correct_flat_field``) with the effects that artefact fitted
(:func:`pipeline.radiometry.response.response_corrected`); the artefact's
``response_corrections`` attribute names them. At one setting for every
wavelength the exposure corrections cancel in the peak normalisation; the
nonlinearity does not.

Uncertainty of each mean: temporal variance of the mask pixels (running
moments across the frames of one wavelength) divided by the number of pixels
and frames, plus the uncertainty of the dark level; the photodiode's
``signal_std`` is taken as the standard uncertainty of its reported reading.
The dark level is shared by all wavelengths of a band; its (small)
correlation is neglected.

Observation table (for closure and the diagnostics): the frame level, one
row per frame and band: ``value_dn`` the frame's dark-corrected mask mean,
``sigma_dn`` its temporal noise (pixel variance / pixels), one free level per
group ``lens/band/wavelength`` (``x_level``); covariates ``wavelength_nm``,
``photodiode_signal``, ``frame``, ``iso``, ``exposure_s``.  A table with one
row per wavelength and band would need one free parameter per row (the
response itself) and be saturated; the frames scatter about their setting
mean, which the noise model must explain (like the foundation's frame tables).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.io.bands import BANDS
from pipeline.io.dataset import Dataset, read_photodiode
from pipeline.errors import InputError
from pipeline.stats.fitting import base_design, wls
from pipeline.io.frames import iter_frames
from pipeline.stats.moments import RunningMoments
from pipeline.stages.observations import table_to_dataset, with_corner_table
from pipeline.radiometry.dark import dark_level_dn
from pipeline.radiometry.measurement import FrameSettings
from pipeline.radiometry.response import flat_field_at, response_corrected, response_effects
from pipeline.radiometry.spectral import band_statistics, peak_normalise_response
from pipeline.radiometry.unlit_corners import FrameCorners

STAGE = "spectral"
#: medium of the lab experiments (the geometry artefact's in-air maps)
MEDIUM = "air"


# ----------------------------------------------------------------------------- shared with absolute
def central_masks(geometry: dict[str, xr.Dataset], half_angle_deg: float, min_pixels: int,
                  medium: str = MEDIUM) -> dict[tuple[str, str], np.ndarray]:
    """Band-pixel masks within ``half_angle_deg`` of the optical axis, per (lens, band).

    When fewer than ``min_pixels`` band pixels fall inside (coarse images),
    the mask is the ``min_pixels`` pixels with the smallest theta.

    Parameters
    ----------
    geometry : dict[str, xarray.Dataset]
        Lens -> its geometry artefact (the ``theta_deg`` map, degree).
    half_angle_deg : float
        The mask's half angle about the axis, degree.
    min_pixels : int
        The fewest band pixels a mask holds.
    medium : str, default "air"
        The medium whose theta map is read.

    Returns
    -------
    dict[tuple[str, str], numpy.ndarray]
        (lens, band) -> boolean mask of the band plane's shape.
    """
    out = {}
    for lens, geo in geometry.items():
        for band in BANDS:
            theta = geo["theta_deg"].sel(medium=medium, band=band).values.astype(float)
            theta = np.where(np.isfinite(theta), theta, np.inf)
            mask = theta <= half_angle_deg
            if mask.sum() < min_pixels:
                order = np.argsort(theta, axis=None)[:min_pixels]
                mask = np.zeros(theta.shape, dtype=bool)
                mask.flat[order] = True
            out[(lens, band)] = mask
    return out


#: wavelength key of frames without a monochromator setting (dark frames, other experiments):
#: NaN cannot serve, it never equals itself as a dictionary key
NO_WAVELENGTH = -1.0
#: the photodiode's reading is in the lab's own unit (spectral/photodiode.csv: proportional to the beam power):
#: written with units "1", this says so; only its ratios between wavelengths enter the response
PHOTODIODE_SCALE = "in the unit of spectral/photodiode.csv, proportional to the beam power (an arbitrary scale)"


def _wavelength_key(row) -> float:
    value = row.get("wavelength_nm", np.nan)
    try:
        value = float(value)
    except (TypeError, ValueError):
        return NO_WAVELENGTH
    return round(value, 6) if np.isfinite(value) else NO_WAVELENGTH


def central_frames(dataset: Dataset, experiment: str, saturation_margin_dn: float = 1.0, progress: bool = False):
    """The experiment's frames as :func:`reduce_central` reads them, decoding from this call on.

    A stage makes its masks and reads its upstream artefacts while the first frame decodes, then hands the
    stream on.

    Parameters
    ----------
    dataset : pipeline.io.dataset.Dataset
        The dataset.
    experiment : str
        The experiment, e.g. ``"spectral"`` or ``"absolute"``.
    saturation_margin_dn : float, default 1.0
        A band pixel is saturated where a CFA site reaches the white level less this, DN.
    progress : bool, default False
        Show a progress bar.

    Returns
    -------
    pipeline.io.frames.FrameStream
        The decoded frames, in frames.csv order.
    """
    return iter_frames(dataset, experiment, dataset.frames(experiment), saturation_margin_dn=saturation_margin_dn,
                       progress=progress)


def reduce_central(dataset: Dataset, experiment: str, masks: dict[tuple[str, str], np.ndarray],
                   saturation_margin_dn: float = 1.0, progress: bool = False,
                   corners: FrameCorners | None = None, stream=None) -> dict:
    """Stream an experiment's frames once: running moments of the mask pixels per setting.

    Setting key: (lens, band, kind, wavelength_nm or NO_WAVELENGTH, iso, exposure_s).

    Parameters
    ----------
    dataset : pipeline.io.dataset.Dataset
        The dataset.
    experiment : str
        The experiment, e.g. ``"spectral"`` or ``"absolute"``.
    masks : dict[tuple[str, str], numpy.ndarray]
        (lens, band) -> the averaging mask (:func:`central_masks`); only these lenses are read.
    saturation_margin_dn : float, default 1.0
        A band pixel is saturated where a CFA site reaches the white level less this, DN.
    progress : bool, default False
        Show a progress bar.
    corners : pipeline.radiometry.unlit_corners.FrameCorners or None, optional
        When given, records each signal frame's unlit corners against the dark model.
    stream : pipeline.io.frames.FrameStream or None, optional
        The frames of :func:`central_frames` already decoding (made here otherwise).

    Returns
    -------
    dict
        ``moments`` (setting key -> running moments of the mask's pixels, DN), ``frames`` (one row per frame,
        lens and band: ``mask_mean_dn`` in DN, ``saturated``, the setting), ``inputs`` (file -> sha256) and
        ``masks``.

    Raises
    ------
    pipeline.errors.InputError
        If a signal frame of the spectral experiment has no wavelength, a band image does not match the mask,
        or there are no frames.
    """
    lenses = sorted({lens for lens, _ in masks})
    moments = defaultdict(RunningMoments)
    rows, inputs = [], {}
    if stream is None:
        stream = central_frames(dataset, experiment, saturation_margin_dn, progress)
    for i, dec in enumerate(stream):
        row = dec.row
        inputs[row["file"]] = dec.raw.sha256
        wl = _wavelength_key(row)
        kind = row["kind"]
        if kind == "signal" and experiment == STAGE and wl == NO_WAVELENGTH:
            raise InputError(dataset.root / experiment / "frames.csv",
                             f"signal frame {row['file']!r} has no wavelength_nm")
        iso, t = float(dec.raw.iso), round(float(dec.raw.exposure_s), 9)
        for lens in (lenses if row["lens"] == "both" else [row["lens"]]):
            if lens not in dec.lenses or (lens, BANDS[0]) not in masks:
                continue
            if corners is not None and kind == "signal":
                corners.add(lens, dec.lenses[lens], dec.raw, row.get("temperature_c", np.nan), file_index=i,
                            wavelength_nm=wl if wl != NO_WAVELENGTH else np.nan)
            for band in BANDS:
                img = dec.lenses[lens].bands[band]
                mask = masks[(lens, band)]
                if img.shape != mask.shape:
                    raise InputError(row["path"], f"band image {img.shape} does not match the geometry "
                                                  f"artefact's maps {mask.shape} (lens {lens})")
                pix = img[mask]
                moments[(lens, band, kind, wl, iso, t)].add(pix)
                rows.append({"lens": lens, "band": band, "kind": kind, "wavelength_nm": wl, "iso": iso,
                             "exposure_s": t, "file_index": i, "mask_mean_dn": float(pix.mean()),
                             "saturated": bool(dec.lenses[lens].saturated[band][mask].any())})
    if not rows:
        raise InputError(dataset.root / experiment / "frames.csv", "no frames")
    return {"moments": moments, "frames": pd.DataFrame(rows), "inputs": inputs, "masks": masks}


def dark_levels(reduced: dict, dark: dict[str, xr.Dataset] | None, frames_csv: Path) -> dict:
    """Dark level (DN) and its uncertainty in the mask, per (lens, band, iso, exposure_s) of signal frames.

    From the experiment's dark frames at the same setting; otherwise the dark
    artefact's model plus its fixed pattern averaged over the mask.

    Parameters
    ----------
    reduced : dict
        What :func:`reduce_central` returned.
    dark : dict[str, xarray.Dataset] or None
        Lens -> its dark artefact, for settings without dark frames.
    frames_csv : pathlib.Path
        The experiment's frames.csv, named in the error.

    Returns
    -------
    dict
        (lens, band, iso, exposure_s) -> ``level_dn`` (DN), ``sigma_dn`` (DN), ``n_frames`` (dark frames
        averaged; 0 from the artefact) and ``source``.

    Raises
    ------
    pipeline.errors.InputError
        If a signal setting has neither dark frames nor a dark artefact.
    """
    moments = reduced["moments"]
    out = {}
    signal_keys = {(k[0], k[1], k[4], k[5]) for k in moments if k[2] == "signal"}
    for lens, band, iso, t in signal_keys:
        dark_keys = [k for k in moments if k[2] == "dark" and k[0] == lens and k[1] == band
                     and k[4] == iso and k[5] == t]
        if dark_keys:
            n = sum(moments[k].n for k in dark_keys)
            level_map = sum(moments[k].mean() * moments[k].n for k in dark_keys) / n
            var = float(np.mean([moments[k].variance().mean() for k in dark_keys]))
            out[(lens, band, iso, t)] = {"level_dn": float(level_map.mean()),
                                         "sigma_dn": float(np.sqrt(var / level_map.size / n)),
                                         "n_frames": n, "source": "dark frames"}
        elif dark is not None and lens in dark:
            d = dark[lens]
            mask = reduced["masks"][(lens, band)]
            fpn = d["fpn_map_dn"].sel(band=band).values
            fpn_mean = float(fpn[mask].mean()) if fpn.shape == mask.shape else 0.0
            sigma = float(d["bias_dn_sigma"].sel(band=band))
            out[(lens, band, iso, t)] = {"level_dn": dark_level_dn(d, band, iso, t) + fpn_mean,
                                         "sigma_dn": sigma, "n_frames": 0, "source": "dark artefact"}
        else:
            raise InputError(frames_csv, f"no dark frames at ISO {iso:g} and {t:g} s for lens {lens}, "
                                         "and no dark artefact was given")
    return out


def frame_table(reduced: dict, darks: dict, linearity: dict[str, xr.Dataset] | None = None) -> pd.DataFrame:
    """Frame-level observation table: dark-corrected mask means with their temporal noise.

    Parameters
    ----------
    reduced : dict
        What :func:`reduce_central` returned.
    darks : dict
        What :func:`dark_levels` returned.
    linearity : dict[str, xarray.Dataset] or None, optional
        Lens -> its linearity artefact, whose response corrections are applied.

    Returns
    -------
    pandas.DataFrame
        One row per frame, lens and band: ``value_dn`` and ``sigma_dn`` in DN above dark, linearised when the
        lens's linearity artefact fitted the nonlinearity; ``dn_per_s`` and ``dn_per_s_sigma`` the same per
        second at ISO 100 through the chain's response corrections (Eq. 2 with the true exposure and gain; the
        nominal Eq. 2 without a linearity artefact), in DN s-1; ``dark_dn``, ``n_mask``, ``pred_dn`` and ``z``
        of a constant level per setting, ``saturated`` and ``used``. Frames without a dark level are left out;
        ``attrs["rms_z"]`` holds the fit's RMS of z.
    """
    linearity = linearity or {}
    fr = reduced["frames"].copy()
    moments = reduced["moments"]
    levels, sig = [], []
    for _, r in fr.iterrows():
        d = darks.get((r["lens"], r["band"], r["iso"], r["exposure_s"]))
        levels.append(d["level_dn"] if d else np.nan)
        mom = moments[(r["lens"], r["band"], r["kind"], r["wavelength_nm"], r["iso"], r["exposure_s"])]
        var = mom.variance()
        sig.append(np.sqrt(max(float(var.mean()), 1e-12) / var.size))
    fr["dark_dn"] = levels
    corrected = [response_corrected(value, linearity.get(lens), band, FrameSettings(exposure_s=t, iso=iso), sigma)
                 for value, sigma, lens, band, t, iso in zip(fr["mask_mean_dn"] - fr["dark_dn"], sig, fr["lens"],
                                                             fr["band"], fr["exposure_s"], fr["iso"])]
    fr["value_dn"] = [float(linear.value) for linear, _ in corrected]
    fr["sigma_dn"] = [float(linear.random_sigma) for linear, _ in corrected]
    fr["dn_per_s"] = [float(rate.value) for _, rate in corrected]
    fr["dn_per_s_sigma"] = [float(rate.random_sigma) for _, rate in corrected]
    fr["n_mask"] = [int(reduced["masks"][(lens, band)].sum()) for lens, band in zip(fr["lens"], fr["band"])]
    wl = fr["wavelength_nm"].map(lambda w: "none" if w == NO_WAVELENGTH else f"{w:g}")
    fr["group"] = fr["lens"] + "/" + fr["band"] + "/" + fr["kind"] + "/" + wl + "/" + \
        fr["iso"].map("{:g}".format) + "/" + fr["exposure_s"].map("{:g}".format)
    fr["frame"] = fr.groupby("group").cumcount()
    fr = fr[np.isfinite(fr["value_dn"])].reset_index(drop=True)
    fr["wavelength_nm"] = fr["wavelength_nm"].where(fr["wavelength_nm"] != NO_WAVELENGTH, np.nan)
    fr["x_level"] = 1.0
    fit = wls(fr["value_dn"].to_numpy(), fr["sigma_dn"].to_numpy(), base_design(fr)[0])
    fr["pred_dn"] = fit.pred
    fr["z"] = fit.z
    fr.attrs["rms_z"] = fit.rms_z
    fr["saturated"] = fr["saturated"].astype(int)
    fr["used"] = 1 - fr["saturated"]
    return fr


# ----------------------------------------------------------------------------- spectral analysis
def analyse_spectral(reduced: dict, darks: dict, photodiode: pd.DataFrame, photodiode_path: Path,
                     config: dict, linearity: dict[str, xr.Dataset] | None = None) -> dict[str, xr.Dataset]:
    """Response, effective wavelength and bandwidth per lens and band.

    Parameters
    ----------
    reduced : dict
        What :func:`reduce_central` returned.
    darks : dict
        What :func:`dark_levels` returned.
    photodiode : pandas.DataFrame
        The photodiode's readings (:func:`pipeline.io.dataset.read_photodiode`): one per wavelength used.
    photodiode_path : pathlib.Path
        The photodiode file, named in the errors (its folder's frames.csv too).
    config : dict
        The run's configuration (section ``spectral``).
    linearity : dict[str, xarray.Dataset] or None, optional
        Lens -> its linearity artefact: brings every setting to DN per second at ISO 100 through the chain's
        response corrections.

    Returns
    -------
    dict[str, xarray.Dataset]
        Lens -> its spectral artefact: the peak-normalised relative response per band and wavelength with its
        uncertainty and covariance, the signal in DN s-1, the peak and effective wavelengths and bandwidths
        (nm), and the frame table.

    Raises
    ------
    pipeline.errors.InputError
        If the mask saturates, a lens has fewer than two wavelengths, or the photodiode has no (or several)
        readings at a wavelength used or a reading that is not positive.
    """
    moments = reduced["moments"]
    linearity = linearity or {}
    fr = frame_table(reduced, darks, linearity)
    sig = fr[fr["kind"] == "signal"]
    if sig["saturated"].any():
        bad = sig[sig["saturated"] == 1].iloc[0]
        raise InputError(photodiode_path.parent / "frames.csv",
                         f"saturated pixels in the mask at {bad['wavelength_nm']:g} nm ({bad['lens']}/{bad['band']}); "
                         "lower the exposure")
    pd_wl = photodiode["wavelength_nm"].to_numpy(float)
    out = {}
    for lens in sorted({k[0] for k in moments}):
        lin = linearity.get(lens)
        keys = [k for k in moments if k[0] == lens and k[2] == "signal"]
        wls_nm = np.array(sorted({k[3] for k in keys}))
        if wls_nm.size < 2:
            raise InputError(photodiode_path.parent / "frames.csv",
                             f"lens {lens}: fewer than two monochromator wavelengths")
        pd_sig, pd_std = np.empty(wls_nm.size), np.empty(wls_nm.size)
        for j, w in enumerate(wls_nm):
            hit = np.flatnonzero(np.abs(pd_wl - w) < 1e-3)
            if hit.size != 1:
                raise InputError(photodiode_path, f"{'no' if hit.size == 0 else 'more than one'} reading at "
                                                  f"{w:g} nm (the frames use it)")
            pd_sig[j] = photodiode["signal"].iloc[hit[0]]
            pd_std[j] = photodiode["signal_std"].iloc[hit[0]]
        if np.any(pd_sig <= 0):
            raise InputError(photodiode_path, "signal must be positive at every wavelength the frames use")
        dn = np.empty((len(BANDS), wls_nm.size))
        dn_sigma = np.empty_like(dn)
        dark_dn = np.empty(len(BANDS))
        n_mask = np.empty(len(BANDS), dtype=int)
        for bi, band in enumerate(BANDS):
            n_mask[bi] = int(reduced["masks"][(lens, band)].sum())
            for j, w in enumerate(wls_nm):
                ks = [k for k in keys if k[1] == band and k[3] == w]
                total, var_sum, n = 0.0, 0.0, 0
                dsig2 = 0.0
                for k in ks:
                    mom = moments[k]
                    d = darks[(lens, band, k[4], k[5])]
                    # Eq. (2) normalisation would cancel in the peak normalisation unless the
                    # settings differ between wavelengths: bring every setting to DN per second at ISO 100,
                    # through the chain's response corrections when the linearity artefact is given
                    frame = FrameSettings(exposure_s=k[5], iso=k[4])
                    flat = flat_field_at(lin, band, reduced["masks"][(lens, band)])
                    _, pixels = response_corrected(mom.mean() - d["level_dn"], lin, band, frame, flat_field=flat)
                    # a unit random term through the chain: its first-order slope, DN s-1 per DN
                    _, unit = response_corrected(float(mom.mean().mean()) - d["level_dn"], lin, band, frame, 1.0)
                    slope = float(unit.random_sigma)
                    total += float(np.mean(pixels.value)) * mom.n
                    var_sum += float(mom.variance().mean()) / mom.mean().size * slope**2 * mom.n
                    dsig2 += (d["sigma_dn"] * slope) ** 2 * mom.n
                    n += mom.n
                    dark_dn[bi] = d["level_dn"]
                dn[bi, j] = total / n
                dn_sigma[bi, j] = np.sqrt(var_sum / n / n + dsig2 / n)
        s, s_sigma, cov = peak_normalise_response(dn, pd_sig, dn_sigma, pd_std, return_covariance=True)
        stats = [band_statistics(wls_nm, s[bi], cov[bi]) for bi in range(len(BANDS))]
        out[lens] = _lens_dataset(lens, wls_nm, dn, dn_sigma, pd_sig, pd_std, s, s_sigma, cov, stats, dark_dn,
                                  n_mask, fr[fr["lens"] == lens].reset_index(drop=True), config,
                                  darks_source={b: darks[next((lens, b, k[4], k[5]) for k in keys if k[1] == b)]["source"]
                                                for b in BANDS})
        out[lens].attrs["response_corrections"] = ",".join(response_effects(lin))
    return out


def _lens_dataset(lens, wl, dn, dn_sigma, pd_sig, pd_std, s, s_sigma, cov, stats, dark_dn, n_mask, fr, config,
                  darks_source) -> xr.Dataset:
    def stat(key):
        return np.array([st[key] for st in stats])

    cfg = config[STAGE]
    ds = xr.Dataset(
        coords={"band": ("band", list(BANDS)),
                "wavelength_nm": ("wavelength_nm", wl, {"long_name": "monochromator wavelength", "units": "nm"}),
                "wavelength2_nm": ("wavelength2_nm", wl, {"long_name": "monochromator wavelength (second axis of covariances)", "units": "nm"})},
        data_vars={
            "response": (("band", "wavelength_nm"), s,
                         {"long_name": "peak-normalised relative spectral response S_R (Fig. 6)", "units": "1"}),
            "response_sigma": (("band", "wavelength_nm"), s_sigma,
                               {"long_name": "standard uncertainty of the response", "units": "1"}),
            "response_covariance": (("band", "wavelength_nm", "wavelength2_nm"), cov,
                                    {"long_name": "covariance of the response (shared peak value)", "units": "1"}),
            "signal_dn_per_s": (("band", "wavelength_nm"), dn,
                                {"long_name": "dark-corrected mean signal in the mask, per second at ISO 100", "units": "DN s-1"}),
            "signal_dn_per_s_sigma": (("band", "wavelength_nm"), dn_sigma,
                                      {"long_name": "standard uncertainty of signal_dn_per_s", "units": "DN s-1"}),
            "photodiode_signal": ("wavelength_nm", pd_sig, {"long_name": "reference photodiode reading", "units": "1",
                                                             "comment": PHOTODIODE_SCALE}),
            "photodiode_signal_std": ("wavelength_nm", pd_std, {"long_name": "uncertainty of the photodiode reading", "units": "1",
                                                                "comment": PHOTODIODE_SCALE}),
            "peak_wavelength_nm": ("band", wl[np.argmax(s, axis=1)], {"long_name": "wavelength of the response peak", "units": "nm"}),
            "effective_wavelength_nm": ("band", stat("effective_wavelength_nm"),
                                        {"long_name": "effective wavelength, Eq. (8), trapezoidal rule", "units": "nm"}),
            "effective_wavelength_nm_sigma": ("band", stat("effective_wavelength_nm_sigma"),
                                              {"long_name": "standard uncertainty of the effective wavelength", "units": "nm"}),
            "bandwidth_nm": ("band", stat("bandwidth_nm"), {"long_name": "bandwidth int S_R dlambda", "units": "nm"}),
            "bandwidth_nm_sigma": ("band", stat("bandwidth_nm_sigma"), {"long_name": "standard uncertainty of the bandwidth", "units": "nm"}),
            "half_bandwidth_nm": ("band", stat("half_bandwidth_nm"),
                                  {"long_name": "half bandwidth (the paper's lambda_eff +/- Lambda/2)", "units": "nm"}),
            "half_bandwidth_nm_sigma": ("band", stat("half_bandwidth_nm_sigma"),
                                        {"long_name": "standard uncertainty of the half bandwidth", "units": "nm"}),
            "dark_level_dn": ("band", dark_dn, {"long_name": "dark level subtracted in the mask", "units": "DN",
                                                "source": ",".join(f"{b}:{darks_source[b]}" for b in BANDS)}),
            "mask_n_pixels": ("band", n_mask, {"long_name": "band pixels in the averaging mask", "units": "1"}),
            "mask_half_angle_deg": ((), float(cfg["mask_half_angle_deg"]),
                                    {"long_name": "requested half-angle of the averaging mask", "units": "degree"}),
            "rms_z": ((), fr.attrs.get("rms_z", np.nan) if len(fr) else np.nan,
                      {"long_name": "RMS of the noise-normalised frame residuals (1 at the noise floor)", "units": "1"}),
        },
    )
    return ds.merge(table_to_dataset(fr, "obs_frame"))


# ----------------------------------------------------------------------------- the stage
def reduce_lens_central(ctx, experiment: str):
    """One lens job's reduction of a central-mask experiment (spectral, absolute).

    The mask from the lens's in-air theta map, the frames streamed once (the first decoding while the mask is
    made and the dark artefact read), the frames recorded, the dark level of each setting.

    Parameters
    ----------
    ctx : pipeline.runner.workflow.StageContext
        The job: the lens's dataset, the stage's configuration (``mask_half_angle_deg``, ``mask_min_pixels``)
        and the upstream ``geometry`` and (when given) ``dark`` artefacts.
    experiment : str
        ``"spectral"`` or ``"absolute"``.

    Returns
    -------
    reduced : dict
        What :func:`reduce_central` returned.
    darks : dict
        What :func:`dark_levels` returned.
    corners : pipeline.radiometry.unlit_corners.FrameCorners
        The signal frames' unlit-corner records.
    """
    cfg = ctx.params
    with central_frames(ctx.dataset, experiment, progress=ctx.progress) as stream:
        masks = central_masks({ctx.lens: ctx.upstream["geometry"]}, cfg["mask_half_angle_deg"],
                              cfg["mask_min_pixels"])
        dark = {ctx.lens: ctx.upstream["dark"]} if "dark" in ctx.upstream else {}
        corners = FrameCorners.of_upstream(ctx.lens, ctx.upstream, ctx.dataset.projection, ctx.config["bias"])
        reduced = reduce_central(ctx.dataset, experiment, masks, corners=corners, stream=stream)
    ctx.record_frames(reduced["inputs"])
    return reduced, dark_levels(reduced, dark, ctx.dataset.root / experiment / "frames.csv"), corners


def compute(ctx) -> xr.Dataset:
    """The spectral artefact of one lens (the stage runner's contract).

    The mask comes from the lens's in-air theta map (geometry artefact); the
    dark artefact, when given, serves only signal settings without dark frames;
    the linearity artefact, when given, corrects every setting's signal
    through the measurement chain (``response_corrections`` attribute).

    Parameters
    ----------
    ctx : pipeline.runner.workflow.StageContext
        The job: the lens's dataset, the configuration and the upstream artefacts.

    Returns
    -------
    xarray.Dataset
        The lens's spectral artefact (:func:`analyse_spectral`) with its ``obs_corner`` table.
    """
    photodiode = read_photodiode(ctx.dataset)      # bad sidecar input fails before any frame is decoded
    reduced, darks, corners = reduce_lens_central(ctx, STAGE)
    linearity = {ctx.lens: ctx.upstream["linearity"]} if "linearity" in ctx.upstream else {}
    arts = analyse_spectral(reduced, darks, photodiode, ctx.dataset.root / STAGE / "photodiode.csv", ctx.config,
                            linearity)
    return with_corner_table(arts[ctx.lens], corners.of_lens(ctx.lens))
