"""Write a simulated calibration dataset (docs/dataset-format.md layout) and its truth folder."""

from __future__ import annotations

import shutil
from dataclasses import asdict, dataclass, replace
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from pipeline import __version__
from pipeline.io.dataset import write_md5sums
from pipeline.effects import get as get_effect
from pipeline.errors import InputError
from pipeline.io.rawio import write_dng
from pipeline.simulate import lab  # noqa: F401  (registers the dark and linearity planners)
from pipeline.simulate import immersion, rolloff  # noqa: F401  (registers the roll-off and immersion planners)
from pipeline.simulate import absolute, spectral  # noqa: F401  (registers the spectral and absolute planners)
from pipeline.simulate import geometry  # noqa: F401  (registers the geometry planner)
from pipeline.simulate import field  # noqa: F401  (registers the field planner)
from pipeline.simulate.camera import Camera, RadiometricParams, SensorParams
from pipeline.simulate.lab_errors import draw_lab_errors, no_lab_errors
from pipeline.simulate.lab_noise import LabNoise, draw_frame_noise, no_lab_noise, room_temperature_offset_c
from pipeline.simulate.plan import PLANNERS, SimContext
from pipeline.simulate.render import Renderer


@dataclass(frozen=True)
class Scale:
    """How big a simulated dataset is: lens region size (raw pixels) and frame counts."""

    name: str
    lens_px: int
    dark_frames: int
    linearity_frames: int
    #: every k-th rotation angle of the roll-off experiment in each medium (1: the paper's every 5 deg
    #: in air and 2 deg in water; a benchmark's subset of the positions, dark frames unchanged)
    rolloff_angle_stride: int = 1


SCALES = {
    # tests: seconds to write, still 64 x 64 band pixels per lens
    "tiny": Scale("tiny", lens_px=128, dark_frames=5, linearity_frames=4),
    # the default run
    "small": Scale("small", lens_px=576, dark_frames=15, linearity_frames=4),
    # geometry accuracy test: a third of the real resolution (576-px band images), where
    # 0.1 degree is ~0.3 band px at the rim; meant for the geometry experiment only
    "medium": Scale("medium", lens_px=1152, dark_frames=5, linearity_frames=4),
    # the real camera: 6912 x 3456 frames, the paper's frame counts
    "full": Scale("full", lens_px=3456, dark_frames=15, linearity_frames=4),
}

#: experiments simulated by default, in acquisition order
EXPERIMENTS = ("dark", "linearity", "geometry", "rolloff", "spectral", "absolute", "immersion", "field")
START_TIME = datetime(2021, 3, 10, 9, 0, 0)
#: seconds between the end of one exposure and the start of the next
FRAME_INTERVAL_S = 1.5


def truth_dir_for(dataset: str | Path) -> Path:
    """The truth folder of a simulated dataset: beside it, never inside.

    Parameters
    ----------
    dataset : str or pathlib.Path
        The simulated dataset's folder.

    Returns
    -------
    pathlib.Path
        ``<dataset>.truth`` in the same parent folder.
    """
    dataset = Path(dataset)
    return dataset.parent / f"{dataset.name}.truth"


def simulate_dataset(out: str | Path, scale: str | Scale = "small", seed: int = 0,
                     effects: list[tuple[str, dict]] = (), experiments=EXPERIMENTS,
                     progress: bool = True, sensor: dict | None = None, lab_errors: bool = False,
                     lab_noise: bool | LabNoise = False, sensitivity_factor: float = 1.0) -> Path:
    """Simulate the calibration experiments into ``out`` (which must not exist yet).

    The dataset is written to a temporary sibling folder and renamed at the
    end, so a crash never leaves a half-written dataset; the truth goes to
    :func:`truth_dir_for` ``(out)``.

    Parameters
    ----------
    out : str or pathlib.Path
        The dataset folder to write; neither it nor its truth folder may exist.
    scale : str or Scale, optional
        A name of :data:`SCALES` (tiny, small, medium, full) or a :class:`Scale` (e.g. the full lens region with
        fewer frames per setting, for a benchmark); the scale's ``name`` chooses the chessboard and the geometry
        frame count. Default ``small``.
    seed : int, optional
        Seed of every random draw (noise, effects, lab errors); default 0.
    effects : list of tuple of (str, dict), optional
        Effects injected into the frames: (name in the effect catalogue, its parameters); default none.
    experiments : sequence of str, optional
        The experiments to write, in acquisition order; default :data:`EXPERIMENTS` (all eight).
    progress : bool, optional
        Show a progress bar of the frames; default True.
    sensor : dict, optional
        Fields of :class:`~pipeline.simulate.camera.SensorParams` to change from their defaults; default none.
    lab_errors : bool, optional
        Draw the lab's systematic errors (calibration lamp, reference radiometer, photodiode;
        :mod:`pipeline.simulate.lab_errors`) once from the seed and write them to the truth (``lab_errors``);
        default False (a perfect lab).
    lab_noise : bool or LabNoise, optional
        Add the lab's frame-to-frame noise: source flicker and drift, bias jitter, room-temperature drift
        (:mod:`pipeline.simulate.lab_noise`; sizes in the truth, ``lab_noise``); True for the default sizes, or a
        :class:`~pipeline.simulate.lab_noise.LabNoise`. Default False.
    sensitivity_factor : float, optional
        Multiplies the camera's responsivity in every band (DN/s per unit radiance: 1 / 1.03 makes R^-1 3 %
        larger), as a unit of the same model or an aged camera would differ; the truth records it and the
        responsivities it gives (``camera.radiometry``). Positive; default 1.

    Returns
    -------
    pathlib.Path
        ``out``: dataset.yaml, each experiment's frames.csv and DNG frames, sidecars, and MD5SUMS.

    Raises
    ------
    InputError
        For an unknown scale, experiment or sensor parameter, a sensitivity factor not positive, or when ``out``
        or its truth folder exists.
    """
    out = Path(out)
    truth = truth_dir_for(out)
    if not isinstance(scale, Scale) and scale not in SCALES:
        raise InputError(None, f"unknown scale '{scale}'; choose one of {', '.join(SCALES)}")
    for path in (out, truth):
        if path.exists():
            raise InputError(path, "already exists; the simulator never overwrites a folder (remove it or choose --out)")
    unknown = [e for e in experiments if e not in PLANNERS]
    if unknown:
        raise InputError(None, f"the simulator does not write {', '.join(unknown)} yet; "
                               f"it writes {', '.join(PLANNERS)}")
    sc = scale if isinstance(scale, Scale) else SCALES[scale]
    if not sensitivity_factor > 0:
        raise InputError(None, f"sensitivity factor {sensitivity_factor!r} must be positive")
    nominal = RadiometricParams()
    radiometry = replace(nominal, responsivity_dn_s_per_radiance={
        band: value * sensitivity_factor for band, value in nominal.responsivity_dn_s_per_radiance.items()})
    try:
        camera = Camera(sensor=replace(SensorParams(), **(sensor or {})), radiometry=radiometry)
    except TypeError as exc:
        raise InputError(None, f"unknown sensor parameter in {sorted(sensor or {})} ({exc})") from None
    effect_objs = [get_effect(name, **params) for name, params in effects]
    renderer = Renderer(camera, sc.lens_px, seed, effect_objs)
    ctx = SimContext(camera=camera, scale=sc, seed=seed, rng=np.random.default_rng([seed, 104729]),
                     effects=effect_objs, lab_errors=draw_lab_errors(seed) if lab_errors else no_lab_errors())

    tmp, tmp_truth = partial_folders(out, truth)

    plans = {exp: PLANNERS[exp](ctx) for exp in experiments}
    noise = (lab_noise if isinstance(lab_noise, LabNoise) else LabNoise()) if lab_noise else no_lab_noise()
    total = sum(len(p.frames) for p in plans.values())
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, unit="frame", desc=f"simulating {sc.name} dataset", leave=False,
                   disable=None)
    clock = START_TIME
    try:
        for exp_id, exp in enumerate(experiments):
            (tmp / exp / "raw").mkdir(parents=True)
            rows = []
            frame_noise = draw_frame_noise(noise, seed, exp_id + 1, len(plans[exp].frames))
            for i, spec in enumerate(plans[exp].frames):
                # frames that carry their own camera-clock time (the field hour) keep it; the lab
                # experiments follow the running clock
                stamp = spec.time if spec.time is not None else clock
                spec.file = f"raw/IMG_{stamp:%Y%m%d_%H%M%S}_{i:05d}.dng"
                # the lab's sources flicker and drift; the field's sky is not the lab's
                light_scale = float(frame_noise.light_factor[i]) if spec.time is None else 1.0
                bias_offset = float(frame_noise.bias_offset_dn[i])
                if spec.temperature_c is not None and noise.room_drift_c:
                    room_c = room_temperature_offset_c(noise, seed, (clock - START_TIME).total_seconds())
                    spec.temperature_c = round(spec.temperature_c + room_c, 2)
                    bias_offset += noise.bias_dn_per_room_c * room_c
                frame = renderer.render(i, exp_id + 1, spec, light_scale=light_scale, bias_offset_dn=bias_offset)
                write_dng(tmp / exp / spec.file, frame, exposure_s=spec.exposure_s, iso=spec.iso,
                          time=stamp, black_level=round(camera.sensor.bias_dn),
                          white_level=camera.sensor.adc_max_dn, cfa_pattern="RGGB",
                          make=camera.make, model=camera.model, serial=camera.serial)
                row = {"file": spec.file, "lens": spec.lens, "kind": spec.kind, **spec.extra}
                if spec.temperature_c is not None:
                    row["temperature_c"] = round(spec.temperature_c, 2)
                rows.append(row)
                if spec.time is None:
                    clock += timedelta(seconds=spec.exposure_s + FRAME_INTERVAL_S)
                if bar is not None:
                    bar.update()
            pd.DataFrame(rows).to_csv(tmp / exp / "frames.csv", index=False)
            for rel, text in plans[exp].sidecars.items():
                (tmp / exp / rel).write_text(text)
        n = sc.lens_px
        meta = {
            "layout": 1,
            "camera": {"make": camera.make, "model": camera.model, "serial": camera.serial},
            "lenses": {lens: {"rows": [i * n, (i + 1) * n], "cols": [0, n]}
                       for i, lens in enumerate(camera.lens_names)},
            "chessboard": geometry.board_design(sc.name).dataset_entry(),
            "description": f"simulated dataset, scale {sc.name}, seed {seed}",
        }
        (tmp / "dataset.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
        write_md5sums(tmp)
        _write_truth(tmp_truth, camera, sc, seed, effect_objs, experiments,
                     {exp: p.truth for exp, p in plans.items() if p.truth}, ctx.lab_errors, noise, sensitivity_factor)
    finally:
        if bar is not None:
            bar.close()
    tmp.rename(out)
    tmp_truth.rename(truth)
    return out


def _write_truth(folder: Path, camera: Camera, scale: Scale, seed: int, effects, experiments,
                 experiment_truth: dict, lab_errors: dict, lab_noise: LabNoise, sensitivity_factor: float = 1.0) -> None:
    s = camera.sensor
    k100 = s.conversion_gain_dn_per_e_iso100
    truth = {
        "pipeline_version": __version__,
        "scale": asdict(scale),
        "seed": seed,
        "experiments": list(experiments),
        "camera": camera.to_dict(),
        # the responsivities of camera.radiometry are the nominal ones times this factor
        "sensitivity_factor": float(sensitivity_factor),
        "effects": {e.name: e.truth() for e in effects},
        "lab_errors": lab_errors,
        "lab_noise": lab_noise.truth(),
        "experiments_truth": yaml_plain(experiment_truth),
        "derived": {
            "bias_dn": s.bias_dn,
            "conversion_gain_dn_per_e_iso100": k100,
            "gain_e_per_dn_iso100": 1.0 / k100,
            "read_noise_e": s.read_noise_e,
            # temporal noise of one raw pixel in the dark at ISO 100 and zero exposure:
            # amplified read noise plus rounding to integers
            "read_noise_dn_iso100": float(np.sqrt((k100 * s.read_noise_e) ** 2 + 1 / 12)),
            # the ADC's top above the bias, or the full well at ISO 100 when that fills first
            "saturation_dn": float(min(s.adc_max_dn - s.bias_dn, k100 * s.full_well_e if s.full_well_e else np.inf)),
            "saturated_by": "full well" if s.full_well_e and k100 * s.full_well_e < s.adc_max_dn - s.bias_dn else "ADC",
        },
    }
    if any(e.name == "dark_current" for e in effects):
        dc = next(e for e in effects if e.name == "dark_current")
        truth["derived"]["dark_current_dn_per_s_iso100"] = dc.params["rate_e_per_s"] * k100
    (folder / "truth.yaml").write_text(yaml.safe_dump(truth, sort_keys=False))


def partial_folders(out: Path, truth: Path) -> tuple[Path, Path]:
    """Fresh hidden folders beside ``out`` and ``truth`` that a simulation fills and then renames into place.

    An interrupted run so leaves no half-written dataset (a partial folder left by an earlier run is removed
    first).

    Parameters
    ----------
    out : pathlib.Path
        The dataset folder to be written.
    truth : pathlib.Path
        Its truth folder.

    Returns
    -------
    out_partial : pathlib.Path
        ``.<out name>.partial`` beside ``out``, created empty.
    truth_partial : pathlib.Path
        ``.<truth name>.partial`` beside ``out``, created empty.
    """
    folders = (out.parent / f".{out.name}.partial", out.parent / f".{truth.name}.partial")
    for path in folders:
        if path.exists():
            shutil.rmtree(path)
        path.mkdir(parents=True)
    return folders


def yaml_plain(value):
    """Numbers and lists YAML can write (numpy arrays and scalars converted).

    Parameters
    ----------
    value : object
        A value of the truth: dicts, lists, tuples, numpy arrays and scalars, nested.

    Returns
    -------
    object
        The same value with dict keys as text, tuples and arrays as lists and numpy scalars as Python numbers.
    """
    if isinstance(value, dict):
        return {str(k): yaml_plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [yaml_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value
