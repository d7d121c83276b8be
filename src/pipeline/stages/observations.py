"""Observation tables: the one contract between the stages, the diagnostics and the report.

Each stage reduces its frames to tables with one row per independent
measurement (a frame, a setting, a height...): the measured ``value_dn``, its
expected noise ``sigma_dn``, the base columns of the stage's linear model
(``x_<name>``, one block per ``group``), the model's prediction ``pred_dn`` and
the noise-normalised residual ``z``. The tables are stored in the stage's
artefact as variables ``<prefix>__<column>`` along a dimension ``<prefix>``
(for example ``obs_setting__z``) so that the diagnostics read them back
without knowing the stage.

:func:`fit_with_effects` is the effect-aware weighted fit that every stage
uses: the base columns plus the signature columns of each effect of the model
that is fitted (rather than corrected in the data) at that level.

:func:`corner_table_dataset` stores a lit stage's per-frame unlit-corner records
(:mod:`pipeline.radiometry.unlit_corners`) as its ``obs_corner`` table: a descriptive
table (no ``value_dn``), which the closure reads across the stages.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.effects import get as get_effect
from pipeline.stats.fitting import Fit, base_design, wls
from pipeline.radiometry.unlit_corners import CORNER_COLUMNS

__all__ = ["COLUMN_MEANINGS", "CORNER_PREFIX", "corner_table_dataset", "dataset_to_table", "datasets_by_lens", "lens_of",
           "with_corner_table", "effect_coefficients", "fit_with_effects",
           "table_to_dataset"]

#: the prefix of the per-frame unlit-corner table in a lit stage's artefact
CORNER_PREFIX = "obs_corner"


#: what the columns that many tables share mean (``long_name`` of their variables); a stage's own columns
#: are named after what they hold, with the unit at the end of the name
COLUMN_MEANINGS = {
    "value_dn": "measured value of the row (the table's units attribute, else DN)",
    "sigma_dn": "expected noise of the measured value (same units)",
    "pred_dn": "the model's prediction of the measured value (same units)",
    "z": "noise-normalised residual (value - prediction) / sigma",
    "group": "block of rows that shares the base columns of the model",
    "used": "1 where the row enters the fit, 0 where it is left out (saturated, flagged, outside the range)",
    "lens": "lens the row belongs to",
    "band": "colour band of the row (R, G or B)",
    "iso": "ISO setting of the frame or setting",
    "exposure_s": "exposure time of the frame or setting",
    "temperature_c": "sensor temperature recorded with the frame",
    "file_index": "index of the raw file in the experiment's frames table",
    "frame": "index of the frame the row comes from",
    "setting": "acquisition setting (ISO and exposure) of the row",
    "sweep": "sweep the setting belongs to (exposure or gain)",
    "kind": "kind of row within the table",
    "medium": "medium in front of the lens (air or water)",
    "saturated": "1 where the row reaches the saturation level",
    "time_s": "acquisition time of the frame, seconds since the first frame of the table",
    "n_frames": "number of frames reduced into the row",
    "corner_dn": "mean level of the frame's unlit corners",
    "dark_corner_dn": "unlit-corner level the dark model predicts for the frame",
    "sigma_corner_dn": "noise of the unlit-corner level",
    "n_corner_sites": "number of unlit-corner sites averaged",
    "wavelength_nm": "wavelength of the row",
}


def _meaning(column: str) -> str | None:
    if column in COLUMN_MEANINGS:
        return COLUMN_MEANINGS[column]
    if column.startswith("x_"):
        return f"base column '{column[2:]}' of the stage's linear model"
    return None


def table_to_dataset(table: pd.DataFrame, prefix: str) -> xr.Dataset:
    """Store an observation table as variables ``<prefix>__<column>`` along dimension ``<prefix>``.

    The columns many tables share get their meaning as ``long_name`` (:data:`COLUMN_MEANINGS`).

    Parameters
    ----------
    table : pandas.DataFrame
        The observation table, one row per measurement; text columns are stored as strings.
    prefix : str
        The table's name in the artefact, e.g. ``"obs_setting"``: the dimension and the variables' prefix.

    Returns
    -------
    xarray.Dataset
        One variable per column along dimension ``prefix``.
    """
    data = {}
    for col in table.columns:
        values = table[col].to_numpy()
        if values.dtype == object or values.dtype.kind in "OUS" or str(table[col].dtype) in ("string", "str"):
            values = table[col].astype(str).to_numpy().astype(str)
        meaning = _meaning(str(col))
        data[f"{prefix}__{col}"] = (prefix, values, {"long_name": meaning} if meaning else {})
    return xr.Dataset(data)


def lens_of(ds: xr.Dataset) -> str | None:
    """The lens a stage artefact is of: its ``lens`` attribute, else the lens of its setting or frame table's
    rows; None when it names none.

    Parameters
    ----------
    ds : xarray.Dataset
        A stage's artefact (or its observation tables).

    Returns
    -------
    str or None
        The lens's name.
    """
    if "lens" in ds.attrs:
        return str(ds.attrs["lens"])
    for name in ("obs_setting__lens", "obs_frame__lens"):
        if name in ds and ds[name].size:
            return str(ds[name].values[0])
    return None


def datasets_by_lens(datasets: list[xr.Dataset]) -> dict[str, xr.Dataset]:
    """Stage artefacts keyed by :func:`lens_of` (those that name no lens left out).

    Parameters
    ----------
    datasets : list[xarray.Dataset]
        Stage artefacts, one per lens.

    Returns
    -------
    dict[str, xarray.Dataset]
        Lens name -> its artefact (the last one given, if several name the same lens).
    """
    return {lens: ds for ds in datasets if (lens := lens_of(ds)) is not None}


def with_corner_table(art: xr.Dataset, records: list[dict]) -> xr.Dataset:
    """A lit stage's artefact with its frames' unlit-corner records as ``obs_corner`` (for the closure,
    pipeline.diagnostics.cross_closure); as it is when there are none (no dark artefact given).

    Parameters
    ----------
    art : xarray.Dataset
        The stage's artefact.
    records : list[dict]
        One record per frame, lens and band, as :func:`corner_table_dataset` takes them.

    Returns
    -------
    xarray.Dataset
        ``art`` merged with the ``obs_corner`` table, or ``art`` itself when ``records`` is empty.
    """
    return art.merge(corner_table_dataset(records)) if records else art


def corner_table_dataset(records: list[dict] | pd.DataFrame) -> xr.Dataset:
    """A lit stage's unlit-corner records (one row per frame, lens and band) as its ``obs_corner`` table, each
    column of :data:`pipeline.radiometry.unlit_corners.CORNER_COLUMNS` with its long name and units; the
    stage's own keys (``file_index``, ``kind``, ``medium``...) as they are.

    Parameters
    ----------
    records : list[dict] or pandas.DataFrame
        The records, one per frame, lens and band (:mod:`pipeline.radiometry.unlit_corners`).

    Returns
    -------
    xarray.Dataset
        Variables ``obs_corner__<column>`` along dimension ``obs_corner``.
    """
    table = pd.DataFrame(records).reset_index(drop=True)
    ds = table_to_dataset(table, CORNER_PREFIX)
    for col, (long_name, units) in CORNER_COLUMNS.items():
        name = f"{CORNER_PREFIX}__{col}"
        if name in ds:
            ds[name].attrs["long_name"] = long_name
            if units:
                ds[name].attrs["units"] = units
    return ds


def dataset_to_table(ds: xr.Dataset, prefix: str) -> pd.DataFrame:
    """Inverse of :func:`table_to_dataset`.

    Parameters
    ----------
    ds : xarray.Dataset
        An artefact holding the table as variables ``<prefix>__<column>``.
    prefix : str
        The table's name, e.g. ``"obs_setting"``.

    Returns
    -------
    pandas.DataFrame
        One column per variable of the table (named without the prefix), in the artefact's order; empty when
        the artefact has no such table.
    """
    cols = {name.split("__", 1)[1]: ds[name].values for name in ds.data_vars if name.startswith(prefix + "__")}
    return pd.DataFrame(cols)


def fit_with_effects(table: pd.DataFrame, level: str, effects: list[str], stage: str,
                     only: tuple[str, ...] | None = None) -> tuple[Fit, dict]:
    """Weighted fit of the base columns plus the columns of the model's effects at this level.

    Effects that correct the data instead of adding columns are skipped.

    Parameters
    ----------
    table : pandas.DataFrame
        The observation table: ``value_dn``, ``sigma_dn`` (its noise, same units), ``group`` and the base
        columns ``x_<name>`` (one block of coefficients per group, :func:`pipeline.stats.fitting.base_design`).
    level : str
        The table's level (e.g. ``"setting"``, ``"frame"``), which with ``stage`` selects each effect's
        signature columns (``Effect.columns``).
    effects : list[str]
        The names of the model's effects.
    stage : str
        The stage fitting, e.g. ``"linearity"``.
    only : tuple[str, ...] or None, optional
        Restricts the effects considered to these; ``None`` (default) considers all of ``effects``.

    Returns
    -------
    fit : pipeline.stats.fitting.Fit
        The weighted least-squares fit of ``value_dn`` on the base and effect columns (coefficients, their
        covariance, prediction, residual ``z``, chi-square and degrees of freedom).
    coefficients : dict[str, tuple[numpy.ndarray, numpy.ndarray]]
        Per effect whose columns entered the fit, its coefficients and their standard errors
        (:func:`effect_coefficients`).
    """
    X, _ = base_design(table)
    extra = []
    for name in effects:
        if only is not None and name not in only:
            continue
        effect = get_effect(name)
        if effect.corrects_data:
            continue
        cols = effect.columns(stage, level, table)
        if cols is not None:
            extra.append((name, cols))
    Xfull = np.hstack([X] + [c for _, c in extra]) if extra else X
    fit = wls(table["value_dn"].to_numpy(), table["sigma_dn"].to_numpy(), Xfull)
    return fit, effect_coefficients(fit, X.shape[1], extra)


def effect_coefficients(fit: Fit, first_column: int, extra: list[tuple[str, np.ndarray]]) -> dict:
    """Slice a fit's coefficients and standard errors per effect, in the order the columns were added.

    Parameters
    ----------
    fit : pipeline.stats.fitting.Fit
        The fit whose design was the base columns followed by each effect's columns.
    first_column : int
        The index of the first effect column (the number of base columns).
    extra : list[tuple[str, numpy.ndarray]]
        (effect name, its columns of shape (rows, k)) in the order they were appended to the design.

    Returns
    -------
    dict[str, tuple[numpy.ndarray, numpy.ndarray]]
        Effect name -> (its k coefficients, their standard errors from the fit's covariance), in the units of
        the table's values per unit of the effect's columns.
    """
    out, col = {}, first_column
    sigma = np.sqrt(np.diag(fit.cov))
    for name, cols in extra:
        k = cols.shape[1]
        out[name] = (fit.coef[col:col + k], sigma[col:col + k])
        col += k
    return out
