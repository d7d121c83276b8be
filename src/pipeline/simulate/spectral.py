"""Spectral-response experiment (Larouche et al. 2024, Section 2.5; Fig. 1b).

Per lens: a monochromator beam, spread by two opal diffusers, fills the
central field of the lens; the monochromator steps from 400 to 700 nm in
10 nm steps and the camera takes 4 frames at each wavelength (ISO 100,
0.1 s, as in the paper), after dark frames at the same settings (empty
``wavelength_nm``).  A reference photodiode reads the beam at each wavelength
(``photodiode.csv``).

Physics.  The beam is narrow (1 nm slit against bands 80-120 nm wide), so
its spectral radiance is a line of integrated radiance E(lambda_0); by Eq. (3)
the effective band radiance it gives band b is

    L_b = E(lambda_0) S_b(lambda_0) / int S_b dlambda

with S_b the TRUE peak-normalised response (integrated on a 0.1 nm grid).
E follows the lamp and the grating: a 2796 K Planck spectrum times a blazed
grating efficiency (peak near 500 nm), so that the photodiode correction
matters.  The photodiode reading is proportional to E with its own relative
noise; ``signal_std`` is the standard uncertainty of each reported reading.
With the lab's systematic errors on (:mod:`pipeline.simulate.lab_errors`),
the reading also carries the photodiode's smooth spectral difference from
the beam that reaches the camera (under 2 %, Section 2.5), one draw per
dataset; the truth's response is the camera's, without it.
"""

from __future__ import annotations

import numpy as np

from pipeline.io.bands import BANDS
from pipeline.radiometry.source import QTH_TEMPERATURE_K, planck_radiance
from pipeline.radiometry.spectral import band_statistics
from pipeline.simulate.lab_errors import photodiode_factor
from pipeline.simulate.plan import ExperimentPlan, FrameSpec, SimContext, planner

#: monochromator grid of Section 2.5 (nm)
WAVELENGTHS_NM = np.arange(400.0, 700.0 + 1e-9, 10.0)
FRAMES_PER_WAVELENGTH = 4          # Section 2.5: four images per wavelength
DARK_FRAMES = 4
ISO = 100.0
EXPOSURE_S = 0.1                   # Section 2.5: gain 100, 0.1 s
#: brightest band pixel at this fraction of the saturation level (well below it)
PEAK_FRACTION_OF_SATURATION = 0.4
#: half-angle of the diffuser-filled field around the optical axis (deg)
FIELD_HALF_ANGLE_DEG = 30.0
#: grating efficiency: blazed near 500 nm, 0.35 to 0.85
GRATING_BLAZE_NM = 500.0
GRATING_WIDTH_NM = 160.0
#: photodiode: relative noise of one reported reading and its scale (arbitrary units, "nA")
PHOTODIODE_RELATIVE_NOISE = 0.005
PHOTODIODE_SCALE = 250.0

#: fine wavelength grid (nm) of the true response's peak and band integrals
_FINE_NM = np.arange(380.0, 720.0 + 1e-9, 0.1)


#: Default "true" response of the simulator's camera: per band, a sum of two
#: Gaussians A1 exp(-(l - m1)^2 / 2 s1^2) + A2 exp(-(l - m2)^2 / 2 s2^2) with
#: A1 = 1, stored as (A2, m1_nm, s1_nm, m2_nm, s2_nm).  Tuned (by least
#: squares, then rounded) so that on the 400-700 nm, 10 nm grid the
#: effective wavelength and half bandwidth are R 600.3 / 37.9, G 539.7 /
#: 60.0, B 480.0 / 49.0 nm against the published 600 / 38, 540 / 60,
#: 480 / 49; peaks at 596, 527 and 465 nm (published: near 600, 520, 460).
DEFAULT_RESPONSE_PARAMETERS = {
    "R": (0.155, 594.0, 27.0, 639.0, 30.0),
    "G": (0.656, 515.0, 33.6, 576.0, 34.9),
    "B": (0.54, 457.6, 28.1, 510.5, 35.0),
}


def _two_gaussians(wl, params):
    a2, m1, s1, m2, s2 = params
    return np.exp(-0.5 * ((wl - m1) / s1) ** 2) + a2 * np.exp(-0.5 * ((wl - m2) / s2) ** 2)


def default_spectral_response(wavelength_nm):
    """Default "true" relative spectral response of the simulator's camera.

    Parameters
    ----------
    wavelength_nm : array_like, nm (designed for 380-720 nm; the Gaussian
        tails are below 0.02 of the peak at 380 and 720 nm for R and G, and
        for B at 720 nm; B keeps 0.02 at 380 nm).

    Returns
    -------
    dict band ("R", "G", "B") -> array shaped like ``wavelength_nm``,
    normalised to a peak of 1 (peak located on a 0.1 nm grid).
    """
    wl = np.asarray(wavelength_nm, dtype=float)
    out = {}
    for band, p in DEFAULT_RESPONSE_PARAMETERS.items():
        peak = _two_gaussians(_FINE_NM, p).max()
        out[band] = _two_gaussians(wl, p) / peak
    return out


def grating_efficiency(wavelength_nm):
    """Relative diffraction efficiency of the monochromator gratings (dimensionless)."""
    wl = np.asarray(wavelength_nm, dtype=float)
    return 0.35 + 0.5 * np.exp(-0.5 * ((wl - GRATING_BLAZE_NM) / GRATING_WIDTH_NM) ** 2)


def beam_relative(wavelength_nm):
    """Relative beam power: 2796 K lamp times grating efficiency, peak 1 on the grid."""
    wl = np.asarray(wavelength_nm, dtype=float)
    b = planck_radiance(wl, QTH_TEMPERATURE_K) * grating_efficiency(wl)
    return b / np.max(planck_radiance(WAVELENGTHS_NM, QTH_TEMPERATURE_K) * grating_efficiency(WAVELENGTHS_NM))


def true_bandwidths_nm() -> dict[str, float]:
    """int S_b dlambda of the true response on a fine grid (nm)."""
    fine = default_spectral_response(_FINE_NM)
    return {b: float(np.trapezoid(fine[b], _FINE_NM)) for b in BANDS}


def _central_scene(values: dict[str, float], half_angle_deg: float):
    lbar = np.array([values[b] for b in BANDS])

    def scene(lens, geometry, band_index):
        return lbar[band_index] * (geometry.theta_deg <= half_angle_deg)

    return scene


@planner("spectral")
def plan_spectral(ctx: SimContext) -> ExperimentPlan:
    camera = ctx.camera
    resp = camera.radiometry.responsivity_dn_s_per_radiance
    saturation = camera.sensor.adc_max_dn - camera.sensor.bias_dn
    wl = WAVELENGTHS_NM
    s_true = default_spectral_response(wl)
    lam = true_bandwidths_nm()
    beam = beam_relative(wl)
    # integrated beam radiance E0 (W sr-1 m-2) at the beam's peak, chosen for the brightest band pixel
    dn_per_e0 = max(float(np.max(resp[b] * beam * s_true[b] / lam[b])) for b in BANDS) * EXPOSURE_S * ISO / 100
    e0 = PEAK_FRACTION_OF_SATURATION * saturation / dn_per_e0

    frames = []
    for lens in camera.lens_names:
        frames += [FrameSpec(lens, "dark", ISO, EXPOSURE_S, {"wavelength_nm": np.nan})
                   for _ in range(DARK_FRAMES)]
        for k, w in enumerate(wl):
            band_radiance = {b: float(e0 * beam[k] * s_true[b][k] / lam[b]) for b in BANDS}
            scene = _central_scene(band_radiance, FIELD_HALF_ANGLE_DEG)
            frames += [FrameSpec(lens, "signal", ISO, EXPOSURE_S, {"wavelength_nm": float(w)}, scene)
                       for _ in range(FRAMES_PER_WAVELENGTH)]

    # the photodiode reads the beam through its own (uncalibrated) spectral difference from the camera's beam
    reading = PHOTODIODE_SCALE * beam * photodiode_factor(wl, ctx.lab_errors) \
        * (1.0 + PHOTODIODE_RELATIVE_NOISE * ctx.rng.standard_normal(wl.size))
    lines = ["wavelength_nm,signal,signal_std"]
    lines += [f"{w:.1f},{r:.8g},{PHOTODIODE_RELATIVE_NOISE * r:.6g}" for w, r in zip(wl, reading)]

    # truth on the measurement grid (peak-normalised on that grid, as a measurement is)
    truth = {"wavelength_nm": wl, "iso": ISO, "exposure_s": EXPOSURE_S,
             "beam_integrated_radiance_peak_W_sr_m2": e0, "field_half_angle_deg": FIELD_HALF_ANGLE_DEG,
             "bands": {}}
    fine = default_spectral_response(_FINE_NM)
    for b in BANDS:
        grid_s = s_true[b] / np.max(s_true[b])
        st = band_statistics(wl, grid_s)
        st_fine = band_statistics(_FINE_NM, fine[b])
        truth["bands"][b] = {
            "response": grid_s,
            "effective_wavelength_nm": st["effective_wavelength_nm"],
            "half_bandwidth_nm": st["half_bandwidth_nm"],
            "effective_wavelength_nm_fine": st_fine["effective_wavelength_nm"],
            "half_bandwidth_nm_fine": st_fine["half_bandwidth_nm"],
        }
    return ExperimentPlan(frames, sidecars={"photodiode.csv": "\n".join(lines) + "\n"}, truth=truth)
