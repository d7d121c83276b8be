"""Immersion factor (Larouche et al. 2024, Section 3.6, Fig. 8, Eqs. 10-11, Table 2)."""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import xarray as xr  # noqa: E402

from pipeline.stages.observations import dataset_to_table  # noqa: E402
from pipeline.report.content import Table, Text, draw  # noqa: E402
from pipeline.report.formatting import bands as band_list  # noqa: E402
from pipeline.report.formatting import fmt_value, quantity, var_units  # noqa: E402
from pipeline.report.palette import OKABE_ITO, BAND_COLOURS  # noqa: E402
from pipeline.report.registry import section  # noqa: E402
from pipeline.report.sections._common import per_lens, residual_figure  # noqa: E402


def _immersion_section(lens: str, ds: xr.Dataset, inputs) -> list:
    out = []
    bands = band_list(ds)
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
                        label=f"fit, K = {fmt_value(k, 3)} {var_units(ds, 'attenuation_per_cm')}{r2}")
                rel = (float(ds["dn_below_sigma"].sel(band=b)) / float(ds["dn_below"].sel(band=b))
                       if "dn_below_sigma" in ds else None)
                ax.errorbar([0.0], [b0], yerr=[rel] if rel else None, fmt="v", color="k", ms=7, capsize=3,
                            label=f"intercept ln y_DN(0−){corr}")
            if "dn_air" in ds:
                rel = (float(ds["dn_air_sigma"].sel(band=b)) / float(ds["dn_air"].sel(band=b))
                       if "dn_air_sigma" in ds else None)
                ax.errorbar([0.0], [math.log(float(ds["dn_air"].sel(band=b)))], yerr=[rel] if rel else None,
                            fmt="*", color=OKABE_ITO[1], ms=10, capsize=3, label="ln y_DN(0+) in air")
            if "immersion_factor" in ds:
                ax.text(0.35, 0.5, f"I = {quantity(ds, 'immersion_factor', band=b)}", transform=ax.transAxes, fontsize=8)
            ax.set_xlabel("water height z [cm]")
            ax.set_ylabel("ln y_DN [ln(DN s⁻¹)]")
            ax.set_title(f"{b} band", fontsize=9)
            ax.legend(fontsize=6)
        fig.tight_layout()
        out.append(draw(fig, f"immersion_{lens}",
                              f"Lens {lens}: natural logarithm of the in-water signal against water height with "
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
        rows.append([b, quantity(ds, "effective_wavelength_nm", band=b), quantity(ds, "dn_air", band=b),
                     quantity(ds, "t_aw", band=b), quantity(ds, "n_w", band=b), quantity(ds, "n2_factor", band=b),
                     quantity(ds, "dn_below", band=b), quantity(ds, "dn_below_over_n2", band=b),
                     quantity(ds, "immersion_factor", band=b) + ci, quantity(ds, "window_index", band=b)])
    out.append(Text("Immersion factor per band (Eq. 11; ± standard uncertainty). Analogue of Table 2:"))
    out.append(Table(["band", "λ", "y_DN(0+) in air", "t_aw", "n_w", "t_aw n_w²", "y_DN(0−)",
                       "y_DN(0−)/(t_aw n_w²)", "I", "n_g (Eq. 10)"], rows))
    water = [f"{lab} {quantity(ds, v)}" for lab, v in (("temperature", "water_temperature_c"),
                                                   ("salinity", "water_salinity_psu")) if v in ds]
    if water:
        out.append(Text(f"Water: {', '.join(water)}."))
    fig = residual_figure(tab, "water_height_cm", "water height z [cm]", f"immersion_{lens}_residuals",
                          f"Lens {lens}: normalised residuals of the log-linear fit against water height, per band; "
                          "a curve here means the in-water signal is not exponential in depth (bubbles, wavelets, "
                          "an angle-dependent immersion factor).")
    if fig is not None:
        out.append(fig)
    return out


@section("immersion", "Immersion factor", order=80,
         intro="Log-linear extrapolation of the in-water signal to just below the surface and the immersion "
               "factor I (Section 3.6).")
def immersion_section(inputs) -> list:
    """The "Immersion factor" section: one group per lens with its immersion artefact, or a note that the stage was not run.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs.

    Returns
    -------
    list
        The section's blocks (:mod:`pipeline.report.content`).
    """
    return per_lens(inputs, "immersion", "immersion factor", _immersion_section)
