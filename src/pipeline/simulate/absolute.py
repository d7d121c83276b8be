"""Absolute-radiance experiment (Larouche et al. 2024, Sections 2.6 and 3.5; Fig. 1c, Table 1).

Per lens: the 1-inch port of the integrating sphere (2796 K QTH lamp) on the
optical axis, filling the central field; 10 signal frames then 5 dark frames
at ISO 100 and 0.1 s (Table 1).

Sidecars written as a lab would:

* ``source_spectrum.csv``: the port's relative spectrum from a fibre
  spectrometer, 380-780 nm in 1 nm steps, arbitrary units, with noise;
  ``radiance_std`` is the standard uncertainty of each value.
* ``source_reference.csv``: the C-OPS reading at 589 nm, 6.8e-4
  W sr-1 m-2 nm-1 with relative uncertainty 0.02/0.68 (Section 3.5).

The camera sees, in band b, the effective band radiance of the TRUE source
spectrum through the TRUE spectral response on a 0.1 nm grid (Eq. 3), so a
pipeline that uses its measured 10 nm response carries that approximation.
Truth: R^-1 = 1 / responsivity per band (W sr-1 m-2 nm-1 per DN/s at ISO 100)
and the effective band radiances.
"""

from __future__ import annotations

import numpy as np

from pipeline.bands import BANDS
from pipeline.radiometry.source import (QTH_TEMPERATURE_K, REFERENCE_RADIANCE_SIGMA_W_SR_M2_NM,
                                        REFERENCE_RADIANCE_W_SR_M2_NM, REFERENCE_WAVELENGTH_NM, planck_radiance)
from pipeline.radiometry.spectral import effective_band_radiance
from pipeline.simulate.plan import ExperimentPlan, FrameSpec, SimContext, planner
from pipeline.simulate.spectral import default_spectral_response

SIGNAL_FRAMES = 10
DARK_FRAMES = 5
ISO = 100.0
EXPOSURE_S = 0.1
#: half-angle of the field filled by the sphere port (deg)
PORT_HALF_ANGLE_DEG = 20.0
#: fibre spectrometer grid (nm) and relative noise of one value
SPECTROMETER_NM = np.arange(380.0, 780.0 + 1e-9, 1.0)
SPECTROMETER_RELATIVE_NOISE = 0.003
#: arbitrary spectrometer units: counts at the reference wavelength
SPECTROMETER_COUNTS_AT_REFERENCE = 20000.0

_FINE_NM = np.arange(380.0, 720.0 + 1e-9, 0.1)


def default_source_radiance(wavelength_nm, temperature_k=QTH_TEMPERATURE_K):
    """Simulator's calibration-source radiance, W sr-1 m-2 nm-1.

    A Planck spectrum at ``temperature_k`` scaled to 6.8e-4 W sr-1 m-2 nm-1
    at 589 nm (exact scaling, no interpolation).  With the default spectral
    response its effective band radiances are about 0.74, 0.48, 0.26 mW
    sr-1 m-2 nm-1 (R, G, B), as in Table 1 of Larouche et al. (2024).
    """
    b = planck_radiance(wavelength_nm, temperature_k)
    return b * (REFERENCE_RADIANCE_W_SR_M2_NM / planck_radiance(REFERENCE_WAVELENGTH_NM, temperature_k))


def true_effective_band_radiance() -> dict[str, float]:
    """Eq. (3) with the true source and the true response on a fine grid (W sr-1 m-2 nm-1)."""
    s = default_spectral_response(_FINE_NM)
    radiance = default_source_radiance(_FINE_NM)
    return {b: float(effective_band_radiance(_FINE_NM, radiance, s[b])) for b in BANDS}


@planner("absolute")
def plan_absolute(ctx: SimContext) -> ExperimentPlan:
    camera = ctx.camera
    lbar = true_effective_band_radiance()
    values = np.array([lbar[b] for b in BANDS])

    def port(lens, geometry, band_index):
        return values[band_index] * (geometry.theta_deg <= PORT_HALF_ANGLE_DEG)

    frames = []
    for lens in camera.lens_names:
        frames += [FrameSpec(lens, "signal", ISO, EXPOSURE_S, {}, port) for _ in range(SIGNAL_FRAMES)]
        frames += [FrameSpec(lens, "dark", ISO, EXPOSURE_S, {}) for _ in range(DARK_FRAMES)]

    wl = SPECTROMETER_NM
    true = default_source_radiance(wl)
    counts = true * (SPECTROMETER_COUNTS_AT_REFERENCE / REFERENCE_RADIANCE_W_SR_M2_NM)
    measured = counts * (1.0 + SPECTROMETER_RELATIVE_NOISE * ctx.rng.standard_normal(wl.size))
    spectrum = ["wavelength_nm,radiance,radiance_std"]
    spectrum += [f"{w:.1f},{m:.8g},{SPECTROMETER_RELATIVE_NOISE * m:.6g}" for w, m in zip(wl, measured)]
    u_ref = REFERENCE_RADIANCE_SIGMA_W_SR_M2_NM / REFERENCE_RADIANCE_W_SR_M2_NM
    reference = ["wavelength_nm,radiance_W_sr_m2_nm,uncertainty_rel",
                 f"{REFERENCE_WAVELENGTH_NM:.1f},{REFERENCE_RADIANCE_W_SR_M2_NM:.8g},{u_ref:.6g}"]

    resp = camera.radiometry.responsivity_dn_s_per_radiance
    truth = {
        "iso": ISO, "exposure_s": EXPOSURE_S, "port_half_angle_deg": PORT_HALF_ANGLE_DEG,
        "bands": {b: {"inverse_responsivity": 1.0 / resp[b],
                      "effective_band_radiance_W_sr_m2_nm": lbar[b],
                      "dn_per_s_iso100": resp[b] * lbar[b]} for b in BANDS},
        "units": {"inverse_responsivity": "W sr-1 m-2 nm-1 per DN s-1 at ISO 100"},
    }
    return ExperimentPlan(frames, sidecars={"source_spectrum.csv": "\n".join(spectrum) + "\n",
                                            "source_reference.csv": "\n".join(reference) + "\n"},
                          truth=truth)
