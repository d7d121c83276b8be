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
from scipy.interpolate import PchipInterpolator

from pipeline.io.bands import BANDS
from pipeline.radiometry.source import QTH_TEMPERATURE_K, planck_radiance
from pipeline.radiometry.spectral import band_statistics
from pipeline.simulate.camera_data import measured_response
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


#: The smartphone simulator's "true" response (the default camera's before it took the measured one):
#: per band, a sum of two Gaussians A1 exp(-(l - m1)^2 / 2 s1^2) + A2 exp(-(l - m2)^2 / 2 s2^2) with
#: A1 = 1, stored as (A2, m1_nm, s1_nm, m2_nm, s2_nm).  Tuned (by least squares, then rounded) so that
#: on the 400-700 nm, 10 nm grid the effective wavelength and half bandwidth are R 600.3 / 37.9,
#: G 539.7 / 60.0, B 480.0 / 49.0 nm against the published 600 / 38, 540 / 60, 480 / 49; peaks at
#: 596, 527 and 465 nm (published: near 600, 520, 460).
TWO_GAUSSIAN_RESPONSE_PARAMETERS = {
    "R": (0.155, 594.0, 27.0, 639.0, 30.0),
    "G": (0.656, 515.0, 33.6, 576.0, 34.9),
    "B": (0.54, 457.6, 28.1, 510.5, 35.0),
}


def _two_gaussians(wl, params):
    a2, m1, s1, m2, s2 = params
    return np.exp(-0.5 * ((wl - m1) / s1) ** 2) + a2 * np.exp(-0.5 * ((wl - m2) / s2) ** 2)


def two_gaussian_response(wavelength_nm):
    """A smooth two-Gaussian relative spectral response close to the published band statistics.

    The smartphone simulator's true response (:data:`TWO_GAUSSIAN_RESPONSE_PARAMETERS`).

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelengths (nm); designed for 380-720 nm (the Gaussian tails are below 0.02 of the peak at
        380 and 720 nm for R and G, and for B at 720 nm; B keeps 0.02 at 380 nm).

    Returns
    -------
    dict
        Band (``"R"``, ``"G"``, ``"B"``) -> array shaped like ``wavelength_nm``, peak 1 (located on a
        0.1 nm grid).
    """
    wl = np.asarray(wavelength_nm, dtype=float)
    out = {}
    for band, p in TWO_GAUSSIAN_RESPONSE_PARAMETERS.items():
        peak = _two_gaussians(_FINE_NM, p).max()
        out[band] = _two_gaussians(wl, p) / peak
    return out


def default_spectral_response(wavelength_nm, lens: str = "close"):
    """Default "true" relative spectral response of one lens of the simulator's camera.

    The real Insta360 ONE's measured response of that lens
    (:func:`pipeline.simulate.camera_data.measured_response`, Larouche et al.'s calibration files,
    MIT licence, (c) 2021 Raphael Larouche), interpolated by monotone piecewise cubics (no overshoot:
    the peak stays 1, the response stays non-negative) and zero outside the measured range (close lens
    400-670 nm, far lens 400-700 nm).

    Parameters
    ----------
    wavelength_nm : array_like
        Wavelengths (nm).
    lens : str
        ``"close"`` (the default) or ``"far"``.

    Returns
    -------
    dict
        Band (``"R"``, ``"G"``, ``"B"``) -> array shaped like ``wavelength_nm``, peak 1.
    """
    wl = np.asarray(wavelength_nm, dtype=float)
    grid, response, _ = measured_response(lens)
    inside = (wl >= grid[0]) & (wl <= grid[-1])
    out = {}
    for band in BANDS:
        values = PchipInterpolator(grid, response[band], extrapolate=False)(np.where(inside, wl, grid[0]))
        out[band] = np.where(inside, values, 0.0)
    return out


def camera_response(camera, lens: str, wavelength_nm):
    """The true response of one lens of a simulated camera.

    Parameters
    ----------
    camera : object
        The simulated camera; one with a ``spectral_response`` attribute (a function of the
        wavelengths, as the smartphone's) uses it, any other has :func:`default_spectral_response`.
    lens : str
        The lens name.
    wavelength_nm : array_like
        Wavelengths (nm).

    Returns
    -------
    dict
        Band -> response at ``wavelength_nm`` (peak 1).
    """
    own = getattr(camera, "spectral_response", None)
    return own(wavelength_nm) if own is not None else default_spectral_response(wavelength_nm, lens)


def grating_efficiency(wavelength_nm):
    """Relative diffraction efficiency of the monochromator gratings (dimensionless)."""
    wl = np.asarray(wavelength_nm, dtype=float)
    return 0.35 + 0.5 * np.exp(-0.5 * ((wl - GRATING_BLAZE_NM) / GRATING_WIDTH_NM) ** 2)


def beam_relative(wavelength_nm):
    """Relative beam power: 2796 K lamp times grating efficiency, peak 1 on the grid."""
    wl = np.asarray(wavelength_nm, dtype=float)
    b = planck_radiance(wl, QTH_TEMPERATURE_K) * grating_efficiency(wl)
    return b / np.max(planck_radiance(WAVELENGTHS_NM, QTH_TEMPERATURE_K) * grating_efficiency(WAVELENGTHS_NM))


def true_bandwidths_nm(response=None) -> dict[str, float]:
    """int S_b dlambda of a true response on a fine grid (nm).

    Parameters
    ----------
    response : callable, optional
        Function of the wavelengths giving band -> response (default: the close lens's
        :func:`default_spectral_response`).

    Returns
    -------
    dict
        Band -> integral of the peak-normalised response (nm).
    """
    fine = (response or default_spectral_response)(_FINE_NM)
    return {b: float(np.trapezoid(fine[b], _FINE_NM)) for b in BANDS}


def _band_truth(wl, s_grid, fine) -> dict:
    """Per band: the true response on the measurement grid and its statistics there and on the fine grid."""
    out = {}
    for b in BANDS:
        grid_s = s_grid[b] / np.max(s_grid[b])
        st = band_statistics(wl, grid_s)
        st_fine = band_statistics(_FINE_NM, fine[b])
        out[b] = {
            "response": grid_s,
            "effective_wavelength_nm": st["effective_wavelength_nm"],
            "half_bandwidth_nm": st["half_bandwidth_nm"],
            "effective_wavelength_nm_fine": st_fine["effective_wavelength_nm"],
            "half_bandwidth_nm_fine": st_fine["half_bandwidth_nm"],
        }
    return out


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
    s_true = {lens: camera_response(camera, lens, wl) for lens in camera.lens_names}
    fine = {lens: camera_response(camera, lens, _FINE_NM) for lens in camera.lens_names}
    lam = {lens: {b: float(np.trapezoid(fine[lens][b], _FINE_NM)) for b in BANDS} for lens in camera.lens_names}
    beam = beam_relative(wl)
    # integrated beam radiance E0 (W sr-1 m-2) at the beam's peak, chosen for the brightest band pixel
    dn_per_e0 = max(float(np.max(resp[b] * beam * s_true[lens][b] / lam[lens][b]))
                    for b in BANDS for lens in camera.lens_names) * EXPOSURE_S * ISO / 100
    e0 = PEAK_FRACTION_OF_SATURATION * saturation / dn_per_e0

    frames = []
    for lens in camera.lens_names:
        frames += [FrameSpec(lens, "dark", ISO, EXPOSURE_S, {"wavelength_nm": np.nan})
                   for _ in range(DARK_FRAMES)]
        for k, w in enumerate(wl):
            band_radiance = {b: float(e0 * beam[k] * s_true[lens][b][k] / lam[lens][b]) for b in BANDS}
            scene = _central_scene(band_radiance, FIELD_HALF_ANGLE_DEG)
            frames += [FrameSpec(lens, "signal", ISO, EXPOSURE_S, {"wavelength_nm": float(w)}, scene)
                       for _ in range(FRAMES_PER_WAVELENGTH)]

    # the photodiode reads the beam through its own (uncalibrated) spectral difference from the camera's beam
    reading = PHOTODIODE_SCALE * beam * photodiode_factor(wl, ctx.lab_errors) \
        * (1.0 + PHOTODIODE_RELATIVE_NOISE * ctx.rng.standard_normal(wl.size))
    lines = ["wavelength_nm,signal,signal_std"]
    lines += [f"{w:.1f},{r:.8g},{PHOTODIODE_RELATIVE_NOISE * r:.6g}" for w, r in zip(wl, reading)]

    # truth per lens on the measurement grid (peak-normalised on that grid, as a measurement is)
    truth = {"wavelength_nm": wl, "iso": ISO, "exposure_s": EXPOSURE_S,
             "beam_integrated_radiance_peak_W_sr_m2": e0, "field_half_angle_deg": FIELD_HALF_ANGLE_DEG,
             "lenses": {lens: {"bands": _band_truth(wl, s_true[lens], fine[lens])} for lens in camera.lens_names}}
    return ExperimentPlan(frames, sidecars={"photodiode.csv": "\n".join(lines) + "\n"}, truth=truth)
