"""The random noise a real lab adds on top of the sensor's own: common to all pixels of a frame.

Unlike the lab's systematic errors (:mod:`pipeline.simulate.lab_errors`,
one draw per dataset), these change from frame to frame, and they are shared
by every pixel of a frame, so that the rows of one frame (lens x band) are
not independent measurements:

* source flicker: the lab source's output is multiplied by ``1 + f`` with
  ``f ~ N(0, flicker_rel_sigma)`` drawn per frame (white); a stabilised
  quartz-tungsten-halogen lamp behind an integrating sphere holds its output
  to a few 0.1 % over seconds;
* source drift: a slow multiplicative drift over each experiment,
  ``drift_rel_amplitude * sin(2 pi (u / period + phase))`` with ``u`` the
  frame's position in the experiment (0 to 1), a random phase per
  experiment and ``drift_period_experiments`` experiment lengths per cycle
  (a lamp settling and the room's air conditioning);
* bias jitter: an additive black-level offset ``N(0, bias_jitter_dn)`` common
  to the whole frame (both lenses), well below the catalogue's ``bias_drift``
  effect (default 3 DN);
* room-temperature drift: the room (and with it the logged sensor
  temperature) drifts slowly over the session, ``room_drift_c *
  sin(2 pi t / room_period_s + phase)`` with ``t`` the lab clock since the
  first frame; the black level follows it by ``bias_dn_per_room_c`` DN per
  degree C (a tenth of the ``temperature`` effect's hidden-effect test value).

Flicker and drift apply to the lab's own sources only, not to the field's
sky. All draws come from their own random stream ([seed, STREAM, experiment]),
so that switching the lab noise on changes no other draw of the simulator.
The sizes are written to the truth folder (``lab_noise``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

#: the draws' own random stream: [seed, this, experiment id]
STREAM = 52711


@dataclass(frozen=True)
class LabNoise:
    """Sizes of the lab's frame-to-frame noise; :func:`no_lab_noise` switches it off."""

    #: white flicker of the lab source, relative sigma per frame
    flicker_rel_sigma: float = 0.002
    #: slow drift of the lab source over an experiment, relative amplitude
    drift_rel_amplitude: float = 0.002
    #: period of the slow drift, in experiment lengths
    drift_period_experiments: float = 2.0
    #: additive black-level offset common to a frame, sigma (DN)
    bias_jitter_dn: float = 0.3
    #: amplitude of the room-temperature drift over the session (degree C)
    room_drift_c: float = 0.5
    #: period of the room-temperature drift (s): an air-conditioning cycle
    room_period_s: float = 3600.0
    #: black-level change per degree C of room temperature (DN degree_C-1)
    bias_dn_per_room_c: float = 0.04

    def truth(self) -> dict:
        """The sizes as written to the truth folder (``lab_noise``).

        Returns
        -------
        dict
            Field name -> size (relative, DN, degree C or s, as each field states).
        """
        return asdict(self)


def no_lab_noise() -> LabNoise:
    """A lab without frame-to-frame noise: every size zero.

    Returns
    -------
    LabNoise
        Flicker, drift, bias jitter, room drift and its bias coefficient all zero.
    """
    return LabNoise(flicker_rel_sigma=0.0, drift_rel_amplitude=0.0, bias_jitter_dn=0.0, room_drift_c=0.0,
                    bias_dn_per_room_c=0.0)


@dataclass
class FrameNoise:
    """The lab noise drawn for every frame of one experiment."""

    light_factor: np.ndarray     # multiplies the lab source's radiance (1 = none)
    bias_offset_dn: np.ndarray   # added to the black level of the whole frame (DN)


def draw_frame_noise(noise: LabNoise, seed: int, experiment_id: int, n_frames: int) -> FrameNoise:
    """Flicker, drift and bias jitter of the ``n_frames`` frames of one experiment, in acquisition order.

    Drawn from ``numpy.random.default_rng([seed, STREAM, experiment_id])``.

    Parameters
    ----------
    noise : LabNoise
        The sizes.
    seed : int
        The dataset's seed.
    experiment_id : int
        The experiment's number (1-based, acquisition order).
    n_frames : int
        Frames of the experiment.

    Returns
    -------
    FrameNoise
        Per frame: the factor on the lab source's radiance, (1 + drift)(1 + flicker), dimensionless, and the
        black-level offset of the whole frame, DN.
    """
    rng = np.random.default_rng([seed, STREAM, experiment_id])
    u = np.arange(n_frames) / max(n_frames, 1)
    phase = rng.uniform()
    drift = noise.drift_rel_amplitude * np.sin(2 * np.pi * (u / noise.drift_period_experiments + phase))
    flicker = noise.flicker_rel_sigma * rng.standard_normal(n_frames)
    jitter = noise.bias_jitter_dn * rng.standard_normal(n_frames)
    return FrameNoise(light_factor=(1.0 + drift) * (1.0 + flicker), bias_offset_dn=jitter)


def room_phase(seed: int) -> float:
    """Phase (0 to 1) of the room-temperature cycle at the session's first frame.

    Parameters
    ----------
    seed : int
        The dataset's seed.

    Returns
    -------
    float
        The phase, in cycles.
    """
    return float(np.random.default_rng([seed, STREAM]).uniform())


def room_temperature_offset_c(noise: LabNoise, seed: int, elapsed_s: float) -> float:
    """Room-temperature departure (degree C) ``elapsed_s`` after the session's first frame.

    Parameters
    ----------
    noise : LabNoise
        The sizes (``room_drift_c``, ``room_period_s``).
    seed : int
        The dataset's seed (the cycle's phase, :func:`room_phase`).
    elapsed_s : float
        Lab-clock time since the first frame, s.

    Returns
    -------
    float
        ``room_drift_c`` sin(2 pi (elapsed_s / room_period_s + phase)), degree C.
    """
    return float(noise.room_drift_c * np.sin(2 * np.pi * (elapsed_s / noise.room_period_s + room_phase(seed))))
