"""Noise floor (Larouche et al. 2024, Section 3.8): noise-equivalent radiance, limit of detection, SNR against radiance."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import xarray as xr  # noqa: E402

from pipeline.report.content import Table, Text, draw  # noqa: E402
from pipeline.report.formatting import fmt_value  # noqa: E402
from pipeline.report.palette import BAND_COLOURS  # noqa: E402
from pipeline.report.registry import section  # noqa: E402

__all__ = ["snr_against_radiance", "noise_floor_blocks"]

RADIANCE_UNITS = "W sr⁻¹ m⁻² nm⁻¹"


def snr_against_radiance(radiance, ner: float, lod: float, lod_snr: float):
    """Signal-to-noise ratio at each radiance, from the noise-equivalent radiance and the limit of detection.

    The measurement chain's random noise is sigma^2 = a + b L (read and dark noise, shot noise) in
    radiance units; NER is where L = sigma (SNR 1), the limit of detection where L = k sigma. The
    two conditions give b = (LoD^2 / k^2 - NER^2) / (LoD - NER), a = NER^2 - b NER, and
    SNR(L) = L / sqrt(a + b L) (Section 3.8).

    Parameters
    ----------
    radiance : array_like
        Spectral radiance L, W sr-1 m-2 nm-1.
    ner : float
        The noise-equivalent radiance, W sr-1 m-2 nm-1.
    lod : float
        The limit of detection, W sr-1 m-2 nm-1 (larger than ``ner``).
    lod_snr : float
        The SNR k at the limit of detection.

    Returns
    -------
    numpy.ndarray
        The SNR at each radiance, dimensionless.
    """
    b = (lod**2 / lod_snr**2 - ner**2) / (lod - ner)
    a = ner**2 - b * ner
    radiance = np.asarray(radiance, dtype=float)
    return radiance / np.sqrt(a + b * radiance)


def operating_point(bundle: xr.Dataset) -> tuple[float, str]:
    """The SNR of the limit of detection and the setting (ISO, exposure) both figures are stated at.

    Parameters
    ----------
    bundle : xarray.Dataset
        The calibration bundle (its ``limit_of_detection`` attributes).

    Returns
    -------
    snr : float
        The SNR of the limit of detection (default 3).
    setting : str
        E.g. ``"ISO 100, 1 s"``.
    """
    lod = bundle["limit_of_detection"]
    return float(lod.attrs.get("snr", 3.0)), f"ISO {lod.attrs.get('iso', 100):g}, {lod.attrs.get('exposure_s', 1):g} s"


def noise_floor_blocks(bundle: xr.Dataset | None) -> list:
    """NER and limit of detection per lens and band from the calibration bundle, and SNR against radiance;
    an empty list without a bundle (or one without the noise floor).

    Parameters
    ----------
    bundle : xarray.Dataset or None
        The calibration bundle.

    Returns
    -------
    list
        The text, the table (W sr-1 m-2 nm-1) and the SNR figure (:mod:`pipeline.report.content`).
    """
    if bundle is None or "noise_equivalent_radiance" not in bundle:
        return []
    ner, lod = bundle["noise_equivalent_radiance"], bundle["limit_of_detection"]
    k, at = operating_point(bundle)
    rows = [[str(lens), str(band), fmt_value(float(ner.sel(lens=lens, band=band)), 2),
             fmt_value(float(lod.sel(lens=lens, band=band)), 2)]
            for lens in bundle["lens"].values for band in bundle["band"].values]
    out = [Text(f"From the calibration bundle at {at}: the radiance on the optical axis whose signal equals its random "
                f"noise (NER, SNR 1) and the limit of detection (SNR {k:g}), through the measurement chain with "
                "the dark stage's read noise, the photon-transfer gain and R⁻¹ (Section 3.8; the paper reports "
                f"NER 1.1e-7, 4.5e-8, 1.1e-7 and limits 4.6e-7, 1.8e-7, 4.6e-7 {RADIANCE_UNITS} for R, G, B)."),
           Table(["lens", "band", f"NER [{RADIANCE_UNITS}]", f"limit of detection, SNR {k:g} [{RADIANCE_UNITS}]"],
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
    ax.set_xlabel(f"spectral radiance [{RADIANCE_UNITS}]")
    ax.set_ylabel(f"signal-to-noise ratio [1] ({at})")
    ax.legend(fontsize=8, ncol=2)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    out.append(draw(fig, "snr_against_radiance",
                    f"Signal-to-noise ratio of one pixel on the optical axis against spectral radiance ({at}); "
                    f"the grey line is SNR {k:g}, the limit of detection.",
                    alt="signal-to-noise ratio against spectral radiance per lens and band"))
    return out


@section("noise-floor", "Noise floor and limit of detection", order=85)
def noise_floor_section(inputs) -> list:
    """The "Noise floor and limit of detection" section (:func:`noise_floor_blocks`), or a note that no bundle with a noise floor was given.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs (its ``calibration``).

    Returns
    -------
    list
        The section's blocks (:mod:`pipeline.report.content`).
    """
    blocks = noise_floor_blocks(inputs.calibration)
    if blocks:
        return blocks
    return [Text("No calibration bundle with a noise floor was given: the bundle needs the dark, linearity, "
                 "geometry, roll-off and absolute stages.", "note")]
