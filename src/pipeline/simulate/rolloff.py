"""Roll-off experiment (Larouche et al. 2024, Section 2.4; Fig. 1(a)).

The camera rotates in front of the integrating-sphere port, in two azimuth
planes (0 and 90 deg), every 5 deg from -80 to 80 deg in air and every 2 deg
from -70 to 70 deg in water (port against the tank wall). A rotation by
``angle_deg`` puts the port at field angle theta = |angle| and camera azimuth
phi = azimuth (angle >= 0) or azimuth + 180 (angle < 0). In water the light
reaching the lens is divided by the immersion factor of each band. Dark
frames with the same settings are taken in each medium.
"""

from __future__ import annotations

import numpy as np

from pipeline.io.bands import BANDS
from pipeline.geometry.scaramuzza import FisheyeModel
from pipeline.simulate.geometry import band_model, true_raw_models
from pipeline.simulate.immersion import true_immersion_factors
from pipeline.simulate.absolute import lens_band_radiance
from pipeline.simulate.lens import HALF_FOV_DEG, RAW_SIZE_PX, default_model, default_rolloff
from pipeline.simulate.plan import ExperimentPlan, FrameSpec, SimContext, planner

ANGLES_DEG = {"air": np.arange(-80.0, 80.0 + 1e-9, 5.0), "water": np.arange(-70.0, 70.0 + 1e-9, 2.0)}
AZIMUTHS_DEG = (0.0, 90.0)
MEDIA = ("air", "water")
#: angular radius of the port at the full scale (2.54 cm port seen from ~40 cm: about 1.8 deg)
PORT_RADIUS_FULL_DEG = 1.8
#: the paper's averaging circle (Section 2.4), raw pixels of the full-resolution lens image
#: (the stage's default ``rolloff.spot_radius_deg`` is the same circle in degrees)
SPOT_RADIUS_PX_FULL = 15.0
EXPOSURE_S = 0.18
ISO = 100.0
FRAMES_PER_SETTING = 2
DARK_FRAMES = 40


def port_radius_deg(band_px: int, medium: str) -> float:
    """Port radius: 1.8 deg, or enough to cover the averaging circle plus one band pixel on coarse images."""
    model = default_model("close", medium, (band_px, band_px))
    deg_per_px = HALF_FOV_DEG[medium] / model.image_circle_radius()
    spot_px = max(1.0, SPOT_RADIUS_PX_FULL * band_px / RAW_SIZE_PX)
    return max(PORT_RADIUS_FULL_DEG, (spot_px + 1.0) * deg_per_px)


def port_direction(angle_deg: float, azimuth_deg: float) -> tuple[float, float]:
    """(theta, phi) of the port in camera coordinates for a signed rotation in an azimuth plane."""
    return abs(angle_deg), azimuth_deg if angle_deg >= 0 else azimuth_deg + 180.0


class PortScene:
    """A uniform disc of band radiance ``radiance`` centred on (theta, phi) with angular radius ``radius_deg``."""

    def __init__(self, radiance: dict, theta_deg: float, phi_deg: float, radius_deg: float):
        self.radiance = np.array([radiance[b] for b in BANDS])
        t, p = np.radians(theta_deg), np.radians(phi_deg)
        self.axis = np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])
        self.cos_radius = np.cos(np.radians(radius_deg))

    def __call__(self, lens, geo, band_index):
        x, y, z = geo.direction
        cos_d = x * self.axis[0] + y * self.axis[1] + z * self.axis[2]
        return np.where(cos_d >= self.cos_radius, self.radiance[band_index], 0.0)


class BandFactor:
    """light_factor callable: one factor per band index."""

    def __init__(self, factors: dict):
        self.values = np.array([factors[b] for b in BANDS])

    def __call__(self, band_index):
        return self.values[band_index]


@planner("rolloff")
def plan_rolloff(ctx: SimContext) -> ExperimentPlan:
    band_px = ctx.scale.lens_px // 2
    sphere = ctx.camera.radiometry.sphere_band_radiance
    immersion = true_immersion_factors()
    frames = []
    radii = {}
    for medium in MEDIA:
        radius = port_radius_deg(band_px, medium)
        radii[medium] = radius
        factor = 1.0 if medium == "air" else BandFactor({b: 1.0 / immersion["immersion_factor"][b] for b in BANDS})
        for _ in range(DARK_FRAMES):
            frames.append(FrameSpec("both", "dark", ISO, EXPOSURE_S,
                                    {"medium": medium, "azimuth_deg": "", "angle_deg": ""}, None, medium=medium))
        for lens in ctx.camera.lens_names:
            for az in AZIMUTHS_DEG:
                for angle in ANGLES_DEG[medium][::ctx.scale.rolloff_angle_stride]:
                    theta, phi = port_direction(float(angle), az)
                    scene = PortScene(lens_band_radiance(ctx.camera, lens, sphere), theta, phi, radius)
                    for _ in range(FRAMES_PER_SETTING):
                        frames.append(FrameSpec(lens, "signal", ISO, EXPOSURE_S,
                                                {"medium": medium, "azimuth_deg": az, "angle_deg": float(angle)},
                                                scene, medium=medium, light_factor=factor))
    truth = {
        "rolloff_coefficients": {lens: {m: {b: default_rolloff(b, m, lens).tolist() for b in BANDS} for m in MEDIA}
                                 for lens in ctx.camera.lens_names},
        "port_radius_deg": radii,
        "immersion_factor": immersion["immersion_factor"],
        "exposure_s": EXPOSURE_S, "iso": ISO, "frames_per_setting": FRAMES_PER_SETTING,
    }
    return ExperimentPlan(frames, truth=truth)


def true_band_models(lens: str, band_px: int) -> dict[tuple[str, str], FisheyeModel]:
    """The simulator's true optics at each band's CFA site: (medium, band) -> band-image model.

    Each band's raw-pixel optics (:func:`pipeline.simulate.geometry.true_raw_models`, with the lens's
    lateral chromatic aberration), through which every experiment is rendered, seen from the band image:
    the R and B band pixels are single sites a quarter band pixel from the band-pixel centre (the G pixel
    averages two sites around it), :func:`pipeline.simulate.geometry.band_model`. What a per-band geometry
    calibration finds.
    """
    models = {}
    for medium in MEDIA:
        raw = true_raw_models(lens, medium, 2 * band_px)
        for b in BANDS:
            models[(medium, b)] = band_model(raw[b], b)
    return models
