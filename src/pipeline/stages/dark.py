"""Dark-frame stage (Larouche et al. 2024, Sections 2.8 and 3.7; Fig. 9).

Streams the dark frames once, keeping per-setting running sums for each lens
and band, and reduces them to:

* per setting (ISO, exposure time): mean level and temporal spread, the
  histogram of the frame-averaged image with its Gaussian centre and width;
* the fixed-pattern (offset) map at the shortest exposure of the lowest ISO;
* the hot-pixel mask (pixels whose dark signal is an outlier in every one of
  the longest exposures) and the read noise per ISO;
* the dark model fitted to one value per setting:
  ``level = b0 + b1 (gain - 1) [+ D gain t]`` per lens and band, with the
  effects of ``model.effects`` (``dark_current`` adds D; ``hot_pixels`` leaves
  the flagged pixels out of the means; ``bias_drift`` removes each frame's
  offset measured on its unlit pixels: the corners outside a fisheye's image
  circle, or, for a rectilinear region (lit to its edges), the sensor's
  optically black pixels when the DNG declares them; without either the
  drift is not testable and the artefact says so);
* the observation tables with the model's predictions and the residuals
  normalised by the expected noise, for closure and the diagnostics.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.bands import BANDS
from pipeline.dataset import Dataset
from pipeline.effects.catalogue import drift_sigma
from pipeline.fitting import base_design
from pipeline.observations import fit_with_effects, table_to_dataset
from pipeline.frames import SITES_PER_BAND_PIXEL, iter_frames
from pipeline.moments import RunningMoments, unlit_mask
from pipeline.radiometry.exposure import gain_from_iso

STAGE = "dark"


def _setting_key(raw) -> tuple[float, float]:
    return (float(raw.iso), round(float(raw.exposure_s), 9))


def bias_reference(projection: str, has_optical_black: bool) -> str:
    """What measures each frame's black level: the unlit corners, the optically black pixels, or nothing."""
    if projection != "rectilinear":
        return "unlit corners"
    return "optically black pixels" if has_optical_black else "none"


def reduce_dark(dataset: Dataset, config: dict, progress: bool = False) -> dict:
    """Stream the dark frames; returns per-lens/band/setting moments and per-frame statistics.

    Each frame's black-level reference (``corner_dn``) is the mean of its unlit corners
    (fisheye) or of the sensor's optically black pixels (rectilinear, when the DNG
    declares them; NaN otherwise).
    """
    frames = dataset.frames(STAGE)
    lenses = list(dataset.lenses)
    projections = {lens: dataset.projection(lens) for lens in lenses}
    moments = defaultdict(RunningMoments)          # (lens, band, setting) -> RunningMoments
    frame_rows = []
    corners = {}
    inputs = {}
    optical_black = []
    for i, dec in enumerate(iter_frames(dataset, STAGE, frames, lenses, progress=progress)):
        key = _setting_key(dec.raw)
        inputs[dec.row["file"]] = dec.raw.sha256
        optical_black.append(dec.raw.optical_black_dn is not None)
        for lens, images in dec.lenses.items():
            for band in BANDS:
                img = images.bands[band]
                if (lens, band) not in corners:
                    corners[(lens, band)] = unlit_mask(img.shape, projections[lens], config["bias"]["corner_min_radius_fraction"])
                cm = corners[(lens, band)]
                moments[(lens, band, key)].add(img)
                if cm.any():
                    corner_dn, n_ob = float(img[cm].mean()), 0
                elif dec.raw.optical_black_dn is not None:
                    corner_dn, n_ob = dec.raw.optical_black_dn, dec.raw.optical_black_count
                else:
                    corner_dn, n_ob = np.nan, 0
                frame_rows.append({
                    "lens": lens, "band": band, "iso": key[0], "exposure_s": key[1], "file_index": i,
                    "circle_mean_dn": float(img[~cm].mean()), "corner_dn": corner_dn,
                    "n_optical_black": n_ob,
                    "temperature_c": dec.row.get("temperature_c", np.nan),
                })
    has_ob = bool(optical_black) and all(optical_black)
    return {"moments": moments, "frames": pd.DataFrame(frame_rows), "corners": corners,
            "inputs": inputs, "lenses": lenses, "projections": projections,
            "bias_reference": {lens: bias_reference(p, has_ob) for lens, p in projections.items()}}


def find_hot_pixels(means: dict[tuple[float, float], np.ndarray], variances, iso: float,
                    threshold_sigma: float, persistence: int) -> np.ndarray:
    """Pixels whose dark rise over the shortest exposure is an outlier in the ``persistence`` longest.

    The outlier test is robust: z = (rise - median) / (1.4826 MAD), so the
    fixed pattern and the temporal noise set the scale, not the hot pixels.
    """
    times = sorted(t for (i, t) in means if i == iso)
    if len(times) < persistence + 1:
        return np.zeros_like(next(iter(means.values())), dtype=bool)
    base = means[(iso, times[0])]
    hot = None
    for t in times[-persistence:]:
        rise = means[(iso, t)] - base
        med = np.median(rise)
        mad = 1.4826 * np.median(np.abs(rise - med))
        z = (rise - med) / max(mad, 1e-6)
        flag = z > threshold_sigma
        hot = flag if hot is None else hot & flag
    return hot


def analyse_dark(reduced: dict, config: dict, effects: list[str]) -> dict[str, xr.Dataset]:
    """Fit the dark model and build one artefact Dataset per lens."""
    cfg = config["dark"]
    moments = reduced["moments"]
    frames = reduced["frames"]
    lenses = reduced["lenses"]
    use_hot = "hot_pixels" in effects
    use_drift = "bias_drift" in effects
    settings = sorted({k[2] for k in moments})
    isos = sorted({s[0] for s in settings})
    ref_iso = isos[0]

    per_lens_band = {}
    setting_rows = []
    for lens in lenses:
        for band in BANDS:
            means = {s: moments[(lens, band, s)].mean() for s in settings}
            varis = {s: moments[(lens, band, s)].variance() for s in settings}
            cm = reduced["corners"][(lens, band)]
            hot = find_hot_pixels(means, varis, ref_iso, cfg["hot_pixel_threshold_sigma"],
                                  cfg["hot_pixel_persistence"])
            circle = ~cm
            used = circle & ~hot if use_hot else circle
            per_lens_band[(lens, band)] = {"means": means, "vars": varis, "hot": hot, "used": used}
            for s in settings:
                m, v = means[s], varis[s]
                mean_all = float(m[circle].mean())
                mean_nonhot = float(m[circle & ~hot].mean())
                # the reference's own noise: the corners' temporal variance, or (optically black
                # pixels, all CFA sites, read noise only) that of one raw pixel of the band
                corner_var = float(v[cm].mean()) if cm.any() else float(v[used].mean()) * SITES_PER_BAND_PIXEL[band]
                setting_rows.append({
                    "lens": lens, "band": band, "iso": s[0], "exposure_s": s[1],
                    "n_frames": moments[(lens, band, s)].n,
                    "pixel_var_dn2": float(v[used].mean()),
                    "corner_var_dn2": corner_var,
                    "n_used": int(used.sum()), "n_corner": int(cm.sum()),
                    "hot_excess_dn": mean_all - mean_nonhot,
                    "n_hot": int((hot & circle).sum()), "n_pixels": int(circle.sum()),
                })
    st = pd.DataFrame(setting_rows)
    st["gain"] = gain_from_iso(st["iso"])
    st["group"] = st["lens"] + "/" + st["band"]
    st["setting"] = st.groupby(["iso", "exposure_s"], sort=True).ngroup()

    # ----- frame level: values, corners and bias drift
    fr = frames.merge(st[["lens", "band", "iso", "exposure_s", "setting", "hot_excess_dn", "pixel_var_dn2",
                          "corner_var_dn2", "n_used", "n_corner"]], on=["lens", "band", "iso", "exposure_s"])
    fr["value_dn"] = fr["circle_mean_dn"] - (fr["hot_excess_dn"] if use_hot else 0.0)
    # optically black pixels (rectilinear regions) stand in for the corners
    fr["n_corner"] = np.where(fr["n_corner"] > 0, fr["n_corner"], fr.pop("n_optical_black"))
    testable = bool(fr["corner_dn"].notna().all())
    drift = (0.0, 0.0, 0.0)
    if testable:
        fr["corner_dev_dn"] = fr["corner_dn"] - fr.groupby(["lens", "band", "setting"])["corner_dn"].transform("mean")
        fr["sigma_corner_dn"] = np.sqrt(fr["corner_var_dn2"] / fr["n_corner"])
    else:
        # nothing measures a frame's own black level: the drift can be neither removed nor
        # tested (the candidate effect has no covariate), and the artefact says so
        fr = fr.drop(columns=["corner_dn"])
        drift = (np.nan, np.nan, np.nan)
    if use_drift and testable:
        fr["value_dn"] -= fr["corner_dev_dn"]
        drift = drift_sigma(fr)
    # A frame's value scatters by the temporal noise of its pixels; the drift that the
    # model removed (or that is left in, without the effect) is not part of this noise.
    fr["sigma_dn"] = np.sqrt(np.maximum(fr["pixel_var_dn2"] - np.nan_to_num(drift[0]) ** 2, 1e-12) / fr["n_used"])
    if use_drift and testable:
        # the corner correction adds the corners' own noise to each frame
        fr["sigma_dn"] = np.hypot(fr["sigma_dn"], fr["sigma_corner_dn"])
    fr["group"] = fr["lens"] + "/" + fr["band"] + "/" + fr["setting"].astype(str)
    fr["frame"] = fr.groupby(["lens", "band", "setting"]).cumcount()
    fr["x_level"] = 1.0
    if fr["temperature_c"].notna().all():
        fr["temperature_ref_c"] = float(fr["temperature_c"].mean())
    ffit, _ = fit_with_effects(fr, "frame", effects, STAGE)
    fr["pred_dn"] = ffit.pred
    fr["z"] = ffit.z

    # ----- setting level: the dark model
    agg = fr.groupby(["lens", "band", "setting"]).agg(value_dn=("value_dn", "mean"),
                                                      frame_sigma=("sigma_dn", "mean"),
                                                      temperature_c=("temperature_c", "mean")).reset_index()
    st = st.merge(agg, on=["lens", "band", "setting"])
    st["sigma_dn"] = np.sqrt(st["frame_sigma"] ** 2 / st["n_frames"] + np.nan_to_num(drift[0]) ** 2 / st["n_frames"])
    st["x_b0"] = 1.0
    st["x_b1"] = st["gain"] - 1.0
    if "temperature_ref_c" in fr:
        st["temperature_ref_c"] = fr["temperature_ref_c"].iloc[0]
    fit, effect_params = fit_with_effects(st, "setting", effects, STAGE)
    st["pred_dn"] = fit.pred
    st["z"] = fit.z
    names = base_design(st)[1]
    params = {name: (fit.coef[k], np.sqrt(fit.cov[k, k])) for k, name in enumerate(names)}
    dark_rate = tuple(float(v[0]) for v in effect_params.get("dark_current", ((0.0,), (0.0,))))
    temperature = effect_params.get("temperature")
    if temperature is not None:
        temperature = {"coef": temperature[0], "sigma": temperature[1],
                       "reference_c": float(st["temperature_ref_c"].iloc[0])}

    if use_drift and testable:
        # each setting's frames share their black-level offsets, whose sample variance every pixel's
        # temporal variance holds; the unlit pixels measure it (less their own noise): the read noise
        # of a pixel is what is left
        per = fr.groupby(["lens", "band", "iso", "exposure_s"])
        offset_var = (per["corner_dev_dn"].apply(lambda d: float(np.sum(np.square(d))) / max(len(d) - 1, 1))
                      - per["sigma_corner_dn"].apply(lambda v: float(np.mean(np.square(v)))))
        for (lens, band, iso, t), v in offset_var.items():
            per_lens_band[(lens, band)].setdefault("offset_var", {})[(float(iso), float(t))] = max(float(v), 0.0)
    out = {lens: _lens_dataset(lens, st, fr, per_lens_band, params, dark_rate, drift, fit, ffit,
                               config, settings, ref_iso)
           for lens in lenses}
    for lens, ds in out.items():
        reference = reduced.get("bias_reference", {}).get(lens, "unlit corners")
        ds.attrs["projection"] = reduced.get("projections", {}).get(lens, "fisheye")
        ds.attrs["bias_reference"] = reference
        ds.attrs["bias_drift_testable"] = int(reference != "none")
        if reference == "none":
            ds.attrs["bias_drift_note"] = ("bias_drift not testable: a rectilinear region has no unlit corners and "
                                           "the DNG declares no optically black pixels (ActiveArea/MaskedAreas)")
        if reference == "optically black pixels":
            # the black-level reference of the later stages: optically black mean less the
            # region's dark level, at the shortest exposure of the lowest ISO (no dark current)
            shortest = min(t for (i, t) in settings if i == ref_iso)
            sel = fr[(fr["lens"] == lens) & (fr["iso"] == ref_iso) & (fr["exposure_s"] == shortest)]
            offset = sel.groupby("band").apply(lambda g: float((g["corner_dn"] - g["circle_mean_dn"]).mean()),
                                               include_groups=False)
            ds["optical_black_offset_dn"] = ("band", offset.reindex(list(BANDS)).to_numpy(float),
                                             {"long_name": "mean of the optically black pixels less the region's "
                                                           "dark level (shortest exposure, lowest ISO)", "units": "DN"})
    if temperature is not None:
        for ds in out.values():
            ds["temperature_bias_dn_per_c"] = ((), temperature["coef"][0],
                                               {"long_name": "black-level change per degree C", "units": "DN degree_C-1"})
            ds["temperature_bias_dn_per_c_sigma"] = ((), temperature["sigma"][0], {"units": "DN degree_C-1"})
            ds["temperature_dark_dn_per_s_per_c"] = ((), temperature["coef"][1],
                                                     {"long_name": "dark-current change per degree C (ISO 100)",
                                                      "units": "DN s-1 degree_C-1"})
            ds["temperature_dark_dn_per_s_per_c_sigma"] = ((), temperature["sigma"][1], {"units": "DN s-1 degree_C-1"})
            ds["temperature_reference_c"] = ((), temperature["reference_c"],
                                             {"long_name": "reference temperature of the dark model", "units": "degree_C"})
    return out


def _lens_dataset(lens, st, fr, per_lens_band, params, dark_rate, drift, fit, ffit, config,
                  settings, ref_iso) -> xr.Dataset:
    cfg = config["dark"]
    lo, hi = (float(v) for v in cfg["histogram_range_dn"])
    first = per_lens_band[(lens, BANDS[0])]
    level = float(np.median(first["means"][settings[0]][first["used"]]))
    if not lo <= level <= hi:
        # another camera's black level (a 12-bit phone's 256 DN): the range keeps its width and moves
        # to the data, the dark level at 30 % of it, instead of leaving the histograms empty
        lo, hi = level - 0.3 * (hi - lo), level + 0.7 * (hi - lo)
    edges = np.arange(lo, hi + 1e-9, cfg["histogram_bin_dn"])
    st_l = st[st["lens"] == lens].reset_index(drop=True)
    fr_l = fr[fr["lens"] == lens].reset_index(drop=True)
    n_set = len(settings)
    hist = np.zeros((len(BANDS), n_set, len(edges) - 1))
    centre = np.zeros((len(BANDS), n_set))
    width = np.zeros((len(BANDS), n_set))
    temporal = np.zeros((len(BANDS), n_set))
    first = per_lens_band[(lens, BANDS[0])]["means"][settings[0]]
    fpn = np.zeros((len(BANDS),) + first.shape, dtype=np.float32)
    hot = np.zeros((len(BANDS),) + first.shape, dtype=np.uint8)
    b0 = np.zeros((len(BANDS), 2))
    b1 = np.zeros((len(BANDS), 2))
    for bi, band in enumerate(BANDS):
        d = per_lens_band[(lens, band)]
        used = d["used"]
        for si, s in enumerate(settings):
            m = d["means"][s][used]
            hist[bi, si] = np.histogram(m, bins=edges)[0]
            centre[bi, si] = m.mean()
            width[bi, si] = m.std()
            # temporal noise of one raw pixel (the G band pixel averages two sites)
            common = d.get("offset_var", {}).get((float(s[0]), float(s[1])), 0.0)
            temporal[bi, si] = np.sqrt(max(d["vars"][s][used].mean() - common, 0.0) * SITES_PER_BAND_PIXEL[band])
        shortest = min(t for (i, t) in settings if i == ref_iso)
        m0 = d["means"][(ref_iso, shortest)]
        fpn[bi] = (m0 - m0[used].mean()).astype(np.float32)
        hot[bi] = d["hot"].astype(np.uint8)
        b0[bi] = params[f"{lens}/{band}:b0"]
        b1[bi] = params[f"{lens}/{band}:b1"]

    iso_s = np.array([s[0] for s in settings])
    t_s = np.array([s[1] for s in settings])
    isos = sorted(set(iso_s))
    read = np.zeros((len(BANDS), len(isos)))
    for k, iso in enumerate(isos):
        shortest = min(t for (i, t) in settings if i == iso)
        read[:, k] = temporal[:, settings.index((iso, shortest))]

    ds = xr.Dataset(
        coords={
            "band": ("band", list(BANDS)),
            "setting": ("setting", np.arange(n_set)),
            "iso": ("iso", np.array(isos, float), {"long_name": "ISO speed", "units": "1"}),
            "hist_bin_centre_dn": ("hist_bin", 0.5 * (edges[1:] + edges[:-1]), {"units": "DN"}),
            "y": ("y", np.arange(first.shape[0])), "x": ("x", np.arange(first.shape[1])),
        },
        data_vars={
            "setting_iso": ("setting", iso_s, {"long_name": "ISO speed of the setting", "units": "1"}),
            "setting_exposure_s": ("setting", t_s, {"long_name": "exposure time", "units": "s"}),
            "dark_centre_dn": (("band", "setting"), centre,
                               {"long_name": "mean of the frame-averaged dark image (Gaussian centre, Fig. 9c)", "units": "DN"}),
            "dark_width_dn": (("band", "setting"), width,
                              {"long_name": "spatial spread of the frame-averaged dark image (Gaussian width, Fig. 9c)", "units": "DN"}),
            "temporal_noise_dn": (("band", "setting"), temporal,
                                  {"long_name": "temporal noise of one raw pixel (with bias_drift in the model, "
                                                "the frames' common offsets left out)", "units": "DN"}),
            "dark_histogram": (("band", "setting", "hist_bin"), hist,
                               {"long_name": "histogram of the frame-averaged dark image (Fig. 9a-b)", "units": "count"}),
            "read_noise_dn": (("band", "iso"), read,
                              {"long_name": "temporal noise of one raw pixel at the shortest exposure", "units": "DN"}),
            "bias_dn": ("band", b0[:, 0], {"long_name": "black level at ISO 100 (b0)", "units": "DN"}),
            "bias_dn_sigma": ("band", b0[:, 1], {"long_name": "standard error of b0", "units": "DN"}),
            "bias_per_gain_dn": ("band", b1[:, 0], {"long_name": "black level change per unit of ISO/100 (b1)", "units": "DN"}),
            "bias_per_gain_dn_sigma": ("band", b1[:, 1], {"long_name": "standard error of b1", "units": "DN"}),
            "dark_current_dn_per_s": ((), dark_rate[0], {"long_name": "dark current at ISO 100 (D); 0 when not in the model", "units": "DN s-1"}),
            "dark_current_dn_per_s_sigma": ((), dark_rate[1], {"long_name": "standard error of D", "units": "DN s-1"}),
            "bias_drift_dn": ((), drift[0], {"long_name": "frame-to-frame black-level spread (0 when not in the model, "
                                                          "NaN when not testable)", "units": "DN"}),
            "bias_drift_dn_low": ((), drift[1], {"long_name": "lower 95 % bound of bias_drift_dn", "units": "DN"}),
            "bias_drift_dn_high": ((), drift[2], {"long_name": "upper 95 % bound of bias_drift_dn", "units": "DN"}),
            "fpn_map_dn": (("band", "y", "x"), fpn,
                           {"long_name": "offset fixed pattern at the shortest exposure and lowest ISO, mean removed", "units": "DN"}),
            "hot_pixel_mask": (("band", "y", "x"), hot, {"long_name": "hot pixel (1) flagged in the longest exposures", "units": "1"}),
            "hot_pixel_count": ("band", hot.reshape(len(BANDS), -1).sum(axis=1), {"long_name": "number of hot band pixels", "units": "1"}),
            "rms_z": ((), np.sqrt((fit.chi2 + ffit.chi2) / max(fit.dof + ffit.dof, 1)),
                      {"long_name": "RMS of the noise-normalised residuals of the dark model (1 at the noise floor)", "units": "1"}),
        },
    )
    ds = ds.merge(table_to_dataset(st_l, "obs_setting")).merge(table_to_dataset(fr_l, "obs_frame"))
    return ds


def compute(ctx) -> xr.Dataset:
    """The dark artefact of one lens (the stage runner's contract)."""
    reduced = reduce_dark(ctx.dataset, ctx.config, progress=ctx.progress)
    ctx.record_frames(reduced["inputs"])
    return analyse_dark(reduced, ctx.config, ctx.effects)[ctx.lens]
