"""The residual tables as the diagnostics read and refit them.

Every stage stores its observation tables (``obs_*`` variables, :mod:`pipeline.stages.observations`); here they
are gathered per experiment and level with both lenses pooled, the design of a model is built from the base
columns and the columns of the model's effects (each lens its own), and the candidates accepted on one table
predict their shift in the tables that are predicted from it. The missing-effect search
(:mod:`pipeline.diagnostics.missing_effects`) and the closures across experiments
(:mod:`pipeline.diagnostics.cross_closure`) both build on these.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from pipeline.effects import get as get_effect
from pipeline.stages.observations import dataset_to_table
from pipeline.stats.fitting import base_design, wls


@dataclass
class Observations:
    experiment: str
    level: str
    table: pd.DataFrame
    #: units of ``value_dn`` (and its prediction and sigma) as the artefact states them, or None
    value_units: str | None = None


def observations_from_artefacts(artefacts: dict[str, list]) -> list[Observations]:
    """Observation tables per experiment and level, lenses concatenated.

    Tables without ``group``, ``value_dn`` and ``sigma_dn`` (descriptive ones) are left out, and only the rows
    marked ``used`` are kept.

    Parameters
    ----------
    artefacts : dict[str, list]
        {experiment: the stage artefacts (xarray.Dataset) of its lenses}.

    Returns
    -------
    list of Observations
        One per experiment and level, with the units of ``value_dn`` when the artefacts agree on one, else None.
    """
    out = []
    for experiment, datasets in artefacts.items():
        levels = sorted({name.split("__", 1)[0][4:] for ds in datasets for name in ds.data_vars
                         if name.startswith("obs_") and "__" in name})
        for level in levels:
            tables = [dataset_to_table(ds, f"obs_{level}") for ds in datasets]
            tables = [t for t in tables if len(t)]
            if not tables:
                continue
            table = pd.concat(tables, ignore_index=True)
            if not {"group", "value_dn", "sigma_dn"} <= set(table.columns):
                continue        # a descriptive table (e.g. the geometry frame list), not residuals
            if "used" in table:
                table = table[table["used"].astype(int) == 1].reset_index(drop=True)
            units = {ds[f"obs_{level}__value_dn"].attrs.get("units") for ds in datasets
                     if f"obs_{level}__value_dn" in ds}
            units.discard(None)
            out.append(Observations(experiment, level, table, units.pop() if len(units) == 1 else None))
    return out


#: (experiment, level) of the tables whose rows no candidate is fitted to: its share there is predicted from the
#: table its ``predicted_from`` names (module docstring)
PREDICTED_TABLES = {("field", "scale")}


def is_predicted(obs: Observations) -> bool:
    """Whether a table is one whose candidates' share is predicted from another (``PREDICTED_TABLES``).

    Parameters
    ----------
    obs : Observations
        One experiment and level's residual table (``value_dn``, ``sigma_dn`` in its ``value_units``).

    Returns
    -------
    bool
        True for a predicted table.
    """
    return (obs.experiment, obs.level) in PREDICTED_TABLES


@dataclass
class Anchor:
    """A candidate's coefficients and covariance as fitted on the table its predicted shift is taken from."""
    effect: str
    coef: np.ndarray
    cov: np.ndarray
    table: pd.DataFrame
    source: str


def predicted_shift(anchor: Anchor, obs: Observations) -> tuple[np.ndarray, np.ndarray] | None:
    """The shift the anchored candidate predicts in ``obs``'s rows and its variance (the coefficients'
    covariance through the shift's central-difference derivative); None when it is silent there.

    Parameters
    ----------
    anchor : Anchor
        The accepted candidate, with its coefficients and covariance.
    obs : Observations
        One experiment and level's residual table (``value_dn``, ``sigma_dn`` in its ``value_units``).

    Returns
    -------
    tuple of numpy.ndarray or None
        (the shift per row, in the table's ``value_units``; its variance per row), or None.
    """
    effect = get_effect(anchor.effect)
    shift = effect.predicted_shift(obs.experiment, obs.level, obs.table, anchor.coef, anchor.table)
    if shift is None:
        return None
    shift = np.asarray(shift, float)
    jac = np.zeros((len(shift), anchor.coef.size))
    for i in range(anchor.coef.size):
        h = max(1e-3 * float(np.sqrt(max(anchor.cov[i, i], 0.0))), 1e-9 * max(abs(float(anchor.coef[i])), 1.0))
        up, down = anchor.coef.astype(float).copy(), anchor.coef.astype(float).copy()
        up[i] += h
        down[i] -= h
        jac[:, i] = (effect.predicted_shift(obs.experiment, obs.level, obs.table, up, anchor.table)
                     - effect.predicted_shift(obs.experiment, obs.level, obs.table, down, anchor.table)) / (2 * h)
    var = np.einsum("ri,ij,rj->r", jac, anchor.cov, jac)
    return shift, np.clip(var, 0.0, None)


def predicted_total(obs: Observations, anchors: list[Anchor]) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The summed shift the anchored candidates predict in ``obs``'s rows, its variance, and the candidates
    that predict one there.

    Parameters
    ----------
    obs : Observations
        One experiment and level's residual table (``value_dn``, ``sigma_dn`` in its ``value_units``).
    anchors : list of Anchor
        The accepted candidates, each with its coefficients and covariance as fitted on its source table.

    Returns
    -------
    shift : numpy.ndarray
        The summed shift per row, in the table's ``value_units``.
    variance : numpy.ndarray
        Its variance per row.
    names : list of str
        The candidates that predict a shift there.
    """
    shift, var, names = np.zeros(len(obs.table)), np.zeros(len(obs.table)), []
    for anchor in anchors:
        found = predicted_shift(anchor, obs)
        if found is not None:
            shift, var = shift + found[0], var + found[1]
            names.append(anchor.effect)
    return shift, var, names


def with_predictions(observations: list[Observations], anchors: list[Anchor]) -> list[Observations]:
    """The observations with the accepted candidates' predicted shifts taken out of the predicted tables' rows
    (their variances added to the rows' noise); the other tables as they are.

    Parameters
    ----------
    observations : list of Observations
        The residual tables.
    anchors : list of Anchor
        The accepted candidates, each with its coefficients and covariance as fitted on its source table.

    Returns
    -------
    list of Observations
        The tables, the predicted ones corrected.
    """
    if not anchors:
        return observations
    out = []
    for obs in observations:
        if not is_predicted(obs):
            out.append(obs)
            continue
        shift, var, _ = predicted_total(obs, anchors)
        table = obs.table.copy()
        table["value_dn"] = table["value_dn"].to_numpy(float) - shift
        table["sigma_dn"] = np.sqrt(table["sigma_dn"].to_numpy(float) ** 2 + var)
        out.append(replace(obs, table=table))
    return out


def model_design(obs: Observations, model_effects: list[str]) -> np.ndarray:
    """Base columns plus the columns of the model's effects; each lens its own (:func:`per_lens_columns`).

    Parameters
    ----------
    obs : Observations
        One experiment and level's residual table (``value_dn``, ``sigma_dn`` in its ``value_units``).
    model_effects : list of str
        The effects of the model; those that correct the data rather than add columns are skipped.

    Returns
    -------
    numpy.ndarray
        The design matrix, one row per table row.
    """
    X, _ = base_design(obs.table)
    cols = [X]
    for name in model_effects:
        effect = get_effect(name)
        if effect.corrects_data:
            continue
        c = effect.columns(obs.experiment, obs.level, obs.table)
        if c is not None:
            cols.append(per_lens_columns(c, obs.table))
    return np.hstack(cols)


def per_lens_columns(columns: np.ndarray, table: pd.DataFrame) -> np.ndarray:
    """An effect's columns once per lens of a table that pools both lenses: every stage fits each lens on its
    own (one job and one artefact per lens), so the model the diagnostics refit has each lens's own value.

    Parameters
    ----------
    columns : numpy.ndarray
        An effect's columns, shape ``(n_rows, k)``.
    table : pandas.DataFrame
        The table (its ``lens`` column).

    Returns
    -------
    numpy.ndarray
        Shape ``(n_rows, k * n_lenses)``: each lens's copy zero outside its rows; ``columns`` itself for one lens
        or no ``lens`` column.
    """
    if "lens" not in table:
        return columns
    lens = table["lens"].astype(str).to_numpy()
    names = list(dict.fromkeys(lens))
    if len(names) < 2:
        return columns
    return np.hstack([columns * (lens == name)[:, None] for name in names])


def blocks_of(table: pd.DataFrame, keys) -> tuple[np.ndarray, str]:
    """Block label of every row (rows sharing a raw frame or setting) and the key used; one block per row
    when the table has none of ``keys`` (``a+b`` combines columns).

    Parameters
    ----------
    table : pandas.DataFrame
        A residual table.
    keys : iterable of str
        Candidate block keys, in order of preference (a column, or columns joined by ``+``).

    Returns
    -------
    labels : numpy.ndarray
        The block label (str) of every row.
    key : str
        The key used, or ``"row"``.
    """
    for key in keys:
        cols = key.split("+")
        if all(c in table for c in cols):
            # the columns' text joined by "/" column-wise (a row-wise join in Python was most of a candidate's
            # significance test on a few hundred rows): the same labels; an empty table or a missing value
            # (which the row-wise join refuses) the row-wise way
            label = table[cols[0]].astype(str)
            for c in cols[1:]:
                label = label + "/" + table[c].astype(str)
            if not len(table) or label.isna().any():
                return table[cols].astype(str).agg("/".join, axis=1).to_numpy(), key
            return label.to_numpy(dtype=object), key
    return np.arange(len(table)).astype(str), "row"


def fit_observations(obs: Observations, X: np.ndarray):
    """Weighted least squares of the table's values on the columns ``X``.

    Parameters
    ----------
    obs : Observations
        One experiment and level's residual table (``value_dn``, ``sigma_dn`` in its ``value_units``).
    X : numpy.ndarray
        The design matrix, one row per table row.

    Returns
    -------
    Fit
        Coefficients, their covariance (from the stated sigmas), predictions, normalised residuals z, chi^2 and
        degrees of freedom.
    """
    return wls(obs.table["value_dn"].to_numpy(float), obs.table["sigma_dn"].to_numpy(float), X)
