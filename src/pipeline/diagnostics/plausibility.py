"""Plausibility of the fitted physics: every fitted quantity that has a physical range, checked against it.

A fit can be precise and still impossible: a lab's mistake (a dark level taken at the wrong time, a roll-off
normalised to the wrong spot, an immersion factor from a tank whose water height was misread) leaves a value
that fits its own data to the noise and that no lens or sensor can have. Each check here takes a fitted
value, its stated standard uncertainty and a range from the ``plausibility`` section of
``src/pipeline/schema.yaml`` (where each range has its default and its reason), and says whether the value lies
outside the range by more than ``plausibility.margin_sigma`` of that uncertainty:

* ``window_index``: the index n_g of the lens's outer surface implied by the fitted immersion factor,
  through the inverse of Eq. (10) of Larouche et al. (2024), Section 2.7
  (:func:`pipeline.radiometry.immersion.window_index_from_immersion_factor`), against the indices of real
  window materials; impossible below the vacuum's 1 or where no index solves Eq. (10) (I outside
  (n_w, n_w^3)). The Insta360 ONE's far lens (authors' files: I = 1.777, 1.776, 1.794) implies 1.12-1.17,
  which no lens material has; its close lens 1.60-1.64 (the paper's values);
* ``conversion_gain_dn_per_e``: the photon-transfer gain, and each ISO's of the gain sweep; impossible at or
  below 0 whatever its uncertainty (its inverse, electrons per DN, is what is used);
* ``quantum_efficiency``: any artefact variable of that name; impossible outside (0, 1];
* ``rolloff``: g(theta) relative to its on-axis value, at every ``plausibility.rolloff_step_deg`` up to the
  largest measured angle of the medium, its uncertainty from the coefficients' covariance; implausible
  above ``plausibility.rolloff_max``. Reported at the angle where it goes furthest beyond its margin;
* ``dark_current_dn_per_s``: impossible below 0 by more than the margin (only where the dark frames
  measured it: attribute ``measured`` not 0).

:func:`check_artefacts` runs every check that the artefacts allow and returns one row per checked value
(:data:`COLUMNS`), its ``status`` ``plausible``, ``implausible`` or ``impossible``; :func:`findings` keeps
those that are not plausible and :func:`finding_sentence` says one in a line, with the value, the range and
its reason. Nothing here stops a run: a finding is reported (by the diagnostics in
``results/diagnostics/plausibility.csv``, by ``python -m pipeline diagnose`` and in the report's summary).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import lru_cache

import numpy as np
import pandas as pd
import xarray as xr
import yaml

from pipeline.config import SCHEMA_PATH, defaults
from pipeline.radiometry.immersion import window_index_from_immersion_factor
from pipeline.radiometry.rolloff import evaluate_rolloff

__all__ = ["Check", "COLUMNS", "STATUSES", "judge", "window_index_checks", "conversion_gain_checks",
           "quantum_efficiency_checks", "rolloff_checks", "dark_current_checks", "check_artefacts",
           "findings", "finding_sentence", "range_reason", "range_text", "summary_lines", "plausibility_settings"]

#: the verdicts, from good to bad: inside the range (or within the margin of it), outside what any real
#: lens or sensor has, outside what physics allows
STATUSES = ("plausible", "implausible", "impossible")
#: the refractive index of vacuum: no window material at optical frequencies has a lower one
VACUUM_INDEX = 1.0


@dataclass(frozen=True)
class Check:
    """One checked value: where it is from, the value and its stated standard uncertainty (NaN: none
    stated), its range (``low``/``high``, infinite where unbounded), how far beyond the range it lies in
    standard uncertainties (``departure_sigma``: NaN inside it or without an uncertainty), the verdict, the
    config key of the range and its reason, and how the value was derived."""

    stage: str
    lens: str
    quantity: str
    band: str
    at: str
    value: float
    sigma: float
    units: str
    low: float
    high: float
    margin_sigma: float
    departure_sigma: float
    status: str
    range_key: str
    reason: str
    derivation: str


COLUMNS = tuple(Check.__dataclass_fields__)

#: what each quantity is, for the sentences
LABELS = {"window_index": "outer-window index n_g implied by the immersion factor (Eq. 10)",
          "conversion_gain_dn_per_e": "photon-transfer conversion gain",
          "quantum_efficiency": "quantum efficiency",
          "rolloff": "roll-off g(theta) relative to its on-axis value",
          "dark_current_dn_per_s": "dark current"}


@lru_cache(maxsize=1)
def _schema_section() -> dict:
    schema = yaml.safe_load(SCHEMA_PATH.read_text())
    return schema["properties"]["plausibility"]["properties"]


def range_reason(key: str) -> str:
    """The one-line reason the schema gives for the range ``plausibility.<key>``.

    Parameters
    ----------
    key : str
        The key within the schema's ``plausibility`` section.

    Returns
    -------
    str
        The reason.
    """
    return str(_schema_section()[key]["description"])


def plausibility_settings(config: dict | None) -> dict:
    """The ``plausibility`` section of ``config``, the schema's defaults where it has none (a config
    validated before the section existed).

    Parameters
    ----------
    config : dict or None
        The run's configuration.

    Returns
    -------
    dict
        The section (a copy).
    """
    section = (config or {}).get("plausibility")
    return dict(section) if section is not None else defaults()["plausibility"]


def judge(value: float, sigma: float, low: float, high: float, margin_sigma: float, *,
          low_inclusive: bool = True) -> tuple[bool, float]:
    """(outside, departure in sigma) of ``value`` against [low, high] (``low_inclusive`` False: (low, high]).

    Outside when beyond a bound by more than ``margin_sigma`` x ``sigma``; with an exclusive low bound a value
    exactly that far below it is outside too (a gain of exactly 0 with no uncertainty).

    Parameters
    ----------
    value : float
        The fitted value.
    sigma : float
        Its standard uncertainty, same units; a non-finite, missing or non-positive sigma counts as 0 (the bound
        itself).
    low : float
        The range's lower bound (``-inf``: none).
    high : float
        The range's upper bound (``inf``: none).
    margin_sigma : float
        The margin, in standard uncertainties (``plausibility.margin_sigma``).
    low_inclusive : bool, default True
        Whether ``low`` itself is inside the range.

    Returns
    -------
    outside : bool
        True when the value is outside the range by more than the margin.
    departure : float
        The distance beyond the range over sigma; NaN inside it or without a positive sigma.
    """
    s = float(sigma) if sigma is not None and np.isfinite(sigma) and sigma > 0 else 0.0
    below, above = low - value, value - high
    beyond = max(below, above)
    outside_low = below > margin_sigma * s or (not low_inclusive and below >= margin_sigma * s)
    outside = outside_low or above > margin_sigma * s
    departure = beyond / s if beyond > 0 and s > 0 else float("nan")
    return bool(outside), float(departure)


def _sigma_or_nan(value) -> float:
    return float(value) if value is not None and np.isfinite(value) else float("nan")


def window_index_checks(immersion_factor, n_w, immersion_factor_sigma=None, *, settings: dict, lens: str = "",
                        bands=None, stage: str = "immersion") -> list[Check]:
    """The outer-window index implied by each band's immersion factor (Eq. 10 inverted), against
    ``plausibility.window_index_range``.

    The index's uncertainty is the factor's propagated to first order. Impossible where no index solves Eq. (10)
    or the index is below 1.

    Parameters
    ----------
    immersion_factor : array_like
        The immersion factor I per band (dimensionless).
    n_w : array_like
        Water's refractive index at each band's effective wavelength.
    immersion_factor_sigma : array_like, optional
        The standard uncertainty of I per band.
    settings : dict
        The ``plausibility`` section of the configuration (:func:`plausibility_settings`).
    lens : str, default ""
        The lens, recorded in the checks.
    bands : sequence of str, optional
        The bands' names, recorded in the checks.
    stage : str, default "immersion"
        The stage, recorded in the checks.

    Returns
    -------
    list of Check
        One per checked value (empty when there is nothing to check).
    """
    i = np.atleast_1d(np.asarray(immersion_factor, dtype=float))
    nw = np.broadcast_to(np.asarray(n_w, dtype=float), i.shape)
    si = (np.full(i.shape, np.nan) if immersion_factor_sigma is None
          else np.broadcast_to(np.asarray(immersion_factor_sigma, dtype=float), i.shape))
    n_g, s_g = window_index_from_immersion_factor(i, nw, np.where(np.isfinite(si), si, 0.0))
    s_g = np.where(np.isfinite(si), s_g, np.nan)
    low, high = (float(v) for v in settings["window_index_range"])
    k = float(settings["margin_sigma"])
    bands = list(bands) if bands is not None else [""] * i.size
    out = []
    for b, ib, sib, nwb, g, sg in zip(bands, i, si, nw, n_g, s_g):
        derivation = (f"I = {ib:.4f}" + (f" ± {sib:.4f}" if np.isfinite(sib) else "")
                      + f", n_w = {nwb:.4f}: n_g = (n_w - r) / (r - 1), r = sqrt(I / n_w)")
        if not np.isfinite(ib):
            continue
        if not np.isfinite(g):
            outside, departure = True, float("nan")
            status = "impossible"
            derivation += f"; I outside (n_w, n_w^3) = ({nwb:.4f}, {nwb ** 3:.4f}): no index solves Eq. (10)"
        else:
            below_vacuum, _ = judge(g, sg, VACUUM_INDEX, np.inf, k)
            outside, departure = judge(g, sg, low, high, k)
            status = "impossible" if below_vacuum else "implausible" if outside else "plausible"
        out.append(Check(stage, lens, "window_index", b, "", float(g), _sigma_or_nan(sg), "1", low, high, k,
                         departure, status, "window_index_range", range_reason("window_index_range"), derivation))
    return out


def conversion_gain_checks(ds: xr.Dataset, *, settings: dict, lens: str = "", stage: str = "linearity") -> list[Check]:
    """The linearity artefact's photon-transfer conversion gain (where measured) and each gain-sweep ISO's,
    against ``plausibility.conversion_gain_min_dn_per_e`` (exclusive, no margin: impossible at or below).

    Parameters
    ----------
    ds : xarray.Dataset
        The linearity artefact of one lens.
    settings : dict
        The ``plausibility`` section of the configuration (:func:`plausibility_settings`).
    lens : str, default ""
        The lens, recorded in the checks.
    stage : str, default "linearity"
        The stage, recorded in the checks.

    Returns
    -------
    list of Check
        One per checked value (empty when there is nothing to check).
    """
    low = float(settings["conversion_gain_min_dn_per_e"])
    k = float(settings["margin_sigma"])
    values = []
    if "conversion_gain_dn_per_e" in ds and int(ds["conversion_gain_dn_per_e"].attrs.get("measured", 1)):
        values.append(("", float(ds["conversion_gain_dn_per_e"].values),
                       float(ds["conversion_gain_dn_per_e_sigma"].values) if "conversion_gain_dn_per_e_sigma" in ds
                       else float("nan"), "photon transfer of the exposure sweep"))
    if "ptc_gain_sweep_conversion_gain_dn_per_e" in ds:
        for iso, g in zip(ds["ptc_iso"].values, ds["ptc_gain_sweep_conversion_gain_dn_per_e"].values):
            values.append((f"ISO {float(iso):g}", float(g), float("nan"), "photon transfer of the gain sweep"))
    out = []
    for at, value, sigma, derivation in values:
        if not np.isfinite(value):
            continue
        outside, departure = judge(value, 0.0, low, np.inf, k, low_inclusive=False)
        out.append(Check(stage, lens, "conversion_gain_dn_per_e", "", at, value, sigma, "DN/electron", low, np.inf,
                         0.0, departure, "impossible" if outside else "plausible", "conversion_gain_min_dn_per_e",
                         range_reason("conversion_gain_min_dn_per_e"),
                         derivation + "; judged on the value alone, its inverse being what is used"))
    return out


def _labels(da: xr.DataArray):
    """(band, at) of every element of ``da``: its ``band`` coordinate, the other coordinates as text."""
    for idx in np.ndindex(da.shape):
        sel = {d: da[d].values[i] if d in da.coords else i for d, i in zip(da.dims, idx)}
        band = str(sel.pop("band")) if "band" in sel else ""
        yield idx, band, ", ".join(f"{d} {v}" for d, v in sel.items())


def quantum_efficiency_checks(ds: xr.Dataset, *, settings: dict, lens: str = "", stage: str = "") -> list[Check]:
    """Every element of an artefact variable ``quantum_efficiency`` (with ``quantum_efficiency_sigma`` when
    stated) against ``plausibility.quantum_efficiency_range``, (low, high].

    Parameters
    ----------
    ds : xarray.Dataset
        An artefact of one lens.
    settings : dict
        The ``plausibility`` section of the configuration (:func:`plausibility_settings`).
    lens : str, default ""
        The lens, recorded in the checks.
    stage : str, default ""
        The stage, recorded in the checks.

    Returns
    -------
    list of Check
        One per checked value (empty when there is nothing to check).
    """
    if "quantum_efficiency" not in ds:
        return []
    low, high = (float(v) for v in settings["quantum_efficiency_range"])
    k = float(settings["margin_sigma"])
    qe = ds["quantum_efficiency"]
    sig = ds["quantum_efficiency_sigma"].values if "quantum_efficiency_sigma" in ds else np.full(qe.shape, np.nan)
    out = []
    for idx, band, at in _labels(qe):
        value, sigma = float(qe.values[idx]), float(np.asarray(sig)[idx])
        if not np.isfinite(value):
            continue
        outside, departure = judge(value, sigma, low, high, k, low_inclusive=False)
        out.append(Check(stage, lens, "quantum_efficiency", band, at, value, sigma, "electron/photon", low, high, k,
                         departure, "impossible" if outside else "plausible", "quantum_efficiency_range",
                         range_reason("quantum_efficiency_range"), "artefact variable quantum_efficiency"))
    return out


def _largest_angle_deg(ds: xr.Dataset, medium: str, band: str) -> float:
    """The largest field angle (degree) the roll-off of ``medium`` and ``band`` was measured at (its
    fitted settings), NaN when the artefact has no settings table."""
    if "obs_setting__theta_deg" not in ds:
        return float("nan")
    theta = np.abs(np.asarray(ds["obs_setting__theta_deg"].values, dtype=float))
    keep = np.isfinite(theta)
    for column, wanted in (("obs_setting__medium", medium), ("obs_setting__band", band)):
        if column in ds:
            keep &= np.asarray(ds[column].values).astype(str) == wanted
    if "obs_setting__used" in ds:
        keep &= np.asarray(ds["obs_setting__used"].values).astype(bool)
    return float(theta[keep].max()) if keep.any() else float("nan")


def rolloff_checks(coefficients, covariance, largest_angle_deg: float, *, settings: dict, lens: str = "",
                   band: str = "", medium: str = "", stage: str = "rolloff") -> list[Check]:
    """g(theta) / g(0) of one roll-off curve (coefficients a0..a8 of Eq. 13, theta in degrees; covariance
    optional) from one ``plausibility.rolloff_step_deg`` off the axis to ``largest_angle_deg``, against
    ``plausibility.rolloff_max``; one Check, at the angle that goes furthest beyond the margin (the closest
    approach when none does).

    Parameters
    ----------
    coefficients : array_like
        The roll-off polynomial's coefficients a0..a8 (Eq. 13, theta in degree).
    covariance : numpy.ndarray or None
        Their covariance.
    largest_angle_deg : float
        The largest measured field angle of the medium, degree.
    settings : dict
        The ``plausibility`` section of the configuration (:func:`plausibility_settings`).
    lens : str, default ""
        The lens, recorded in the checks.
    band : str, default ""
        The band, recorded in the check.
    medium : str, default ""
        The medium, recorded in the check.
    stage : str, default "rolloff"
        The stage, recorded in the check.

    Returns
    -------
    list of Check
        One check (empty for non-finite coefficients, a0 <= 0 or no angle to check).
    """
    coef = np.asarray(coefficients, dtype=float)
    if not (np.all(np.isfinite(coef)) and np.isfinite(largest_angle_deg)) or coef[0] <= 0:
        return []
    step = float(settings["rolloff_step_deg"])
    theta = np.arange(step, largest_angle_deg + step / 2, step)
    if theta.size == 0:
        return []
    if covariance is not None and np.all(np.isfinite(covariance)):
        g, sg = evaluate_rolloff(coef, theta, np.asarray(covariance, dtype=float))
    else:
        g, sg = evaluate_rolloff(coef, theta), np.full(theta.shape, np.nan)
    # relative to the on-axis value a0 (1 for a normalised curve, whose a0 has no variance)
    g, sg = g / coef[0], sg / coef[0]
    high = float(settings["rolloff_max"])
    k = float(settings["margin_sigma"])
    excess = g - high - k * np.where(np.isfinite(sg), sg, 0.0)
    at = int(np.argmax(excess))
    outside, departure = judge(float(g[at]), float(sg[at]), -np.inf, high, k)
    derivation = (f"Eq. (13) over {step:g} to {largest_angle_deg:.1f} degree in steps of {step:g}, divided by its "
                  f"on-axis value a0 = {coef[0]:.4g}" + ("" if np.isfinite(sg[at]) else "; no covariance stated"))
    return [Check(stage, lens, "rolloff", band, f"{medium + ', ' if medium else ''}theta {theta[at]:g} degree",
                  float(g[at]), float(sg[at]), "1", -np.inf, high, k, departure,
                  "implausible" if outside else "plausible", "rolloff_max", range_reason("rolloff_max"), derivation)]


def dark_current_checks(ds: xr.Dataset, *, settings: dict, lens: str = "", stage: str = "dark") -> list[Check]:
    """The dark artefact's dark current D (DN/s at ISO 100) where the dark frames measured it, against
    ``plausibility.dark_current_min_dn_per_s``.

    Parameters
    ----------
    ds : xarray.Dataset
        The dark artefact of one lens.
    settings : dict
        The ``plausibility`` section of the configuration (:func:`plausibility_settings`).
    lens : str, default ""
        The lens, recorded in the checks.
    stage : str, default "dark"
        The stage, recorded in the check.

    Returns
    -------
    list of Check
        One check, or none where the dark current was not measured.
    """
    if "dark_current_dn_per_s" not in ds or not int(ds["dark_current_dn_per_s"].attrs.get("measured", 1)):
        return []
    value = float(ds["dark_current_dn_per_s"].values)
    sigma = float(ds["dark_current_dn_per_s_sigma"].values) if "dark_current_dn_per_s_sigma" in ds else float("nan")
    if not np.isfinite(value):
        return []
    low = float(settings["dark_current_min_dn_per_s"])
    k = float(settings["margin_sigma"])
    outside, departure = judge(value, sigma, low, np.inf, k)
    return [Check(stage, lens, "dark_current_dn_per_s", "", "ISO 100", value, sigma, "DN s-1", low, np.inf, k,
                  departure, "impossible" if outside else "plausible", "dark_current_min_dn_per_s",
                  range_reason("dark_current_min_dn_per_s"), "the dark model's D, Eq. (1)")]


def _immersion(ds: xr.Dataset, settings: dict, lens: str, stage: str) -> list[Check]:
    if "immersion_factor" not in ds or "n_w" not in ds:
        return []
    sigma = ds["immersion_factor_sigma"].values if "immersion_factor_sigma" in ds else None
    bands = [str(b) for b in ds["band"].values] if "band" in ds.coords else None
    return window_index_checks(ds["immersion_factor"].values, ds["n_w"].values, sigma, settings=settings, lens=lens,
                               bands=bands, stage=stage)


def _rolloff(ds: xr.Dataset, settings: dict, lens: str, stage: str) -> list[Check]:
    if "rolloff_coefficients" not in ds:
        return []
    coef = ds["rolloff_coefficients"]
    out = []
    for medium in (coef["medium"].values if "medium" in coef.dims else [""]):
        for band in (coef["band"].values if "band" in coef.dims else [""]):
            sel = {d: v for d, v in (("medium", medium), ("band", band)) if d in coef.dims}
            cov = ds["rolloff_covariance"].sel(sel).values if "rolloff_covariance" in ds else None
            out += rolloff_checks(coef.sel(sel).values, cov, _largest_angle_deg(ds, str(medium), str(band)),
                                  settings=settings, lens=lens, band=str(band), medium=str(medium), stage=stage)
    return out


def check_artefacts(artefacts: dict[str, dict[str, xr.Dataset]], config: dict | None = None) -> pd.DataFrame:
    """Every check the artefacts allow, one row per checked value (:data:`COLUMNS`), in the order of the chain.

    Parameters
    ----------
    artefacts : dict[str, dict[str, xarray.Dataset]]
        {stage: {lens: the stage's artefact}}.
    config : dict, optional
        The run's configuration (its ``plausibility`` section; the schema's defaults without one).

    Returns
    -------
    pandas.DataFrame
        One row per checked value: where it is from, value and sigma with units, range, margin, departure,
        ``status`` (plausible, implausible or impossible), the range's key and reason, and the derivation.
    """
    settings = plausibility_settings(config)
    rows: list[Check] = []
    for stage, by_lens in artefacts.items():
        for lens, ds in by_lens.items():
            if stage == "dark":
                rows += dark_current_checks(ds, settings=settings, lens=lens, stage=stage)
            if stage == "linearity":
                rows += conversion_gain_checks(ds, settings=settings, lens=lens, stage=stage)
            if stage == "rolloff":
                rows += _rolloff(ds, settings, lens, stage)
            if stage == "immersion":
                rows += _immersion(ds, settings, lens, stage)
            rows += quantum_efficiency_checks(ds, settings=settings, lens=lens, stage=stage)
    return pd.DataFrame([asdict(r) for r in rows], columns=list(COLUMNS))


def findings(table: pd.DataFrame) -> pd.DataFrame:
    """The rows of a :func:`check_artefacts` table (or its CSV) that are not plausible, the impossible
    first.

    Parameters
    ----------
    table : pandas.DataFrame
        A :func:`check_artefacts` table (or its CSV read back), columns ``COLUMNS``.

    Returns
    -------
    pandas.DataFrame
        The rows whose status is not ``plausible``, ``impossible`` first.
    """
    if table is None or table.empty or "status" not in table:
        return pd.DataFrame(columns=list(COLUMNS))
    bad = table[table["status"].astype(str) != "plausible"]
    order = bad["status"].map({s: -i for i, s in enumerate(STATUSES)})
    return bad.assign(_order=order).sort_values("_order", kind="stable").drop(columns="_order")


def _number(value: float) -> str:
    return f"{float(value):.4g}"


def range_text(low: float, high: float) -> str:
    """A range as words: 'at least 0', 'at most 1', '1.3 to 2'.

    Parameters
    ----------
    low : float
        The lower bound (``-inf``: none).
    high : float
        The upper bound (``inf``: none).

    Returns
    -------
    str
        The words.
    """
    low_ok, high_ok = np.isfinite(float(low)), np.isfinite(float(high))
    if low_ok and high_ok:
        return f"{_number(low)} to {_number(high)}"
    return f"at least {_number(low)}" if low_ok else f"at most {_number(high)}" if high_ok else "any value"


def finding_sentence(row, with_reason: bool = False) -> str:
    """One checked value in a line: lens, band and where, the quantity, value ± sigma with units, the range
    and the config key that sets it, how far beyond it, the verdict and how the value was derived; with
    ``with_reason`` the range's reason after it.

    Parameters
    ----------
    row : pandas.Series or dict
        A row of a :func:`check_artefacts` table.
    with_reason : bool, default False
        Append the range's reason.

    Returns
    -------
    str
        The line.
    """
    units = "" if str(row["units"]) in ("1", "", "nan") else f" {row['units']}"
    sigma = float(row["sigma"])
    value = _number(row["value"]) + (f" ± {float(sigma):.2g}" if np.isfinite(sigma) else "") + units
    if not np.isfinite(float(row["value"])):
        value = "none"
    where = ", ".join(str(p) for p in (row["band"], row["at"]) if isinstance(p, str) and p and p != "nan")
    lens = f"the {row['lens']} lens" if isinstance(row["lens"], str) and row["lens"] else "the camera"
    departure = float(row["departure_sigma"])
    beyond = f", {departure:.1f} standard uncertainties beyond it" if np.isfinite(departure) else ""
    return (f"{lens}{' (' + where + ')' if where else ''}, {row['stage']}: "
            f"{LABELS.get(str(row['quantity']), str(row['quantity']))} {value}, "
            f"{'within' if str(row['status']) == 'plausible' else 'outside'} "
            f"{range_text(row['low'], row['high'])} (plausibility.{row['range_key']}){beyond}: {row['status']} "
            f"({row['derivation']})" + (f". {row['reason']}" if with_reason else ""))


def summary_lines(table: pd.DataFrame) -> list[str]:
    """One line per checked quantity of a :func:`check_artefacts` table: how many values, their span, the
    range and the config key, how many fall outside it (the findings themselves: :func:`finding_sentence`).

    Parameters
    ----------
    table : pandas.DataFrame
        A :func:`check_artefacts` table (or its CSV read back), columns ``COLUMNS``.

    Returns
    -------
    list of str
        The lines (empty for an empty table).
    """
    if table is None or table.empty or "quantity" not in table:
        return []
    out = []
    for quantity, rows in table.groupby("quantity", sort=False):
        values = rows["value"].astype(float)
        finite = values[np.isfinite(values)]
        span = (f"{_number(finite.min())} to {_number(finite.max())}" if len(finite) else "none finite")
        units = "" if str(rows["units"].iloc[0]) in ("1", "", "nan") else f" {rows['units'].iloc[0]}"
        bad = int((rows["status"].astype(str) != "plausible").sum())
        out.append(f"{LABELS.get(str(quantity), str(quantity))}: {len(rows)} value(s), {span}{units}; range "
                   f"{range_text(rows['low'].iloc[0], rows['high'].iloc[0])} (plausibility.{rows['range_key'].iloc[0]}); "
                   + (f"{bad} outside" if bad else "all within"))
    return out
