"""Immersion-factor stage (Larouche et al. 2024, Sections 2.7 and 3.6; Eqs. (10), (11), Table 2, Fig. 8).

Streams the immersion frames once (dark frames first): dark correction with
the per-pixel mean of the lens's dark frames, mean in the
``immersion.mask_half_angle_deg`` mask of the geometry artefact (water maps
for in-water frames, air maps in air; at least the pixel nearest the axis),
then per lens and band: log-linear regression of the in-water means against
water height, intercept y(0-), t_aw n_w^2 at the band's effective wavelength
(spectral artefact when given, else 600/540/480 nm) for the water of
immersion/water.yaml, I by Eq. (11) with its 95 % interval, n_g from Eq. (10).
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.io.bands import BANDS
from pipeline.io.dataset import read_water
from pipeline.errors import InputError
from pipeline.stats.fitting import wls
from pipeline.io.frames import iter_frames
from pipeline.stats.moments import RunningMoments
from pipeline.radiometry.fresnel import transmittance_air_water
from pipeline.radiometry.exposure import exposure_gain_s
from pipeline.radiometry.measurement import FrameSettings
from pipeline.radiometry.response import response_corrected, response_effects
from pipeline.radiometry.immersion import (fit_immersion_factor, n_squared_law_factor,
                                           window_index_from_immersion_factor)
from pipeline.radiometry.water import refractive_index_water
from pipeline.stages.observations import table_to_dataset, with_corner_table
from pipeline.radiometry.unlit_corners import FrameCorners

STAGE = "immersion"
NOMINAL_WAVELENGTH_NM = {"R": 600.0, "G": 540.0, "B": 480.0}


def effective_wavelengths(spectral: xr.Dataset | None) -> dict[str, float]:
    """The wavelength each band's water optics are evaluated at: the spectral stage's effective wavelengths, else the nominal ones.

    Parameters
    ----------
    spectral : xarray.Dataset or None
        The lens's spectral artefact, or ``None`` when the spectral stage has not run.

    Returns
    -------
    dict[str, float]
        Band -> wavelength, nm (``NOMINAL_WAVELENGTH_NM`` without the artefact).
    """
    if spectral is not None and "effective_wavelength_nm" in spectral:
        return {b: float(spectral["effective_wavelength_nm"].sel(band=b)) for b in BANDS}
    return dict(NOMINAL_WAVELENGTH_NM)


def _mask(theta: np.ndarray, half: float, min_pixels: int) -> np.ndarray:
    """Pixels within ``half`` of the axis, or the ``min_pixels`` nearest the axis when fewer."""
    m = np.isfinite(theta) & (theta <= half)
    if m.sum() < min_pixels:
        t = np.where(np.isfinite(theta), theta, np.inf)
        m = t <= np.sort(t, axis=None)[min_pixels - 1]
    return m


def reduce_immersion(dataset, geometry: dict[str, xr.Dataset], config: dict, progress=False,
                     corners: FrameCorners | None = None) -> dict:
    """Stream the immersion frames once (dark frames first).

    Parameters
    ----------
    dataset : pipeline.io.dataset.Dataset
        The dataset; its ``immersion`` experiment's frames are read.
    geometry : dict[str, xarray.Dataset]
        Lens -> its geometry artefact (the theta maps of each medium, for the central masks).
    config : dict
        The run's configuration (section ``immersion``: ``mask_half_angle_deg``, ``min_mask_pixels``).
    progress : bool, default False
        Show a progress bar.
    corners : pipeline.radiometry.unlit_corners.FrameCorners or None, optional
        When given, records each signal frame's unlit corners against the dark model.

    Returns
    -------
    dict
        ``frames`` (one row per signal frame, lens and band: ``condition``, ``water_height_cm`` (cm, 0 in
        air), ``dn`` (mean dark-subtracted DN in the central mask), ``exposure_s``, ``iso``, ``n_mask``) and
        ``inputs`` (file -> sha256).

    Raises
    ------
    pipeline.errors.InputError
        If a lens has signal frames but no dark frames.
    """
    half = config[STAGE]["mask_half_angle_deg"]
    frames = dataset.frames(STAGE)
    order = pd.concat([frames[frames["kind"] == "dark"], frames[frames["kind"] == "signal"]])
    dark = defaultdict(RunningMoments)
    # each (lens, band)'s dark mean map, made once when the first signal frame needs it (the dark frames
    # come first) instead of once per signal frame; only the signal frames' mask pixels are converted
    dark_mean = {}
    inputs, rows = {}, []
    masks = {}
    for file_index, dec in enumerate(iter_frames(dataset, STAGE, order, progress=progress)):
        row = dec.row
        inputs[row["file"]] = dec.raw.sha256
        lenses = list(dataset.lenses) if row["lens"] == "both" else [row["lens"]]
        for lens in lenses:
            if corners is not None and row["kind"] != "dark":
                corners.add(lens, dec.lenses[lens], dec.raw, row.get("temperature_c", np.nan), file_index=file_index,
                            medium="water" if row["condition"] == "water" else "air",
                            water_height_cm=float(row["water_height_cm"]) if row["condition"] == "water" else 0.0)
            for band in BANDS:
                img = dec.lenses[lens].bands[band]
                if row["kind"] == "dark":
                    dark[(lens, band)].add(img)      # float64 sums of the float32 image
                    dark_mean.pop((lens, band), None)
                    continue
                medium = "water" if row["condition"] == "water" else "air"
                key = (lens, medium, band)
                if key not in masks:
                    masks[key] = _mask(geometry[lens]["theta_deg"].sel(medium=medium, band=band).values, half,
                                       int(config[STAGE]["min_mask_pixels"]))
                if dark[(lens, band)].n == 0:
                    raise InputError(dataset.root / STAGE / "frames.csv", f"no dark frames for lens {lens}")
                m = masks[key]
                if (lens, band) not in dark_mean:
                    dark_mean[(lens, band)] = dark[(lens, band)].mean()
                rows.append({"lens": lens, "band": band, "condition": row["condition"],
                             "water_height_cm": float(row["water_height_cm"]) if medium == "water" else 0.0,
                             "dn": float((img[m].astype(float) - dark_mean[(lens, band)][m]).mean()),
                             "exposure_s": float(dec.raw.exposure_s), "iso": float(dec.raw.iso),
                             "n_mask": int(m.sum())})
    return {"frames": pd.DataFrame(rows), "inputs": inputs}


def response_normalised(fr: pd.DataFrame, linearity: xr.Dataset | None) -> np.ndarray:
    """Each frame's mask DN as DN s-1 at ISO 100 (Eq. 2), through the measurement chain's response steps.

    With the lens's linearity artefact, the fitted response corrections of its
    model (shutter offset: true exposure t + dt; per-ISO gain factors;
    inverse nonlinearity) are applied (radiometry.response.response_corrected),
    so air and water frames taken at different settings compare on the true
    exposure; without it, the nominal t ISO/100. The mask mean is corrected
    (not pixel by pixel): the 1.5 degree masks are small enough that the
    pixel-to-pixel response spread averages out in the ratio.

    Parameters
    ----------
    fr : pandas.DataFrame
        The frames of one lens (``dn`` in DN, ``exposure_s`` in s, ``iso``, ``band``).
    linearity : xarray.Dataset or None
        The lens's linearity artefact, or ``None``.

    Returns
    -------
    numpy.ndarray
        Each frame's signal, DN s-1 at ISO 100, in the rows' order.
    """
    if linearity is None:
        return (fr["dn"] / exposure_gain_s(fr["exposure_s"], fr["iso"])).to_numpy(float)
    out = np.empty(len(fr))
    for k, (_, r) in enumerate(fr.iterrows()):
        frame = FrameSettings(exposure_s=float(r["exposure_s"]), iso=float(r["iso"]))
        _, per_s = response_corrected(float(r["dn"]), linearity, r["band"], frame)
        out[k] = float(per_s.value)
    return out


def analyse_immersion(reduced: dict, water: dict, wavelengths: dict[str, float],
                      linearity: dict[str, xr.Dataset] | None = None) -> dict[str, xr.Dataset]:
    """The immersion factor of every lens and band from the signal in air and under water at several heights; one artefact per lens.

    The water column's attenuation is fitted to ln DN against height, its intercept against the air frames
    gives the immersion factor, and with the water's refractive index and air-water transmittance (at the
    band's wavelength) the index of the lens's front window.

    Parameters
    ----------
    reduced : dict
        What :func:`reduce_immersion` returned.
    water : dict
        The tank's water (:func:`pipeline.io.dataset.read_water`): ``temperature_c`` (degree Celsius) and
        ``salinity_psu`` (PSU).
    wavelengths : dict[str, float]
        Band -> wavelength the water's optics are taken at, nm (:func:`effective_wavelengths`).
    linearity : dict[str, xarray.Dataset] or None, optional
        Lens -> its linearity artefact, whose response corrections are applied (:func:`response_normalised`).

    Returns
    -------
    dict[str, xarray.Dataset]
        Lens -> its immersion artefact: per band the immersion factor and its uncertainty, the water's index
        and transmittance, the window's index, and the ``obs_height`` table of ln DN per water height.
    """
    fr = reduced["frames"].copy()
    # DN per second at ISO 100, Eq. (2) (the frames may use different settings), per lens through
    # the fitted response when its linearity artefact is given
    for lens in fr["lens"].unique():
        sel = fr["lens"] == lens
        fr.loc[sel, "dn"] = response_normalised(fr[sel], (linearity or {}).get(lens))
    out = {}
    for lens, fl in fr.groupby("lens"):
        res, obs = {}, []
        for band in BANDS:
            fb = fl[fl["band"] == band]
            air = fb.loc[fb["condition"] == "air", "dn"].to_numpy()
            wat = fb[fb["condition"] == "water"]
            lam = wavelengths[band]
            t_aw = float(transmittance_air_water(lam, water["temperature_c"], water["salinity_psu"]))
            n_w = float(refractive_index_water(lam, water["temperature_c"], water["salinity_psu"]))
            n2 = float(n_squared_law_factor(t_aw, n_w))
            fit = fit_immersion_factor(wat["water_height_cm"], wat["dn"], air, n2)
            n_g, n_g_se = window_index_from_immersion_factor(fit.immersion_factor, n_w, fit.immersion_factor_sigma)
            res[band] = dict(fit=fit, t_aw=t_aw, n_w=n_w, n2=n2, n_g=float(n_g), n_g_se=float(n_g_se), lam=lam)
            # one row per water height: mean ln DN, noise from the frame scatter pooled over heights
            g = wat.assign(ln_dn=np.log(wat["dn"])).groupby("water_height_cm")["ln_dn"]
            per = pd.DataFrame({"value_dn": g.mean(), "var": g.var(ddof=1), "n": g.size()}).reset_index()
            pooled = float(np.sum(per["var"] * (per["n"] - 1)) / max(np.sum(per["n"] - 1), 1))
            per["sigma_dn"] = np.sqrt(pooled / per["n"])
            per["x_intercept"] = 1.0
            per["x_slope"] = -per["water_height_cm"]
            per["group"] = f"{lens}/{band}"
            per["lens"], per["band"] = lens, band
            f2 = wls(per["value_dn"].to_numpy(), per["sigma_dn"].to_numpy(), per[["x_intercept", "x_slope"]].to_numpy())
            per["pred_dn"] = f2.pred
            per["z"] = f2.z
            per["used"] = 1
            obs.append(per.drop(columns=["var"]))
        out[lens] = _dataset(res, pd.concat(obs, ignore_index=True), water)
        out[lens].attrs["response_corrections"] = ",".join(response_effects((linearity or {}).get(lens)))
    return out


def _dataset(res: dict, obs: pd.DataFrame, water: dict) -> xr.Dataset:
    def arr(fn):
        return np.array([fn(res[b]) for b in BANDS], dtype=float)

    d = ("band",)
    data = {
        "dn_air": (d, arr(lambda r: r["fit"].dn_air), {"long_name": "y_DN(0+): in-air mask mean, DN per second at ISO 100", "units": "DN s-1"}),
        "dn_air_sigma": (d, arr(lambda r: r["fit"].dn_air_sigma), {"units": "DN s-1"}),
        "dn_below": (d, arr(lambda r: r["fit"].dn_below), {"long_name": "y_DN(0-): intercept of the log-linear fit (Fig. 8)", "units": "DN s-1"}),
        "dn_below_sigma": (d, arr(lambda r: r["fit"].dn_below_sigma), {"units": "DN s-1"}),
        "dn_below_over_n2": (d, arr(lambda r: r["fit"].dn_below / r["n2"]),
                             {"long_name": "y_DN(0-) / t_aw n_w^2 (Table 2, column 4)", "units": "DN s-1"}),
        "attenuation_per_cm": (d, arr(lambda r: r["fit"].attenuation_per_cm),
                               {"long_name": "slope K of ln y_DN against water height", "units": "cm-1"}),
        "attenuation_per_cm_sigma": (d, arr(lambda r: r["fit"].attenuation_per_cm_sigma), {"units": "cm-1"}),
        "r_squared": (d, arr(lambda r: r["fit"].r_squared), {"long_name": "R^2 of the log-linear fit", "units": "1"}),
        "effective_wavelength_nm": (d, arr(lambda r: r["lam"]), {"long_name": "wavelength at which n_w and t_aw are evaluated", "units": "nm"}),
        "t_aw": (d, arr(lambda r: r["t_aw"]), {"long_name": "Fresnel transmittance of the air-water surface, normal incidence", "units": "1"}),
        "n_w": (d, arr(lambda r: r["n_w"]), {"long_name": "refractive index of water (Quan and Fry 1995)", "units": "1"}),
        "n2_factor": (d, arr(lambda r: r["n2"]), {"long_name": "t_aw n_w^2 (n-squared law, Table 2)", "units": "1"}),
        "immersion_factor": (d, arr(lambda r: r["fit"].immersion_factor), {"long_name": "immersion factor I, Eq. (11)", "units": "1"}),
        "immersion_factor_sigma": (d, arr(lambda r: r["fit"].immersion_factor_sigma), {"units": "1"}),
        "immersion_factor_ci95_low": (d, arr(lambda r: r["fit"].immersion_factor_ci95[0]), {"units": "1"}),
        "immersion_factor_ci95_high": (d, arr(lambda r: r["fit"].immersion_factor_ci95[1]), {"units": "1"}),
        "window_index": (d, arr(lambda r: r["n_g"]), {"long_name": "n_g of the external surface from Eq. (10)", "units": "1"}),
        "window_index_sigma": (d, arr(lambda r: r["n_g_se"]), {"units": "1"}),
        "water_temperature_c": ((), float(water["temperature_c"]), {"long_name": "water temperature", "units": "degree_C"}),
        "water_salinity_psu": ((), float(water["salinity_psu"]), {"long_name": "practical salinity of the water (PSS-78, "
                                                                                "the dataset's salinity_psu)", "units": "1",
                                                                  "standard_name": "sea_water_practical_salinity"}),
    }
    ds = xr.Dataset(data, coords={"band": list(BANDS)})
    return ds.merge(table_to_dataset(obs, "obs_height"))


def compute(ctx) -> xr.Dataset:
    """The immersion artefact of one lens (the stage runner's contract).

    The water's refractive index and t_aw are taken at this lens's effective
    wavelengths (its spectral artefact) when the spectral stage has run.

    Parameters
    ----------
    ctx : pipeline.runner.workflow.StageContext
        The job: the lens's dataset (and its immersion/water.yaml), the configuration and the upstream
        ``geometry`` and, when given, ``dark``, ``spectral`` and ``linearity`` artefacts.

    Returns
    -------
    xarray.Dataset
        The lens's immersion artefact (:func:`analyse_immersion`) with its ``obs_corner`` table.

    Raises
    ------
    pipeline.errors.InputError
        If the immersion frames hold none of the lens.
    """
    corners = FrameCorners.of_upstream(ctx.lens, ctx.upstream, ctx.dataset.projection, ctx.config["bias"])
    reduced = reduce_immersion(ctx.dataset, {ctx.lens: ctx.upstream["geometry"]}, ctx.config, progress=ctx.progress,
                               corners=corners)
    ctx.record_frames(reduced["inputs"])
    linearity = {ctx.lens: ctx.upstream["linearity"]} if "linearity" in ctx.upstream else None
    arts = analyse_immersion(reduced, read_water(ctx.dataset), effective_wavelengths(ctx.upstream.get("spectral")),
                             linearity)
    if ctx.lens not in arts:
        raise InputError(ctx.dataset.root / STAGE / "frames.csv", f"no immersion frames for lens {ctx.lens}")
    # the signal frames' unlit corners against the dark model, for the closure (pipeline.diagnostics.cross_closure)
    return with_corner_table(arts[ctx.lens], corners.of_lens(ctx.lens))
