"""What an experiment's simulation consists of: frames, sidecar files and truth.

An experiment module registers a planner with :func:`planner`; the planner
returns an :class:`ExperimentPlan` (the frames to render in acquisition
order, the sidecar files the lab would write, what only the simulator knows).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from datetime import datetime

import numpy as np

from pipeline.simulate.camera import Camera
from pipeline.simulate.lab_errors import no_lab_errors


@dataclass
class LensGeometry:
    """Where every raw pixel of one lens looks, in one medium (true optics)."""

    theta_deg: np.ndarray
    phi_deg: np.ndarray
    lit: np.ndarray          # inside the image circle

    @cached_property
    def direction(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The unit viewing vector of every raw pixel (sin t cos p, sin t sin p, cos t), computed once per lens
        and medium: a scene called for hundreds of frames of one geometry reads it instead of recomputing it."""
        t, p = np.radians(self.theta_deg), np.radians(self.phi_deg)
        return np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)


@dataclass
class FrameSpec:
    lens: str                 # lens facing the source, or "both"
    kind: str                 # signal or dark
    iso: float
    exposure_s: float
    extra: dict = field(default_factory=dict)   # experiment-specific frames.csv columns
    #: None (no light), {band: radiance} (uniform), or a scene:
    #: scene(lens, LensGeometry, band_index) -> per-raw-pixel effective band radiance
    #: (W sr-1 m-2 nm-1) seen by the camera band of each site
    radiance: dict | Callable | None = None
    medium: str = "air"
    temperature_c: float | None = None
    #: extra factor on the light (e.g. 1/immersion factor in water), per band index or scalar
    light_factor: Callable | float = 1.0
    file: str = ""
    #: camera clock (local time, as DateTimeOriginal) of this frame; None: the simulator's running lab clock
    time: datetime | None = None
    #: lenses the light reaches; None: ``lens`` (both lenses for "both")
    lit: tuple[str, ...] | None = None


@dataclass
class ExperimentPlan:
    frames: list[FrameSpec]
    sidecars: dict[str, str] = field(default_factory=dict)   # path relative to the experiment -> text
    truth: dict = field(default_factory=dict)


@dataclass
class SimContext:
    camera: Camera
    scale: object             # simulate.dataset.Scale
    seed: int
    rng: np.random.Generator  # static draws of the planners (deterministic per seed)
    effects: list = field(default_factory=list)   # the true effects switched on (pipeline.effects objects)
    #: the lab's systematic errors of this dataset (:mod:`pipeline.simulate.lab_errors`); all zero: a perfect lab
    lab_errors: dict = field(default_factory=no_lab_errors)


PLANNERS: dict[str, Callable[[SimContext], ExperimentPlan]] = {}


def planner(name: str):
    """Decorator registering the planner of experiment ``name``.

    Parameters
    ----------
    name : str
        The experiment (``dark``, ``linearity``, ...): the key of :data:`PLANNERS`.

    Returns
    -------
    callable
        The decorator: it registers a planner ``fn(SimContext) -> ExperimentPlan`` and returns it unchanged.
    """
    def wrap(fn):
        PLANNERS[name] = fn
        return fn
    return wrap
