"""Dark-frame and linearity experiments (Sections 2.2 and 2.8)."""

from __future__ import annotations

import numpy as np

from pipeline.io.bands import BANDS
from pipeline.simulate.absolute import lens_band_radiance
from pipeline.simulate.camera import DarkPlan, LinearityPlan
from pipeline.simulate.plan import ExperimentPlan, FrameSpec, SimContext, planner


@planner("dark")
def plan_dark(ctx: SimContext) -> ExperimentPlan:
    """Plan the dark-frame experiment: both lenses capped, every (ISO, exposure) setting of the dark plan.

    Parameters
    ----------
    ctx : SimContext
        The simulation (the scale's dark frames per setting; the generator of the logged temperature).

    Returns
    -------
    ExperimentPlan
        The dark frames, each with the sensor temperature logged to 0.01 deg C (a sensor warming up during the
        session).
    """
    plan = DarkPlan(frames_per_setting=ctx.scale.dark_frames)
    frames = [FrameSpec("both", "dark", iso, t)
              for iso, t in plan.settings() for _ in range(plan.frames_per_setting)]
    _log_temperature(ctx, frames)
    return ExperimentPlan(frames)


def _log_temperature(ctx: SimContext, frames: list[FrameSpec], start_c: float = 22.0,
                     rise_c: float = 8.0, noise_c: float = 0.1) -> None:
    """A sensor warming up during the session (first-order rise), logged to 0.01 C."""
    n = len(frames)
    i = np.arange(n)
    temp = start_c + rise_c * (1.0 - np.exp(-i / max(0.4 * n, 1.0))) + noise_c * ctx.rng.standard_normal(n)
    for spec, t in zip(frames, temp):
        spec.temperature_c = round(float(t), 2)


@planner("linearity")
def plan_linearity(ctx: SimContext) -> ExperimentPlan:
    """Both sweeps for each lens in turn, the integrating sphere filling the field.

    The exposure sweep at one ISO and the gain sweep at one exposure, each setting repeated the scale's
    linearity frames per setting.

    Parameters
    ----------
    ctx : SimContext
        The simulation (the camera's sphere radiance, the scale, the generator of the logged temperature).

    Returns
    -------
    ExperimentPlan
        The signal frames (``sweep`` column ``exposure`` or ``gain``, temperature logged) and the truth: the
        source's band radiance in each sweep, W m-2 sr-1 nm-1.
    """
    plan = LinearityPlan(frames_per_setting=ctx.scale.linearity_frames)
    sphere = ctx.camera.radiometry.sphere_band_radiance
    # per lens: the sphere's lamp through each lens's true response (absolute.lens_band_radiance)
    exposure_source = {lens: lens_band_radiance(ctx.camera, lens, {b: plan.exposure_source_fraction * sphere[b]
                                                                   for b in BANDS})
                       for lens in ctx.camera.lens_names}
    gain_source = {lens: lens_band_radiance(ctx.camera, lens, {b: plan.gain_source_fraction * sphere[b] for b in BANDS})
                   for lens in ctx.camera.lens_names}
    frames = []
    for lens in ctx.camera.lens_names:
        for t in plan.exposures_s:
            frames += [FrameSpec(lens, "signal", plan.exposure_sweep_iso, t, {"sweep": "exposure"},
                                 exposure_source[lens]) for _ in range(plan.frames_per_setting)]
        for iso in plan.isos:
            frames += [FrameSpec(lens, "signal", iso, plan.gain_sweep_exposure_s, {"sweep": "gain"},
                                 gain_source[lens]) for _ in range(plan.frames_per_setting)]
    _log_temperature(ctx, frames)
    return ExperimentPlan(frames, truth={"exposure_source_band_radiance": exposure_source,
                                         "gain_source_band_radiance": gain_source})
