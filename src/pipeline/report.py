"""One self-contained HTML report of a calibration run.

:func:`build_report` reads the dark and linearity artefacts (NetCDF) and the
diagnostics tables (CSV) and writes a single HTML file: figures are embedded
as base64 PNG, the style sheet is inline and nothing is loaded from the
network. Every number in the report is read from those inputs; the module
holds no calibration values of its own.
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
import os
import re
from datetime import datetime, timezone
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import xarray as xr  # noqa: E402

from pipeline.artefact import read_artefact  # noqa: E402
from pipeline.observations import dataset_to_table  # noqa: E402
from pipeline.radiometry.exposure import gain_from_iso  # noqa: E402
from pipeline.report_field import field_section, field_summary  # noqa: E402

try:  # G band pixels average two photosites (see pipeline.stages.linearity.photon_transfer)
    from pipeline.frames import SITES_PER_BAND_PIXEL
except ImportError:  # pragma: no cover - keep the report usable if the constant moves
    SITES_PER_BAND_PIXEL = {"R": 1, "G": 2, "B": 1}

__all__ = ["build_report", "fmt_value", "fmt_uncertain"]

BAND_COLOURS = {"R": "tab:red", "G": "tab:green", "B": "tab:blue"}
SWEEP_MARKERS = {"exposure": "o", "gain": "s"}

CSS = """
body{font-family:Georgia,'Times New Roman',serif;max-width:1100px;margin:2em auto;padding:0 1em;
color:#222;line-height:1.45}
h1,h2,h3{font-family:Helvetica,Arial,sans-serif;color:#123}
h2{border-bottom:2px solid #9ab;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;margin:.6em 0 1.2em 0;font-size:.9em}
th,td{border:1px solid #bbb;padding:.25em .55em;text-align:right;vertical-align:top}
th{background:#e8eef3}
td.l,th.l{text-align:left}
figure{margin:1em 0;text-align:center}
figure img{max-width:100%;border:1px solid #ddd}
figcaption{font-size:.88em;color:#444;text-align:left;margin-top:.3em}
.callout{background:#fff4e0;border-left:5px solid #e8a33d;padding:.6em 1em;margin:1em 0}
.ok{background:#eaf6ea;border-left:5px solid #4a9a4a;padding:.6em 1em;margin:1em 0}
.note{color:#555;font-size:.9em}
code{background:#f3f3f3;padding:0 .2em}
nav ul{columns:2}
details pre{white-space:pre-wrap;font-size:.8em;background:#f7f7f7;padding:.5em}
"""


# ---------------------------------------------------------------- formatting

def _finite(x) -> bool:
    try:
        return math.isfinite(float(x))
    except (TypeError, ValueError):
        return False


def fmt_value(value, digits: int = 4) -> str:
    """A number with ``digits`` significant figures (plain notation unless very large or small)."""
    if value is None:
        return "—"
    try:
        v = float(value)
    except (TypeError, ValueError):
        return str(value)
    if math.isnan(v):
        return "n/a"
    if math.isinf(v):
        return "∞" if v > 0 else "−∞"
    if v == 0:
        return "0"
    if v == int(v) and abs(v) < 1e9 and isinstance(value, (int, np.integer)):
        return str(int(v))
    mag = math.floor(math.log10(abs(v)))
    if mag < -3 or mag >= 6:
        return f"{v:.{digits - 1}e}"
    decimals = max(digits - 1 - mag, 0)
    return f"{v:.{decimals}f}"


def fmt_uncertain(value, sigma) -> str:
    """``value ± sigma``, sigma to two significant figures and the value to the same decimal place.

    Falls back to :func:`fmt_value` when sigma is missing, zero or not finite.
    """
    if not _finite(value):
        return fmt_value(value)
    v = float(value)
    if not _finite(sigma) or float(sigma) <= 0:
        return fmt_value(v)
    s = float(sigma)
    ref = max(abs(v), s)
    mag = math.floor(math.log10(ref))
    if mag < -3 or mag >= 6:
        scale = 10.0 ** mag
        vs, ss = v / scale, s / scale
        dec = max(1 - math.floor(math.log10(ss)), 0)
        return f"({vs:.{dec}f} ± {ss:.{dec}f})×10^{mag}"
    dec = max(1 - math.floor(math.log10(s)), 0)
    return f"{v:.{dec}f} ± {s:.{dec}f}"


def _unit(units: str | None) -> str:
    if not units or units == "1":
        return ""
    u = str(units)
    for a, b in (("s-1", "s⁻¹"), ("ms-1", "ms⁻¹"), ("dn2", "DN²"), ("DN2", "DN²")):
        u = u.replace(a, b)
    return u


def _e(x) -> str:
    return html.escape(str(x))


def _var_units(ds: xr.Dataset, name: str) -> str:
    return _unit(ds[name].attrs.get("units", "")) if name in ds else ""


def _bias_drift_text(ds: xr.Dataset) -> str:
    """The bias drift, or why it could not be tested (no unlit corners, no optically black pixels)."""
    if not int(ds.attrs.get("bias_drift_testable", 1)):
        return ds.attrs.get("bias_drift_note", "not testable")
    return _q(ds, "bias_drift_dn")


def _q(ds: xr.Dataset, name: str, **sel) -> str:
    """The artefact value ``name`` (selected by ``sel``) with its uncertainty and units."""
    if name not in ds:
        return "n/a"
    da = ds[name].sel(**sel) if sel else ds[name]
    val = float(da)
    sig = None
    for cand in (f"{name}_sigma", f"{name.removesuffix('_dn')}_sigma_dn"):
        if cand in ds:
            sd = ds[cand]
            sd = sd.sel(**{k: v for k, v in sel.items() if k in sd.dims})
            sig = float(sd) if sd.size == 1 else None
            break
    text = fmt_uncertain(val, sig)
    lo, hi = f"{name}_low", f"{name}_high"
    if lo in ds and hi in ds:
        lv = ds[lo].sel(**{k: v for k, v in sel.items() if k in ds[lo].dims})
        hv = ds[hi].sel(**{k: v for k, v in sel.items() if k in ds[hi].dims})
        text += f" [95 %: {fmt_value(float(lv))}, {fmt_value(float(hv))}]"
    u = _var_units(ds, name)
    return f"{text} {u}".strip()


def _table(header: list[str], rows: list[list], left: int = 1) -> str:
    """An HTML table; the first ``left`` columns are left-aligned. Cells are escaped."""
    def cell(tag, i, x):
        cls = ' class="l"' if i < left else ""
        return f"<{tag}{cls}>{_e(x)}</{tag}>"
    out = ["<table>", "<tr>" + "".join(cell("th", i, h) for i, h in enumerate(header)) + "</tr>"]
    for r in rows:
        out.append("<tr>" + "".join(cell("td", i, x) for i, x in enumerate(r)) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


# ---------------------------------------------------------------- figures

class _Figures:
    """Turn matplotlib figures into embedded <img> tags (and optional PNG files)."""

    def __init__(self, figures_dir: Path | None):
        self.dir = Path(figures_dir) if figures_dir is not None else None
        if self.dir is not None:
            self.dir.mkdir(parents=True, exist_ok=True)
        self.count = 0

    def embed(self, fig, name: str, caption: str) -> str:
        buf = io.BytesIO()
        try:
            fig.savefig(buf, format="png", dpi=90)
        finally:
            plt.close(fig)
        data = buf.getvalue()
        self.count += 1
        if self.dir is not None:
            target = self.dir / f"{self.count:02d}_{name}.png"
            tmp = target.with_name(f".{target.name}.tmp")
            tmp.write_bytes(data)
            os.replace(tmp, target)
        b64 = base64.b64encode(data).decode("ascii")
        return (f'<figure><img src="data:image/png;base64,{b64}" alt="{_e(name)}">'
                f"<figcaption><b>Figure {self.count}.</b> {caption}</figcaption></figure>")


def _bands(ds: xr.Dataset) -> list[str]:
    return [str(b) for b in ds["band"].values] if "band" in ds.coords else []


def _z_guides(ax):
    for level, style in ((0, "-"), (1, ":"), (-1, ":"), (3, "--"), (-3, "--")):
        ax.axhline(level, color="grey", lw=0.8, ls=style, zorder=0)


# ---------------------------------------------------------------- dark section

def _dark_section(lens: str, ds: xr.Dataset, figs: _Figures) -> str:
    out = [f'<h3 id="dark-{_e(lens)}">Lens “{_e(lens)}”</h3>']
    bands = _bands(ds)
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

    # histograms (Fig. 9a-b analogue)
    if "dark_histogram" in ds:
        centres = ds["hist_bin_centre_dn"].values if "hist_bin_centre_dn" in ds else np.arange(ds.sizes["hist_bin"])
        fig, axes = plt.subplots(len(bands), 2, figsize=(11, 2.6 * len(bands)), squeeze=False)
        for i, b in enumerate(bands):
            for j, (idx, lab) in enumerate(((low, "exposure"), (at_t, "iso"))):
                ax = axes[i, j]
                cmap = plt.get_cmap("viridis", max(len(idx), 2))
                for k, s in enumerate(idx):
                    h = ds["dark_histogram"].sel(band=b).isel(setting=int(s)).values
                    txt = (f"{exp_s[s] * 1e3:.4g} ms" if lab == "exposure" else f"ISO {iso_s[s]:.0f}")
                    ax.step(centres, h, where="mid", color=cmap(k), lw=1, label=txt)
                nz = np.nonzero(ds["dark_histogram"].sel(band=b).isel(setting=list(map(int, idx))).sum("setting").values)[0]
                if len(nz):
                    ax.set_xlim(centres[max(nz[0] - 3, 0)], centres[min(nz[-1] + 3, len(centres) - 1)])
                ax.set_yscale("log")
                ax.set_xlabel("frame-averaged dark level [DN]")
                ax.set_ylabel("pixels")
                ttl = (f"{b} band, ISO {iso_min:.0f}, per exposure" if lab == "exposure"
                       else f"{b} band, {t_iso:.4g} s, per ISO")
                ax.set_title(ttl, fontsize=9)
                ax.legend(fontsize=6, ncol=2)
        fig.tight_layout()
        out.append(figs.embed(fig, f"dark_{lens}_histograms",
                              f"Lens {_e(lens)}: histograms of the frame-averaged dark image "
                              f"(left: each exposure time at the lowest ISO, {iso_min:.0f}; right: each ISO at "
                              f"{t_iso:.4g} s). Analogue of Larouche et al. (2024) Fig. 9a–b."))

    # centre and width vs exposure and ISO, with the fitted model
    try:
        from pipeline.radiometry.dark import dark_level_dn
    except ImportError:  # pragma: no cover
        dark_level_dn = None
    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5))
    for b in bands:
        c = BAND_COLOURS.get(b, None)
        cen = ds["dark_centre_dn"].sel(band=b).values
        wid = ds["dark_width_dn"].sel(band=b).values
        axes[0, 0].plot(exp_s[low], cen[low], "o", color=c, label=f"{b} measured")
        axes[1, 0].plot(exp_s[low], wid[low], "o-", color=c, label=b)
        axes[0, 1].plot(iso_s[at_t], cen[at_t], "o", color=c, label=f"{b} measured")
        axes[1, 1].plot(iso_s[at_t], wid[at_t], "o-", color=c, label=b)
        if dark_level_dn is not None:
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
        ax.set_xlabel(f"ISO (exposure {t_iso:.4g} s)")
    for ax in axes[0]:
        ax.set_ylabel("dark centre [DN]")
    for ax in axes[1]:
        ax.set_ylabel("dark width [DN]")
    for ax in axes.ravel():
        ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    out.append(figs.embed(fig, f"dark_{lens}_centre_width",
                          f"Lens {_e(lens)}: centre (top) and spatial width (bottom) of the frame-averaged "
                          "dark image against exposure time (left) and ISO (right); lines are the fitted "
                          "dark model b0 + b1·(ISO/100 − 1) + D·(ISO/100)·t. Analogue of Fig. 9c."))

    # fitted parameters
    rows = []
    for b in bands:
        rows.append([b, _q(ds, "bias_dn", band=b), _q(ds, "bias_per_gain_dn", band=b),
                     fmt_value(int(ds["hot_pixel_count"].sel(band=b))) if "hot_pixel_count" in ds else "n/a"])
    out.append("<p>Fitted dark model per band (uncertainties are standard errors):</p>")
    out.append(_table(["band", "bias b0 (ISO 100)", "bias per ISO/100 b1", "hot pixels"], rows))
    scal = [["dark current D (ISO 100)", _q(ds, "dark_current_dn_per_s")]]
    if "bias_drift_dn" in ds:
        scal.append(["frame-to-frame bias drift", _bias_drift_text(ds)])
    if "projection" in ds.attrs:
        scal.append(["lens projection (dataset.yaml)", str(ds.attrs["projection"])])
    if "bias_reference" in ds.attrs:
        scal.append(["each frame's black level from", str(ds.attrs["bias_reference"])])
    if "rms_z" in ds:
        scal.append(["rms of normalised residuals (1 = noise floor)", fmt_value(float(ds["rms_z"]), 3)])
    out.append(_table(["quantity", "value"], scal))
    if "read_noise_dn" in ds:
        isos = ds["iso"].values
        u = _var_units(ds, "read_noise_dn")
        rows = [[b] + [fmt_value(float(ds["read_noise_dn"].sel(band=b, iso=i)), 3) for i in isos] for b in bands]
        out.append(f"<p>Read noise (temporal noise of one raw pixel at the shortest exposure) per ISO, "
                   f"in {_e(u)}:</p>")
        out.append(_table(["band"] + [f"ISO {i:.0f}" for i in isos], rows))

    # FPN map and hot pixels
    if "fpn_map_dn" in ds:
        fig, axes = plt.subplots(1, len(bands), figsize=(3.6 * len(bands), 3.3), squeeze=False)
        for ax, b in zip(axes[0], bands):
            m = ds["fpn_map_dn"].sel(band=b).values
            lim = np.nanpercentile(np.abs(m), 99) or 1.0
            im = ax.imshow(m, cmap="RdBu_r", vmin=-lim, vmax=lim, origin="upper")
            if "hot_pixel_mask" in ds:
                yy, xx = np.nonzero(ds["hot_pixel_mask"].sel(band=b).values)
                ax.plot(xx, yy, "o", mfc="none", mec="k", ms=6, label=f"hot ({len(xx)})")
                ax.legend(fontsize=6, loc="lower right")
            ax.set_title(f"{b} band", fontsize=9)
            fig.colorbar(im, ax=ax, shrink=0.8, label=f"offset FPN [{_var_units(ds, 'fpn_map_dn')}]")
        fig.tight_layout()
        out.append(figs.embed(fig, f"dark_{lens}_fpn",
                              f"Lens {_e(lens)}: offset fixed-pattern map at the shortest exposure and lowest "
                              "ISO (mean removed); circles mark the flagged hot pixels."))

    # residuals
    tab = dataset_to_table(ds, "obs_setting")
    if len(tab) and "z" in tab:
        fig, ax = plt.subplots(figsize=(8, 3.8))
        isos = np.unique(tab["iso"])
        cmap = plt.get_cmap("plasma", max(len(isos) + 1, 2))
        markers = {"R": "^", "G": "o", "B": "s"}
        for k, i in enumerate(isos):
            for b in bands:
                sub = tab[(tab["iso"] == i) & (tab["band"] == b)]
                if len(sub):
                    ax.plot(sub["exposure_s"], sub["z"], markers.get(b, "o"), color=cmap(k), ms=5,
                            label=f"ISO {i:.0f}" if b == bands[0] else None)
        _z_guides(ax)
        ax.set_xscale("log")
        ax.set_xlabel("exposure time [s]")
        ax.set_ylabel("residual z (data − model)/σ")
        ax.legend(fontsize=6, ncol=3, title="▲R ●G ■B", title_fontsize=7)
        fig.tight_layout()
        out.append(figs.embed(fig, f"dark_{lens}_residuals",
                              f"Lens {_e(lens)}: setting-level residuals of the dark model, normalised by their "
                              "uncertainty, against exposure time. Dotted: ±1, dashed: ±3. A trend with "
                              "exposure time points to an unmodelled effect."))
    return "\n".join(out)


# ---------------------------------------------------------------- linearity section

def _mask(ds: xr.Dataset) -> np.ndarray:
    ny, nx = ds["pearson_r"].shape[-2:]
    yy, xx = np.mgrid[0:ny, 0:nx]
    cx, cy = float(ds["mask_centre_x_px"]), float(ds["mask_centre_y_px"])
    return np.hypot(xx - cx, yy - cy) <= float(ds["mask_radius_px"])


def _sweep_x(tab: pd.DataFrame, sweep: str) -> np.ndarray:
    return (tab["exposure_s"].to_numpy() * 1e3 if sweep == "exposure" else gain_from_iso(tab["iso"].to_numpy()))


SWEEP_XLABEL = {"exposure": "exposure time [ms]", "gain": "ISO/100"}


def _linearity_section(lens: str, ds: xr.Dataset, figs: _Figures) -> str:
    out = [f'<h3 id="lin-{_e(lens)}">Lens “{_e(lens)}”</h3>']
    bands = _bands(ds)
    sweeps = [str(s) for s in ds["sweep"].values] if "sweep" in ds.coords else []
    tab = dataset_to_table(ds, "obs_setting")
    if "used" in tab:
        tab["used"] = tab["used"].astype(bool)

    # Pearson r inside the mask (Fig. 2)
    if "pearson_r" in ds and all(k in ds for k in ("mask_centre_x_px", "mask_centre_y_px", "mask_radius_px")):
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
            ax.set_xlabel("Pearson r per pixel")
            ax.set_ylabel("pixels")
            ax.set_title(f"{sw} sweep", fontsize=9)
            ax.legend(fontsize=7)
        fig.tight_layout()
        out.append(figs.embed(fig, f"lin_{lens}_pearson",
                              f"Lens {_e(lens)}: per-pixel Pearson correlation of single frames with exposure time "
                              f"or gain, for the {int(m.sum())} pixels within {fmt_value(float(ds['mask_radius_px']), 3)} px "
                              "of the mask centre. Analogue of Larouche et al. (2024) Fig. 2."))

    # mean DN vs exposure and vs ISO with regression lines (Fig. 3)
    if len(tab) and "value_dn" in tab:
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
        out.append(figs.embed(fig, f"lin_{lens}_lines",
                              f"Lens {_e(lens)}: mean dark-corrected signal in the mask against exposure time and "
                              "against ISO/100, with the least-squares lines (slope, intercept with 95 % "
                              "half-intervals, and Pearson r in the legend). Hollow markers were not used "
                              "(e.g. saturated). Analogue of Larouche et al. (2024) Fig. 3."))

        # nonlinearity residuals
        if "nonlinearity_pct" in tab:
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
            out.append(figs.embed(fig, f"lin_{lens}_nonlinearity",
                                  f"Lens {_e(lens)}: nonlinearity residuals, the relative departure of the "
                                  "mean signal from the regression line, in percent."))

        # photon transfer curve
        if "pixel_var_dn2" in tab and "conversion_gain_dn_per_e" in ds:
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
                        label=f"K = {_q(ds, 'conversion_gain_dn_per_e')}\nread noise = {_q(ds, 'read_noise_e')}")
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
                ax.set_xlabel("ISO")
                ax.set_ylabel("conversion gain [DN/electron]")
                ax.set_title("conversion gain per ISO (gain sweep)", fontsize=9)
            fig.tight_layout()
            out.append(figs.embed(fig, f"lin_{lens}_ptc",
                                  f"Lens {_e(lens)}: photon-transfer curve (G-band variance doubled to one photosite) "
                                  "with the fitted line var = K·signal + (K·read noise)²."))

        # residual z vs signal
        if "z" in tab:
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
            _z_guides(ax)
            ax.set_xscale("log")
            ax.set_xlabel("mean signal [DN]")
            ax.set_ylabel("residual z (data − model)/σ")
            ax.legend(fontsize=6, ncol=2)
            fig.tight_layout()
            out.append(figs.embed(fig, f"lin_{lens}_residuals",
                                  f"Lens {_e(lens)}: setting-level residuals of the linearity model against signal "
                                  "level (circles: exposure sweep, squares: gain sweep; hollow: not used). "
                                  "Structure at low signal, e.g. a rising z at short exposures, suggests a "
                                  "shutter offset."))

    # scalar results
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
            rows.append([label, (_bias_drift_text(ds) if name == "bias_drift_dn" else _q(ds, name)) + extra])
    if "projection" in ds.attrs:
        rows.append(["lens projection; mask field angles from",
                     f"{ds.attrs['projection']}; {ds.attrs.get('field_angles_from', 'n/a')}"])
    if "rms_z" in ds:
        rows.append(["rms of normalised residuals (1 = noise floor)", fmt_value(float(ds["rms_z"]), 3)])
    out.append("<p>Fitted linearity and noise parameters:</p>")
    out.append(_table(["quantity", "value"], rows))

    if "rate_dn_per_s" in ds:
        rows = []
        for sw in sweeps:
            for b in bands:
                rows.append([sw, b, _q(ds, "rate_dn_per_s", sweep=sw, band=b),
                             fmt_uncertain(float(ds["line_slope"].sel(sweep=sw, band=b)),
                                           float(ds["line_slope_ci95"].sel(sweep=sw, band=b))),
                             fmt_uncertain(float(ds["line_intercept_dn"].sel(sweep=sw, band=b)),
                                           float(ds["line_intercept_ci95_dn"].sel(sweep=sw, band=b))),
                             f"{float(ds['line_r'].sel(sweep=sw, band=b)):.6f}"])
        out.append("<p>Model rate (± standard error) and the regression of the mask means "
                   "(± 95 % half-interval; slope in DN/ms for the exposure sweep, DN per ISO/100 for the gain sweep):</p>")
        out.append(_table(["sweep", "band", "rate at ISO 100", "line slope", "line intercept [DN]", "line r"], rows,
                          left=2))

    effects = [v for v in ds.data_vars if v.startswith("effect_") and not v.endswith("_sigma")]
    if effects:
        rows = []
        for v in effects:
            da = ds[v]
            sig_da = ds[f"{v}_sigma"] if f"{v}_sigma" in ds and ds[f"{v}_sigma"].shape == da.shape else None
            name = v.removeprefix("effect_")
            for idx in np.ndindex(da.shape):
                label = ""
                if da.size > 1:
                    parts = []
                    for d, i in zip(da.dims, idx):
                        parts.append(f"{d}={da[d].values[i]}" if d in da.coords else f"{d}[{i}]")
                    label = f" ({', '.join(parts)})"
                val = float(da.values[idx]) if da.ndim else float(da.values)
                sig = (float(sig_da.values[idx]) if da.ndim else float(sig_da.values)) if sig_da is not None else None
                rows.append([name + label, da.attrs.get("long_name", ""),
                             f"{fmt_uncertain(val, sig)} {_var_units(ds, v)}".strip()])
        out.append("<p>Fitted effect parameters (± standard error):</p>")
        out.append(_table(["effect", "description", "value"], rows, left=2))
    else:
        out.append('<p class="note">No effect parameters are fitted in the linearity model of this run.</p>')
    return "\n".join(out)


# ---------------------------------------------------------------- later stages (geometry … immersion)

_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def _u(ds: xr.Dataset, name: str) -> str:
    """Units of an artefact variable with exponents as superscripts ("W sr-1 m-2" -> "W sr⁻¹ m⁻²")."""
    if name not in ds:
        return ""
    units = str(ds[name].attrs.get("units", "") or "")
    if units in ("", "1"):
        return ""
    units = re.sub(r"\^?\(?(-?\d+)\)?(?=$|\s)", lambda m: m.group(1).translate(_SUPERSCRIPT), units)
    return units.replace("degree", "°").replace("degC", "°C")


def _sel(da: xr.DataArray, sel: dict) -> xr.DataArray:
    return da.sel(**{k: v for k, v in sel.items() if k in da.dims})


def _num(ds: xr.Dataset, name: str, sigma: str | None = None, digits: int = 4, units: bool = True, **sel) -> str:
    """``name`` (selected by ``sel``) ± ``sigma`` (default ``name_sigma``) with units; "n/a" when absent."""
    if name not in ds:
        return "n/a"
    da = _sel(ds[name], sel)
    if da.size != 1:
        return "n/a"
    sig_name = sigma or f"{name}_sigma"
    sig = None
    if sig_name in ds:
        sd = _sel(ds[sig_name], sel)
        sig = float(sd) if sd.size == 1 else None
    v = da.values.item()
    text = fmt_uncertain(v, sig) if sig is not None else fmt_value(v, digits)
    return f"{text} {_u(ds, name)}".strip() if units else text


def _pct(x) -> str:
    return f"{100 * float(x):.2f} %" if _finite(x) else "n/a"


def _media(ds: xr.Dataset) -> list[str]:
    return [str(m) for m in ds["medium"].values] if "medium" in ds.coords else []


def _not_run(stage: str, title: str, skipped: dict[str, str]) -> str:
    reason = skipped.get(stage)
    why = (f": {_e(reason)}" if reason else "; no artefacts were given")
    return (f'<p class="note">The {_e(title)} stage was not run{why} '
            f'(see <a href="#skipped">Stages not run</a>).</p>')


def _effects_table(ds: xr.Dataset) -> str:
    """Fitted effect parameters stored as ``effect_<name>`` (+ ``_sigma``), if any."""
    names = [v for v in ds.data_vars if v.startswith("effect_") and not v.endswith("_sigma")]
    rows = []
    for v in names:
        da = ds[v]
        sd = ds[f"{v}_sigma"] if f"{v}_sigma" in ds and ds[f"{v}_sigma"].shape == da.shape else None
        for idx in np.ndindex(da.shape):
            label = v.removeprefix("effect_") + (f"[{', '.join(map(str, idx))}]" if da.size > 1 else "")
            val = float(da.values[idx]) if da.ndim else float(da.values)
            sig = (float(sd.values[idx]) if da.ndim else float(sd.values)) if sd is not None else None
            rows.append([label, da.attrs.get("long_name", ""), f"{fmt_uncertain(val, sig)} {_u(ds, v)}".strip()])
    if not rows:
        return '<p class="note">No effect parameters are fitted in this stage for this run.</p>'
    return "<p>Fitted effect parameters (± standard error):</p>" + _table(["effect", "description", "value"], rows,
                                                                          left=2)


def _geometry_section(lens: str, ds: xr.Dataset, figs: _Figures) -> str:
    out = [f'<h3 id="geometry-{_e(lens)}">Lens “{_e(lens)}”</h3>']
    media, bands = _media(ds), _bands(ds)
    has_curves = "projection_theta_deg" in ds and "rho_px" in ds.coords
    if media and "theta_deg" in ds:
        fig, axes = plt.subplots(2, len(media), figsize=(5.5 * len(media), 7), squeeze=False)
        for k, m in enumerate(media):
            ax, axd = axes[0, k], axes[1, k]
            if has_curves:
                rho = ds["rho_px"].values
                ax.plot(rho, ds["projection_theta_deg"].sel(medium=m, band="G").values, "-", color="tab:green",
                        lw=2, label="fitted (G)")
                for ref, ls in (("equidistant", "--"), ("stereographic", "-."), ("orthographic", ":")):
                    v = f"reference_{ref}_theta_deg"
                    if v in ds:
                        ax.plot(rho, ds[v].sel(medium=m, band="G").values, ls, color="grey", lw=1, label=ref)
                if "theta_difference_vs_green_deg" in ds:
                    for b in bands:
                        if b != "G":
                            axd.plot(rho, ds["theta_difference_vs_green_deg"].sel(medium=m, band=b).values, "-",
                                     color=BAND_COLOURS.get(b), label=f"{b} − G")
            else:
                # no stored curves (maps-only artefact): theta of the map pixels against their radius
                th = ds["theta_deg"].sel(medium=m)
                ny, nx = th.shape[-2:]
                yy, xx = np.mgrid[0:ny, 0:nx]
                xc, yc = float(ds["xc_px"].sel(medium=m, band="G")), float(ds["yc_px"].sel(medium=m, band="G"))
                rho_map = np.hypot(xx - xc, yy - yc)
                tg = th.sel(band="G").values.astype(float)
                hf_g = float(ds["half_fov_deg"].sel(medium=m, band="G")) if "half_fov_deg" in ds else np.inf
                ok = np.isfinite(tg) & (tg <= (hf_g if np.isfinite(hf_g) else np.inf))
                step = max(1, int(ok.sum() // 4000))
                ax.plot(rho_map[ok][::step], tg[ok][::step], ".", color="tab:green", ms=2, label="theta map (G)")
                if "poly" in ds:
                    a0 = float(ds["poly"].sel(medium=m, band="G").values[0])
                    r = np.linspace(0, float(rho_map[ok].max()) if ok.any() else 1.0, 200)
                    with np.errstate(invalid="ignore"):
                        ax.plot(r, np.degrees(r / a0), "--", color="grey", lw=1, label="equidistant")
                        ax.plot(r, np.degrees(2 * np.arctan(r / (2 * a0))), "-.", color="grey", lw=1,
                                label="stereographic")
                        ax.plot(r, np.degrees(np.arcsin(np.where(r <= a0, r / a0, np.nan))), ":", color="grey",
                                lw=1, label="orthographic")
                for b in bands:
                    if b != "G":
                        d = th.sel(band=b).values.astype(float) - tg
                        okb = np.isfinite(d) & ok
                        axd.plot(rho_map[okb][::step], d[okb][::step], ".", ms=2, color=BAND_COLOURS.get(b),
                                 label=f"{b} − G (maps)")
            hf = float(ds["half_fov_deg"].sel(medium=m, band="G")) if "half_fov_deg" in ds else float("nan")
            if _finite(hf):
                ax.axhline(hf, color="k", lw=0.6, ls=":")
                ax.text(0.02, 0.95, f"half FOV (G) {hf:.2f}°", transform=ax.transAxes, fontsize=7, va="top")
            ax.set_xlabel("ρ, distance from the principal point [band px]")
            ax.set_ylabel("θ [°]")
            ax.set_title(f"{m}: projection function", fontsize=9)
            ax.legend(fontsize=7, loc="lower right")
            axd.axhline(0, color="grey", lw=0.8)
            axd.set_xlabel("ρ [band px]")
            axd.set_ylabel("θ(band) − θ(G) [°]")
            axd.set_title(f"{m}: band differences against G", fontsize=9)
            if axd.get_legend_handles_labels()[0]:
                axd.legend(fontsize=7)
        fig.tight_layout()
        src = ("fitted curves stored in the artefact" if has_curves else
               "the artefact has no stored projection curves, so the θ map is plotted against pixel radius")
        out.append(figs.embed(fig, f"geometry_{lens}_projection",
                              f"Lens {_e(lens)}: projection function θ(ρ) of the G band with the equidistant, "
                              "stereographic and orthographic references of the same focal length a0 (top), and "
                              f"the R and B mapping minus G (bottom), per medium ({_e(src)}). "
                              "Analogue of Larouche et al. (2024) Fig. 4."))
    if "error_vs_radius_px" in ds and "error_vs_radius_rho_px" in ds and media:
        fig, axes = plt.subplots(1, len(media), figsize=(5.5 * len(media), 3.4), squeeze=False)
        for ax, m in zip(axes[0], media):
            for b in bands:
                ax.plot(ds["error_vs_radius_rho_px"].sel(medium=m, band=b).values,
                        ds["error_vs_radius_px"].sel(medium=m, band=b).values, "o-", ms=3,
                        color=BAND_COLOURS.get(b), label=b)
            ax.set_xlabel("ρ [band px]")
            ax.set_ylabel(f"mean reprojection error [{_u(ds, 'error_vs_radius_px') or 'px'}]")
            ax.set_title(m, fontsize=9)
            ax.legend(fontsize=7)
        fig.tight_layout()
        out.append(figs.embed(fig, f"geometry_{lens}_error_radius",
                              f"Lens {_e(lens)}: mean reprojection error of the used corners in radial bins. "
                              "Analogue of Fig. S1."))
    elif media:
        out.append('<p class="note">The artefact holds no reprojection errors (maps only).</p>')
    # per medium and band table
    cols = [("principal point x", "xc_px"), ("principal point y", "yc_px"), ("half FOV", "half_fov_deg"),
            ("pixel angle on axis", "deg_per_px_axis"), ("mean reproj. error", "mean_error_px"),
            ("rms reproj. error", "rms_error_px"), ("image circle radius", "circle_radius_px"),
            ("max |θ − θ_G|", "theta_map_max_difference_vs_green_deg")]
    cols = [(t, v) for t, v in cols if v in ds]
    sigma_theta = "theta_deg_sigma_at_field_angle" in ds    # the fit's theta uncertainty, azimuthal RMS
    rows = []
    for m in media:
        for b in bands:
            r = [m, b] + [_num(ds, v, digits=4, medium=m, band=b) for _, v in cols]
            if "n_frames_used" in ds and "n_frames" in ds:
                r.append(f"{fmt_value(float(ds['n_frames_used'].sel(medium=m, band=b)))} / "
                         f"{fmt_value(float(ds['n_frames'].sel(medium=m, band=b)))}")
            if sigma_theta:
                values = ds["theta_deg_sigma_at_field_angle"].sel(medium=m, band=b).values
                r.append(", ".join("–" if not np.isfinite(x) else f"{x:.3f}" for x in values))
            rows.append(r)
    if rows:
        hdr = ["medium", "band"] + [t for t, _ in cols] + (["frames used"] if "n_frames_used" in ds and "n_frames" in ds else [])
        if sigma_theta:
            at = ", ".join(f"{x:g}" for x in ds["theta_summary_deg"].values)
            hdr.append(f"σ(θ) [°] at θ = {at}°")
        out.append("<p>Fitted camera model per medium and band:</p>")
        out.append(_table(hdr, rows, left=2))
    if "obs_frame__reason" in ds:
        fr = dataset_to_table(ds, "obs_frame")
        bad = fr[fr["reason"].astype(str).str.len() > 0] if len(fr) else fr
        if len(bad):
            rows = [[r.get("file", ""), r.get("medium", ""), r.get("band", ""), r["reason"]] for _, r in bad.iterrows()]
            out.append(f"<details><summary>{len(bad)} dropped frame/band combinations</summary>"
                       + _table(["file", "medium", "band", "reason"], rows, left=4) + "</details>")
    return "\n".join(out)


def _rolloff_section(lens: str, ds: xr.Dataset, figs: _Figures) -> str:
    from pipeline.radiometry.rolloff import evaluate_rolloff

    out = [f'<h3 id="rolloff-{_e(lens)}">Lens “{_e(lens)}”</h3>']
    media, bands = _media(ds), _bands(ds)
    tab = dataset_to_table(ds, "obs_setting") if "obs_setting" in ds.dims else pd.DataFrame()
    if len(tab) and "kind" in tab:
        tab = tab[tab["kind"] == "spot"]
    az_markers = ["o", "s", "^", "D", "v"]
    if media and "rolloff_coefficients" in ds:
        fig, axes = plt.subplots(1, len(media), figsize=(5.5 * len(media), 4), squeeze=False)
        for ax, m in zip(axes[0], media):
            sub_m = tab[tab["medium"] == m] if len(tab) else tab
            azs = sorted(set(sub_m["azimuth_deg"])) if len(sub_m) else []
            t_max = float(sub_m["theta_deg"].max()) if len(sub_m) else 80.0
            tt = np.linspace(0, t_max, 200)
            for b in bands:
                c = BAND_COLOURS.get(b)
                coef = ds["rolloff_coefficients"].sel(medium=m, band=b).values
                if not np.all(np.isfinite(coef)):
                    continue
                if "rolloff_covariance" in ds:
                    g, sg = evaluate_rolloff(coef, tt, ds["rolloff_covariance"].sel(medium=m, band=b).values)
                    ax.fill_between(tt, g - sg, g + sg, color=c, alpha=0.2, lw=0)
                else:
                    g = evaluate_rolloff(coef, tt)
                chi = (f", χ²ν = {fmt_value(float(ds['rolloff_reduced_chi2'].sel(medium=m, band=b)), 3)}"
                       if "rolloff_reduced_chi2" in ds else "")
                ax.plot(tt, g, "-", color=c, lw=1.3, label=f"{b} fit{chi}")
                for k, az in enumerate(azs):
                    s = sub_m[(sub_m["band"] == b) & (sub_m["azimuth_deg"] == az)]
                    if "used" in s:
                        s = s[s["used"].astype(bool)]
                    y = s["value_dn"] - (s["effect_dn"] if "effect_dn" in s else 0.0)
                    ax.errorbar(s["theta_deg"], y, yerr=s["sigma_dn"] if "sigma_dn" in s else None,
                                fmt=az_markers[k % len(az_markers)], ms=3.5, color=c, mfc="none", lw=0.8,
                                label=f"azimuth plane φ = {az:g}°" if b == bands[0] else None)
            ax.set_xlabel("θ, angle from the optical axis [°]")
            ax.set_ylabel("relative illumination g(θ)")
            ax.set_title(f"{m}", fontsize=9)
            ax.legend(fontsize=6, ncol=2)
        fig.tight_layout()
        out.append(figs.embed(fig, f"rolloff_{lens}",
                              f"Lens {_e(lens)}: roll-off per band and medium: normalised spot means (open markers, "
                              "one marker shape per azimuth plane; fitted effect contributions removed) and the "
                              "even 8th-degree polynomial of Eq. (13) with its ±1σ band. Analogue of "
                              "Larouche et al. (2024) Fig. 5."))
        # table: coefficients and g at the largest measured angle
        rows = []
        cov = ds["rolloff_covariance"] if "rolloff_covariance" in ds else None
        powers = [int(p) for p in ds["power"].values] if "power" in ds.coords else list(range(0, 10, 2))
        for m in media:
            sub_m = tab[tab["medium"] == m] if len(tab) else tab
            t_max = float(sub_m["theta_deg"].max()) if len(sub_m) else float("nan")
            for b in bands:
                coef = ds["rolloff_coefficients"].sel(medium=m, band=b).values
                cv = cov.sel(medium=m, band=b).values if cov is not None else None
                se = np.sqrt(np.clip(np.diag(cv), 0, None)) if cv is not None else [None] * len(coef)
                cells = [fmt_uncertain(c_, s_) if s_ else fmt_value(c_) for c_, s_ in zip(coef, se)]
                if _finite(t_max) and np.all(np.isfinite(coef)):
                    if cv is not None:
                        g, sg = evaluate_rolloff(coef, t_max, cv)
                        gtxt = fmt_uncertain(float(g), float(sg))
                    else:
                        gtxt = fmt_value(float(evaluate_rolloff(coef, t_max)))
                else:
                    gtxt = "n/a"
                rows.append([m, b] + cells + [f"{gtxt} (θ = {fmt_value(t_max, 3)}°)",
                                              _num(ds, "rolloff_reduced_chi2", digits=3, medium=m, band=b)])
        unit = _u(ds, "rolloff_coefficients")
        out.append(f"<p>Roll-off polynomial g(θ) = Σ a_k θ^k (θ in degrees; a_k in {_e(unit or '°⁻ᵏ')}; "
                   "± standard error) and g at the largest measured angle:</p>")
        out.append(_table(["medium", "band"] + [f"a{p}" for p in powers] + ["g(θ_max)", "reduced χ²"], rows, left=2))
    scal = []
    if "water_closure_scale" in ds:
        scal += [[f"in-water closure scale c ({b}), g_water(θ_w) = c g_air(θ_a) F(θ_a, θ_w)",
                  fmt_uncertain(float(ds["water_closure_scale"].sel(band=b)),
                                float(ds["water_closure_scale_sigma"].sel(band=b)))]
                 for b in bands]
    if "rms_z" in ds:
        scal.append(["rms of normalised residuals (1 = noise floor)", fmt_value(float(ds["rms_z"]), 3)])
    if scal:
        out.append(_table(["quantity", "value"], scal))
    out.append(_effects_table(ds))
    return "\n".join(out)


def _spectral_section(lens: str, ds: xr.Dataset, figs: _Figures) -> str:
    out = [f'<h3 id="spectral-{_e(lens)}">Lens “{_e(lens)}”</h3>']
    bands = _bands(ds)
    if "response" in ds and "wavelength_nm" in ds.coords:
        wl = ds["wavelength_nm"].values.astype(float)
        fig, ax = plt.subplots(figsize=(8, 4))
        for ib, b in enumerate(bands):
            c = BAND_COLOURS.get(b)
            ybar = 1.04 + 0.05 * ib
            s = ds["response"].sel(band=b).values
            ax.plot(wl, s, "o-", ms=3, color=c, label=b)
            if "response_sigma" in ds:
                sg = ds["response_sigma"].sel(band=b).values
                ax.fill_between(wl, s - sg, s + sg, color=c, alpha=0.25, lw=0)
            if "effective_wavelength_nm" in ds:
                le = float(ds["effective_wavelength_nm"].sel(band=b))
                ax.axvline(le, color=c, ls="--", lw=0.8)
                hb = float(ds["half_bandwidth_nm"].sel(band=b)) if "half_bandwidth_nm" in ds else float("nan")
                if _finite(hb):
                    ax.errorbar([le], [ybar], xerr=[hb], fmt="|", color=c, capsize=3)
                ax.text(le, ybar + 0.01, f"{le:.1f} nm", color=c, ha="center", va="bottom", fontsize=7)
        ax.set_ylim(-0.05, 1.05 + 0.05 * len(bands) + 0.05)
        ax.set_xlabel("wavelength [nm]")
        ax.set_ylabel("peak-normalised response S_R")
        ax.legend(fontsize=8)
        fig.tight_layout()
        out.append(figs.embed(fig, f"spectral_{lens}",
                              f"Lens {_e(lens)}: relative spectral response per band (shaded: ±1σ); dashed lines "
                              "mark the effective wavelength (Eq. 8) and the bars its ± half bandwidth. "
                              "Analogue of Larouche et al. (2024) Fig. 6."))
    rows = []
    for b in bands:
        rows.append([b, _num(ds, "effective_wavelength_nm", band=b), _num(ds, "half_bandwidth_nm", band=b),
                     _num(ds, "bandwidth_nm", band=b), _num(ds, "peak_wavelength_nm", band=b),
                     _num(ds, "mask_n_pixels", band=b), _num(ds, "dark_level_dn", band=b)])
    out.append("<p>Band statistics (± standard uncertainty propagated from the response covariance):</p>")
    out.append(_table(["band", "effective wavelength λ_eff", "half bandwidth Λ/2", "bandwidth ∫S dλ",
                       "peak wavelength", "mask pixels", "dark level"], rows))
    if "rms_z" in ds:
        out.append(f"<p>rms of normalised frame residuals (1 = noise floor): {fmt_value(float(ds['rms_z']), 3)}</p>")
    return "\n".join(out)


def snr_against_radiance(radiance, ner: float, lod: float, lod_snr: float):
    """Signal-to-noise ratio at each radiance, from the noise-equivalent radiance and the limit of detection.

    The measurement chain's random noise is sigma^2 = a + b L (read and dark noise, shot noise) in
    radiance units; NER is where L = sigma (SNR 1), the limit of detection where L = k sigma. The
    two conditions give b = (LoD^2 / k^2 - NER^2) / (LoD - NER), a = NER^2 - b NER, and
    SNR(L) = L / sqrt(a + b L) (Section 3.8).
    """
    b = (lod**2 / lod_snr**2 - ner**2) / (lod - ner)
    a = ner**2 - b * ner
    radiance = np.asarray(radiance, dtype=float)
    return radiance / np.sqrt(a + b * radiance)


def _noise_floor_section(bundle: xr.Dataset | None, figs: _Figures) -> str:
    """NER and limit of detection per lens and band from the calibration bundle, and SNR against radiance."""
    if bundle is None or "noise_equivalent_radiance" not in bundle:
        return ""
    ner, lod = bundle["noise_equivalent_radiance"], bundle["limit_of_detection"]
    k = float(lod.attrs.get("snr", 3.0))
    at = f"ISO {lod.attrs.get('iso', 100):g}, {lod.attrs.get('exposure_s', 1):g} s"
    rows = [[str(lens), str(band), f"{float(ner.sel(lens=lens, band=band)):.3g}",
             f"{float(lod.sel(lens=lens, band=band)):.3g}"]
            for lens in bundle["lens"].values for band in bundle["band"].values]
    out = [f'<h3 id="noise-floor">Noise-equivalent radiance and limit of detection ({_e(at)})</h3>',
           "<p>From the calibration bundle: the radiance on the optical axis whose signal equals its random "
           f"noise (NER, SNR 1) and the limit of detection (SNR {k:g}), through the measurement chain with "
           "the dark stage's read noise, the photon-transfer gain and R⁻¹ (Section 3.8; the paper reports "
           "NER 1.1e-7, 4.5e-8, 1.1e-7 and limits 4.6e-7, 1.8e-7, 4.6e-7 W sr⁻¹ m⁻² nm⁻¹ for R, G, B).</p>",
           _table(["lens", "band", "NER [W sr⁻¹ m⁻² nm⁻¹]", f"limit of detection, SNR {k:g} [W sr⁻¹ m⁻² nm⁻¹]"],
                  rows, left=2)]
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    radiance = np.logspace(-9, -1, 200)
    for lens, style in zip(bundle["lens"].values, ("-", "--", ":")):
        for band in bundle["band"].values:
            n, d = float(ner.sel(lens=lens, band=band)), float(lod.sel(lens=lens, band=band))
            if np.isfinite(n) and np.isfinite(d) and d > n > 0:
                ax.loglog(radiance, snr_against_radiance(radiance, n, d, k), style, color=BAND_COLOURS.get(str(band)),
                          label=f"{lens} {band}")
    ax.axhline(k, color="0.4", lw=0.8)
    ax.set_xlabel("spectral radiance [W sr⁻¹ m⁻² nm⁻¹]")
    ax.set_ylabel(f"signal-to-noise ratio ({at})")
    ax.legend(fontsize=8, ncol=2)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    out.append(figs.embed(fig, "snr_against_radiance",
                          f"Signal-to-noise ratio of one pixel on the optical axis against spectral radiance ({at}); "
                          f"the grey line is SNR {k:g}, the limit of detection."))
    return "\n".join(out)


def _absolute_section(lens: str, ds: xr.Dataset, figs: _Figures, spectral: xr.Dataset | None) -> str:
    out = [f'<h3 id="absolute-{_e(lens)}">Lens “{_e(lens)}”</h3>']
    bands = _bands(ds)
    if "source_radiance" in ds and "source_wavelength_nm" in ds.coords:
        fig, ax = plt.subplots(figsize=(8, 4))
        ax.plot(ds["source_wavelength_nm"].values, ds["source_radiance"].values, "-", color="k", lw=1,
                label="source spectrum (scaled)")
        have_wl = spectral is not None and "effective_wavelength_nm" in spectral
        for b in bands:
            if not have_wl or "effective_radiance" not in ds:
                continue
            le = float(spectral["effective_wavelength_nm"].sel(band=b))
            hb = float(spectral["half_bandwidth_nm"].sel(band=b)) if "half_bandwidth_nm" in spectral else None
            sig = float(ds["effective_radiance_sigma"].sel(band=b)) if "effective_radiance_sigma" in ds else None
            ax.errorbar([le], [float(ds["effective_radiance"].sel(band=b))], xerr=[hb] if hb else None,
                        yerr=[sig] if sig else None, fmt="o", color=BAND_COLOURS.get(b), capsize=3,
                        label=f"L̄ {b} (Eq. 3)")
        if "reference_radiance" in ds and "reference_wavelength_nm" in ds:
            ref = float(ds["reference_radiance"])
            rel = float(ds["reference_relative_sigma"]) if "reference_relative_sigma" in ds else 0.0
            ax.errorbar([float(ds["reference_wavelength_nm"])], [ref], yerr=[ref * rel], fmt="^", color="purple",
                        capsize=3, ms=7, label="reference reading")
        ax.set_xlabel("wavelength [nm]")
        ax.set_ylabel(f"radiance [{_u(ds, 'source_radiance')}]")
        ax.legend(fontsize=7)
        fig.tight_layout()
        where = ("plotted at each band's effective wavelength with ± half bandwidth bars (spectral artefact)"
                 if have_wl else "not plotted: no spectral artefact gives the effective wavelengths")
        out.append(figs.embed(fig, f"absolute_{lens}_source",
                              f"Lens {_e(lens)}: calibration-source spectral radiance scaled to the reference "
                              f"reading (triangle); effective band radiances {_e(where)}. "
                              "Analogue of Larouche et al. (2024) Fig. 7."))
    rows = []
    for b in bands:
        dom = str(ds["dominant_term"].sel(band=b).values) if "dominant_term" in ds else "n/a"
        rows.append([b, _num(ds, "effective_radiance", band=b), _num(ds, "dn_per_s", band=b),
                     _num(ds, "inverse_responsivity", band=b),
                     _pct(ds["relative_sigma"].sel(band=b)) if "relative_sigma" in ds else "n/a", dom])
    out.append("<p>Absolute calibration (Eq. 9; ± standard uncertainty). Analogue of Table 1:</p>")
    out.append(_table(["band", "effective band radiance L̄", "y_DN (DN/s at ISO 100)", "R⁻¹",
                       "relative uncertainty of R⁻¹", "dominant term"], rows))
    if "uncertainty_contribution" in ds and "term" in ds.coords:
        terms = [str(t) for t in ds["term"].values]
        rows = [[b] + [_pct(ds["uncertainty_contribution"].sel(band=b, term=t)) for t in terms]
                + [_pct(ds["relative_sigma"].sel(band=b)) if "relative_sigma" in ds else "n/a"] for b in bands]
        out.append("<p>Uncertainty budget of R⁻¹ (relative standard uncertainty of each term):</p>")
        out.append(_table(["band"] + [t.replace("_", " ") for t in terms] + ["total"], rows))
    scal = []
    for label, v in (("reference reading", "reference_radiance"), ("reference wavelength", "reference_wavelength_nm"),
                     ("mask half-angle", "mask_half_angle_deg")):
        if v in ds:
            scal.append([label, _num(ds, v)])
    if "reference_relative_sigma" in ds:
        scal.append(["reference relative uncertainty", _pct(ds["reference_relative_sigma"])])
    if "rms_z" in ds:
        scal.append(["rms of normalised frame residuals (1 = noise floor)", fmt_value(float(ds["rms_z"]), 3)])
    if scal:
        out.append(_table(["quantity", "value"], scal))
    return "\n".join(out)


def _immersion_section(lens: str, ds: xr.Dataset, figs: _Figures) -> str:
    out = [f'<h3 id="immersion-{_e(lens)}">Lens “{_e(lens)}”</h3>']
    bands = _bands(ds)
    tab = dataset_to_table(ds, "obs_height") if "obs_height" in ds.dims else pd.DataFrame()
    if len(tab) and bands:
        fig, axes = plt.subplots(1, len(bands), figsize=(4.2 * len(bands), 3.8), squeeze=False)
        for ax, b in zip(axes[0], bands):
            c = BAND_COLOURS.get(b)
            s = tab[tab["band"] == b].sort_values("water_height_cm")
            # corrected for the n-squared law as in Fig. 8: ln y - ln(t_aw n_w^2)
            ln_n2 = math.log(float(ds["n2_factor"].sel(band=b))) if "n2_factor" in ds else 0.0
            corr = " − ln(t_aw n_w²)" if "n2_factor" in ds else ""
            ax.errorbar(s["water_height_cm"], s["value_dn"] - ln_n2, yerr=s["sigma_dn"] if "sigma_dn" in s else None,
                        fmt="o", color=c, ms=4, label=f"ln y_DN(z){corr}, mean per height")
            z = np.linspace(0.0, float(s["water_height_cm"].max()) if len(s) else 1.0, 50)
            if "dn_below" in ds and "attenuation_per_cm" in ds:
                b0 = math.log(float(ds["dn_below"].sel(band=b))) - ln_n2
                k = float(ds["attenuation_per_cm"].sel(band=b))
                r2 = f", R² = {float(ds['r_squared'].sel(band=b)):.3f}" if "r_squared" in ds else ""
                ax.plot(z, b0 - k * z, "-", color=c, lw=1,
                        label=f"fit, K = {fmt_value(k, 3)} {_u(ds, 'attenuation_per_cm')}{r2}")
                rel = (float(ds["dn_below_sigma"].sel(band=b)) / float(ds["dn_below"].sel(band=b))
                       if "dn_below_sigma" in ds else None)
                ax.errorbar([0.0], [b0], yerr=[rel] if rel else None, fmt="v", color="k", ms=7, capsize=3,
                            label=f"intercept ln y_DN(0−){corr}")
            if "dn_air" in ds:
                rel = (float(ds["dn_air_sigma"].sel(band=b)) / float(ds["dn_air"].sel(band=b))
                       if "dn_air_sigma" in ds else None)
                ax.errorbar([0.0], [math.log(float(ds["dn_air"].sel(band=b)))], yerr=[rel] if rel else None,
                            fmt="*", color="orange", ms=10, capsize=3, label="ln y_DN(0+) in air")
            if "immersion_factor" in ds:
                ax.text(0.35, 0.5, f"I = {_num(ds, 'immersion_factor', band=b)}", transform=ax.transAxes, fontsize=8)
            ax.set_xlabel("water height z [cm]")
            ax.set_ylabel("ln y_DN [ln(DN s⁻¹)]")
            ax.set_title(f"{b} band", fontsize=9)
            ax.legend(fontsize=6)
        fig.tight_layout()
        out.append(figs.embed(fig, f"immersion_{lens}",
                              f"Lens {_e(lens)}: natural logarithm of the in-water signal against water height with "
                              "the log-linear fit extrapolated to just below the surface (0−, triangle), both corrected for "
                              "the n-squared law t_aw n_w²; the star is the in-air signal y(0+): the gap between "
                              "star and triangle is ln I (Eq. 11). "
                              "Analogue of Larouche et al. (2024) Fig. 8."))
    rows = []
    for b in bands:
        ci = ""
        if "immersion_factor_ci95_low" in ds and "immersion_factor_ci95_high" in ds:
            ci = (f" [95 %: {fmt_value(float(ds['immersion_factor_ci95_low'].sel(band=b)))}, "
                  f"{fmt_value(float(ds['immersion_factor_ci95_high'].sel(band=b)))}]")
        rows.append([b, _num(ds, "effective_wavelength_nm", band=b), _num(ds, "dn_air", band=b),
                     _num(ds, "t_aw", band=b), _num(ds, "n_w", band=b), _num(ds, "n2_factor", band=b),
                     _num(ds, "dn_below", band=b), _num(ds, "dn_below_over_n2", band=b),
                     _num(ds, "immersion_factor", band=b) + ci, _num(ds, "window_index", band=b)])
    out.append("<p>Immersion factor per band (Eq. 11; ± standard uncertainty). Analogue of Table 2:</p>")
    out.append(_table(["band", "λ", "y_DN(0+) in air", "t_aw", "n_w", "t_aw n_w²", "y_DN(0−)",
                       "y_DN(0−)/(t_aw n_w²)", "I", "n_g (Eq. 10)"], rows))
    water = [f"{lab} {_num(ds, v)}" for lab, v in (("temperature", "water_temperature_c"),
                                                   ("salinity", "water_salinity_psu")) if v in ds]
    if water:
        out.append(f"<p>Water: {_e(', '.join(water))}.</p>")
    return "\n".join(out)


def _calibration_summary(absolute: dict[str, xr.Dataset], immersion: dict[str, xr.Dataset]) -> str:
    lines = []
    for lens in dict.fromkeys(list(absolute) + list(immersion)):
        parts = []
        a = absolute.get(lens)
        if a is not None and "inverse_responsivity" in a:
            vals = ", ".join(f"{b} {_num(a, 'inverse_responsivity', units=False, band=b)}" for b in _bands(a))
            parts.append(f"R⁻¹ [{_u(a, 'inverse_responsivity')}]: {vals}")
        i = immersion.get(lens)
        if i is not None and "immersion_factor" in i:
            vals = ", ".join(f"{b} {_num(i, 'immersion_factor', units=False, band=b)}" for b in _bands(i))
            parts.append(f"I: {vals}")
        if parts:
            lines.append(f"<li><b>{_e(lens)}</b>: {_e('; '.join(parts))}</li>")
    if not lines:
        return ""
    return "<p>Calibration per lens (± standard uncertainty):</p><ul>" + "".join(lines) + "</ul>"


# ---------------------------------------------------------------- diagnostics

def read_csv_or_empty(path: Path) -> pd.DataFrame:
    """A CSV table, or an empty one when the file is absent or empty (a stage that did not run)."""
    try:
        return pd.read_csv(path)
    except (FileNotFoundError, pd.errors.EmptyDataError):
        return pd.DataFrame()


def _as_bool(x) -> bool:
    if isinstance(x, str):
        return x.strip().lower() in ("true", "1", "yes")
    try:
        return bool(x) and not (isinstance(x, float) and math.isnan(x))
    except (TypeError, ValueError):
        return False


def _top_effect(missing: pd.DataFrame):
    if missing.empty:
        return None
    m = missing.sort_values("rank") if "rank" in missing else missing
    return m.iloc[0]


def _amplitude_text(row) -> str:
    units = "" if pd.isna(row.get("units")) or str(row.get("units")) == "1" else f" {row['units']}"
    name = row.get("amplitude_name")
    name = f"{name} = " if isinstance(name, str) and name else ""
    return (f"{name}{fmt_value(row['amplitude'], 3)}{units}, 95 % interval "
            f"[{fmt_value(row['amplitude_low'], 3)}, {fmt_value(row['amplitude_high'], 3)}]{units}")


def _history_figure(history: pd.DataFrame, figs: _Figures) -> str:
    if history.empty or not {"run_time", "experiment", "rms_z"} <= set(history.columns):
        return '<p class="note">No error history yet.</p>'
    runs = list(dict.fromkeys(history["run_time"].astype(str)))
    idx = {r: i for i, r in enumerate(runs)}
    h = history.assign(run=history["run_time"].astype(str).map(idx))
    labels = []
    for r in runs:
        effs = h.loc[h["run_time"].astype(str) == r, "model_effects"] if "model_effects" in h else pd.Series([""])
        e = effs.iloc[0] if len(effs) and isinstance(effs.iloc[0], str) else "(none)"
        labels.append(f"run {len(labels) + 1}\n" + e.replace(" ", "\n").replace(",", "\n"))
    fig, ax = plt.subplots(figsize=(max(6, 1.6 * len(runs) + 3), 4))
    for exp, grp in h.groupby("experiment"):
        grp = grp.sort_values("run")
        ax.plot(grp["run"], grp["rms_z"], "o-", label=str(exp))
    ax.axhline(1.0, color="grey", ls="--", lw=0.8, label="noise floor")
    ax.set_xticks(range(len(runs)))
    ax.set_xticklabels(labels, fontsize=7)
    ax.set_xlabel("run (labelled with the model effects)")
    ax.set_ylabel("rms z")
    ax.set_xlim(-0.5, len(runs) - 0.5)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return figs.embed(fig, "error_history",
                      "Error history: rms of the normalised residuals per experiment for each run, labelled "
                      "with the model effects of that run. Adding a missing effect should bring rms z towards 1.")


# ---------------------------------------------------------------- assembly

def _input_count(ds: xr.Dataset) -> str:
    try:
        return str(len(json.loads(ds.attrs.get("input_sha256", "{}"))))
    except (TypeError, ValueError):
        return "n/a"


def build_report(*, dark: dict[str, Path], linearity: dict[str, Path], missing_effects: Path,
                 unexplained: Path, run_errors: Path, error_history: Path, out_html: Path,
                 skipped: dict[str, str] | None = None, figures_dir: Path | None = None,
                 geometry: dict[str, Path] | None = None, rolloff: dict[str, Path] | None = None,
                 spectral: dict[str, Path] | None = None, absolute: dict[str, Path] | None = None,
                 immersion: dict[str, Path] | None = None, calibration: Path | None = None,
                 field: dict[str, Path] | None = None, failed: dict[str, str] | None = None) -> Path:
    """Write the calibration report as one self-contained HTML file and return its path.

    ``dark`` and ``linearity`` map lens name to artefact path; the four CSVs
    come from the diagnostics stage; ``skipped`` maps a stage name to the
    reason it did not run. ``geometry``, ``rolloff``, ``spectral``,
    ``absolute`` and ``immersion`` (optional) map lens name to that stage's
    artefact; a stage given as None or empty gets a section saying it was not
    run. ``calibration`` (optional) is the calibration bundle: its noise-equivalent
    radiance and limit of detection go into the absolute section. PNG copies of the figures go to ``figures_dir`` when given. The file
    is written to a temporary sibling and renamed. ``failed`` (after a run with failed jobs) maps
    a stage that did not finish to its error line: the summary names them first and the stages
    not run list them with the others.
    """
    out_html = Path(out_html)
    failed = dict(failed or {})
    skipped = {**dict(skipped or {}), **failed}
    figs = _Figures(figures_dir)
    dark_ds = {lens: read_artefact(p, "dark") for lens, p in dark.items()}
    lin_ds = {lens: read_artefact(p, "linearity") for lens, p in linearity.items()}
    missing = read_csv_or_empty(Path(missing_effects))
    unexp = read_csv_or_empty(Path(unexplained))
    errors = read_csv_or_empty(Path(run_errors))
    history = read_csv_or_empty(Path(error_history))
    later_paths = {"geometry": dict(geometry or {}), "rolloff": dict(rolloff or {}),
                   "spectral": dict(spectral or {}), "absolute": dict(absolute or {}),
                   "immersion": dict(immersion or {}), "field": dict(field or {})}
    later = {st: {lens: read_artefact(p, st) for lens, p in paths.items()} for st, paths in later_paths.items()}
    all_arts = [("dark", lens, dark[lens], ds) for lens, ds in dark_ds.items()] + \
               [("linearity", lens, linearity[lens], ds) for lens, ds in lin_ds.items()] + \
               [(st, lens, later_paths[st][lens], ds) for st, arts in later.items() for lens, ds in arts.items()]
    # section numbers: the later stages sit between linearity and the diagnostics
    titles = [("summary", "Summary"), ("dark", "Dark frames"), ("linearity", "Linearity"),
              ("geometry", "Geometry"), ("rolloff", "Roll-off"), ("spectral", "Relative spectral response"),
              ("absolute", "Absolute spectral radiance"), ("immersion", "Immersion factor"),
              ("field", "Field match-up"), ("diagnostics", "Diagnostics"), ("skipped", "Stages not run"), ("provenance", "Provenance")]
    num = {a: i + 1 for i, (a, _) in enumerate(titles)}

    body = []
    # 1. summary
    s = ['<h2 id="summary">1. Summary</h2>']
    if all_arts:
        first = all_arts[0][3].attrs
        pv = sorted({str(a[3].attrs.get("pipeline_version", "?")) for a in all_arts})
        effs = sorted({str(a[3].attrs.get("model_effects", "")) for a in all_arts})
        created = sorted(str(a[3].attrs.get("created", "?")) for a in all_arts)
        s.append(_table(["item", "value"], [
            ["pipeline version", ", ".join(pv)],
            ["artefacts created", f"{created[0]} … {created[-1]}" if len(created) > 1 else created[0]],
            ["model effects", " | ".join(e.replace(",", ", ") or "(none)" for e in effs)],
            ["lenses", ", ".join(dict.fromkeys([a[1] for a in all_arts]))],
            ["dataset (inputs of first artefact)", f"{_input_count(all_arts[0][3])} raw files, e.g. "
             f"{next(iter(json.loads(first.get('input_sha256', '{}') or '{}')), '—')}"],
        ], left=2))
        cfgs = [[a[0], a[1], str(a[3].attrs.get("config_sha256", "?"))[:16] + "…"] for a in all_arts]
        s.append("<p>Configuration fingerprints (SHA-256 of each stage's config subset):</p>")
        s.append(_table(["stage", "lens", "config sha256"], cfgs, left=3))
    if not errors.empty and {"experiment", "rms_z"} <= set(errors.columns):
        rows = [[r["experiment"], fmt_value(r["rms_z"], 3),
                 fmt_value(r.get("chi2"), 4), fmt_value(r.get("dof"), 4), fmt_value(r.get("n_obs"), 4)]
                for _, r in errors.iterrows()]
        s.append("<p>Residual error of this run per experiment (rms z = 1 at the noise floor; larger values "
                 "mean the model leaves structure the noise cannot explain):</p>")
        s.append(_table(["experiment", "rms z", "χ²", "dof", "observations"], rows))
    s.append(_calibration_summary(later["absolute"], later["immersion"]))
    for lens, ds in later["field"].items():
        s.append(field_summary(lens, ds))
    top = _top_effect(missing)
    if top is not None and _as_bool(top.get("significant")):
        s.append(f'<div class="callout">The residuals point to a missing effect: <b>{_e(top["effect"])}</b> '
                 f"in the {_e(top['experiment'])} experiment ({_e(_amplitude_text(top))}; it explains "
                 f"{100 * float(top['explained_fraction']):.0f} % of the excess χ²). Add it to "
                 f"<code>model.effects</code> in <code>config/config.yaml</code> and rerun.</div>")
    elif top is not None:
        s.append(f'<div class="ok">No significant missing effect. The top-ranked candidate, '
                 f"<b>{_e(top['effect'])}</b>, is not significant (p = {fmt_value(top.get('p_value'), 3)}).</div>")
    else:
        s.append('<div class="ok">The missing-effect search returned no candidates.</div>')
    if failed:
        s.insert(1, '<div class="callout">This run failed: ' + "; ".join(
            f"<b>{_e(stage)}</b> {_e(why)}" for stage, why in failed.items()) +
            ". This report covers the stages that finished.</div>")
    if skipped:
        s.append(f"<p>Stages not run: {_e(', '.join(skipped))} (see section {num['skipped']}).</p>")
    body.append("\n".join(s))

    # 2. dark
    d = ['<h2 id="dark">2. Dark frames</h2>']
    d.append("<p>Dark frames per lens: distribution of the frame-averaged dark image, its centre and width against "
             "exposure time and ISO, the fitted bias and dark current, read noise and hot pixels.</p>")
    if not dark_ds:
        d.append('<p class="note">No dark artefacts were given.</p>')
    for lens, ds in dark_ds.items():
        d.append(_dark_section(lens, ds, figs))
    body.append("\n".join(d))

    # 3. linearity
    li = ['<h2 id="linearity">3. Linearity</h2>']
    if not lin_ds:
        li.append('<p class="note">No linearity artefacts were given.</p>')
    for lens, ds in lin_ds.items():
        li.append(_linearity_section(lens, ds, figs))
    body.append("\n".join(li))

    # 4-8. geometry, roll-off, spectral, absolute, immersion
    intros = {
        "geometry": "Fisheye camera model per lens, medium and band (Section 3.2): projection function against the "
                    "usual fisheye references, band differences against G, reprojection errors and half field of view.",
        "rolloff": "Relative illumination against field angle per band and medium, both azimuth planes, with the "
                   "even 8th-degree polynomial of Eq. (13) (Section 3.3).",
        "spectral": "Peak-normalised relative spectral response with effective wavelengths and bandwidths "
                    "(Section 3.4).",
        "absolute": "Effective band radiance of the calibration source, dark-subtracted DN per second and the "
                    "calibration coefficient R⁻¹ with its uncertainty budget (Section 3.5).",
        "immersion": "Log-linear extrapolation of the in-water signal to just below the surface and the immersion "
                     "factor I (Section 3.6).",
        "field": "The calibration bundle applied to sky frames of the lens at the zenith and compared with a co-located "
                 "reference radiometer (Sections 2.9 and 3.8, Eq. 12, Fig. 10): the only closure of the lab "
                 "calibration against data it was not fitted on.",
    }
    for st in ("geometry", "rolloff", "spectral", "absolute", "immersion", "field"):
        title = dict(titles)[st]
        sec = [f'<h2 id="{st}">{num[st]}. {title}</h2>', f"<p>{_e(intros[st])}</p>"]
        if not later[st]:
            sec.append(_not_run(st, title.lower(), skipped))
        for lens, ds in later[st].items():
            if st == "geometry":
                sec.append(_geometry_section(lens, ds, figs))
            elif st == "rolloff":
                sec.append(_rolloff_section(lens, ds, figs))
            elif st == "spectral":
                sec.append(_spectral_section(lens, ds, figs))
            elif st == "absolute":
                sec.append(_absolute_section(lens, ds, figs, later["spectral"].get(lens)))
            elif st == "field":
                sec.append(field_section(lens, ds, figs))
            else:
                sec.append(_immersion_section(lens, ds, figs))
        if st == "absolute" and calibration is not None:
            sec.append(_noise_floor_section(read_artefact(calibration, "calibration"), figs))
        body.append("\n".join(sec))

    # diagnostics
    dg = [f'<h2 id="diagnostics">{num["diagnostics"]}. Diagnostics</h2>', "<h3>Missing-effect search</h3>"]
    if missing.empty:
        dg.append('<p class="note">No candidate effects were tested.</p>')
    else:
        rows = []
        m = missing.sort_values("rank") if "rank" in missing else missing
        for _, r in m.iterrows():
            units = "" if pd.isna(r.get("units")) or str(r.get("units")) == "1" else str(r["units"])
            rows.append([fmt_value(r.get("rank")), r.get("effect"), r.get("experiment"),
                         fmt_value(r.get("evidence"), 3), "yes" if _as_bool(r.get("significant")) else "no",
                         fmt_value(r.get("p_value"), 3),
                         f"{100 * float(r['explained_fraction']):.1f} %" if _finite(r.get("explained_fraction")) else "n/a",
                         f"{fmt_value(r.get('amplitude'), 3)} [{fmt_value(r.get('amplitude_low'), 3)}, "
                         f"{fmt_value(r.get('amplitude_high'), 3)}] {units}".strip(),
                         f"{fmt_value(r.get('detectable_amplitude'), 3)} {units}".strip(),
                         "" if pd.isna(r.get("note")) else r.get("note")])
        dg.append("<p>Candidate effects ranked by evidence (drop in χ² penalised for the added parameters). "
                  "Amplitudes with their 95 % interval; “detectable” is the smallest amplitude this dataset "
                  "would have revealed.</p>")
        dg.append(_table(["rank", "effect", "experiment", "evidence", "significant", "p", "explained",
                          "amplitude [95 % interval]", "detectable", "note"], rows, left=3))
    dg.append("<h3>Unexplained structure</h3>")
    if unexp.empty:
        dg.append("<p>No residual structure was found that the candidate effects leave unexplained.</p>")
    else:
        items = []
        for _, r in unexp.iterrows():
            extra = []
            if "rms_z" in r and _finite(r["rms_z"]):
                extra.append(f"rms z {fmt_value(r['rms_z'], 3)}")
            if "covariate" in r and isinstance(r["covariate"], str):
                extra.append(f"covariate {r['covariate']}")
            if "association" in r and _finite(r["association"]):
                extra.append(f"association {fmt_value(r['association'], 3)}")
            items.append(f"<li><b>{_e(r.get('experiment', ''))}</b>: {_e(r.get('message', ''))} "
                         f"<span class='note'>({_e('; '.join(extra))})</span></li>")
        dg.append("<ul>" + "".join(items) + "</ul>")
    dg.append("<h3>Error history</h3>")
    dg.append(_history_figure(history, figs))
    if not history.empty:
        cols = [c for c in ("run_time", "experiment", "model_effects", "rms_z", "chi2", "dof", "n_obs")
                if c in history]
        rows = [[r[c] if c in ("run_time", "experiment", "model_effects") else fmt_value(r[c], 4) for c in cols]
                for _, r in history.iterrows()]
        dg.append("<details><summary>Error history table</summary>" + _table(cols, rows, left=3) + "</details>")
    body.append("\n".join(dg))

    # stages not run
    sk = [f'<h2 id="skipped">{num["skipped"]}. Stages not run</h2>']
    if skipped:
        sk.append(_table(["stage", "reason"], [[k, v] for k, v in skipped.items()], left=2))
    else:
        sk.append("<p>All requested stages ran.</p>")
    body.append("\n".join(sk))

    # provenance
    pr = [f'<h2 id="provenance">{num["provenance"]}. Provenance</h2>']
    rows = [[st, lens, Path(p).name, str(ds.attrs.get("artefact_version", "?")),
             str(ds.attrs.get("pipeline_version", "?")), str(ds.attrs.get("created", "?")),
             str(ds.attrs.get("model_effects", "")).replace(",", ", ") or "(none)",
             _input_count(ds), str(ds.attrs.get("config_sha256", "?"))]
            for st, lens, p, ds in all_arts]
    pr.append(_table(["stage", "lens", "file", "artefact version", "pipeline version", "created",
                      "model effects", "input files", "config sha256"], rows, left=3))
    for st, lens, _path, ds in all_arts:
        cfg = ds.attrs.get("config")
        if cfg:
            try:
                cfg = json.dumps(json.loads(cfg), indent=2, sort_keys=True)
            except ValueError:
                pass
            pr.append(f"<details><summary>Config subset of {_e(st)} / {_e(lens)}</summary>"
                      f"<pre>{_e(cfg)}</pre></details>")
    pr.append(f'<p class="note">Report written {_e(datetime.now(timezone.utc).isoformat(timespec="seconds"))} '
              f"with {figs.count} figures.</p>")
    body.append("\n".join(pr))

    nav = ("<nav><ul>" + "".join(f'<li><a href="#{a}">{num[a]}. {t}</a></li>' for a, t in titles)
           + "</ul></nav>")
    doc = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
           "<title>Calibration report</title>"
           f"<style>{CSS}</style></head><body>\n<h1>Camera calibration report</h1>\n{nav}\n"
           + "\n".join(body) + "\n</body></html>\n")

    out_html.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_html.with_name(f".{out_html.name}.tmp")
    try:
        tmp.write_text(doc, encoding="utf-8")
        os.replace(tmp, out_html)
    finally:
        if tmp.exists():
            tmp.unlink()
    return out_html
