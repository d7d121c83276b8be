"""What the Snakemake rules need from the package: dataset index, params, script entry point."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from pipeline.config import STAGE_SECTIONS, stage_params  # noqa: F401  (used by the rules)
from pipeline.dataset import Dataset
from pipeline.errors import InputError
from pipeline.validation import format_problems, inspect_dataset

#: experiments each stage reads (a stage runs only when all are present)
STAGE_EXPERIMENTS = {
    "dark": ("dark",),
    "linearity": ("linearity", "dark"),
    "geometry": ("geometry",),
    "rolloff": ("rolloff", "geometry"),
    "spectral": ("spectral", "geometry"),
    "absolute": ("absolute", "spectral", "geometry"),
    "immersion": ("immersion", "geometry"),
}


class DatasetIndex:
    """A dataset validated once per workflow run: layout, checksums list, frames.csv and tags."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.dataset: Dataset | None = None

    def load(self) -> "DatasetIndex":
        """Validate once (``pipeline.validation``); on problems print them grouped and raise InputError."""
        if self.dataset is None:
            dataset, problems = inspect_dataset(self.root)
            if problems:
                print(format_problems(problems, self.root), file=sys.stderr)
                raise InputError.from_problems(problems, "listed above")
            self.dataset = dataset
        return self

    def lenses(self) -> list[str]:
        return list(self.load().dataset.lenses)

    def stage_runnable(self, stage: str) -> bool:
        present = set(self.load().dataset.experiments())
        return all(exp in present for exp in STAGE_EXPERIMENTS[stage])

    def skipped(self) -> dict[str, str]:
        present = set(self.load().dataset.experiments())
        out = {}
        for stage, needs in STAGE_EXPERIMENTS.items():
            missing = [e for e in needs if e not in present]
            if missing:
                out[stage] = f"the dataset has no {', '.join(m + '/' for m in missing)} folder"
        if "field" not in present:
            out["field"] = "the dataset has no field/ folder"
        else:
            out["field"] = "field/ is present but this version of the pipeline has no field stage yet"
        return out

    def experiment_files(self, experiment: str) -> list[str]:
        dataset = self.load().dataset
        if experiment not in dataset.experiments():
            return []
        return [str(dataset.root / experiment / "frames.csv")] + [str(p) for p in dataset.raw_files(experiment)]


def _setup_log(path: str | None) -> None:
    handlers = [logging.StreamHandler(sys.stderr)]
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        handlers.append(logging.FileHandler(path, mode="w"))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s", handlers=handlers,
                        force=True)


def run_stage_script(smk, stage: str) -> None:
    """Entry point of the thin workflow scripts: unpack ``snakemake`` and call the package.

    The stage's module provides ``run_from_snakemake(smk)``: ``pipeline.stage_io``
    for the foundation rules, ``pipeline.stages.<stage>`` for the others.
    Bad input ends the job with one line naming the file and the problem.
    """
    import importlib

    from pipeline import stage_io

    log = smk.log[0] if smk.log else None
    _setup_log(log)
    try:
        runner = stage_io.RUNNERS.get(stage)
        if runner is None:
            runner = importlib.import_module(f"pipeline.stages.{stage}").run_from_snakemake
        runner(smk)
    except InputError as exc:
        logging.getLogger("pipeline").error("%s", exc)
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(1)
