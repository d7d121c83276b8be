"""Dark frames (Larouche et al. 2024, Section 3.7, Fig. 9): histograms, centre and width, fitted dark model, FPN map, residuals."""

from __future__ import annotations


import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import xarray as xr  # noqa: E402

from pipeline.stages.observations import dataset_to_table  # noqa: E402
from pipeline.radiometry.dark import dark_level_dn  # noqa: E402
from pipeline.report.content import Table, Text, draw  # noqa: E402
from pipeline.report.formatting import bands as band_list  # noqa: E402
from pipeline.report.formatting import bias_drift_text, fmt_value, quantity, var_units  # noqa: E402
from pipeline.report.palette import BAND_COLOURS, DIVERGING_MAP, sequence  # noqa: E402
from pipeline.report.registry import section  # noqa: E402
from pipeline.report.sections._common import per_lens, z_guides  # noqa: E402


def _dark_section(lens: str, ds: xr.Dataset, inputs) -> list:
    """The dark section of one lens: the histograms, the centre and width against exposure and ISO with the
    fitted model, the fitted parameters and read noise, the fixed-pattern map and the residuals."""
    out = []
    bands = band_list(ds)
    series = _setting_series(ds)
    if "dark_histogram" in ds:
        out.append(_histogram_figure(lens, ds, bands, series))
    out.append(_centre_width_figure(lens, ds, bands, series))
    out.extend(_parameter_tables(ds, bands))
    if "fpn_map_dn" in ds:
        out.append(_fpn_figure(lens, ds, bands))
    tab = dataset_to_table(ds, "obs_setting")
    if len(tab) and "z" in tab:
        out.append(_residuals_figure(lens, tab, bands))
    return out


def _setting_series(ds: xr.Dataset) -> dict:
    """The two series of settings the figures show.

    Returns a dict: ``iso``, ``exposure_s`` (per setting), ``iso_min`` and ``low`` (the settings at the lowest
    ISO, by exposure), ``t_iso`` and ``at_t`` (the settings at the exposure time closest to 1 s that has more
    than one ISO, by ISO).
    """
    iso_s = ds["setting_iso"].values
    exp_s = ds["setting_exposure_s"].values
    iso_min = float(np.min(iso_s))
    low = np.where(iso_s == iso_min)[0]
    low = low[np.argsort(exp_s[low])]
    # the ISO series: settings sharing the exposure time closest to 1 s that has >1 ISO
    exps, counts = np.unique(exp_s, return_counts=True)
    multi = exps[counts > 1] if np.any(counts > 1) else exps
    t_iso = float(multi[np.argmin(np.abs(np.log(multi / 1.0)))])
    at_t = np.where(exp_s == t_iso)[0]
    at_t = at_t[np.argsort(iso_s[at_t])]
    return {"iso": iso_s, "exposure_s": exp_s, "iso_min": iso_min, "low": low, "t_iso": t_iso, "at_t": at_t}


def _histogram_figure(lens: str, ds: xr.Dataset, bands: list[str], series: dict):
    """Histograms of the frame-averaged dark image per exposure at the lowest ISO and per ISO (Fig. 9a-b)."""
    iso_s, exp_s, iso_min, t_iso = series["iso"], series["exposure_s"], series["iso_min"], series["t_iso"]
    centres = ds["hist_bin_centre_dn"].values if "hist_bin_centre_dn" in ds else np.arange(ds.sizes["hist_bin"])
    fig, axes = plt.subplots(len(bands), 2, figsize=(11, 2.6 * len(bands)), squeeze=False)
    for i, b in enumerate(bands):
        for j, (idx, lab) in enumerate(((series["low"], "exposure"), (series["at_t"], "iso"))):
            ax = axes[i, j]
            colours = sequence(len(idx))
            for k, s in enumerate(idx):
                h = ds["dark_histogram"].sel(band=b).isel(setting=int(s)).values
                txt = (f"{exp_s[s] * 1e3:.4g} ms" if lab == "exposure" else f"ISO {iso_s[s]:.0f}")
                ax.step(centres, h, where="mid", color=colours[k], lw=1, label=txt)
            nz = np.nonzero(ds["dark_histogram"].sel(band=b).isel(setting=list(map(int, idx))).sum("setting").values)[0]
            if len(nz):
                ax.set_xlim(centres[max(nz[0] - 3, 0)], centres[min(nz[-1] + 3, len(centres) - 1)])
            ax.set_yscale("log")
            ax.set_xlabel("frame-averaged dark level [DN]")
            ax.set_ylabel("pixels [count]")
            ttl = (f"{b} band, ISO {iso_min:.0f}, per exposure" if lab == "exposure"
                   else f"{b} band, {t_iso:.4g} s, per ISO")
            ax.set_title(ttl, fontsize=9)
            ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    return draw(fig, f"dark_{lens}_histograms",
                f"Lens {lens}: histograms of the frame-averaged dark image "
                f"(left: each exposure time at the lowest ISO, {iso_min:.0f}; right: each ISO at "
                f"{t_iso:.4g} s). Analogue of Larouche et al. (2024) Fig. 9a–b.")


def _centre_width_figure(lens: str, ds: xr.Dataset, bands: list[str], series: dict):
    """Centre and width of the dark image against exposure time and ISO, with the fitted model (Fig. 9c)."""
    iso_s, exp_s, iso_min, t_iso = series["iso"], series["exposure_s"], series["iso_min"], series["t_iso"]
    low, at_t = series["low"], series["at_t"]
    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5))
    for b in bands:
        c = BAND_COLOURS.get(b, None)
        cen = ds["dark_centre_dn"].sel(band=b).values
        wid = ds["dark_width_dn"].sel(band=b).values
        axes[0, 0].plot(exp_s[low], cen[low], "o", color=c, label=f"{b} measured")
        axes[1, 0].plot(exp_s[low], wid[low], "o-", color=c, label=b)
        axes[0, 1].plot(iso_s[at_t], cen[at_t], "o", color=c, label=f"{b} measured")
        axes[1, 1].plot(iso_s[at_t], wid[at_t], "o-", color=c, label=b)
        tt = np.geomspace(exp_s[low].min(), exp_s[low].max(), 25)
        axes[0, 0].plot(tt, [dark_level_dn(ds, b, iso_min, t) for t in tt], "-", color=c, lw=1,
                        label=f"{b} model")
        ii = np.geomspace(iso_s[at_t].min(), iso_s[at_t].max(), 25)
        axes[0, 1].plot(ii, [dark_level_dn(ds, b, i, t_iso) for i in ii], "-", color=c, lw=1,
                        label=f"{b} model")
    for ax in axes[:, 0]:
        ax.set_xscale("log")
        ax.set_xlabel(f"exposure time [s] (ISO {iso_min:.0f})")
    for ax in axes[:, 1]:
        ax.set_xscale("log")
        ax.set_xlabel(f"ISO setting [1] (exposure {t_iso:.4g} s)")
    for ax in axes[0]:
        ax.set_ylabel("dark centre [DN]")
    for ax in axes[1]:
        ax.set_ylabel("dark width [DN]")
    for ax in axes.ravel():
        ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    return draw(fig, f"dark_{lens}_centre_width",
                f"Lens {lens}: centre (top) and spatial width (bottom) of the frame-averaged "
                "dark image against exposure time (left) and ISO (right); lines are the fitted "
                "dark model b0 + b1·(ISO/100 − 1) + D·(ISO/100)·t. Analogue of Fig. 9c.")


def _parameter_tables(ds: xr.Dataset, bands: list[str]) -> list:
    """The fitted dark model per band, the lens's scalar results (dark current, bias drift, reference, rms z,
    DSNU1288) and the read noise per ISO."""
    out = []
    rows = []
    for b in bands:
        rows.append([b, quantity(ds, "bias_dn", band=b), quantity(ds, "bias_per_gain_dn", band=b),
                     fmt_value(int(ds["hot_pixel_count"].sel(band=b))) if "hot_pixel_count" in ds else "n/a"])
    out.append(Text("Fitted dark model per band (uncertainties are standard errors):"))
    out.append(Table(["band", "bias b0 (ISO 100)", "bias per ISO/100 b1", "hot pixels"], rows))
    scal = [["dark current D (ISO 100)", quantity(ds, "dark_current_dn_per_s")]]
    if "bias_drift_dn" in ds:
        scal.append(["frame-to-frame bias drift", bias_drift_text(ds)])
    if "projection" in ds.attrs:
        scal.append(["lens projection (dataset.yaml)", str(ds.attrs["projection"])])
    if "bias_reference" in ds.attrs:
        scal.append(["each frame's black level from", str(ds.attrs["bias_reference"])])
    if "rms_z" in ds:
        scal.append(["rms of normalised residuals (1 = noise floor)", fmt_value(float(ds["rms_z"]), 3)])
    if "dsnu1288_dn" in ds and np.any(np.isfinite(ds["dsnu1288_dn"].values)):
        attrs = ds["dsnu1288_dn"].attrs
        scal.append([f"DSNU1288 (EMVA1288; the setting with the most frames, {int(attrs.get('n_frames', 0))} at "
                     f"{fmt_value(float(attrs.get('setting_exposure_s', np.nan)))} s)",
                     ", ".join(f"{b} {fmt_value(float(ds['dsnu1288_dn'].sel(band=b)), 3)}" for b in bands) + " DN"])
    out.append(Table(["quantity", "value"], scal))
    if "read_noise_dn" in ds:
        isos = ds["iso"].values
        u = var_units(ds, "read_noise_dn")
        rows = [[b] + [fmt_value(float(ds["read_noise_dn"].sel(band=b, iso=i)), 3) for i in isos] for b in bands]
        out.append(Text(f"Read noise (temporal noise of one raw pixel at the shortest exposure) per ISO, "
                   f"in {u}:"))
        out.append(Table(["band"] + [f"ISO {i:.0f}" for i in isos], rows))
    return out


def _fpn_figure(lens: str, ds: xr.Dataset, bands: list[str]):
    """The offset fixed-pattern map per band with the flagged hot pixels circled."""
    fig, axes = plt.subplots(1, len(bands), figsize=(3.6 * len(bands), 3.3), squeeze=False)
    for ax, b in zip(axes[0], bands):
        m = ds["fpn_map_dn"].sel(band=b).values
        lim = np.nanpercentile(np.abs(m), 99) or 1.0
        im = ax.imshow(m, cmap=DIVERGING_MAP, vmin=-lim, vmax=lim, origin="upper")
        if "hot_pixel_mask" in ds:
            yy, xx = np.nonzero(ds["hot_pixel_mask"].sel(band=b).values)
            ax.plot(xx, yy, "o", mfc="none", mec="k", ms=6, label=f"hot ({len(xx)})")
            ax.legend(fontsize=6, loc="lower right")
        ax.set_title(f"{b} band", fontsize=9)
        fig.colorbar(im, ax=ax, shrink=0.8, label=f"offset FPN [{var_units(ds, 'fpn_map_dn')}]")
    fig.tight_layout()
    return draw(fig, f"dark_{lens}_fpn",
                f"Lens {lens}: offset fixed-pattern map at the shortest exposure and lowest "
                "ISO (mean removed); circles mark the flagged hot pixels.")


def _residuals_figure(lens: str, tab, bands: list[str]):
    """The setting-level residuals z of the dark model against exposure time, coloured by ISO."""
    fig, ax = plt.subplots(figsize=(8, 3.8))
    isos = np.unique(tab["iso"])
    colours = sequence(len(isos))
    markers = {"R": "^", "G": "o", "B": "s"}
    for k, i in enumerate(isos):
        for b in bands:
            sub = tab[(tab["iso"] == i) & (tab["band"] == b)]
            if len(sub):
                ax.plot(sub["exposure_s"], sub["z"], markers.get(b, "o"), color=colours[k], ms=5,
                        label=f"ISO {i:.0f}" if b == bands[0] else None)
    z_guides(ax)
    ax.set_xscale("log")
    ax.set_xlabel("exposure time [s]")
    ax.set_ylabel("residual z (data − model)/σ [1]")
    ax.legend(fontsize=6, ncol=3, title="▲R ●G ■B", title_fontsize=7)
    fig.tight_layout()
    return draw(fig, f"dark_{lens}_residuals",
                f"Lens {lens}: setting-level residuals of the dark model, normalised by their "
                "uncertainty, against exposure time. Dotted: ±1, dashed: ±3. A trend with "
                "exposure time points to an unmodelled effect.")


@section("dark", "Dark frames", order=20,
         intro="Dark frames per lens: distribution of the frame-averaged dark image, its centre and width against "
               "exposure time and ISO, the fitted bias and dark current, read noise and hot pixels (Section 3.7).")
def dark_section(inputs) -> list:
    """The "Dark frames" section: one group per lens with its dark artefact, or a note that the stage was not run.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs.

    Returns
    -------
    list
        The section's blocks (:mod:`pipeline.report.content`).
    """
    return per_lens(inputs, "dark", "dark", _dark_section)
