"""Everything a report section may read, loaded once: artefacts per stage and lens, diagnostics tables."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
import xarray as xr

__all__ = ["ReportInputs", "read_csv_or_empty", "input_count"]


def read_csv_or_empty(path: Path) -> pd.DataFrame:
    """A CSV table, or an empty one when the file is absent or empty (a stage that did not run).

    Parameters
    ----------
    path : pathlib.Path
        The CSV file.

    Returns
    -------
    pandas.DataFrame
        The table, or an empty DataFrame.
    """
    try:
        return pd.read_csv(path)
    except (FileNotFoundError, pd.errors.EmptyDataError):
        return pd.DataFrame()


def input_count(ds: xr.Dataset) -> str:
    """How many input files an artefact was made from (its ``input_sha256`` attribute).

    Parameters
    ----------
    ds : xarray.Dataset
        An artefact.

    Returns
    -------
    str
        The number of input files, or ``"n/a"`` when the attribute cannot be read.
    """
    try:
        return str(len(json.loads(ds.attrs.get("input_sha256", "{}"))))
    except (TypeError, ValueError):
        return "n/a"


@dataclass
class ReportInputs:
    """The artefacts (``artefacts[stage][lens]``, their ``paths``), diagnostics tables and run facts;
    ``residual_tests`` (one row per experiment and level) and ``closure`` (the closure table, every
    measurement with its prediction and z) are empty / None when the diagnostics did not write them."""

    artefacts: dict[str, dict[str, xr.Dataset]]
    paths: dict[str, dict[str, Path]]
    missing_effects: pd.DataFrame
    unexplained: pd.DataFrame
    run_errors: pd.DataFrame
    error_history: pd.DataFrame
    residual_tests: pd.DataFrame = field(default_factory=pd.DataFrame)
    closure: xr.Dataset | None = None
    #: ``lens_tests.csv``: per effect that may differ between the sensors, one shared value against one per lens
    lens_tests: pd.DataFrame = field(default_factory=pd.DataFrame)
    #: ``field_scale.csv``: per band, the field camera/reference scale against the lab calibration's prediction
    field_scale: pd.DataFrame = field(default_factory=pd.DataFrame)
    #: ``plausibility.csv``: per fitted quantity with a physical range, the value, the range and the verdict
    plausibility: pd.DataFrame = field(default_factory=pd.DataFrame)
    skipped: dict[str, str] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)
    calibration: xr.Dataset | None = None
    dataset: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)

    def stage(self, name: str) -> dict[str, xr.Dataset]:
        """The artefacts of one stage by lens (empty when the stage did not run).

        Parameters
        ----------
        name : str
            The stage, e.g. ``"dark"``.

        Returns
        -------
        dict[str, xarray.Dataset]
            Lens -> its artefact.
        """
        return self.artefacts.get(name, {})

    def model_effects(self) -> list[str]:
        """The model's effects as the artefacts record them (the first artefact's; every stage of one run has
        the same model).

        Returns
        -------
        list[str]
            The effects' names; empty when there is no artefact or it records none.
        """
        for _, _, _, ds in self.all_artefacts():
            text = str(ds.attrs.get("model_effects", ""))
            return [e.strip() for e in text.split(",") if e.strip()]
        return []

    def all_artefacts(self):
        """(stage, lens, path, dataset) of every artefact, in the order of the chain.

        Yields
        ------
        tuple[str, str, pathlib.Path, xarray.Dataset]
            (stage, lens, the artefact's file, the artefact).
        """
        for stage, by_lens in self.artefacts.items():
            for lens, ds in by_lens.items():
                yield stage, lens, self.paths[stage][lens], ds
