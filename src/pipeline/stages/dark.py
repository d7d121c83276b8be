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
  offset measured on the unlit corners);
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
from pipeline.effects import get as get_effect
from pipeline.effects.catalogue import drift_sigma
from pipeline.fitting import base_design, wls
from pipeline.frames import SITES_PER_BAND_PIXEL, iter_frames
from pipeline.moments import RunningMoments, corner_mask

STAGE = "dark"


def _setting_key(raw) -> tuple[float, float]:
    return (float(raw.iso), round(float(raw.exposure_s), 9))


def reduce_dark(dataset: Dataset, config: dict, progress: bool = False) -> dict:
    """Stream the dark frames; returns per-lens/band/setting moments and per-frame statistics."""
    frames = dataset.frames(STAGE)
    lenses = list(dataset.lenses)
    corner_fraction = config["bias"]["corner_min_radius_fraction"]
    moments = defaultdict(RunningMoments)          # (lens, band, setting) -> RunningMoments
    frame_rows = []
    corners = {}
    inputs = {}
    for i, dec in enumerate(iter_frames(dataset, STAGE, frames, lenses, progress=progress)):
        key = _setting_key(dec.raw)
        inputs[dec.row["file"]] = dec.raw.sha256
        for lens, images in dec.lenses.items():
            for band in BANDS:
                img = images.bands[band]
                if (lens, band) not in corners:
                    corners[(lens, band)] = corner_mask(img.shape, corner_fraction)
                cm = corners[(lens, band)]
                moments[(lens, band, key)].add(img)
                frame_rows.append({
                    "lens": lens, "band": band, "iso": key[0], "exposure_s": key[1], "file_index": i,
                    "circle_mean_dn": float(img[~cm].mean()), "corner_dn": float(img[cm].mean()),
                    "temperature_c": dec.row.get("temperature_c", np.nan),
                })
    return {"moments": moments, "frames": pd.DataFrame(frame_rows), "corners": corners,
            "inputs": inputs, "lenses": lenses}


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
                setting_rows.append({
                    "lens": lens, "band": band, "iso": s[0], "exposure_s": s[1],
                    "n_frames": moments[(lens, band, s)].n,
                    "pixel_var_dn2": float(v[used].mean()),
                    "corner_var_dn2": float(v[cm].mean()),
                    "n_used": int(used.sum()), "n_corner": int(cm.sum()),
                    "hot_excess_dn": mean_all - mean_nonhot,
                    "n_hot": int((hot & circle).sum()), "n_pixels": int(circle.sum()),
                })
    st = pd.DataFrame(setting_rows)
    st["gain"] = st["iso"] / 100.0
    st["group"] = st["lens"] + "/" + st["band"]
    st["setting"] = st.groupby(["iso", "exposure_s"], sort=True).ngroup()

    # ----- frame level: values, corners and bias drift
    fr = frames.merge(st[["lens", "band", "iso", "exposure_s", "setting", "hot_excess_dn", "pixel_var_dn2",
                          "corner_var_dn2", "n_used", "n_corner"]], on=["lens", "band", "iso", "exposure_s"])
    fr["value_dn"] = fr["circle_mean_dn"] - (fr["hot_excess_dn"] if use_hot else 0.0)
    fr["corner_dev_dn"] = fr["corner_dn"] - fr.groupby(["lens", "band", "setting"])["corner_dn"].transform("mean")
    fr["sigma_corner_dn"] = np.sqrt(fr["corner_var_dn2"] / fr["n_corner"])
    drift = (0.0, 0.0, 0.0)
    if use_drift:
        fr["value_dn"] -= fr["corner_dev_dn"]
        drift = drift_sigma(fr)
    # A frame's value scatters by the temporal noise of its pixels; the drift that the
    # model removed (or that is left in, without the effect) is not part of this noise.
    fr["sigma_dn"] = np.sqrt(np.maximum(fr["pixel_var_dn2"] - drift[0] ** 2, 1e-12) / fr["n_used"])
    if use_drift:
        # the corner correction adds the corners' own noise to each frame
        fr["sigma_dn"] = np.hypot(fr["sigma_dn"], fr["sigma_corner_dn"])
    fr["group"] = fr["lens"] + "/" + fr["band"] + "/" + fr["setting"].astype(str)
    fr["frame"] = fr.groupby(["lens", "band", "setting"]).cumcount()
    fr["x_level"] = 1.0
    if fr["temperature_c"].notna().all():
        fr["temperature_ref_c"] = float(fr["temperature_c"].mean())
    ffit, _ = fit_with_effects(fr, "frame", effects)
    fr["pred_dn"] = ffit.pred
    fr["z"] = ffit.z

    # ----- setting level: the dark model
    agg = fr.groupby(["lens", "band", "setting"]).agg(value_dn=("value_dn", "mean"),
                                                      frame_sigma=("sigma_dn", "mean"),
                                                      temperature_c=("temperature_c", "mean")).reset_index()
    st = st.merge(agg, on=["lens", "band", "setting"])
    st["sigma_dn"] = np.sqrt(st["frame_sigma"] ** 2 / st["n_frames"] + drift[0] ** 2 / st["n_frames"])
    st["x_b0"] = 1.0
    st["x_b1"] = st["gain"] - 1.0
    if "temperature_ref_c" in fr:
        st["temperature_ref_c"] = fr["temperature_ref_c"].iloc[0]
    fit, effect_params = fit_with_effects(st, "setting", effects)
    st["pred_dn"] = fit.pred
    st["z"] = fit.z
    names = base_design(st)[1]
    params = {name: (fit.coef[k], np.sqrt(fit.cov[k, k])) for k, name in enumerate(names)}
    dark_rate = tuple(float(v[0]) for v in effect_params.get("dark_current", ((0.0,), (0.0,))))
    temperature = effect_params.get("temperature")
    if temperature is not None:
        temperature = {"coef": temperature[0], "sigma": temperature[1],
                       "reference_c": float(st["temperature_ref_c"].iloc[0])}

    out = {lens: _lens_dataset(lens, st, fr, per_lens_band, params, dark_rate, drift, fit, ffit,
                               config, settings, ref_iso)
           for lens in lenses}
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


def fit_with_effects(table: pd.DataFrame, level: str, effects: list[str], stage: str = STAGE):
    """Weighted fit of the base columns plus the columns of the model's effects at this level.

    Returns the fit and, per effect, its coefficients and standard errors.
    """
    X, names = base_design(table)
    extra = []
    for name in effects:
        effect = get_effect(name)
        if effect.corrects_data:
            continue
        cols = effect.columns(stage, level, table)
        if cols is not None:
            extra.append((name, cols))
    Xfull = np.hstack([X] + [c for _, c in extra]) if extra else X
    fit = wls(table["value_dn"].to_numpy(), table["sigma_dn"].to_numpy(), Xfull)
    out, col = {}, X.shape[1]
    for name, cols in extra:
        k = cols.shape[1]
        out[name] = (fit.coef[col:col + k], np.sqrt(np.diag(fit.cov)[col:col + k]))
        col += k
    return fit, out


def _lens_dataset(lens, st, fr, per_lens_band, params, dark_rate, drift, fit, ffit, config,
                  settings, ref_iso) -> xr.Dataset:
    cfg = config["dark"]
    edges = np.arange(cfg["histogram_range_dn"][0], cfg["histogram_range_dn"][1] + 1e-9, cfg["histogram_bin_dn"])
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
            temporal[bi, si] = np.sqrt(d["vars"][s][used].mean() * SITES_PER_BAND_PIXEL[band])
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
                                  {"long_name": "temporal noise of one raw pixel", "units": "DN"}),
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
            "bias_drift_dn": ((), drift[0], {"long_name": "frame-to-frame black-level spread (0 when not in the model)", "units": "DN"}),
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


def table_to_dataset(table: pd.DataFrame, prefix: str) -> xr.Dataset:
    """Store an observation table as variables ``<prefix>__<column>`` along dimension ``<prefix>``."""
    data = {}
    for col in table.columns:
        values = table[col].to_numpy()
        if values.dtype == object or values.dtype.kind in "OUS" or str(table[col].dtype) in ("string", "str"):
            values = table[col].astype(str).to_numpy().astype(str)
        data[f"{prefix}__{col}"] = (prefix, values)
    return xr.Dataset(data)


def dataset_to_table(ds: xr.Dataset, prefix: str) -> pd.DataFrame:
    """Inverse of :func:`table_to_dataset`."""
    cols = {name.split("__", 1)[1]: ds[name].values for name in ds.data_vars if name.startswith(prefix + "__")}
    return pd.DataFrame(cols)


def dark_level_dn(ds: xr.Dataset, band: str, iso: float, exposure_s: float,
                  temperature_c: float | None = None) -> float:
    """Mean dark level predicted by the fitted dark model for one band and setting.

    With the ``temperature`` effect in the dark model and a logged temperature,
    the level follows it.
    """
    b = ds.sel(band=band)
    gain = iso / 100.0
    level = float(b["bias_dn"] + b["bias_per_gain_dn"] * (gain - 1.0)
                  + ds["dark_current_dn_per_s"] * gain * exposure_s)
    if temperature_c is not None and np.isfinite(temperature_c) and "temperature_bias_dn_per_c" in ds:
        dt = temperature_c - float(ds["temperature_reference_c"])
        level += float(ds["temperature_bias_dn_per_c"]) * dt
        level += float(ds["temperature_dark_dn_per_s_per_c"]) * gain * exposure_s * dt
    return level
