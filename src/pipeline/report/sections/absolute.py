"""Absolute spectral radiance (Larouche et al. 2024, Section 3.5, Fig. 7, Eq. 9, Table 1)."""

from __future__ import annotations


import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import xarray as xr  # noqa: E402

from pipeline.report.content import Table, Text, draw  # noqa: E402
from pipeline.report.formatting import bands as band_list  # noqa: E402
from pipeline.report.formatting import fmt_value, pct, quantity, var_units  # noqa: E402
from pipeline.report.palette import OKABE_ITO, BAND_COLOURS  # noqa: E402
from pipeline.report.registry import section  # noqa: E402
from pipeline.report.sections._common import per_lens  # noqa: E402


def _absolute_section(lens: str, ds: xr.Dataset, inputs) -> list:
    spectral = inputs.stage("spectral").get(lens)
    out = []
    bands = band_list(ds)
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
            ax.errorbar([float(ds["reference_wavelength_nm"])], [ref], yerr=[ref * rel], fmt="^", color=OKABE_ITO[6],
                        capsize=3, ms=7, label="reference reading")
        ax.set_xlabel("wavelength [nm]")
        ax.set_ylabel(f"radiance [{var_units(ds, 'source_radiance')}]")
        ax.legend(fontsize=7)
        fig.tight_layout()
        where = ("plotted at each band's effective wavelength with ± half bandwidth bars (spectral artefact)"
                 if have_wl else "not plotted: no spectral artefact gives the effective wavelengths")
        out.append(draw(fig, f"absolute_{lens}_source",
                              f"Lens {lens}: calibration-source spectral radiance scaled to the reference "
                              f"reading (triangle); effective band radiances {where}. "
                              "Analogue of Larouche et al. (2024) Fig. 7."))
    rows = []
    for b in bands:
        dom = str(ds["dominant_term"].sel(band=b).values) if "dominant_term" in ds else "n/a"
        rows.append([b, quantity(ds, "effective_radiance", band=b), quantity(ds, "dn_per_s", band=b),
                     quantity(ds, "inverse_responsivity", band=b),
                     pct(ds["relative_sigma"].sel(band=b)) if "relative_sigma" in ds else "n/a", dom])
    out.append(Text("Absolute calibration (Eq. 9; ± standard uncertainty). Analogue of Table 1:"))
    out.append(Table(["band", "effective band radiance L̄", "y_DN (DN/s at ISO 100)", "R⁻¹",
                       "relative uncertainty of R⁻¹", "dominant term"], rows))
    if "uncertainty_contribution" in ds and "term" in ds.coords:
        terms = [str(t) for t in ds["term"].values]
        rows = [[b] + [pct(ds["uncertainty_contribution"].sel(band=b, term=t)) for t in terms]
                + [pct(ds["relative_sigma"].sel(band=b)) if "relative_sigma" in ds else "n/a"] for b in bands]
        out.append(Text("Uncertainty budget of R⁻¹ (relative standard uncertainty of each term):"))
        out.append(Table(["band"] + [t.replace("_", " ") for t in terms] + ["total"], rows))
    scal = []
    for label, v in (("reference reading", "reference_radiance"), ("reference wavelength", "reference_wavelength_nm"),
                     ("mask half-angle", "mask_half_angle_deg")):
        if v in ds:
            scal.append([label, quantity(ds, v)])
    if "reference_relative_sigma" in ds:
        scal.append(["reference relative uncertainty", pct(ds["reference_relative_sigma"])])
    if "rms_z" in ds:
        scal.append(["rms of normalised frame residuals (1 = noise floor)", fmt_value(float(ds["rms_z"]), 3)])
    if scal:
        out.append(Table(["quantity", "value"], scal))
    return out


@section("absolute", "Absolute spectral radiance", order=70,
         intro="Effective band radiance of the calibration source, dark-subtracted DN per second and the "
               "calibration coefficient R⁻¹ with its uncertainty budget (Section 3.5).")
def absolute_section(inputs) -> list:
    """The "Absolute spectral radiance" section: one group per lens with its absolute artefact, or a note that the stage was not run.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs.

    Returns
    -------
    list
        The section's blocks (:mod:`pipeline.report.content`).
    """
    return per_lens(inputs, "absolute", "absolute spectral radiance", _absolute_section)
