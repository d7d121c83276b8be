"""Run a stage from files to files: what the workflow scripts and the CLI call.

Each function opens the dataset (validated), runs the stage's package
functions and writes its artefacts with provenance. They hold no physics.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from pipeline.artefact import read_artefact, write_artefact
from pipeline.dataset import open_dataset
from pipeline.effects import load_plugins


def _model(config: dict) -> list[str]:
    load_plugins(config["model"].get("plugins", []))
    return list(config["model"]["effects"])


def stage_config(config: dict, stage: str) -> dict:
    """The subset of the config a stage depends on (its rerun trigger and provenance)."""
    from pipeline.config import stage_params

    return stage_params(config, stage)


def run_dark(dataset: str | Path, config: dict, outputs: dict[str, str | Path], progress=False) -> None:
    from pipeline.stages.dark import analyse_dark, reduce_dark

    effects = _model(config)
    ds = open_dataset(dataset)
    reduced = reduce_dark(ds, config, progress=progress)
    arts = analyse_dark(reduced, config, effects)
    for lens, art in arts.items():
        write_artefact(art, outputs[lens], stage="dark", inputs=reduced["inputs"],
                       config_subset=stage_config(config, "dark"), effects=effects)


def run_linearity(dataset: str | Path, config: dict, dark_paths: dict[str, str | Path],
                  outputs: dict[str, str | Path], progress=False) -> None:
    from pipeline.stages.linearity import analyse_linearity, reduce_linearity

    effects = _model(config)
    ds = open_dataset(dataset)
    dark = {lens: read_artefact(p, "dark") for lens, p in dark_paths.items()}
    reduced = reduce_linearity(ds, dark, config, effects, progress=progress)
    arts = analyse_linearity(reduced, dark, config, effects)
    inputs = dict(reduced["inputs"])
    for lens, art in arts.items():
        write_artefact(art, outputs[lens], stage="linearity", inputs=inputs,
                       config_subset=stage_config(config, "linearity"), effects=effects)


def run_diagnostics(artefacts: dict[str, list[str | Path]], config: dict, missing_csv, unexplained_csv,
                    errors_csv, history_csv) -> None:
    """Rank missing effects, write this run's error figures and append them to the ledger."""
    from pipeline.diagnostics import (append_error_history, error_figures,
                                      observations_from_artefacts, rank_missing_effects)

    effects = _model(config)
    loaded = {exp: [read_artefact(p, exp) for p in paths] for exp, paths in artefacts.items() if paths}
    obs = observations_from_artefacts(loaded)
    ranked, unexplained = rank_missing_effects(obs, effects, config)
    figures = error_figures(obs, effects)
    for path, table in ((missing_csv, ranked), (unexplained_csv, unexplained), (errors_csv, figures)):
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(path).with_name(f".{Path(path).name}.tmp")
        table.to_csv(tmp, index=False)
        tmp.replace(path)
    append_error_history(history_csv, figures, effects)


def read_table(path) -> pd.DataFrame:
    return pd.read_csv(path)


# ---------------------------------------------------------------- snakemake runners
def _simulate(smk) -> None:
    from pipeline.cli import simulate_from_config

    simulate_from_config(smk.output.dataset, smk.params.simulation)


def _dark(smk) -> None:
    run_dark(smk.params.dataset, smk.params.config, dict(zip(smk.params.lenses, smk.output.artefacts)))


def _linearity(smk) -> None:
    run_linearity(smk.params.dataset, smk.params.config, dict(zip(smk.params.lenses, smk.input.dark)),
                  dict(zip(smk.params.lenses, smk.output.artefacts)))


def _diagnostics(smk) -> None:
    artefacts = {k: list(v) for k, v in smk.input.items()}
    run_diagnostics(artefacts, smk.params.config, smk.output.missing_effects, smk.output.unexplained,
                    smk.output.run_errors, smk.params.error_history)


def _report(smk) -> None:
    from pipeline.report import build_report

    def by_lens(key):
        return dict(zip(smk.params.lenses, smk.input[key])) if key in smk.input.keys() else {}

    build_report(dark=by_lens("dark"), linearity=by_lens("linearity"),
                 missing_effects=smk.input.missing_effects, unexplained=smk.input.unexplained,
                 run_errors=smk.input.run_errors, error_history=smk.params.error_history,
                 out_html=smk.output.html, skipped=smk.params.skipped,
                 geometry=by_lens("geometry"), rolloff=by_lens("rolloff"), spectral=by_lens("spectral"),
                 absolute=by_lens("absolute"), immersion=by_lens("immersion"))


RUNNERS = {"simulate_dataset": _simulate, "dark": _dark, "linearity": _linearity,
           "diagnostics": _diagnostics, "report": _report}
