# Shared input functions and helpers. Logic lives in the `pipeline` package.

import signal
import sys
import time
from pathlib import Path

from pipeline.errors import InputError
from pipeline.runner.workflow import (
    STAGES,
    DatasetIndex,
    SignalWatch,
    dataset_to_simulate,
    stage_code_sha256,
    stage_params,
)

# from the artefact module, not pipeline.bundle.calibration: the Snakefile (parsed again by every cluster job)
# then does not import the radiometry and scipy.stats
from pipeline.io.artefact import BUNDLE_STAGES as CALIBRATION_STAGES
from pipeline.io.artefact import BUNDLE_REQUIRED_STAGES as CALIBRATION_REQUIRED

# the run's start: a failed run's report reads only the job logs written after it
RUN_START = time.time()
# Ctrl-C (SIGINT) from here on, SIGTERM from onstart (Snakemake's scheduler installs its handler first):
# an interrupted run ends with 128 + the signal, not with the failed-run report (report_failed_run)
SIGNALS = SignalWatch()
SIGNALS.watch(signal.SIGINT)
DATASET = Path(config["dataset"])
try:
    # simulate only the configured default dataset (or with --config simulate=true), never a path a user gave
    SIMULATE = dataset_to_simulate(config)
except InputError as exc:
    sys.exit(f"error: {exc}")

# the field section: the reference radiometer's match-up window and clock search the check compares with
INDEX = DatasetIndex(DATASET, config)
if not SIMULATE:
    # validate dataset.yaml, MD5SUMS, every frames.csv and every frame's tags before any stage runs
    try:
        INDEX.load()
    except InputError as exc:
        sys.exit(f"error: {exc}")


wildcard_constraints:
    lens="[A-Za-z0-9_-]+",


def _ready():
    """The dataset index, after the simulation checkpoint when the dataset is simulated."""
    if SIMULATE:
        checkpoints.simulate_dataset.get()
    try:
        INDEX.load()
    except InputError as exc:
        sys.exit(f"error: {exc}")
    return INDEX


def stage_inputs(stage):
    """Input function of a stage's rule: the files its lens job reads and its upstream artefacts.

    dataset.yaml and MD5SUMS are declared but their time stamps do not trigger reruns:
    the part of dataset.yaml a job reads is one of its params (see dataset_subset), so editing
    the chessboard reruns geometry and what depends on it, a lens region that lens's jobs; the
    lines of MD5SUMS that matter belong to frames that are inputs themselves, so rewriting
    MD5SUMS after adding frames to one experiment reruns only that experiment's stages.
    """

    def inputs(wildcards):
        index = _ready()
        spec = STAGES[stage]
        files = index.lens_files(stage, wildcards.lens)
        out = {"files": files, "layout": [ancient(f) for f in index.layout_files()]}
        for name in spec.upstream:
            out[name] = f"results/{name}/{wildcards.lens}.nc"
        for name in spec.optional_upstream:
            if index.stage_runnable(name):
                out[name] = f"results/{name}/{wildcards.lens}.nc"
        if spec.bundle:
            out.update(calibration_bundle())
        return out

    return inputs


def dataset_subset(stage):
    """Params function: the part of dataset.yaml that a stage's lens job reads."""

    def subset(wildcards):
        return _ready().dataset_subset(stage, wildcards.lens)

    return subset


def job_memory_mb(stage):
    """Resources function: memory of one lens job, from the lens region's size (pipeline.runner.workflow)."""

    def memory(wildcards, attempt):
        return _ready().job_memory_mb(stage, wildcards.lens, attempt)

    return memory


def artefacts_of(stage):
    """Artefact paths of a stage, one per lens it runs for (the field: the lens at the zenith)."""
    return [
        f"results/{stage}/{lens}.nc" for lens in sorted(_ready().stage_lenses(stage))
    ]


def diagnostics_inputs(wildcards):
    index = _ready()
    return {
        stage: artefacts_of(stage) for stage in STAGES if index.stage_runnable(stage)
    }


def camera_meta(wildcards):
    """Params function: dataset.yaml's camera (make, model, serial) and lens regions, written into the bundle."""
    meta = _ready().load().dataset.meta
    return {"camera": meta.get("camera", {}), "lenses": meta.get("lenses", {})}


def calibration_bundle():
    """The bundle of the dataset's camera, or nothing when the dataset lacks a stage it needs."""
    index = _ready()
    if not all(index.stage_runnable(stage) for stage in CALIBRATION_REQUIRED):
        return {}
    serial = str(camera_meta(None)["camera"].get("serial") or "camera")
    return {"calibration": f"results/calibration/{serial}.nc"}


def calibration_inputs(wildcards):
    """Input function of the calibration rule: every artefact of the stages the dataset can run."""
    index = _ready()
    return {
        stage: artefacts_of(stage)
        for stage in CALIBRATION_STAGES
        if index.stage_runnable(stage)
    }


def report_inputs(wildcards):
    out = diagnostics_inputs(wildcards)
    out.update(calibration_bundle())
    out.update(
        {
            "missing_effects": "results/diagnostics/missing_effects.csv",
            "unexplained": "results/diagnostics/unexplained.csv",
            "run_errors": "results/diagnostics/run_errors.csv",
            "error_history": "results/diagnostics/error_history.csv",
            "residual_tests": "results/diagnostics/residual_tests.csv",
            "lens_tests": "results/diagnostics/lens_tests.csv",
            "field_scale": "results/diagnostics/field_scale.csv",
            "plausibility": "results/diagnostics/plausibility.csv",
            "closure": "results/closure/residuals.nc",
        }
    )
    return out


def skipped_stages(wildcards):
    return _ready().skipped()


def report_dataset(wildcards):
    """The report's summary: dataset folder, camera and the experiments it holds."""
    dataset = _ready().load().dataset
    return {
        "path": str(dataset.root),
        "camera": dataset.meta.get("camera"),
        "experiments": dataset.experiments(),
    }


def report_settings(wildcards):
    """The config the report reads: its own section and the diagnostics' structured_rms_z."""
    from pipeline.report import report_settings as settings

    return settings(config)


def report_figure_category(wildcards, output):
    """Snakemake report: a figure's category is its section of the HTML report."""
    from pipeline.report.render import read_figure_index

    return read_figure_index(output.figures)[wildcards.figure]["category"]


def report_figure_labels(wildcards, output):
    """Snakemake report: a figure's number and caption, as the HTML report gives them."""
    from pipeline.report.render import read_figure_index

    entry = read_figure_index(output.figures)[wildcards.figure]
    return {"figure": f"Figure {entry['number']}", "caption": entry["caption"]}


def print_run_summary():
    """After a run: where the report is and, per experiment, what the diagnostics found."""
    from pipeline.runner.run_summary import summarise_run

    try:
        skipped = _ready().skipped()
    except SystemExit:
        skipped = {}
    lines = summarise_run(
        "results",
        config["model"]["effects"],
        skipped,
        config["diagnostics"]["structured_rms_z"],
    )
    print("\n".join(lines))


def report_failed_run():
    """After a run with failed jobs (with --keep-going, after every job that could run): the
    diagnostics and the report on the artefacts written, naming each stage that did not finish.
    """
    from pipeline.runner.run_summary import report_after_failure

    # Snakemake calls onerror for an interrupted run too: an interrupt is no failure to report
    SIGNALS.exit_if_interrupted()
    index = _ready()
    stage_lenses = {
        stage: sorted(index.stage_lenses(stage))
        for stage in STAGES
        if index.stage_runnable(stage)
    }
    lines = report_after_failure(
        "results", stage_lenses, config, index.skipped(), since=RUN_START
    )
    print("\n".join(lines), file=sys.stderr)
