"""Write a simulated calibration dataset (DATASET.md layout) and its truth folder."""

from __future__ import annotations

import shutil
from dataclasses import asdict, dataclass
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from pipeline import __version__
from pipeline.camera import BANDS, Camera, DarkPlan, LinearityPlan
from pipeline.dataset import write_md5sums
from pipeline.effects import get as get_effect
from pipeline.errors import InputError
from pipeline.rawio import write_dng
from pipeline.simulate import optics
from pipeline.simulate.sensor import draw_static_pattern, expose


@dataclass(frozen=True)
class Scale:
    """How big a simulated dataset is: lens region size (raw pixels) and frame counts."""

    name: str
    lens_px: int
    dark_frames: int
    linearity_frames: int


SCALES = {
    # tests: seconds to write, still 64 x 64 band pixels per lens
    "tiny": Scale("tiny", lens_px=128, dark_frames=5, linearity_frames=4),
    # the default run
    "small": Scale("small", lens_px=576, dark_frames=15, linearity_frames=4),
    # the real camera: 6912 x 3456 frames, the paper's frame counts
    "full": Scale("full", lens_px=3456, dark_frames=15, linearity_frames=4),
}

EXPERIMENTS = ("dark", "linearity")
START_TIME = datetime(2021, 3, 10, 9, 0, 0)
#: seconds between the end of one exposure and the start of the next
FRAME_INTERVAL_S = 1.5


def truth_dir_for(dataset: str | Path) -> Path:
    """The truth folder of a simulated dataset: beside it, never inside."""
    dataset = Path(dataset)
    return dataset.parent / f"{dataset.name}.truth"


@dataclass
class FrameSpec:
    file: str
    lens: str             # lens facing the source, or "both"
    kind: str             # signal or dark
    iso: float
    exposure_s: float
    extra: dict           # experiment-specific frames.csv columns
    radiance: dict | None  # band -> effective band radiance (W sr-1 m-2 nm-1) seen by `lens`


def _plan_dark(scale: Scale) -> list[FrameSpec]:
    plan = DarkPlan(frames_per_setting=scale.dark_frames)
    out = []
    for iso, t in plan.settings():
        for _ in range(plan.frames_per_setting):
            out.append(FrameSpec("", "both", "dark", iso, t, {}, None))
    return out


def _plan_linearity(scale: Scale, camera: Camera) -> list[FrameSpec]:
    plan = LinearityPlan(frames_per_setting=scale.linearity_frames)
    sphere = camera.radiometry.sphere_band_radiance
    out = []
    for lens in camera.lens_names:
        exposure_source = {b: plan.exposure_source_fraction * sphere[b] for b in BANDS}
        gain_source = {b: plan.gain_source_fraction * sphere[b] for b in BANDS}
        for t in plan.exposures_s:
            for _ in range(plan.frames_per_setting):
                out.append(FrameSpec("", lens, "signal", plan.exposure_sweep_iso, t,
                                     {"sweep": "exposure"}, exposure_source))
        for iso in plan.isos:
            for _ in range(plan.frames_per_setting):
                out.append(FrameSpec("", lens, "signal", iso, plan.gain_sweep_exposure_s,
                                     {"sweep": "gain"}, gain_source))
    return out


class _Renderer:
    """Holds the per-lens static maps and turns a FrameSpec into a raw frame."""

    def __init__(self, camera: Camera, scale: Scale, seed: int, effects):
        self.camera = camera
        self.scale = scale
        self.seed = seed
        self.effects = effects
        n = scale.lens_px
        self.shape = (n, n)
        static = np.random.default_rng([seed, 7919])
        context = {"lens_names": camera.lens_names, "lens_shape": self.shape}
        for effect in effects:
            effect.prepare(static, context)
        self.patterns = {lens: draw_static_pattern(static, self.shape, camera.sensor)
                         for lens in camera.lens_names}
        # CFA site -> band index for RGGB
        site = np.empty((2, 2), dtype=np.int8)
        site[0, 0], site[0, 1], site[1, 0], site[1, 1] = 0, 1, 1, 2
        self.band_index = np.tile(site, (n // 2, n // 2))
        k100 = camera.sensor.conversion_gain_dn_per_e_iso100
        resp_e = np.array([camera.radiometry.responsivity_dn_s_per_radiance[b] / k100 for b in BANDS])
        from pipeline.radiometry.rolloff import default_rolloff, evaluate_rolloff

        self.unit_rate = {}
        for lens in camera.lens_names:
            theta = optics.theta_map_deg(lens, n)
            lit = optics.lit_mask(theta, "air")
            rate = np.zeros(self.shape)
            for b, band in enumerate(BANDS):
                g = evaluate_rolloff(default_rolloff(band, "air"), np.minimum(theta, optics.HALF_FOV_DEG["air"]))
                sel = self.band_index == b
                rate[sel] = resp_e[b] * g[sel]
            self.unit_rate[lens] = rate * lit   # e-/s per unit band radiance

    def render(self, index: int, experiment_id: int, spec: FrameSpec) -> np.ndarray:
        rng = np.random.default_rng([self.seed, experiment_id, index])
        offset = sum(e.frame_offset_dn(rng) for e in self.effects)
        n = self.scale.lens_px
        frame = np.empty((2 * n, n), dtype=np.uint16)
        for row, lens in enumerate(self.camera.lens_names):
            if spec.radiance is not None and spec.lens in (lens, "both"):
                lbar = np.array([spec.radiance[b] for b in BANDS])
                photo = self.unit_rate[lens] * lbar[self.band_index]
            else:
                photo = 0.0
            frame[row * n:(row + 1) * n] = expose(
                rng, lens=lens, photo_rate_e_per_s=photo, exposure_s=spec.exposure_s, iso=spec.iso,
                sensor=self.camera.sensor, pattern=self.patterns[lens], effects=self.effects,
                frame_offset_dn=offset, shape=self.shape)
        return frame


def simulate_dataset(out: str | Path, scale: str = "small", seed: int = 0,
                     effects: list[tuple[str, dict]] = (), experiments=EXPERIMENTS,
                     progress: bool = True) -> Path:
    """Simulate the calibration experiments into ``out`` (which must not exist yet).

    The dataset is written to a temporary sibling folder and renamed at the
    end, so a crash never leaves a half-written dataset; the truth goes to
    :func:`truth_dir_for` ``(out)``.
    """
    out = Path(out)
    truth = truth_dir_for(out)
    if scale not in SCALES:
        raise InputError(None, f"unknown scale '{scale}'; choose one of {', '.join(SCALES)}")
    for path in (out, truth):
        if path.exists():
            raise InputError(path, "already exists; the simulator never overwrites a folder (remove it or choose --out)")
    unknown = [e for e in experiments if e not in EXPERIMENTS]
    if unknown:
        raise InputError(None, f"the simulator does not write {', '.join(unknown)} yet; it writes {', '.join(EXPERIMENTS)}")
    sc = SCALES[scale]
    camera = Camera()
    effect_objs = [get_effect(name, **params) for name, params in effects]
    renderer = _Renderer(camera, sc, seed, effect_objs)

    tmp = out.parent / f".{out.name}.partial"
    tmp_truth = out.parent / f".{truth.name}.partial"
    for path in (tmp, tmp_truth):
        if path.exists():
            shutil.rmtree(path)
    tmp.mkdir(parents=True)
    tmp_truth.mkdir(parents=True)

    plans = {"dark": lambda: _plan_dark(sc), "linearity": lambda: _plan_linearity(sc, camera)}
    all_specs = {exp: plans[exp]() for exp in experiments}
    total = sum(len(v) for v in all_specs.values())
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, unit="frame", desc=f"simulating {scale} dataset", leave=False,
                   disable=None)
    clock = START_TIME
    try:
        for exp_id, exp in enumerate(experiments):
            (tmp / exp / "raw").mkdir(parents=True)
            rows = []
            for i, spec in enumerate(all_specs[exp]):
                spec.file = f"raw/IMG_{clock:%Y%m%d_%H%M%S}_{i:05d}.dng"
                frame = renderer.render(i, exp_id + 1, spec)
                write_dng(tmp / exp / spec.file, frame, exposure_s=spec.exposure_s, iso=spec.iso,
                          time=clock, black_level=round(camera.sensor.bias_dn),
                          white_level=camera.sensor.adc_max_dn, cfa_pattern="RGGB",
                          make=camera.make, model=camera.model, serial=camera.serial)
                rows.append({"file": spec.file, "lens": spec.lens, "kind": spec.kind, **spec.extra})
                clock += timedelta(seconds=spec.exposure_s + FRAME_INTERVAL_S)
                if bar is not None:
                    bar.update()
            pd.DataFrame(rows).to_csv(tmp / exp / "frames.csv", index=False)
        n = sc.lens_px
        meta = {
            "layout": 1,
            "camera": {"make": camera.make, "model": camera.model, "serial": camera.serial},
            "lenses": {lens: {"rows": [i * n, (i + 1) * n], "cols": [0, n]}
                       for i, lens in enumerate(camera.lens_names)},
            "chessboard": {"inner_corners": [8, 6], "square_mm": {"air": 30.0, "water": 20.0}},
            "description": f"simulated dataset, scale {scale}, seed {seed}",
        }
        (tmp / "dataset.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
        write_md5sums(tmp)
        _write_truth(tmp_truth, camera, sc, seed, effect_objs, experiments)
    finally:
        if bar is not None:
            bar.close()
    tmp.rename(out)
    tmp_truth.rename(truth)
    return out


def _write_truth(folder: Path, camera: Camera, scale: Scale, seed: int, effects, experiments) -> None:
    s = camera.sensor
    k100 = s.conversion_gain_dn_per_e_iso100
    truth = {
        "pipeline_version": __version__,
        "scale": asdict(scale),
        "seed": seed,
        "experiments": list(experiments),
        "camera": camera.to_dict(),
        "effects": {e.name: e.truth() for e in effects},
        "derived": {
            "bias_dn": s.bias_dn,
            "conversion_gain_dn_per_e_iso100": k100,
            "gain_e_per_dn_iso100": 1.0 / k100,
            "read_noise_e": s.read_noise_e,
            # temporal noise of one raw pixel in the dark at ISO 100 and zero exposure:
            # amplified read noise plus rounding to integers
            "read_noise_dn_iso100": float(np.sqrt((k100 * s.read_noise_e) ** 2 + 1 / 12)),
            "saturation_dn": float(s.adc_max_dn - s.bias_dn),
        },
    }
    if any(e.name == "dark_current" for e in effects):
        dc = next(e for e in effects if e.name == "dark_current")
        truth["derived"]["dark_current_dn_per_s_iso100"] = dc.params["rate_e_per_s"] * k100
    (folder / "truth.yaml").write_text(yaml.safe_dump(truth, sort_keys=False))
