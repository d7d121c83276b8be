"""Immersion-factor experiment (Larouche et al. 2024, Sections 2.7 and 3.6; Fig. 1(d)).

The lens looks up at a source above the tank, on its optical axis: first in
the empty tank (condition ``air``, 5 frames), then under 6 to 11 cm of water
in 0.5 cm steps (5 frames each). The radiance reaching the lens in water is

    L_air * t_aw n_w^2 * exp(-(a + b) z)

(n-squared law with the Fresnel transmission of the surface, docs/design.md
"Immersion"), and the camera's in-water response is the in-air one divided
by the immersion factor I of an external surface of index n_g, Eq. (10).
The external-surface indices are the paper's retrieved values (Section 3.6:
n_g = 1.60, 1.63, 1.58 for R, G, B), which give I close to Table 2
(1.69, 1.69, 1.71). In-air levels follow Table 2 (5267, 8259, 3737 ADU at 0.1 s).

Attenuation of pure water (m^-1): absorption a from Pope and Fry (1997) at
600, 540 and 480 nm (0.2224, 0.0409, 0.0145) and scattering b from Morel
(1974) (about 0.0012, 0.0021, 0.0035).
"""

from __future__ import annotations

import numpy as np
import yaml

from pipeline.io.bands import BANDS
from pipeline.radiometry.immersion import immersion_factor_flat_window, n_squared_law_factor_at
from pipeline.radiometry.water import refractive_index_water
from pipeline.simulate.plan import ExperimentPlan, FrameSpec, SimContext, planner

#: nominal effective wavelengths of the bands (docs/design.md, the simulator's default camera)
BAND_WAVELENGTH_NM = {"R": 600.0, "G": 540.0, "B": 480.0}
WINDOW_INDEX = {"R": 1.60, "G": 1.63, "B": 1.58}
ABSORPTION_PER_M = {"R": 0.2224, "G": 0.0409, "B": 0.0145}
SCATTERING_PER_M = {"R": 0.0012, "G": 0.0021, "B": 0.0035}
IN_AIR_DN = {"R": 5267.0, "G": 8259.0, "B": 3737.0}
WATER = {"temperature_c": 25.0, "salinity_psu": 0.0}
HEIGHTS_CM = np.arange(6.0, 11.0 + 1e-9, 0.5)
FRAMES_PER_LEVEL = 5
DARK_FRAMES = 5
EXPOSURE_S = 0.1
ISO = 100.0
#: angular radius of the source disc (covers the 1.5 deg mask with margin at every scale)
SOURCE_RADIUS_DEG = 15.0


def true_immersion_factors(temperature_c=WATER["temperature_c"], salinity_psu=WATER["salinity_psu"]) -> dict:
    """The true indices and immersion factors of the experiment's water and window, per band.

    Parameters
    ----------
    temperature_c : float, optional
        The water's temperature, deg C; default 25.
    salinity_psu : float, optional
        The water's salinity, PSU; default 0 (pure water).

    Returns
    -------
    dict
        Per band (R, G, B) at the band's nominal wavelength: ``n_w`` (water's refractive index), ``n_g`` (the
        window's), ``immersion_factor`` (I of a flat external window, Eq. 10) and ``n2_factor`` (the n-squared
        law's factor with the surface's Fresnel transmission, t_aw n_w^2); all dimensionless.
    """
    n_w = {b: float(refractive_index_water(BAND_WAVELENGTH_NM[b], temperature_c, salinity_psu)) for b in BANDS}
    return {
        "n_w": n_w,
        "n_g": dict(WINDOW_INDEX),
        "immersion_factor": {b: float(immersion_factor_flat_window(n_w[b], WINDOW_INDEX[b])) for b in BANDS},
        "n2_factor": {b: float(n_squared_law_factor_at(BAND_WAVELENGTH_NM[b], temperature_c, salinity_psu))
                      for b in BANDS},
    }


class OnAxisSource:
    def __init__(self, radiance: dict, radius_deg: float):
        self.radiance = np.array([radiance[b] for b in BANDS])
        self.radius = radius_deg

    def __call__(self, lens, geo, band_index):
        return np.where(geo.theta_deg <= self.radius, self.radiance[band_index], 0.0)


class WaterFactor:
    def __init__(self, values: dict):
        self.values = np.array([values[b] for b in BANDS])

    def __call__(self, band_index):
        return self.values[band_index]


@planner("immersion")
def plan_immersion(ctx: SimContext) -> ExperimentPlan:
    """Plan the immersion-factor experiment: each lens under a source on its axis, in air and under water.

    Per lens: dark frames, frames in the empty tank, then frames at each water height of :data:`HEIGHTS_CM`,
    the light multiplied by t_aw n_w^2 exp(-(a + b) z) / I per band.

    Parameters
    ----------
    ctx : SimContext
        The simulation (the camera's responsivity sets the source's radiance to the in-air levels of Table 2).

    Returns
    -------
    ExperimentPlan
        The frames (columns ``condition`` and ``water_height_cm``), the ``water.yaml`` sidecar (temperature,
        salinity) and the truth: immersion factors, indices, attenuation (m-1) and the source's band radiance
        (W m-2 sr-1 nm-1).
    """
    resp = ctx.camera.radiometry.responsivity_dn_s_per_radiance
    radiance = {b: IN_AIR_DN[b] / (resp[b] * EXPOSURE_S * ISO / 100.0) for b in BANDS}
    true = true_immersion_factors()
    c = {b: ABSORPTION_PER_M[b] + SCATTERING_PER_M[b] for b in BANDS}
    source = OnAxisSource(radiance, SOURCE_RADIUS_DEG)
    frames = []
    for lens in ctx.camera.lens_names:
        for _ in range(DARK_FRAMES):
            frames.append(FrameSpec(lens, "dark", ISO, EXPOSURE_S, {"condition": "air", "water_height_cm": ""}))
        for _ in range(FRAMES_PER_LEVEL):
            frames.append(FrameSpec(lens, "signal", ISO, EXPOSURE_S, {"condition": "air", "water_height_cm": ""},
                                    source, medium="air"))
        for z in HEIGHTS_CM:
            factor = WaterFactor({b: true["n2_factor"][b] * np.exp(-c[b] * z / 100.0) / true["immersion_factor"][b]
                                  for b in BANDS})
            for _ in range(FRAMES_PER_LEVEL):
                frames.append(FrameSpec(lens, "signal", ISO, EXPOSURE_S,
                                        {"condition": "water", "water_height_cm": float(z)},
                                        source, medium="water", light_factor=factor))
    truth = {**true, "attenuation_per_m": c, "absorption_per_m": dict(ABSORPTION_PER_M),
             "scattering_per_m": dict(SCATTERING_PER_M), "source_band_radiance": radiance,
             "band_wavelength_nm": dict(BAND_WAVELENGTH_NM), "water": dict(WATER)}
    return ExperimentPlan(frames, sidecars={"water.yaml": yaml.safe_dump(WATER)}, truth=truth)
