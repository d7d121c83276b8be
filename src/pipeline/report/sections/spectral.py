"""Relative spectral response (Larouche et al. 2024, Section 3.4, Fig. 6, Eq. 8)."""

from __future__ import annotations


import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import xarray as xr  # noqa: E402

from pipeline.stages.observations import dataset_to_table  # noqa: E402
from pipeline.report.content import Table, Text, draw  # noqa: E402
from pipeline.report.formatting import bands as band_list  # noqa: E402
from pipeline.report.formatting import finite, fmt_value, quantity  # noqa: E402
from pipeline.report.palette import BAND_COLOURS  # noqa: E402
from pipeline.report.registry import section  # noqa: E402
from pipeline.report.sections._common import per_lens, residual_figure  # noqa: E402


def _spectral_section(lens: str, ds: xr.Dataset, inputs) -> list:
    out = []
    bands = band_list(ds)
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
                if finite(hb):
                    ax.errorbar([le], [ybar], xerr=[hb], fmt="|", color=c, capsize=3)
                ax.text(le, ybar + 0.01, f"{le:.1f} nm", color=c, ha="center", va="bottom", fontsize=7)
        ax.set_ylim(-0.05, 1.05 + 0.05 * len(bands) + 0.05)
        ax.set_xlabel("wavelength [nm]")
        ax.set_ylabel("peak-normalised response S_R [1]")
        ax.legend(fontsize=8)
        fig.tight_layout()
        out.append(draw(fig, f"spectral_{lens}",
                              f"Lens {lens}: relative spectral response per band (shaded: ±1σ); dashed lines "
                              "mark the effective wavelength (Eq. 8) and the bars its ± half bandwidth. "
                              "Analogue of Larouche et al. (2024) Fig. 6."))
    rows = []
    for b in bands:
        rows.append([b, quantity(ds, "effective_wavelength_nm", band=b), quantity(ds, "half_bandwidth_nm", band=b),
                     quantity(ds, "bandwidth_nm", band=b), quantity(ds, "peak_wavelength_nm", band=b),
                     quantity(ds, "mask_n_pixels", band=b), quantity(ds, "dark_level_dn", band=b)])
    out.append(Text("Band statistics (± standard uncertainty propagated from the response covariance):"))
    out.append(Table(["band", "effective wavelength λ_eff", "half bandwidth Λ/2", "bandwidth ∫S dλ",
                       "peak wavelength", "mask pixels", "dark level"], rows))
    if "rms_z" in ds:
        out.append(Text(f"rms of normalised frame residuals (1 = noise floor): {fmt_value(float(ds['rms_z']), 3)}"))
    if "obs_frame__z" in ds:
        fig = residual_figure(dataset_to_table(ds, "obs_frame"), "wavelength_nm", "wavelength [nm]",
                              f"spectral_{lens}_residuals",
                              f"Lens {lens}: normalised residuals of the spectral-response frames against the "
                              "monochromator wavelength, per band.")
        if fig is not None:
            out.append(fig)
    return out


@section("spectral", "Relative spectral response", order=60,
         intro="Peak-normalised relative spectral response with effective wavelengths and bandwidths (Section 3.4).")
def spectral_section(inputs) -> list:
    """The "Relative spectral response" section: one group per lens with its spectral artefact, or a note that the stage was not run.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs.

    Returns
    -------
    list
        The section's blocks (:mod:`pipeline.report.content`).
    """
    return per_lens(inputs, "spectral", "relative spectral response", _spectral_section)
