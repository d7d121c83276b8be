"""Linearity (Larouche et al. 2024, Section 3.1, Figs. 2-3): Pearson r, regression lines, nonlinearity, photon transfer, residuals."""

from __future__ import annotations


import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import xarray as xr  # noqa: E402

from pipeline.stages.observations import dataset_to_table  # noqa: E402
from pipeline.radiometry.exposure import gain_from_iso  # noqa: E402
from pipeline.io.frames import SITES_PER_BAND_PIXEL  # noqa: E402
from pipeline.report.content import Table, Text, draw  # noqa: E402
from pipeline.report.formatting import bands as band_list  # noqa: E402
from pipeline.report.formatting import bias_drift_text, fmt_uncertain, fmt_value, quantity  # noqa: E402
from pipeline.report.palette import BAND_COLOURS  # noqa: E402
from pipeline.report.registry import section  # noqa: E402
from pipeline.report.sections._common import effects_table, per_lens, z_guides  # noqa: E402


def _mask(ds: xr.Dataset) -> np.ndarray:
    ny, nx = ds["pearson_r"].shape[-2:]
    yy, xx = np.mgrid[0:ny, 0:nx]
    cx, cy = float(ds["mask_centre_x_px"]), float(ds["mask_centre_y_px"])
    return np.hypot(xx - cx, yy - cy) <= float(ds["mask_radius_px"])


def _sweep_x(tab: pd.DataFrame, sweep: str) -> np.ndarray:
    return (tab["exposure_s"].to_numpy() * 1e3 if sweep == "exposure" else gain_from_iso(tab["iso"].to_numpy()))


SWEEP_MARKERS = {"exposure": "o", "gain": "s"}
SWEEP_XLABEL = {"exposure": "exposure time [ms]", "gain": "gain ISO/100 [1]"}


def _linearity_section(lens: str, ds: xr.Dataset, inputs) -> list:
    """The linearity section of one lens: the Pearson r, regression-line, nonlinearity, photon-transfer and
    residual figures, then the fitted parameters, the sweeps' rates and lines and the EMVA1288 figures."""
    out = []
    bands = band_list(ds)
    sweeps = [str(s) for s in ds["sweep"].values] if "sweep" in ds.coords else []
    tab = dataset_to_table(ds, "obs_setting")
    if "used" in tab:
        tab["used"] = tab["used"].astype(bool)
    if "pearson_r" in ds and all(k in ds for k in ("mask_centre_x_px", "mask_centre_y_px", "mask_radius_px")):
        out.append(_pearson_figure(lens, ds, bands, sweeps))
    if len(tab) and "value_dn" in tab:
        out.append(_lines_figure(lens, ds, tab, bands, sweeps))
        if "nonlinearity_pct" in tab:
            out.append(_nonlinearity_figure(lens, tab, bands, sweeps))
        if "pixel_var_dn2" in tab and "conversion_gain_dn_per_e" in ds:
            out.append(_photon_transfer_figure(lens, ds, tab, bands))
        if "z" in tab:
            out.append(_residuals_figure(lens, tab, bands, sweeps))
    out.append(Text("Fitted linearity and noise parameters:"))
    out.append(Table(["quantity", "value"], _parameter_rows(ds)))
    if "rate_dn_per_s" in ds:
        out.append(Text("Model rate (± standard error) and the regression of the mask means "
                   "(± 95 % half-interval; slope in DN/ms for the exposure sweep, DN per ISO/100 for the gain sweep):"))
        out.append(Table(["sweep", "band", "rate at ISO 100", "line slope", "line intercept [DN]", "line r"],
                         _rate_rows(ds, bands, sweeps), left=2))
    emva = _emva1288_table(ds, bands)
    if emva is not None:
        out.append(Text("EMVA1288 figures (release 3.0 definitions) per band, from the exposure sweep: saturation "
                        "at the last unsaturated setting; dynamic range mu_e,sat / (sigma_y,dark / K + 1/2); "
                        "linearity error over 5-95 % of the saturation signal; responsivity and quantum "
                        "efficiency only when linearity/frames.csv gives photons_per_pixel. Not measured: "
                        + ("; ".join(sorted({str(ds[n].attrs['not_measured']) for n in EMVA1288_SHOWN
                                             if n in ds and 'not_measured' in ds[n].attrs})) or "none") + "."))
        out.append(emva)
    out.append(effects_table(ds))
    return out


def _pearson_figure(lens: str, ds: xr.Dataset, bands: list[str], sweeps: list[str]):
    """Histograms of the per-pixel Pearson r inside the mask, one panel per sweep (Fig. 2)."""
    m = _mask(ds)
    fig, axes = plt.subplots(1, len(sweeps), figsize=(5.5 * len(sweeps), 3.6), squeeze=False)
    for ax, sw in zip(axes[0], sweeps):
        per_band = {b: ds["pearson_r"].sel(sweep=sw, band=b).values[m] for b in bands}
        per_band = {b: r[np.isfinite(r)] for b, r in per_band.items()}
        pooled = np.concatenate([r for r in per_band.values()] or [np.zeros(0)])
        if len(pooled):
            lo, hi = float(pooled.min()), float(pooled.max())
            edges = np.linspace(lo, hi if hi > lo else lo + 1e-9, max(min(len(pooled) // 3, 40), 6))
            for b, r in per_band.items():
                if len(r):
                    ax.hist(r, bins=edges, histtype="step", lw=1.5, color=BAND_COLOURS.get(b),
                            label=f"{b}: mean r = {np.mean(r):.6f} (n = {len(r)})")
        ax.ticklabel_format(axis="x", useOffset=False)
        ax.tick_params(axis="x", labelrotation=30, labelsize=7)
        ax.set_xlabel("Pearson r per pixel [1]")
        ax.set_ylabel("pixels [count]")
        ax.set_title(f"{sw} sweep", fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return draw(fig, f"lin_{lens}_pearson",
                f"Lens {lens}: per-pixel Pearson correlation of single frames with exposure time "
                f"or gain, for the {int(m.sum())} pixels within {fmt_value(float(ds['mask_radius_px']), 3)} px "
                "of the mask centre. Analogue of Larouche et al. (2024) Fig. 2.")


def _lines_figure(lens: str, ds: xr.Dataset, tab: pd.DataFrame, bands: list[str], sweeps: list[str]):
    """Mean dark-corrected DN against exposure and against ISO with the regression lines (Fig. 3)."""
    fig, axes = plt.subplots(1, len(sweeps), figsize=(5.5 * len(sweeps), 4), squeeze=False)
    slope_u = {"exposure": "DN/ms", "gain": "DN per ISO/100"}
    for ax, sw in zip(axes[0], sweeps):
        for b in bands:
            sub = tab[(tab["sweep"] == sw) & (tab["band"] == b)]
            if not len(sub):
                continue
            c = BAND_COLOURS.get(b)
            x = _sweep_x(sub, sw)
            used = sub["used"].to_numpy() if "used" in sub else np.ones(len(sub), bool)
            ax.errorbar(x[used], sub["value_dn"][used], yerr=sub["sigma_dn"][used] if "sigma_dn" in sub else None,
                        fmt="o", color=c, ms=4)
            if (~used).any():
                ax.plot(x[~used], sub["value_dn"][~used], "o", mfc="none", mec=c, ms=6)
            sl = ds["line_slope"].sel(sweep=sw, band=b)
            ic = ds["line_intercept_dn"].sel(sweep=sw, band=b)
            xx = np.linspace(0, x.max(), 50)
            lab = (f"{b}: slope {fmt_uncertain(float(sl), float(ds['line_slope_ci95'].sel(sweep=sw, band=b)))} "
                   f"{slope_u.get(sw, '')}, intercept "
                   f"{fmt_uncertain(float(ic), float(ds['line_intercept_ci95_dn'].sel(sweep=sw, band=b)))} DN, "
                   f"r = {float(ds['line_r'].sel(sweep=sw, band=b)):.6f}")
            ax.plot(xx, float(sl) * xx + float(ic), "-", color=c, lw=1, label=lab)
        ax.set_xlabel(SWEEP_XLABEL.get(sw, sw))
        ax.set_ylabel("mean dark-corrected signal [DN]")
        ax.set_title(f"{sw} sweep (± values are 95 % half-intervals)", fontsize=9)
        ax.legend(fontsize=6, loc="upper left")
    fig.tight_layout()
    return draw(fig, f"lin_{lens}_lines",
                f"Lens {lens}: mean dark-corrected signal in the mask against exposure time and "
                "against ISO/100, with the least-squares lines (slope, intercept with 95 % "
                "half-intervals, and Pearson r in the legend). Hollow markers were not used "
                "(e.g. saturated). Analogue of Larouche et al. (2024) Fig. 3.")


def _nonlinearity_figure(lens: str, tab: pd.DataFrame, bands: list[str], sweeps: list[str]):
    """The nonlinearity residuals: the mean signal's relative departure from the regression line, per sweep."""
    fig, axes = plt.subplots(1, len(sweeps), figsize=(5.5 * len(sweeps), 3.4), squeeze=False)
    for ax, sw in zip(axes[0], sweeps):
        for b in bands:
            sub = tab[(tab["sweep"] == sw) & (tab["band"] == b)]
            if len(sub):
                used = sub["used"].to_numpy() if "used" in sub else np.ones(len(sub), bool)
                x = _sweep_x(sub, sw)
                ax.plot(x[used], sub["nonlinearity_pct"][used], "o-", color=BAND_COLOURS.get(b), ms=4, label=b)
        ax.axhline(0, color="grey", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel(SWEEP_XLABEL.get(sw, sw))
        ax.set_ylabel("(data − line)/line [%]")
        ax.set_title(f"{sw} sweep", fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return draw(fig, f"lin_{lens}_nonlinearity",
                f"Lens {lens}: nonlinearity residuals, the relative departure of the "
                "mean signal from the regression line, in percent.")


def _photon_transfer_figure(lens: str, ds: xr.Dataset, tab: pd.DataFrame, bands: list[str]):
    """The photon-transfer curve of the exposure sweep with its fitted line, and the conversion gain per ISO of
    the gain sweep when there is one."""
    k = float(ds["conversion_gain_dn_per_e"])
    rn_e = float(ds["read_noise_e"]) if "read_noise_e" in ds else float("nan")
    sub = tab[(tab["sweep"] == "exposure")]
    if "used" in sub:
        sub = sub[sub["used"]]
    ncols = 2 if "ptc_gain_sweep_conversion_gain_dn_per_e" in ds else 1
    fig, axes = plt.subplots(1, ncols, figsize=(5.5 * ncols, 4), squeeze=False)
    ax = axes[0, 0]
    for b in bands:
        sb = sub[sub["band"] == b]
        if len(sb):
            site_var = sb["pixel_var_dn2"] * SITES_PER_BAND_PIXEL.get(b, 1)
            ax.plot(sb["value_dn"], site_var, "o", color=BAND_COLOURS.get(b), ms=4, label=f"{b}")
    if len(sub) and np.isfinite(k):
        ss = np.geomspace(max(sub["value_dn"].min(), 1e-3), sub["value_dn"].max(), 60)
        rv = (rn_e * k) ** 2 if np.isfinite(rn_e) else 0.0
        ax.plot(ss, k * ss + rv, "k-", lw=1,
                label=f"K = {quantity(ds, 'conversion_gain_dn_per_e')}\nread noise = {quantity(ds, 'read_noise_e')}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("mean signal [DN]")
    ax.set_ylabel("temporal variance per photosite [DN²]")
    ax.set_title("photon transfer, exposure sweep", fontsize=9)
    ax.legend(fontsize=7)
    if ncols == 2:
        ax = axes[0, 1]
        iso = ds["ptc_iso"].values
        ax.plot(iso, ds["ptc_gain_sweep_conversion_gain_dn_per_e"].values, "o-")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("ISO setting [1]")
        ax.set_ylabel("conversion gain [DN/electron]")
        ax.set_title("conversion gain per ISO (gain sweep)", fontsize=9)
    fig.tight_layout()
    return draw(fig, f"lin_{lens}_ptc",
                f"Lens {lens}: photon-transfer curve (G-band variance doubled to one photosite) "
                "with the fitted line var = K·signal + (K·read noise)².")


def _residuals_figure(lens: str, tab: pd.DataFrame, bands: list[str], sweeps: list[str]):
    """The setting-level residuals z of the linearity model against the signal level."""
    fig, ax = plt.subplots(figsize=(8, 3.8))
    for sw in sweeps:
        for b in bands:
            sub = tab[(tab["sweep"] == sw) & (tab["band"] == b)]
            if not len(sub):
                continue
            used = sub["used"].to_numpy() if "used" in sub else np.ones(len(sub), bool)
            c = BAND_COLOURS.get(b)
            mk = SWEEP_MARKERS.get(sw, "o")
            ax.plot(sub["value_dn"][used], sub["z"][used], mk, color=c, ms=5, label=f"{b}, {sw}")
            if (~used).any():
                ax.plot(sub["value_dn"][~used], sub["z"][~used], mk, mfc="none", mec=c, ms=6)
    z_guides(ax)
    ax.set_xscale("log")
    ax.set_xlabel("mean signal [DN]")
    ax.set_ylabel("residual z (data − model)/σ [1]")
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    return draw(fig, f"lin_{lens}_residuals",
                f"Lens {lens}: setting-level residuals of the linearity model against signal "
                "level (circles: exposure sweep, squares: gain sweep; hollow: not used). "
                "Structure at low signal, e.g. a rising z at short exposures, suggests a "
                "shutter offset.")


def _parameter_rows(ds: xr.Dataset) -> list[list[str]]:
    """The fitted linearity and noise parameters' rows (quantity, value): saturation, photon transfer, the mask,
    the bias drift, the projection and the RMS of the normalised residuals."""
    rows = []
    for name, label in (("saturation_dn", "saturation level above dark"),
                        ("conversion_gain_dn_per_e", "conversion gain K"),
                        ("gain_e_per_dn", "gain 1/K"),
                        ("read_noise_e", "read noise (photon transfer)"),
                        ("image_circle_radius_px", "image circle radius (rectilinear: half diagonal)"),
                        ("mask_radius_px", "averaging mask radius"),
                        ("mask_centre_x_px", "mask centre x"),
                        ("mask_centre_y_px", "mask centre y"),
                        ("bias_drift_dn", "frame-to-frame bias drift")):
        if name in ds:
            extra = ""
            if name == "saturation_dn" and "reached" in ds[name].attrs:
                extra = " (reached)" if int(ds[name].attrs["reached"]) else " (not reached: lower bound)"
                if "n_saturated_settings" in ds and int(ds["n_saturated_settings"]):
                    n = int(ds["n_saturated_settings"])
                    extra = extra[:-1] + f"; {n} saturated setting{'s' if n > 1 else ''} left out of the fits)"
            rows.append([label, (bias_drift_text(ds) if name == "bias_drift_dn" else quantity(ds, name)) + extra])
    if "projection" in ds.attrs:
        rows.append(["lens projection; mask field angles from",
                     f"{ds.attrs['projection']}; {ds.attrs.get('field_angles_from', 'n/a')}"])
    if "rms_z" in ds:
        parts = [f"{what} table {fmt_value(float(ds['rms_z'].attrs[f'{what}_table']), 3)}"
                 for what in ("setting", "frame", "flat") if f"{what}_table" in ds["rms_z"].attrs
                 and np.isfinite(float(ds["rms_z"].attrs[f"{what}_table"]))]
        rows.append(["rms of normalised residuals (1 = noise floor)",
                     fmt_value(float(ds["rms_z"]), 3) + (f" ({', '.join(parts)})" if parts else "")])
    return rows


def _rate_rows(ds: xr.Dataset, bands: list[str], sweeps: list[str]) -> list[list[str]]:
    """Per sweep and band the model's rate at ISO 100 and the regression line of the mask means."""
    rows = []
    for sw in sweeps:
        for b in bands:
            rows.append([sw, b, quantity(ds, "rate_dn_per_s", sweep=sw, band=b),
                         fmt_uncertain(float(ds["line_slope"].sel(sweep=sw, band=b)),
                                       float(ds["line_slope_ci95"].sel(sweep=sw, band=b))),
                         fmt_uncertain(float(ds["line_intercept_dn"].sel(sweep=sw, band=b)),
                                       float(ds["line_intercept_ci95_dn"].sel(sweep=sw, band=b))),
                         f"{float(ds['line_r'].sel(sweep=sw, band=b)):.6f}"])
    return rows


#: the EMVA1288 figures shown, with their labels
EMVA1288_SHOWN = {"temporal_dark_noise_dn": "temporal dark noise sigma_y,dark",
                  "saturation_signal_dn": "saturation signal mu_y,sat",
                  "saturation_capacity_e": "saturation capacity mu_e,sat",
                  "dynamic_range": "dynamic range", "dynamic_range_db": "dynamic range",
                  "dynamic_range_bits": "dynamic range",
                  "snr_max": "SNR_max", "snr_max_db": "SNR_max",
                  "linearity_error_min_pct": "linearity error LE_min",
                  "linearity_error_max_pct": "linearity error LE_max",
                  "responsivity_dn_per_photon": "responsivity R",
                  "quantum_efficiency": "quantum efficiency eta",
                  "prnu1288_pct": "PRNU1288 (photon-transfer region, the setting with the most frames)"}


def _emva1288_table(ds: xr.Dataset, bands: list[str]) -> Table | None:
    names = [n for n in EMVA1288_SHOWN if n in ds and "band" in ds[n].dims
             and np.any(np.isfinite(ds[n].values))]
    if not names:
        return None
    # a figure in decibels is a number on disk (units 1: UDUNITS-2 has no decibel); its name says dB
    rows = [[EMVA1288_SHOWN[n], "dB" if n.endswith("_db") else str(ds[n].attrs.get("units", ""))]
            + [quantity(ds, n, units=False, band=b) for b in bands] for n in names]
    return Table(["quantity", "unit"] + list(bands), rows, left=2)




@section("linearity", "Linearity", order=30,
         intro="Response against exposure time and ISO gain inside the averaging mask, the photon-transfer gain "
               "and read noise, and the residuals of the linearity model (Section 3.1).")
def linearity_section(inputs) -> list:
    """The "Linearity" section: one group per lens with its linearity artefact, or a note that the stage was not run.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs.

    Returns
    -------
    list
        The section's blocks (:mod:`pipeline.report.content`).
    """
    return per_lens(inputs, "linearity", "linearity", _linearity_section, anchor="lin")
