"""Catalogue effects injected in forms the package does not use, by rewriting a dataset's raw files.

Each form takes a dataset simulated WITHOUT the effect (dark and linearity experiments), reads every
raw frame with :func:`pipeline.io.rawio.read_raw`, changes the CFA mosaic by its own physics and writes
it back with :func:`pipeline.io.rawio.write_dng`, keeping every tag (exposure, ISO, time, black and white
levels, pattern, make, model, serial); ``MD5SUMS`` is rewritten after. None of these shapes is the
simulator's or the pipeline's own (``pipeline.effects.catalogue``): a signature that finds them is not
just recognising its own forward code (docs/design.md, "Closure and diagnostics").

A form is called as ``FORMS[name].inject(root, amplitude, conversion_gain_dn_per_e_iso100, seed)``;
``amplitude`` is the form's own parameter (documented on each), ``FORMS[name].amplitudes`` gives two
values, a clear one and one near the tiny dataset's detection limit, for the detection benchmark.
The conversion gain is the simulated camera's (the truth's ``derived`` entry): a form that adds
electrons needs it to draw their shot noise.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
import yaml
from scipy.optimize import brentq

from pipeline.io.dataset import write_md5sums
from pipeline.io.rawio import read_raw, write_dng

#: experiments the forms rewrite by default (the foundation stages' data)
EXPERIMENTS = ("dark", "linearity")
#: experiments whose frames a form may rewrite
REWRITABLE = ("dark", "linearity", "rolloff")


@dataclass
class FrameInfo:
    """What a form may know about one frame: its tags, its frames.csv row and its place in the session."""

    experiment: str
    row: dict
    exposure_s: float
    iso: float
    time_s: float              # seconds since the session's first frame
    session_fraction: float    # 0 at the first frame of the session, 1 at the last
    black_level: float
    full_scale_dn: float       # white level less black level
    lenses: dict               # lens -> (row slice, column slice) in the raw frame


def _lens_slices(root: Path) -> dict:
    meta = yaml.safe_load((root / "dataset.yaml").read_text())
    return {lens: (slice(*spec["rows"]), slice(*spec["cols"])) for lens, spec in meta["lenses"].items()}


def rewrite_frames(root, change: Callable[[np.ndarray, FrameInfo], np.ndarray], experiments=EXPERIMENTS) -> int:
    """Apply ``change(signal_dn, info) -> signal_dn`` to every raw frame of ``experiments`` in ``root``;
    returns the count of frames rewritten.

    ``signal_dn`` is the mosaic less the black-level tag (float64, both lenses); the result is put back
    on the black level, rounded and clipped to 0..white level like an ADC. Pixels at the white level
    stay there (a saturated pixel carries no information a form could bend).
    """
    root = Path(root)
    lenses = _lens_slices(root)
    tables = {exp: pd.read_csv(root / exp / "frames.csv") for exp in REWRITABLE if (root / exp).is_dir()}
    raws = {exp: [read_raw(root / exp / f) for f in t["file"]] for exp, t in tables.items()}
    times = [r.time for rs in raws.values() for r in rs]
    t0, t1 = min(times), max(times)
    span = max((t1 - t0).total_seconds(), 1e-9)
    count = 0
    for exp, table in tables.items():
        if exp not in experiments:
            continue
        for row, raw in zip(table.to_dict("records"), raws[exp]):
            elapsed = (raw.time - t0).total_seconds()
            info = FrameInfo(exp, row, float(raw.exposure_s), float(raw.iso), elapsed, elapsed / span,
                             raw.black_level, raw.white_level - raw.black_level, lenses)
            saturated = raw.cfa >= raw.white_level
            signal = change(raw.cfa.astype(np.float64) - raw.black_level, info)
            dn = np.clip(np.rint(signal + raw.black_level), 0, raw.white_level)
            dn[saturated] = raw.white_level
            write_dng(raw.path, dn.astype(np.uint16), exposure_s=raw.exposure_s, iso=raw.iso, time=raw.time,
                      black_level=raw.black_level, white_level=raw.white_level, cfa_pattern=raw.cfa_pattern,
                      make=raw.make, model=raw.model, serial=raw.serial)
            count += 1
    write_md5sums(root)
    return count


def _rng(name: str, seed: int) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(name.encode())])


def _gain(info: FrameInfo, k100: float) -> float:
    return k100 * info.iso / 100.0


# --------------------------------------------------------------------------- the forms


def nonlinearity_tanh(root, amplitude, k100, seed):
    """Soft saturation per raw pixel: ``s -> F tanh(s / F)``, applied to every pixel's signal.

    An amplifier that compresses smoothly towards its rails. ``amplitude`` is the relative deficit at
    full scale, 1 - tanh(x0)/x0 with x0 = full_scale / F. The leading bend is cubic (s^3 / 3F^2), not
    the package's quadratic s^2 / full_scale: at half scale it loses a quarter of the full-scale
    deficit where the quadratic loses half. Only the linearity frames are rewritten: the dark frames'
    signals (under 100 DN) would bend by under 1e-4 DN.
    """
    d = float(amplitude)
    x0 = brentq(lambda x: 1.0 - np.tanh(x) / x - d, 1e-6, 20.0)

    def change(s, info):
        f = info.full_scale_dn / x0
        return f * np.tanh(s / f)

    return rewrite_frames(root, change, ("linearity",))


def shutter_offset_per_lens(root, amplitude, k100, seed):
    """True exposure = nominal + an offset of each lens's own shutter: ``amplitude`` s on the far lens,
    a third of it on the close lens.

    The two lenses are two sensors read out on their own; the package fits one offset shared by both.
    The extra light is the frame's own photo-signal times offset / t (its shot noise scaled with it,
    a variance (1 + offset/t)^2 instead of 1 + offset/t: under 8 % more at the shortest exposure).
    Dark frames have no light and are left as they are; so are the prnu form's (a flat field acts on
    light, and the dark frames' pixel offsets are a separate pattern).
    """
    offsets = {"far": float(amplitude), "close": float(amplitude) / 3.0}

    def change(s, info):
        if info.experiment != "linearity" or info.row.get("kind") != "signal":
            return s
        for lens, (rows, cols) in info.lenses.items():
            s[rows, cols] *= 1.0 + offsets[lens] / info.exposure_s
        return s

    return rewrite_frames(root, change, ("linearity",))


def prnu_gradient(root, amplitude, k100, seed):
    """Flat field with large-scale structure: a linear gradient of ``amplitude`` relative change per
    lens half-width, in a direction of its own per lens, times pixel noise of half ``amplitude``.

    Dust shadows, a vignetting the roll-off does not share, the microlens shift across the die: a
    smooth part beside the pixel-to-pixel part the package's Gaussian map has. Multiplies the
    whole signal above black of each pixel in the linearity frames, fixed across frames.
    """
    rng = _rng("prnu_gradient", seed)
    maps = {}

    def change(s, info):
        for lens, (rows, cols) in info.lenses.items():
            if lens not in maps:
                n_r, n_c = rows.stop - rows.start, cols.stop - cols.start
                y, x = np.mgrid[0:n_r, 0:n_c]
                u = (x - n_c / 2) / (n_c / 2)
                v = (y - n_r / 2) / (n_r / 2)
                angle = rng.uniform(0, 2 * np.pi)
                smooth = 1.0 + amplitude * (np.cos(angle) * u + np.sin(angle) * v)
                maps[lens] = smooth * (1.0 + 0.5 * amplitude * rng.standard_normal((n_r, n_c)))
            s[rows, cols] *= maps[lens]
        return s

    return rewrite_frames(root, change, ("linearity",))


#: the self-heating sensor's warming (degree C), time constant (s) and dark-current doubling (degree C)
HEATING_C, HEATING_TAU_S, DOUBLING_C = 4.0, 1.0, 6.0


def self_heating_electrons(rate_e_per_s: float, exposure_s: float) -> float:
    """Dark electrons of one exposure of a self-heating sensor (trapezoids on 200 steps)."""
    u = np.linspace(0.0, 1.0, 201) * exposure_s
    rate = 2.0 ** (HEATING_C * (1.0 - np.exp(-u / HEATING_TAU_S)) / DOUBLING_C)
    return float(rate_e_per_s) * float(np.trapezoid(rate, u))


def dark_current_self_heating(root, amplitude, k100, seed):
    """Dark current of ``amplitude`` e-/s at the start of each exposure, doubling every 6 degree C as
    the sensor warms during it: T(u) = T0 + 4 (1 - exp(-u / 1 s)) degree C after u seconds.

    A sensor read out continuously heats itself; the dark electrons of an exposure t are
    r0 * integral_0^t 2^(dT(u) / 6) du (numerically, 200 steps), 1.31 times r0 t at 2 s and 1.19 at 1 s: the package's
    term is linear in t. Poisson electrons per raw pixel, times the frame's conversion gain.
    """
    rng = _rng("dark_current_self_heating", seed)

    def change(s, info):
        n = rng.poisson(self_heating_electrons(amplitude, info.exposure_s), size=s.shape)
        return s + _gain(info, k100) * n

    return rewrite_frames(root, change)


def hot_pixels_pareto(root, amplitude, k100, seed):
    """Hot pixels with a long-tailed (Pareto, index 1.2) rate: a fraction ``amplitude`` of raw pixels
    with rates r_min (1 - U)^(-1/1.2), r_min = 30 e-/s, capped at 2e4 e-/s.

    Radiation damage leaves a power-law population, many weak sites and a few bright ones, where the
    package's simulator draws a log-normal around one median. The weak ones stay below any outlier
    threshold. One map per lens, fixed over the session; Poisson electrons per exposure.
    """
    rng = _rng("hot_pixels_pareto", seed)
    maps = {}

    def change(s, info):
        for lens, (rows, cols) in info.lenses.items():
            if lens not in maps:
                shape = (rows.stop - rows.start, cols.stop - cols.start)
                hot = rng.random(shape) < float(amplitude)
                rate = np.zeros(shape)
                rate[hot] = np.minimum(30.0 * (1.0 - rng.random(int(hot.sum()))) ** (-1 / 1.2), 2e4)
                maps[lens] = rate
            s[rows, cols] += _gain(info, k100) * rng.poisson(maps[lens] * info.exposure_s)
        return s

    return rewrite_frames(root, change)


def bias_drift_ramp(root, amplitude, k100, seed):
    """Black level drifting as a slow ramp over the session, ``amplitude`` DN from the first frame to
    the last (centred on zero), common to the whole frame (corners included).

    The electronics warming up after power-on, not the white frame-to-frame jitter of the package's
    simulator: neighbouring frames share almost the same offset, the settings differ.
    """
    def change(s, info):
        return s + float(amplitude) * (info.session_fraction - 0.5)

    return rewrite_frames(root, change)


def iso_gain_power_law(root, amplitude, k100, seed):
    """Analogue gain that grows as (ISO/100)^(1 - ``amplitude``) instead of ISO/100: a smooth
    compression of the gain ladder (each doubling short by the same fraction), not independent
    random factors per ISO step. Applied to the signal above black (light, dark current and read
    noise alike), ISO 100 unchanged; only the linearity frames (the dark model's gain dependence would
    absorb a smooth law in the dark frames as its b1 and D terms do for the nominal gain).
    """
    def change(s, info):
        return s * (info.iso / 100.0) ** (-float(amplitude))

    return rewrite_frames(root, change, ("linearity",))


def temperature_bias_quadratic(root, amplitude, k100, seed):
    """Black level that follows the logged sensor temperature T along a parabola,
    ``amplitude`` ((T - 22) + (T - 22)^2 / 32) DN with T in degree C (T rises from 22 to about 29 in each
    experiment as the sensor warms): an amplifier offset whose temperature coefficient itself grows
    with temperature, where the package's term is linear in T. Common to the whole frame.
    """
    def change(s, info):
        dt = float(info.row["temperature_c"]) - 22.0
        return s + float(amplitude) * (dt + dt**2 / 32.0)

    return rewrite_frames(root, change)


#: the power-law PSF's core radius (band pixels) and index: K ~ (1 + (r / core)^2)^(-index / 2)
PSF_CORE_BAND_PX, PSF_INDEX = 1.0, 3.0


def power_law_psf(radius_band_px: int) -> np.ndarray:
    """A normalised power-law point-spread kernel on the band grid, (2 radius + 1) pixels square."""
    y, x = np.mgrid[-radius_band_px:radius_band_px + 1, -radius_band_px:radius_band_px + 1]
    k = (1.0 + (x**2 + y**2) / PSF_CORE_BAND_PX**2) ** (-PSF_INDEX / 2.0)
    return k / k.sum()


def stray_light_power_law(root, amplitude, k100, seed):
    """Stray light with power-law wings: a fraction ``amplitude`` of each pixel's light spread by
    K(r) ~ (1 + r^2)^(-3/2) (r in band pixels, out to the lens region's width), the rest kept:
    ``s -> (1 - f) s + f (K * s)``, each colour site convolved on its own grid (the light keeps its colour).

    Scattering by surface roughness and dust gives wings falling as a power of the angle (Wei et al.
    2012 measure the radiance camera's PSF over decades); the package's signature is a Gaussian halo.
    The roll-off frames are rewritten; the spread light carries no shot noise of its own (it is under
    a few per cent of the halo pixels' signal).
    """
    from scipy.signal import fftconvolve

    kernels = {}

    def change(s, info):
        if info.row.get("kind") != "signal":
            return s
        for rows, cols in info.lenses.values():
            region = s[rows, cols]
            n = max(region.shape) // 2
            if n not in kernels:
                kernels[n] = power_law_psf(n)
            for dy in (0, 1):
                for dx in (0, 1):
                    plane = region[dy::2, dx::2]
                    spread = fftconvolve(plane, kernels[n], mode="same")
                    region[dy::2, dx::2] = (1.0 - amplitude) * plane + amplitude * spread
            s[rows, cols] = region
        return s

    return rewrite_frames(root, change, ("rolloff",))


def rolloff_azimuth_illumination_gradient(root, amplitude, k100, seed, phi0_deg=50.0):
    """A decentred optic as an illumination gradient across the image plane: every signal frame of the
    roll-off experiment times 1 + A ((x - x_m) cos phi0 + (y - y_m) sin phi0) / R, x to the right and y down
    in raw pixels of each lens region, (x_m, y_m) the region's middle, R its half width (the image
    circle's radius only roughly: the gradient runs on past the rim). The package's signature is
    A (theta / 90 deg) cos(phi - phi0) in field angle about the fitted centre: the two agree only as far as
    the lens is equidistant and centred in its region. Dark frames are left alone (the source is off)."""

    def change(s, info):
        if info.row.get("kind") != "signal":
            return s
        for rows, cols in info.lenses.values():
            ny, nx = rows.stop - rows.start, cols.stop - cols.start
            y, x = np.mgrid[0:ny, 0:nx].astype(float)
            half = 0.5 * nx
            ramp = ((x - (nx - 1) / 2) * np.cos(np.radians(phi0_deg)) + (y - (ny - 1) / 2) * np.sin(np.radians(phi0_deg)))
            s[rows, cols] = s[rows, cols] * (1.0 + amplitude * ramp / half)
        return s

    return rewrite_frames(root, change, ("rolloff",))


@dataclass(frozen=True)
class Form:
    effect: str                  # the catalogue name the diagnostics should find
    inject: Callable
    amplitudes: tuple            # (clear, near the tiny dataset's detection limit), the form's own units
    units: str
    experiments: tuple = EXPERIMENTS   # the experiments whose frames the form rewrites


FORMS = {
    "nonlinearity_tanh": Form("nonlinearity", nonlinearity_tanh, (0.04, 0.008), "deficit at full scale",
                              ("linearity",)),
    "shutter_offset_per_lens": Form("shutter_offset", shutter_offset_per_lens, (6e-4, 1e-4), "s (far lens)",
                                    ("linearity",)),
    "prnu_gradient": Form("prnu", prnu_gradient, (0.03, 0.01), "relative change per half-width",
                          ("linearity",)),
    "dark_current_self_heating": Form("dark_current", dark_current_self_heating, (1.3, 0.3), "e- s-1"),
    "hot_pixels_pareto": Form("hot_pixels", hot_pixels_pareto, (1e-3, 2e-4), "fraction of raw pixels"),
    "bias_drift_ramp": Form("bias_drift", bias_drift_ramp, (6.0, 1.5), "DN over the session"),
    # clear at 0.02: on the measured-response camera (more far-lens linearity frames saturate) the detectable
    # largest gain error is 0.034, which 0.01 (3.4 % at ISO 3200) only reached; 0.02 gives 6.7 %, twice it
    "iso_gain_power_law": Form("iso_gain", iso_gain_power_law, (0.02, 0.003), "exponent deficit",
                               ("linearity",)),
    "temperature_bias_quadratic": Form("temperature", temperature_bias_quadratic, (0.4, 0.1), "DN degree_C-1"),
    "stray_light_power_law": Form("stray_light", stray_light_power_law, (0.02, 0.005), "fraction spread",
                                  ("rolloff",)),
}
