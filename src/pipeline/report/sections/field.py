"""Field match-up (Larouche et al. 2024, Sections 2.9 and 3.8, Eq. 12, Fig. 10): the camera against the reference radiometer.

Per lens at the zenith: the match-up statistics per band and comparison (nearest channel,
band-convolved reference) with their intervals, the time series and scatter of Fig. 10, and the
all-sky radiance map of one field frame.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import xarray as xr  # noqa: E402

from pipeline.report.content import Group, Table, draw  # noqa: E402
from pipeline.report.formatting import fmt_value  # noqa: E402
from pipeline.report.palette import BAND_COLOURS, sequential_map  # noqa: E402
from pipeline.report.registry import section  # noqa: E402
from pipeline.stages.observations import dataset_to_table  # noqa: E402
from pipeline.report.sections._common import lens_title, not_run, residual_figure  # noqa: E402

__all__ = ["field_agreement_rows", "COMPARISON_LABELS"]

COMPARISON_LABELS = {"nearest": "nearest channel", "convolved": "band-convolved reference"}
RADIANCE_UNITS = "W sr⁻¹ m⁻² nm⁻¹"


def _num(x, digits: int = 3) -> str:
    return fmt_value(float(x), digits)


def _interval(ds, name, b, c, digits=3) -> str:
    v = ds[name].isel(band=b, comparison=c)
    lo, hi = ds[f"{name}_low"].isel(band=b, comparison=c), ds[f"{name}_high"].isel(band=b, comparison=c)
    return f"{_num(v, digits)} [{_num(lo, digits)}, {_num(hi, digits)}]"


def _statistics_table(ds: xr.Dataset) -> Table:
    level = float(ds.attrs.get("confidence_level", 0.95))
    rows = []
    for b, band in enumerate(ds["band"].values):
        for c, comp in enumerate(ds["comparison"].values):
            sel = {"band": b, "comparison": c}
            rows.append([f"{band} ({_num(ds['effective_wavelength_nm'].isel(band=b), 4)} nm) vs "
                         + (f"{_num(ds['nearest_channel_nm'].isel(band=b), 4)} nm" if comp == "nearest" else "convolved"),
                         int(ds["n_matchups"].isel(**sel)),
                         _interval(ds, "stat_mupd", b, c), _interval(ds, "stat_median_symmetric_accuracy", b, c),
                         _interval(ds, "stat_signed_symmetric_bias", b, c),
                         f"{_num(ds['stat_ols_slope'].isel(**sel))} [{_num(ds['stat_ols_slope_low'].isel(**sel))}, "
                         f"{_num(ds['stat_ols_slope_high'].isel(**sel))}]",
                         _num(ds["stat_ols_intercept"].isel(**sel)),
                         f"{_num(ds['stat_odr_slope'].isel(**sel))} ± {_num(ds['stat_odr_slope_se'].isel(**sel), 2)}",
                         _interval(ds, "stat_pearson_r", b, c), _num(ds["stat_rmse_about_fit"].isel(**sel)),
                         _num(ds["stat_rmse_one_to_one"].isel(**sel))])
    caption = (f"Match-up statistics per band ({100 * level:.0f} % intervals: paired bootstrap for MUPD, ζ, SSPB "
               "and r; Student t for the OLS line). MUPD is Eq. (12); ζ the median symmetric accuracy and SSPB the "
               "signed symmetric percentage bias (Burggraaff et al. 2022); ODR the errors-in-both line weighted by "
               f"both instruments' uncertainties; RMSE in {RADIANCE_UNITS}. Published for the real camera: MUPD 21.1, "
               "20.3, 18.6 % (R, G, B) against the nearest channels.")
    return Table(["band vs reference", "N", "MUPD %", "ζ %", "SSPB %", "OLS slope", "OLS intercept",
                  "ODR slope", "Pearson r", "RMSE about fit", "RMSE about 1:1"], rows, caption)


def _figure_series(ds: xr.Dataset, lens: str):
    bands = list(ds["band"].values)
    t_min = ds["time_s"].values / 60.0
    fig, axes = plt.subplots(len(bands), 2, figsize=(10, 2.8 * len(bands)), squeeze=False)
    for j, band in enumerate(bands):
        colour = BAND_COLOURS.get(str(band), "k")
        cam = ds["camera_radiance"].sel(band=band).values
        err = np.hypot(ds["camera_random_sigma"].sel(band=band).values, ds["camera_systematic_sigma"].sel(band=band).values)
        ax = axes[j, 0]
        for comp, style in (("nearest", "-"), ("convolved", "--")):
            ax.plot(t_min, ds[f"reference_{comp}"].sel(band=band).values, style, color="0.3", lw=1,
                    label=f"reference, {COMPARISON_LABELS[comp]}")
        ax.errorbar(t_min, cam, yerr=err, fmt="o", ms=3, color=colour, capsize=2, label=f"camera {band}")
        ax.set_xlabel("time since the first frame [min]")
        ax.set_ylabel(f"L [{RADIANCE_UNITS}]")
        ax.legend(fontsize=7)
        ax = axes[j, 1]
        for comp, marker in (("nearest", "o"), ("convolved", "s")):
            ref = ds[f"reference_{comp}"].sel(band=band).values
            ok = ds["is_matchup"].sel(band=band).values.astype(bool)
            ax.plot(ref[ok], cam[ok], marker, ms=3, color=colour, alpha=0.8 if comp == "convolved" else 0.4,
                    label=COMPARISON_LABELS[comp])
            c = list(ds["comparison"].values).index(comp)
            b = bands.index(band)
            m = float(ds["stat_ols_slope"].isel(band=b, comparison=c))
            q = float(ds["stat_ols_intercept"].isel(band=b, comparison=c))
            xs = np.array([np.nanmin(ref[ok]), np.nanmax(ref[ok])])
            ax.plot(xs, m * xs + q, "-" if comp == "convolved" else ":", color=colour, lw=1)
        lim = [np.nanmin(cam) * 0.9, np.nanmax(cam) * 1.1]
        ax.plot(lim, lim, "k:", lw=1, label="1:1")
        ax.set_xlabel(f"reference L [{RADIANCE_UNITS}]")
        ax.set_ylabel(f"camera L [{RADIANCE_UNITS}]")
        ax.legend(fontsize=7)
    fig.tight_layout()
    return draw(fig, f"field_{lens}_matchup",
                f"Lens {lens}: sky radiance at the zenith (mask of {_num(ds['mask_half_angle_deg'])} degrees) "
                "from the camera (error bars: random and systematic standard uncertainty) and the reference "
                f"averaged over {_num(ds.attrs.get('reference_window_s', np.nan))} s around each frame, nearest "
                "channel and band-convolved; right: camera against reference with the OLS lines and the 1:1 "
                "line. Analogue of Larouche et al. (2024) Fig. 10.",
                alt=f"lens {lens}: camera and reference radiance time series and scatter per band")


def _figure_sky(ds: xr.Dataset, lens: str):
    bands = list(ds["band"].values)
    zen = ds["zenith"].values
    azi = np.deg2rad(ds["azimuth"].values)
    up = zen <= 90.0
    fig, axes = plt.subplots(1, len(bands), figsize=(3.6 * len(bands), 3.8), subplot_kw={"projection": "polar"})
    for ax, band in zip(np.atleast_1d(axes), bands):
        values = ds["sky_radiance"].sel(band=band).values[up]
        mesh = ax.pcolormesh(azi, zen[up], values, shading="auto", cmap=sequential_map(),
                             norm=matplotlib.colors.LogNorm(vmin=np.nanpercentile(values, 1), vmax=np.nanpercentile(values, 99.5)))
        ax.set_theta_zero_location("N")
        ax.set_theta_direction(-1)
        ax.set_ylim(0, 90)
        ax.set_title(f"band {band} (radius: zenith angle [°])")
        fig.colorbar(mesh, ax=ax, shrink=0.7, label=f"L [{RADIANCE_UNITS}]")
    fig.tight_layout()
    frame = ds["sky_radiance"].attrs.get("frame_file", "")
    return draw(fig, f"field_{lens}_sky",
                f"Lens {lens}: all-sky radiance of the middle field frame {frame} from the calibration "
                "bundle (zenith at the centre, zenith angle radially to 90 degrees, azimuth of the sphere "
                "convention of apply); white cells hold no unflagged pixel (the saturated sun disc, beyond "
                "the calibrated field angle).", alt=f"lens {lens}: all-sky radiance map per band")


def field_agreement_rows(lens: str, ds: xr.Dataset) -> list[list[str]]:
    """Rows of the summary's field table: per band, camera / reference and MUPD against both references.

    Parameters
    ----------
    lens : str
        The zenith lens.
    ds : xarray.Dataset
        Its field artefact.

    Returns
    -------
    list[list[str]]
        Per band: lens, band, camera / reference band scale, MUPD (%) against the nearest and the convolved
        reference, the number of match-ups (nearest) and the fit's rms z.
    """
    c_near = list(ds["comparison"].values).index("nearest")
    c_conv = list(ds["comparison"].values).index("convolved")
    return [[lens, str(band), _num(ds["band_scale"].isel(band=b), 3),
             _num(ds["stat_mupd"].isel(band=b, comparison=c_near), 3),
             _num(ds["stat_mupd"].isel(band=b, comparison=c_conv), 3),
             str(int(ds["n_matchups"].isel(band=b, comparison=c_near))), _num(ds["rms_z"], 3)]
            for b, band in enumerate(ds["band"].values)]


def _field_lens(lens: str, ds: xr.Dataset) -> list:
    out = [_statistics_table(ds)]
    model = str(ds.attrs.get("model_effects", ""))
    notes = [["frames, match-ups", f"{ds.sizes['frame']}, {int(ds['n_matchups'].min())} to {int(ds['n_matchups'].max())} "
              f"per band; {int(ds['n_frames_without_reference'])} without reference data in the window"],
             ["prediction of the model", COMPARISON_LABELS.get(ds.attrs.get("prediction", ""), ds.attrs.get("prediction", ""))],
             ["band scales camera / reference", ", ".join(f"{b} {_num(v, 4)}" for b, v in
                                                         zip(ds["band"].values, ds["band_scale"].values))],
             ["rms of the normalised residuals about the scales (1 = noise floor)", _num(ds["rms_z"])],
             ["camera clock minus UTC applied", f"{_num(ds['clock_offset_s'], 4)} s"
              + (" (fitted: clock_offset in the model)" if "clock_offset" in model
                 else " (not fitted: clock_offset not in the model)")]]
    if "sun_seen" in ds:
        notes.append(["frames with the sun seen (stray_light's switch)", f"{int(ds['sun_seen'].sum())} of {ds.sizes['frame']}"])
    if "stray_light_glare_sr" in ds:
        glare = ds["stray_light_mask_glare"].values
        share = np.nanmean(glare / ds["camera_radiance"].values, axis=0)
        notes.append(["sun glare (stray_light), spread at the reference angle",
                      f"{_num(ds['stray_light_glare_sr'], 3)} ± {_num(ds['stray_light_glare_sr_sigma'], 2)} sr⁻¹; "
                      "mean share of the mask radiance " + ", ".join(f"{b} {100 * v:.2g} %" for b, v in
                                                                   zip(ds["band"].values, share))])
    out.append(Table(["quantity", "value"], notes))
    out.append(_figure_series(ds, lens))
    if "obs_frame__z" in ds:
        fig = residual_figure(dataset_to_table(ds, "obs_frame"), "time_s", "time of the frame [s]", f"field_{lens}_residuals",
                              f"Lens {lens}: normalised residuals of the match-up (camera against k_b × reference) "
                              "against the time of the frame, per band. Residuals that follow the sky's change "
                              "(dL/dt) point to clock_offset, residuals that follow its colour to spectral_mismatch.")
        if fig is not None:
            out.append(fig)
    if "sky_radiance" in ds:
        out.append(_figure_sky(ds, lens))
    return out


@section("field", "Field match-up", order=90,
         intro="The calibration bundle applied to sky frames of the lens at the zenith and compared with a co-located "
               "reference radiometer (Sections 2.9 and 3.8, Eq. 12, Fig. 10): the only closure of the lab "
               "calibration against data it was not fitted on.")
def field_section(inputs) -> list:
    """The "Field match-up" section: one group per zenith lens with its field artefact, or a note that the stage was not run.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs.

    Returns
    -------
    list
        The section's blocks (:mod:`pipeline.report.content`).
    """
    arts = inputs.stage("field")
    if not arts:
        return [not_run("field", "field match-up", inputs.skipped)]
    return [Group(lens_title(lens, " at the zenith"), _field_lens(lens, ds), id=f"field-{lens}") for lens, ds in arts.items()]
