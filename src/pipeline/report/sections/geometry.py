"""Geometry (Larouche et al. 2024, Section 3.2, Fig. 4 and Fig. S1): projection function, band differences, reprojection errors."""

from __future__ import annotations


import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import xarray as xr  # noqa: E402

from pipeline.stages.observations import dataset_to_table  # noqa: E402
from pipeline.report.content import Details, Table, Text, draw  # noqa: E402
from pipeline.report.formatting import bands as band_list  # noqa: E402
from pipeline.report.formatting import finite, fmt_value, quantity, var_units  # noqa: E402
from pipeline.report.formatting import media as media_list  # noqa: E402
from pipeline.report.palette import BAND_COLOURS  # noqa: E402
from pipeline.report.registry import section  # noqa: E402
from pipeline.report.sections._common import per_lens  # noqa: E402


def _geometry_section(lens: str, ds: xr.Dataset, inputs) -> list:
    """The geometry section of one lens: the projection function and band differences, the reprojection error
    against radius, the fitted camera model per medium and band and the dropped frames."""
    out = []
    if ds.attrs.get("projection") == "rectilinear":
        out.append(Text(f"Lens {lens}: rectilinear region (dataset.yaml), fitted with the pinhole model and its "
                        "radial and tangential distortion; the θ, φ and solid-angle maps come from that fit."))
    media, bands = media_list(ds), band_list(ds)
    if media and "theta_deg" in ds:
        out.append(_projection_figure(lens, ds, media, bands))
    if "error_vs_radius_px" in ds and "error_vs_radius_rho_px" in ds and media:
        out.append(_error_radius_figure(lens, ds, media, bands))
    elif media:
        out.append(Text('The artefact holds no reprojection errors (maps only).', 'note'))
    out.extend(_camera_model_table(ds, media, bands))
    if "obs_frame__reason" in ds:
        out.extend(_dropped_frames(ds))
    return out


def _projection_figure(lens: str, ds: xr.Dataset, media: list[str], bands: list[str]):
    """Per medium the projection function θ(ρ) of the G band against the fisheye references (top) and the other
    bands minus G (bottom), from the stored curves or, without them, from the θ maps (Fig. 4)."""
    has_curves = "projection_theta_deg" in ds and "rho_px" in ds.coords
    fig, axes = plt.subplots(2, len(media), figsize=(5.5 * len(media), 7), squeeze=False)
    for k, m in enumerate(media):
        ax, axd = axes[0, k], axes[1, k]
        if has_curves:
            _plot_stored_curves(ax, axd, ds, m, bands)
        else:
            _plot_map_curves(ax, axd, ds, m, bands)
        hf = float(ds["half_fov_deg"].sel(medium=m, band="G")) if "half_fov_deg" in ds else float("nan")
        if finite(hf):
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
    return draw(fig, f"geometry_{lens}_projection",
                f"Lens {lens}: projection function θ(ρ) of the G band with the equidistant, "
                "stereographic and orthographic references of the same focal length a0 (top), and "
                f"the R and B mapping minus G (bottom), per medium ({src}). "
                "Analogue of Larouche et al. (2024) Fig. 4.")


def _plot_stored_curves(ax, axd, ds: xr.Dataset, m: str, bands: list[str]) -> None:
    """The artefact's fitted θ(ρ) of G with its reference projections on ``ax``, the band differences on ``axd``."""
    rho = ds["rho_px"].values
    ax.plot(rho, ds["projection_theta_deg"].sel(medium=m, band="G").values, "-", color=BAND_COLOURS["G"],
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


def _plot_map_curves(ax, axd, ds: xr.Dataset, m: str, bands: list[str]) -> None:
    """No stored curves (maps-only artefact): θ of the map pixels against their radius, with the references of
    the polynomial's a0, on ``ax``; the band maps minus G on ``axd``."""
    th = ds["theta_deg"].sel(medium=m)
    ny, nx = th.shape[-2:]
    yy, xx = np.mgrid[0:ny, 0:nx]
    xc, yc = float(ds["xc_px"].sel(medium=m, band="G")), float(ds["yc_px"].sel(medium=m, band="G"))
    rho_map = np.hypot(xx - xc, yy - yc)
    tg = th.sel(band="G").values.astype(float)
    hf_g = float(ds["half_fov_deg"].sel(medium=m, band="G")) if "half_fov_deg" in ds else np.inf
    ok = np.isfinite(tg) & (tg <= (hf_g if np.isfinite(hf_g) else np.inf))
    step = max(1, int(ok.sum() // 4000))
    ax.plot(rho_map[ok][::step], tg[ok][::step], ".", color=BAND_COLOURS["G"], ms=2, label="theta map (G)")
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


def _error_radius_figure(lens: str, ds: xr.Dataset, media: list[str], bands: list[str]):
    """The mean reprojection error of the used corners in radial bins, per medium and band (Fig. S1)."""
    fig, axes = plt.subplots(1, len(media), figsize=(5.5 * len(media), 3.4), squeeze=False)
    for ax, m in zip(axes[0], media):
        for b in bands:
            ax.plot(ds["error_vs_radius_rho_px"].sel(medium=m, band=b).values,
                    ds["error_vs_radius_px"].sel(medium=m, band=b).values, "o-", ms=3,
                    color=BAND_COLOURS.get(b), label=b)
        ax.set_xlabel("ρ [band px]")
        ax.set_ylabel(f"mean reprojection error [{var_units(ds, 'error_vs_radius_px') or 'px'}]")
        ax.set_title(m, fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return draw(fig, f"geometry_{lens}_error_radius",
                f"Lens {lens}: mean reprojection error of the used corners in radial bins. "
                "Analogue of Fig. S1.")


def _camera_model_table(ds: xr.Dataset, media: list[str], bands: list[str]) -> list:
    """The fitted camera model per medium and band (principal point, half FOV, errors, frames used, σ(θ)):
    its heading and table, nothing without rows."""
    cols = [("principal point x", "xc_px"), ("principal point y", "yc_px"), ("half FOV", "half_fov_deg"),
            ("pixel angle on axis", "deg_per_px_axis"), ("mean reproj. error", "mean_error_px"),
            ("rms reproj. error", "rms_error_px"), ("image circle radius", "circle_radius_px"),
            ("max |θ − θ_G|", "theta_map_max_difference_vs_green_deg")]
    cols = [(t, v) for t, v in cols if v in ds]
    sigma_theta = "theta_deg_sigma_at_field_angle" in ds    # the fit's theta uncertainty, azimuthal RMS
    rows = []
    for m in media:
        for b in bands:
            r = [m, b] + [quantity(ds, v, digits=4, medium=m, band=b) for _, v in cols]
            if "n_frames_used" in ds and "n_frames" in ds:
                r.append(f"{fmt_value(float(ds['n_frames_used'].sel(medium=m, band=b)))} / "
                         f"{fmt_value(float(ds['n_frames'].sel(medium=m, band=b)))}")
            if sigma_theta:
                values = ds["theta_deg_sigma_at_field_angle"].sel(medium=m, band=b).values
                r.append(", ".join("–" if not np.isfinite(x) else f"{x:.3f}" for x in values))
            rows.append(r)
    if not rows:
        return []
    hdr = ["medium", "band"] + [t for t, _ in cols] + (["frames used"] if "n_frames_used" in ds and "n_frames" in ds else [])
    if sigma_theta:
        at = ", ".join(f"{x:g}" for x in ds["theta_summary_deg"].values)
        hdr.append(f"σ(θ) [°] at θ = {at}°")
    return [Text("Fitted camera model per medium and band:"), Table(hdr, rows, left=2)]


def _dropped_frames(ds: xr.Dataset) -> list:
    """The frame and band combinations the geometry stage dropped, with the reason (collapsed), if any."""
    fr = dataset_to_table(ds, "obs_frame")
    bad = fr[fr["reason"].astype(str).str.len() > 0] if len(fr) else fr
    if not len(bad):
        return []
    rows = [[r.get("file", ""), r.get("medium", ""), r.get("band", ""), r["reason"]] for _, r in bad.iterrows()]
    return [Details(f"{len(bad)} dropped frame/band combinations",
                    [Table(["file", "medium", "band", "reason"], rows, left=4)])]


@section("geometry", "Geometry", order=40,
         intro="Camera model per lens, medium and band (Section 3.2): for a fisheye region (the default projection) "
               "the projection function against the usual fisheye references, band differences against G, "
               "reprojection errors and half field of view; a region declared `projection: rectilinear` is fitted "
               "with the pinhole model and its distortion, and its artefact says so.")
def geometry_section(inputs) -> list:
    """The "Geometry" section: one group per lens with its geometry artefact, or a note that the stage was not run.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs.

    Returns
    -------
    list
        The section's blocks (:mod:`pipeline.report.content`).
    """
    return per_lens(inputs, "geometry", "geometry", _geometry_section)
