# Shared input functions and helpers. Logic lives in the `pipeline` package.

import sys
from pathlib import Path

from pipeline.camera import Camera
from pipeline.errors import InputError
from pipeline.workflow import STAGE_EXPERIMENTS, DatasetIndex, stage_params

STAGES = list(STAGE_EXPERIMENTS)

DATASET = Path(config["dataset"])
SIMULATE = not DATASET.exists() and config["simulate_if_missing"]["enabled"]
if not DATASET.exists() and not SIMULATE:
    sys.exit(f"error: {DATASET}: dataset folder not found (set --config dataset=PATH)")

INDEX = DatasetIndex(DATASET)
if not SIMULATE:
    # validate dataset.yaml, MD5SUMS, every frames.csv and every frame's tags before any stage runs
    try:
        INDEX.load()
    except InputError as exc:
        sys.exit(f"error: {exc}")

LENSES = INDEX.lenses() if not SIMULATE else list(Camera().lens_names)


def _ready():
    """The dataset index, after the simulation checkpoint when the dataset is simulated."""
    if SIMULATE:
        checkpoints.simulate_dataset.get()
    try:
        INDEX.load()
    except InputError as exc:
        sys.exit(f"error: {exc}")
    return INDEX


def dark_inputs(wildcards):
    return _ready().experiment_files("dark")


def linearity_inputs(wildcards):
    return _ready().experiment_files("linearity")


def _with_sidecars(experiment, *names):
    files = _ready().experiment_files(experiment)
    return files + [str(DATASET / experiment / name) for name in names] if files else files


def geometry_inputs(wildcards):
    return _ready().experiment_files("geometry")


def rolloff_inputs(wildcards):
    return _ready().experiment_files("rolloff")


def spectral_inputs(wildcards):
    return _with_sidecars("spectral", "photodiode.csv")


def absolute_inputs(wildcards):
    return _with_sidecars("absolute", "source_spectrum.csv", "source_reference.csv")


def immersion_inputs(wildcards):
    index = _ready()
    out = {"frames": _with_sidecars("immersion", "water.yaml"), "geometry": artefacts_of("geometry")}
    if index.stage_runnable("spectral"):
        out["spectral"] = artefacts_of("spectral")
    return out


def artefacts_of(stage):
    """Artefact paths of a stage, or none when its experiment is absent from the dataset."""
    return [f"results/{stage}/{lens}.nc" for lens in LENSES]


def diagnostics_inputs(wildcards):
    index = _ready()
    out = {}
    for stage in STAGES:
        if index.stage_runnable(stage):
            out[stage] = artefacts_of(stage)
    return out


def report_inputs(wildcards):
    index = _ready()
    out = diagnostics_inputs(wildcards)
    out.update({
        "missing_effects": "results/diagnostics/missing_effects.csv",
        "unexplained": "results/diagnostics/unexplained.csv",
        "run_errors": "results/diagnostics/run_errors.csv",
    })
    return out


def skipped_stages(wildcards):
    return _ready().skipped()
