"""Roll-off (Larouche et al. 2024, Section 3.3, Fig. 5, Eq. 13): relative illumination against field angle."""

from __future__ import annotations


import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import xarray as xr  # noqa: E402

from pipeline.stages.observations import dataset_to_table  # noqa: E402
from pipeline.report.content import Table, Text, draw  # noqa: E402
from pipeline.report.formatting import bands as band_list  # noqa: E402
from pipeline.report.formatting import finite, fmt_uncertain, fmt_value, quantity, var_units  # noqa: E402
from pipeline.report.formatting import media as media_list  # noqa: E402
from pipeline.report.palette import BAND_COLOURS  # noqa: E402
from pipeline.report.registry import section  # noqa: E402
from pipeline.report.sections._common import effects_table, per_lens, residual_figure  # noqa: E402


def _rolloff_section(lens: str, ds: xr.Dataset, inputs) -> list:
    from pipeline.radiometry.rolloff import evaluate_rolloff

    out = []
    media, bands = media_list(ds), band_list(ds)
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
            ax.set_ylabel("relative illumination g(θ) [1]")
            ax.set_title(f"{m}", fontsize=9)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=6, ncol=2)
            else:   # no band of this medium has finite coefficients
                ax.text(0.5, 0.5, f"no roll-off fitted in {m}", transform=ax.transAxes, ha="center", va="center")
        fig.tight_layout()
        out.append(draw(fig, f"rolloff_{lens}",
                              f"Lens {lens}: roll-off per band and medium: normalised spot means (open markers, "
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
                if finite(t_max) and np.all(np.isfinite(coef)):
                    if cv is not None:
                        g, sg = evaluate_rolloff(coef, t_max, cv)
                        gtxt = fmt_uncertain(float(g), float(sg))
                    else:
                        gtxt = fmt_value(float(evaluate_rolloff(coef, t_max)))
                else:
                    gtxt = "n/a"
                rows.append([m, b] + cells + [f"{gtxt} (θ = {fmt_value(t_max, 3)}°)",
                                              quantity(ds, "rolloff_reduced_chi2", digits=3, medium=m, band=b)])
        unit = var_units(ds, "rolloff_coefficients")
        out.append(Text(f"Roll-off polynomial g(θ) = Σ a_k θ^k (θ in degrees; a_k in {unit or '°⁻ᵏ'}; "
                   "± standard error) and g at the largest measured angle:"))
        out.append(Table(["medium", "band"] + [f"a{p}" for p in powers] + ["g(θ_max)", "reduced χ²"], rows, left=2))
    scal = []
    if "water_closure_scale" in ds:
        scal += [[f"in-water closure scale c ({b}), g_water(θ_w) = c g_air(θ_a) F(θ_a, θ_w)",
                  fmt_uncertain(float(ds["water_closure_scale"].sel(band=b)),
                                float(ds["water_closure_scale_sigma"].sel(band=b)))]
                 for b in bands]
    if "rms_z" in ds:
        scal.append(["rms of normalised residuals (1 = noise floor)", fmt_value(float(ds["rms_z"]), 3)])
    if scal:
        out.append(Table(["quantity", "value"], scal))
    if len(tab) and {"medium", "azimuth_deg"} <= set(tab.columns):
        plane = tab["medium"].astype(str) + " φ=" + tab["azimuth_deg"].map(lambda a: f"{a:g}°")
        fig = residual_figure(tab.assign(plane=plane), "theta_deg", "θ, angle from the optical axis [°]",
                              f"rolloff_{lens}_residuals",
                              f"Lens {lens}: normalised residuals of the roll-off fit against field angle, one marker "
                              "per medium and azimuth plane. Residuals of opposite sign in the two planes, growing "
                              "with θ, are the signature of rolloff_azimuth (decentred or tilted optics).",
                              group="plane", group_label="")
        if fig is not None:
            out.append(fig)
    out.append(effects_table(ds))
    return out


@section("rolloff", "Roll-off", order=50,
         intro="Relative illumination against field angle per band and medium, both azimuth planes, with the "
               "even 8th-degree polynomial of Eq. (13) (Section 3.3).")
def rolloff_section(inputs) -> list:
    """The "Roll-off" section: one group per lens with its roll-off artefact, or a note that the stage was not run.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs.

    Returns
    -------
    list
        The section's blocks (:mod:`pipeline.report.content`).
    """
    return per_lens(inputs, "rolloff", "roll-off", _rolloff_section)
