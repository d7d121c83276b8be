"""Closure across experiments, and per-lens parameters (docs/design.md, "Closure and diagnostics"; issue 10).

Each stage predicts its own measurements; here the calibration predicts measurements of one
experiment from the fitted parameters of another, as observation tables of the experiment
``closure`` that the diagnostics test like any other (:func:`closure_observations`: residual
chi-square against its degrees of freedom, the closure table, ``diagnose``'s sentences).

* ``closure/responsivity``: the DN per second at ISO 100 on the optical axis that each experiment
  saw, ln of it, one row per source, lens and band. The sources are not the same: the linearity
  sweeps and the roll-off look at the integrating sphere (docs/dataset-format.md), at levels the lab does not
  log (the gain sweep's is dimmer so that ISO 3200 does not saturate); the absolute experiment looks
  at a port whose spectrum it measures (``source_spectrum.csv``), which no other experiment states.
  What can honestly be compared is therefore (i) the band ratios of the sources that share the
  sphere, whose spectrum does not change when its level is changed by an aperture (a neutral
  attenuation; ``diagnostics.closure_shared_spectrum_sources``), and (ii) the ratio of the two
  lenses' responsivities in every band, which every experiment sees (each lens faces the same
  source in turn). The model: ln DN/s = ln R(lens, band) + ln L(source), with one free level per
  shared-spectrum source and one per band for each other source. Each experiment's DN/s is
  corrected with its own fitted parameters and the linearity's: the exposure sweep's rate is the
  linearity model's (shutter offset, ISO gain and nonlinearity fitted beside it); the gain sweep's
  rate, fitted against the nominal exposure, is divided by (t + shutter offset) / t; the roll-off's
  on-axis DN (a0 of its polynomial fit to the spot signals in air, Eq. 13) is linearised with the
  linearity's nonlinearity and divided by the true exposure (t + offset) times ISO / 100 (the
  roll-off frames are at ISO 100, where the ISO gain factor is 1 by definition; at another ISO its
  factor would be left out); the
  absolute stage's DN/s comes corrected by the fitted response. Each mask mean is the axis value
  times the mean roll-off over the mask (equidistant: weight theta d theta), from the roll-off
  artefact, which the linearity and absolute rows are divided by (the mask half-angles as the
  linearity artefact's recorded config and the absolute artefact state them). The uncertainty of each row is
  its own stage's standard error (relative, since the value is a logarithm), and in quadrature the lab's
  stated stability of the source's level between the two lenses' sessions
  (``diagnostics.closure_source_level_rel_sigma``, default 0: the quiet lab): each experiment takes one
  lens's frames and then the other's, so a slow drift of the source moves each lens's rows of a source by
  its own factor, which each lens's fit takes as its level and no stage's error holds (on the simulator's
  lab noise, drift 0.2 % amplitude, it is what lifts the table to chi2 18 to 33 for 13 dof; 0.001 to 0.0015
  brings it back to about its dof). A diagonal term, though the drift is common to a source and lens's three bands: the
  rows are tested one block each (below), and the stated size is the lab's, not fitted. The table is tested by
  its chi-square tail, one block per row: the three bands of one source and lens share frames, but
  with eight source-lens blocks a block test cannot tell a source whose level moved between the
  lenses' sessions from block noise, and that movement is what the table is there to find; the
  stages' standard errors hold the frames' common fluctuations as far as their noise models do.
* ``closure/dark_corners``: the dark model (bias, bias per gain, dark current and temperature term
  of the dark stage, and its fixed-pattern map over the same corner pixels) against the unlit
  corners of every lit frame. Every lit stage records each signal frame's unlit-corner mean and the
  dark model's prediction there (``corner_dn``, ``dark_corner_dn``, ``sigma_corner_dn``: the linearity
  in its ``obs_frame``, the roll-off, spectral, absolute and immersion stages in their ``obs_corner``,
  :mod:`pipeline.radiometry.unlit_corners`), and the table holds the rows of all of them
  (:data:`CORNER_EXPERIMENTS`), each named by the covariate ``experiment``. The
  value is the measured minus the predicted mean, its noise the corners' read noise over their
  pixel count (and, with ``bias_drift`` in the model, the lens's fitted frame-to-frame black-level
  spread from its linearity artefact, for every experiment's frames). One free level per lens, band
  and ISO, shared by the experiments: the dark model has one fixed-pattern map for all ISOs, and
  its mean over a small image's few hundred corner pixels departs at another ISO by a few tenths
  of the corners' noise (measured on the tiny simulated camera: per-setting means of z up to 0.6);
  the table tests how the corners follow the experiment, exposure time, temperature and the frame
  sequence, which a dark model wrong for one experiment's frames (their black level off), a missing
  dark current, a temperature term or a frame's bias offset change. A level per experiment would take
  up the first of these, so there is none. Without ``bias_drift``
  the model says the rows are independent (the corners of the three bands are different pixels), so
  each row is its own block (the frame is named by ``frame_index``, counted within its experiment);
  with it, the frames' black-level spread is common to a frame's rows, and the frame (``file_index``,
  the experiments' frame numbers made distinct) is the block. The table carries the covariates every
  experiment's record has (ISO, gain, exposure, temperature, the linearity's ``sweep``, '' elsewhere);
  the stages' own keys (medium, azimuth, wavelength, water height) stay in their artefacts.
* ``closure/field_angle``: the geometric calibration against the roll-off's rotation stage, the lens
  model's field angle of each port spot in the rotation plane against the stage's logged angle, with the
  model's covariance as whitened nuisance columns and their prior rows
  (:mod:`pipeline.diagnostics.field_angle_closure`).

Per-lens parameters (:func:`lens_interaction_tests`): the two lenses are two sensors, so dark
current, shutter offset and the ISO gain factors may differ between them. Every stage fits each lens
on its own (one job and one artefact per lens), so an effect of the model has each lens's own value
in its artefact, and the diagnostics refit it per lens on their pooled tables
(:func:`pipeline.diagnostics.missing_effects.per_lens_columns`); a candidate is tested with one column shared by the
lenses (``Effect.columns``). Whether one shared value is enough: for each effect of
``diagnostics.lens_interaction_effects`` (in the model or a candidate), on every table whose rows
carry both lenses, the effect's columns shared by the lenses are compared with the same columns split
per lens (the rest of the model as it is): the drop in chi-square F-tested against the split model's residual variance and, by
block, with the same drop by generalised least squares under the noise common to a block
(:func:`pipeline.stats.fitting.block_gls_drop`, the reference of ``diagnostics.block_reference``, as the
candidates are tested; the larger
p-value, Bonferroni over the tests made). Each lens's value and its 95 % interval come from the split fit.

Nothing here reads a simulator's truth: only the stage artefacts.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import xarray as xr
from scipy import stats

from pipeline.io.bands import BANDS
from pipeline.stats.block_bootstrap import BlockTestPart, block_test_p_value
from pipeline.diagnostics.tables import Observations, blocks_of, fit_observations, model_design
from pipeline.effects import available
from pipeline.effects import get as get_effect
from pipeline.diagnostics.field_angle_closure import LEVEL as FIELD_ANGLE_LEVEL
from pipeline.diagnostics.field_angle_closure import PRIOR_KIND as FIELD_ANGLE_PRIOR_KIND
from pipeline.diagnostics.field_angle_closure import field_angle_table
from pipeline.stats.fitting import base_design, block_gls_drop, wls
from pipeline.stages.observations import CORNER_PREFIX, dataset_to_table, datasets_by_lens, lens_of
from pipeline.radiometry.exposure import gain_from_iso
from pipeline.radiometry.rolloff import evaluate_rolloff

__all__ = ["EXPERIMENT", "LENS_TEST_COLUMNS", "closure_observations", "dark_corner_table", "describe_closure", "lens_findings",
           "lens_interaction_tests", "responsivity_table"]

#: the experiment name of the cross-experiment tables
EXPERIMENT = "closure"
#: sources of the responsivity closure: the linearity's two sweeps, the roll-off in air, the absolute port
SOURCES = ("linearity_exposure", "linearity_gain", "rolloff_air", "absolute")
#: experiments whose lit frames record their unlit corners against the dark model, in the table's row order
CORNER_EXPERIMENTS = ("linearity", "rolloff", "spectral", "absolute", "immersion")
#: the lit stages' own keys of a corner record (``obs_corner``) that tell its settings apart (the closure table
#: carries only the columns every experiment has: ISO, gain, exposure, temperature, the frame)
STAGE_CORNER_KEYS = ("medium", "azimuth_deg", "angle_deg", "wavelength_nm", "water_height_cm")
#: columns of ``lens_tests.csv``, one row per effect and table tested
LENS_TEST_COLUMNS = ("effect", "experiment", "level", "in_model", "lenses", "values", "lows", "highs", "units",
                     "amplitude_name", "shared", "chi2_shared", "chi2_split", "dof_split", "n_params", "p_value",
                     "p_value_model", "p_value_block", "n_blocks", "significant", "message")


def _stage_setting(ds: xr.Dataset, stage: str, key: str, default: float) -> float:
    """A setting of the stage that wrote ``ds``, from the config subset its artefact records (the diagnostics
    rule is given only the model and diagnostics sections)."""
    try:
        return float(json.loads(ds.attrs.get("config", "{}")).get(stage, {}).get(key, default))
    except (json.JSONDecodeError, TypeError, ValueError):
        return default


def _effect_value(ds: xr.Dataset, name: str) -> float:
    """The first fitted parameter of effect ``name`` in a stage artefact, 0 when it is not in its model."""
    var = f"effect_{name}"
    return float(np.ravel(ds[var].values)[0]) if var in ds else 0.0


def mean_mask_rolloff(coefficients, half_angle_deg: float, n: int = 64) -> float:
    """Mean of g(theta) over a disc of half-angle ``half_angle_deg`` about the axis.

    Weight theta dtheta (an equidistant projection's pixel area), for the roll-off polynomial ``coefficients``
    (Eq. 13).

    Parameters
    ----------
    coefficients : array_like
        The roll-off polynomial's coefficients (:func:`pipeline.radiometry.rolloff.evaluate_rolloff`).
    half_angle_deg : float
        The disc's half angle, degree.
    n : int, default 64
        Points of the trapezoidal rule.

    Returns
    -------
    float
        The mean relative response (dimensionless; g(0) for a half angle of 0).
    """
    theta = np.linspace(0.0, float(half_angle_deg), n)
    g = np.asarray(evaluate_rolloff(coefficients, theta), dtype=float)
    return float(np.trapezoid(g * theta, theta) / np.trapezoid(theta, theta)) if half_angle_deg > 0 else float(g[0])


def _rolloff_axis(ds: xr.Dataset) -> pd.DataFrame:
    """Per band, the roll-off's on-axis DN in air (a0 of the polynomial fit, Eq. 13) with its standard
    error, the frames' exposure and ISO: the spot rows of ``obs_setting`` refitted on their base columns."""
    t = dataset_to_table(ds, "obs_setting")
    need = {"kind", "medium", "signal_dn", "value_dn", "sigma_dn", "exposure_s", "iso"}
    if not need <= set(t.columns):
        return pd.DataFrame()
    t = t[(t["kind"].astype(str) == "spot") & (t["medium"].astype(str) == "air")]
    if "used" in t:
        t = t[t["used"].astype(int) == 1]
    rows = []
    for band, g in t.groupby("band"):
        g = g.reset_index(drop=True)
        a0 = float(np.median(g["signal_dn"] / g["value_dn"]))      # the stage's normalisation (DN)
        X, names = base_design(g)
        # less the fitted effects' share of each spot (stray light with it in the model), as the stage fits a0
        y = g["value_dn"].to_numpy(float) - (np.nan_to_num(g["effect_dn"].to_numpy(float)) if "effect_dn" in g else 0.0)
        fit = wls(y, g["sigma_dn"].to_numpy(float), X)
        k = [i for i, n in enumerate(names) if n.endswith(":p0")]
        if not k:
            continue
        scale = max(fit.chi2 / max(fit.dof, 1), 1.0)
        rows.append({"band": str(band), "axis_dn": a0 * float(fit.coef[k[0]]),
                     "axis_sigma_dn": a0 * float(np.sqrt(fit.cov[k[0], k[0]] * scale)),
                     "exposure_s": float(g["exposure_s"].mean()), "iso": float(g["iso"].mean())})
    return pd.DataFrame(rows)


def responsivity_table(loaded: dict[str, list[xr.Dataset]], config: dict) -> pd.DataFrame:
    """``closure/responsivity`` (module docstring): ln DN/s at ISO 100 on the axis per source, lens and band.

    Parameters
    ----------
    loaded : dict[str, list of xarray.Dataset]
        The stage artefacts per stage, one per lens.
    config : dict
        The configuration (its ``diagnostics`` section).

    Returns
    -------
    pandas.DataFrame
        One row per source, lens and band: the axis rate at ISO 100 (``rate``, DN s-1) and its sigma,
        ``value_dn`` = ln(rate) and ``sigma_dn`` its relative sigma (with the source level's between the
        sessions), and the response and source columns ``x_*``; empty when there is nothing to close.
    """
    lin = datasets_by_lens(loaded.get("linearity", []))
    roll = datasets_by_lens(loaded.get("rolloff", []))
    absolute = datasets_by_lens(loaded.get("absolute", []))
    shared = set(config["diagnostics"]["closure_shared_spectrum_sources"])
    rows = []

    def mask_factor(lens, band, half_angle):
        if lens not in roll or "rolloff_coefficients" not in roll[lens]:
            return 1.0
        c = roll[lens]["rolloff_coefficients"].sel(medium="air", band=band).values
        return mean_mask_rolloff(c, half_angle) if np.all(np.isfinite(c)) else 1.0

    for lens, ds in lin.items():
        offset = _effect_value(ds, "shutter_offset")
        st = dataset_to_table(ds, "obs_setting")
        t_gain = st.loc[st["sweep"].astype(str) == "gain", "exposure_s"]
        for sweep in ("exposure", "gain"):
            if sweep not in [str(s) for s in ds["rate_dn_per_s"]["sweep"].values]:
                continue
            for band in BANDS:
                rate = float(ds["rate_dn_per_s"].sel(sweep=sweep, band=band))
                relative = float(ds["rate_dn_per_s_sigma"].sel(sweep=sweep, band=band)) / rate
                if sweep == "gain" and len(t_gain):
                    t = float(t_gain.iloc[0])
                    rate *= t / (t + offset)
                rate /= mask_factor(lens, band, _stage_setting(ds, "linearity", "mask_half_angle_deg", 0.0))
                rows.append({"source": f"linearity_{sweep}", "lens": lens, "band": band, "rate": rate,
                             "sigma": relative * rate})
    for lens, ds in roll.items():
        axis = _rolloff_axis(ds)
        lin_ds = lin.get(lens)
        offset = _effect_value(lin_ds, "shutter_offset") if lin_ds is not None else 0.0
        beta = _effect_value(lin_ds, "nonlinearity") if lin_ds is not None else 0.0
        full = float(lin_ds["nonlinearity_full_scale_dn"]) if lin_ds is not None and beta else np.nan
        for r in axis.itertuples():
            dn = r.axis_dn / (1.0 - beta * r.axis_dn / full) if beta and np.isfinite(full) else r.axis_dn
            per_s = (r.exposure_s + offset) * r.iso / 100.0
            rows.append({"source": "rolloff_air", "lens": lens, "band": r.band, "rate": dn / per_s,
                         "sigma": r.axis_sigma_dn * dn / r.axis_dn / per_s})
    for lens, ds in absolute.items():
        for band in BANDS:
            f = mask_factor(lens, band, float(ds["mask_half_angle_deg"]))
            se = np.hypot(float(ds["dn_per_s_standard_error"].sel(band=band)),
                          float(ds["dn_per_s_response_sigma"].sel(band=band)))
            rows.append({"source": "absolute", "lens": lens, "band": band,
                         "rate": float(ds["dn_per_s"].sel(band=band)) / f, "sigma": se / f})
    tab = pd.DataFrame(rows)
    if not len(tab) or tab["lens"].nunique() < 2 and tab["source"].nunique() < 2:
        return pd.DataFrame()
    tab = tab[np.isfinite(tab["rate"]) & (tab["rate"] > 0) & np.isfinite(tab["sigma"]) & (tab["sigma"] > 0)]
    tab = tab.reset_index(drop=True)
    tab["value_dn"] = np.log(tab["rate"])
    # the source's level between the lenses' sessions (module docstring), which no stage's error holds
    level = float(config["diagnostics"].get("closure_source_level_rel_sigma", 0.0))
    tab["sigma_dn"] = np.hypot(tab["sigma"] / tab["rate"], level)
    tab["group"] = EXPERIMENT
    for lens in sorted(tab["lens"].unique()):
        for band in BANDS:
            tab[f"x_response_{lens}_{band}"] = ((tab["lens"] == lens) & (tab["band"] == band)).astype(float)
    for source in sorted(tab["source"].unique()):
        if source in shared:
            tab[f"x_source_{source}"] = (tab["source"] == source).astype(float)
        else:
            for band in BANDS:
                tab[f"x_source_{source}_{band}"] = ((tab["source"] == source) & (tab["band"] == band)).astype(float)
    return tab


def _drift_dn(ds: xr.Dataset) -> float:
    """The frames' fitted black-level spread of a linearity artefact (0 without ``bias_drift`` in its model)."""
    if "bias_drift" in str(ds.attrs.get("model_effects", "")).split(",") and "bias_drift_dn" in ds:
        return float(ds["bias_drift_dn"])
    return 0.0


def _linearity_corners(ds: xr.Dataset, blocked: bool) -> pd.DataFrame:
    """The linearity frames' corner rows, from its ``obs_frame`` (the values its ``obs_corner`` also holds)."""
    t = dataset_to_table(ds, "obs_frame")
    if not {"corner_dn", "dark_corner_dn", "sigma_corner_dn"} <= set(t.columns) or not len(t):
        return pd.DataFrame()
    t = t[np.isfinite(t["corner_dn"].astype(float)) & ~t["saturated"].astype(bool)].reset_index(drop=True)
    out = t[[c for c in ("lens", "band", "sweep", "iso", "exposure_s", "gain", "temperature_c") if c in t]].copy()
    out["frame_index"] = t["file_index"].to_numpy()
    if blocked:
        out["file_index"] = t["file_index"].to_numpy()
        out["setting"] = t["setting"].to_numpy()
    for col in ("corner_dn", "dark_corner_dn", "sigma_corner_dn"):
        out[col] = t[col].astype(float).to_numpy()
    return out


def _stage_corners(ds: xr.Dataset, blocked: bool) -> pd.DataFrame:
    """A lit stage's corner rows, from its ``obs_corner`` (:mod:`pipeline.radiometry.unlit_corners`)."""
    t = dataset_to_table(ds, CORNER_PREFIX)
    if not {"corner_dn", "dark_corner_dn", "sigma_corner_dn"} <= set(t.columns) or not len(t):
        return pd.DataFrame()
    ok = np.isfinite(t["corner_dn"].astype(float)) & np.isfinite(t["dark_corner_dn"].astype(float))
    if "saturated" in t:
        ok &= ~t["saturated"].astype(bool)
    t = t[ok].reset_index(drop=True)
    out = t[["lens", "band", "iso", "exposure_s"]].copy()
    out["gain"] = gain_from_iso(out["iso"].astype(float))
    if "temperature_c" in t and np.isfinite(t["temperature_c"].astype(float)).any():
        out["temperature_c"] = t["temperature_c"].astype(float).to_numpy()
    out["frame_index"] = t["file_index"].to_numpy()
    if blocked:
        out["file_index"] = t["file_index"].to_numpy()
        # the frames of one setting: the same ISO and exposure and the stage's own keys (medium, wavelength...)
        keys = [c for c in STAGE_CORNER_KEYS if c in t]
        out["setting"] = t.groupby(["iso", "exposure_s", *keys], sort=True, dropna=False).ngroup().to_numpy()
    for col in ("corner_dn", "dark_corner_dn", "sigma_corner_dn"):
        out[col] = t[col].astype(float).to_numpy()
    return out


def dark_corner_table(loaded: dict[str, list[xr.Dataset]], config: dict) -> pd.DataFrame:
    """``closure/dark_corners`` (module docstring): each lit frame's unlit-corner mean against the dark model's
    prediction there, one row per frame, lens and band, of every experiment that recorded them
    (:data:`CORNER_EXPERIMENTS`), named in the covariate ``experiment``.

    Parameters
    ----------
    loaded : dict[str, list of xarray.Dataset]
        The stage artefacts per stage, one per lens.
    config : dict
        The configuration (its ``diagnostics`` section).

    Returns
    -------
    pandas.DataFrame
        ``value_dn`` the corner mean less the dark model's prediction (DN), ``sigma_dn`` its sigma (DN, the
        frames' black-level spread added with ``bias_drift``), ``group`` (lens/band/ISO) and ``x_level``; empty
        when no experiment recorded corners.
    """
    drift = {lens: _drift_dn(ds) for lens, ds in datasets_by_lens(loaded.get("linearity", [])).items()}
    # the frames' fitted black-level offsets are common to a frame's rows: then one block each
    blocked = any(d > 0 for d in drift.values())
    parts = []
    for experiment in CORNER_EXPERIMENTS:
        for ds in loaded.get(experiment, []):
            lens = lens_of(ds) or (str(ds[f"{CORNER_PREFIX}__lens"].values[0])
                                    if f"{CORNER_PREFIX}__lens" in ds and ds[f"{CORNER_PREFIX}__lens"].size else None)
            d = drift.get(lens, 0.0) if experiment != "linearity" else _drift_dn(ds)
            t = _linearity_corners(ds, blocked) if experiment == "linearity" else _stage_corners(ds, blocked)
            if not len(t):
                continue
            t.insert(0, "experiment", experiment)
            t["value_dn"] = t["corner_dn"] - t["dark_corner_dn"]
            t["sigma_dn"] = np.hypot(t["sigma_corner_dn"], np.nan_to_num(d))
            parts.append(t.drop(columns=["corner_dn", "dark_corner_dn", "sigma_corner_dn"]))
    if not parts:
        return pd.DataFrame()
    out = pd.concat(parts, ignore_index=True)
    if "sweep" in out:      # the linearity's sweeps; the other experiments' frames belong to none
        out["sweep"] = out["sweep"].fillna("").astype(str)
    if "file_index" in out:
        # with bias_drift the frame is the block: the experiments' frame numbers made distinct (each experiment's
        # frames after the previous one's), their settings likewise
        for col in ("file_index", "setting"):
            base = 0
            values = out[col].astype(float).to_numpy().copy()
            for experiment in out["experiment"].unique():
                sel = (out["experiment"] == experiment).to_numpy()
                values[sel] += base
                base = float(np.nanmax(values[sel])) + 1.0
            out[col] = values.astype(int)
    # one free level per lens, band and ISO, shared by the experiments: a dark-model failure in one experiment's
    # frames is left in its rows' residuals (covariate ``experiment``)
    out["group"] = out["lens"].astype(str) + "/" + out["band"].astype(str) + "/iso" + \
        out["iso"].astype(float).round().astype(int).astype(str)
    out["x_level"] = 1.0
    return out


def closure_observations(loaded: dict[str, list[xr.Dataset]], config: dict) -> list[Observations]:
    """The cross-experiment tables that the artefacts allow, as observation tables of experiment ``closure``.

    Parameters
    ----------
    loaded : dict[str, list of xarray.Dataset]
        The stage artefacts per stage, one per lens.
    config : dict
        The configuration (its ``diagnostics`` section).

    Returns
    -------
    list of Observations
        The ``responsivity`` (units 1), ``dark_corners`` (DN) and field-angle (degree) tables the artefacts allow.
    """
    out = []
    resp = responsivity_table(loaded, config)
    if len(resp) and len(resp) > int(np.linalg.matrix_rank(base_design(resp)[0])):
        out.append(Observations(EXPERIMENT, "responsivity", resp, "1"))
    dark = dark_corner_table(loaded, config)
    if len(dark):
        out.append(Observations(EXPERIMENT, "dark_corners", dark, "DN"))
    angles = field_angle_table(loaded, config)
    if len(angles):
        out.append(Observations(EXPERIMENT, FIELD_ANGLE_LEVEL, angles, "degree"))
    return out


#: what a structured closure table means, per level
MEANING = {
    "responsivity": "the DN per second on the axis that different experiments saw disagree (the band ratios of "
                    "the sphere's sources, or the ratio of the two lenses' responsivities)",
    "dark_corners": "the dark model mispredicts the unlit corners of the lit {experiments} frames",
    FIELD_ANGLE_LEVEL: "the geometric calibration's field angle of the roll-off's port spots disagrees with the "
                       "rotation stage's angle",
}


def _meaning(obs: Observations) -> str:
    """What a structured closure table means, with the experiments whose rows it holds."""
    text = MEANING.get(obs.level, "a cross-experiment closure fails")
    if "{experiments}" in text:
        present = [e for e in CORNER_EXPERIMENTS if "experiment" in obs.table and (obs.table["experiment"] == e).any()]
        named = ", ".join(present[:-1]) + f" and {present[-1]}" if len(present) > 1 else "".join(present)
        text = text.format(experiments=named)
    return text


def _largest_departure(obs: Observations, model_effects: list[str]) -> str:
    fit = fit_observations(obs, model_design(obs, model_effects))
    z = np.abs(fit.z)
    if "kind" in obs.table:     # a prior's pseudo-measurement is not a departure of the data
        z = np.where(obs.table["kind"].astype(str) == FIELD_ANGLE_PRIOR_KIND, np.nan, z)
    i = int(np.nanargmax(z))
    r = obs.table.iloc[i]
    if obs.level == FIELD_ANGLE_LEVEL:
        prior = (obs.table["kind"].astype(str) == FIELD_ANGLE_PRIOR_KIND).to_numpy()
        pulled, n_prior = float(np.sum(fit.z[prior] ** 2)), int(prior.sum())
        return (f"the largest departure is the {r['lens']} lens in {r['medium']}, azimuth plane "
                f"{float(r['azimuth_deg']):g} deg, stage at {float(r['angle_deg']):+g} deg: "
                f"{r['value_dn'] - fit.pred[i]:+.2f} deg ({fit.z[i]:+.1f} sigma); to follow the stage the lens "
                f"models move by chi2 {pulled:.1f} over their stated covariance "
                f"({n_prior} directions, p {stats.chi2.sf(pulled, max(n_prior, 1)):.2g})")
    if obs.level == "responsivity":
        return (f"the largest departure is {r['source']} ({r['lens']} lens, {r['band']}): "
                f"{100.0 * np.expm1(r['value_dn'] - fit.pred[i]):+.2g} % ({fit.z[i]:+.1f} sigma)")
    frame = f"frame {int(r['frame_index'])}, " if "frame_index" in r and np.isfinite(float(r["frame_index"])) else ""
    where = f" ({r['experiment']})" if "experiment" in r else ""
    return (f"the largest departure is {frame}{r['lens']} lens, {r['band']}, ISO {float(r['iso']):.0f}, "
            f"{float(r['exposure_s']):.4g} s{where}: {r['value_dn'] - fit.pred[i]:+.3g} DN ({fit.z[i]:+.1f} sigma)")


def describe_closure(unexplained: pd.DataFrame, observations: list[Observations],
                     model_effects: list[str]) -> pd.DataFrame:
    """The unexplained-structure sentences of the closure tables, with what the table compares and where
    its largest departure is.

    Parameters
    ----------
    unexplained : pandas.DataFrame
        The unexplained-structure table (its ``experiment``, ``level`` and ``message`` columns).
    observations : list of Observations
        The observation tables, the closure's among them.
    model_effects : list of str
        The effects of the model.

    Returns
    -------
    pandas.DataFrame
        A copy of ``unexplained``, the closure tables' messages extended.
    """
    out = unexplained.copy()
    by_level = {o.level: o for o in observations if o.experiment == EXPERIMENT}
    for i, row in out.iterrows():
        if row["experiment"] != EXPERIMENT or row["level"] not in by_level:
            continue
        obs = by_level[row["level"]]
        out.loc[i, "message"] = (f"{_meaning(obs)}: {row['message']}; "
                                 f"{_largest_departure(obs, model_effects)}")
    return out


# ------------------------------------------------------------------------------------------- per lens

def _amount(value: float, units: str) -> str:
    if units == "s" and abs(value) < 0.1:       # shutter offsets read in milliseconds
        return f"{1e3 * value:.3g} ms"
    return f"{value:.3g}" + ("" if units in ("", "1") else f" {units}")


def lens_interaction_tests(observations: list[Observations], model_effects: list[str], config: dict) -> pd.DataFrame:
    """Per effect of ``diagnostics.lens_interaction_effects`` and table with both lenses: one value shared by
    the lenses against one per lens (module docstring). One row per test (columns :data:`LENS_TEST_COLUMNS`).

    Parameters
    ----------
    observations : list of Observations
        The observation tables.
    model_effects : list of str
        The effects of the model.
    config : dict
        The configuration (its ``diagnostics`` section: ``lens_interaction_effects``, block keys and noise
        forms, significance level).

    Returns
    -------
    pandas.DataFrame
        One row per test, columns ``LENS_TEST_COLUMNS``: each lens's value and 95 % interval, the shared value,
        the chi^2 of both fits, the p-values, whether significant, and the sentence.
    """
    cfg = config["diagnostics"]
    names = [n for n in cfg["lens_interaction_effects"] if n in available()]
    rows = []
    for name in names:
        effect = get_effect(name)
        if effect.corrects_data:
            continue
        for obs in observations:
            t = obs.table
            if "lens" not in t:
                continue
            S = effect.columns(obs.experiment, obs.level, t)
            if S is None or not np.any(S):
                continue
            lens_of = t["lens"].astype(str).to_numpy()
            lenses = [lens for lens in sorted(set(lens_of)) if np.any(S[lens_of == lens])]
            if len(lenses) < 2:
                continue
            X = model_design(obs, [e for e in model_effects if e != name])
            per_lens = [S * (lens_of == lens)[:, None] for lens in lenses]
            Xs, Xp = np.hstack([X, S]), np.hstack([X] + per_lens)
            # the same space as Xp: shared columns plus each further lens's difference from the first
            Xd = np.hstack([X, S] + per_lens[1:])
            k = int(np.linalg.matrix_rank(Xp) - np.linalg.matrix_rank(Xs))
            if k <= 0:
                continue
            fit_s, fit_p, fit_d = fit_observations(obs, Xs), fit_observations(obs, Xp), fit_observations(obs, Xd)
            s2 = max(fit_p.chi2 / max(fit_p.dof, 1), 1.0)
            p_model = float(stats.f.sf((fit_s.chi2 - fit_p.chi2) / k / s2, k, max(fit_p.dof, 1)))
            sigma = t["sigma_dn"].to_numpy(float)
            y = t["value_dn"].to_numpy(float)
            blocks, _ = blocks_of(t, cfg["block_keys"])
            forms = cfg["block_noise_forms"]
            # the same drop with the noise common to a block as a random effect (generalised least squares),
            # as the candidates are tested (pipeline.diagnostics.missing_effects)
            gls = block_gls_drop(y, sigma, Xs, Xd, blocks, forms, fit_d)
            p_block, n_blocks = float("nan"), 0
            if gls.k > 0 and gls.n_blocks - 1 > gls.k:
                n_blocks = gls.n_blocks
                f_block = gls.delta_chi2 / gls.k / (gls.chi2 / max(gls.dof, 1))
                # the reference of diagnostics.block_reference, drawn where the rows' test is below the level
                # before the Bonferroni correction (a superset of where it can change the verdict)
                p_block, _, _, _ = block_test_p_value(f_block, gls.k, n_blocks,
                                                   [BlockTestPart(sigma, Xs, Xd, blocks, fit_d, tuple(forms))],
                                                   p_model, cfg["significance_level"], cfg)
            p_value = max(p_model, p_block) if n_blocks else p_model
            # each lens's value and interval: the split fit's covariance, scaled by the residual variance, or
            # the block-noise one (t(G - 1) quantile) where it is wider
            V = fit_p.cov * s2
            split = block_gls_drop(y, sigma, X, Xp, blocks, forms, fit_p)
            if split.n_blocks - 1 > k:
                t_ratio = stats.t.isf(0.025, split.n_blocks - 1) / stats.norm.isf(0.025)
                Vb = split.cov * max(split.chi2 / max(split.dof, 1), 1.0) * t_ratio**2
                d = np.diag(V)[X.shape[1]:]
                if Vb.shape == (len(d), len(d)) and np.all(d > 0) and np.mean(np.diag(Vb) / d) > 1.0:
                    V = V.copy()
                    V[X.shape[1]:, X.shape[1]:] = Vb
            m = S.shape[1]
            values, lows, highs = [], [], []
            for i, lens in enumerate(lenses):
                sl = slice(X.shape[1] + i * m, X.shape[1] + (i + 1) * m)
                amp, lo, hi = effect.amplitude(obs.experiment, obs.level, t[lens_of == lens].reset_index(drop=True),
                                               fit_p.coef[sl], V[sl, sl])
                values.append(amp)
                lows.append(lo)
                highs.append(hi)
            shared_amp = effect.amplitude(obs.experiment, obs.level, t, fit_s.coef[X.shape[1]:],
                                          fit_s.cov[X.shape[1]:, X.shape[1]:])[0]
            label, units = effect.amplitude_label(obs.experiment)
            rows.append({"effect": name, "experiment": obs.experiment, "level": obs.level,
                         "in_model": name in model_effects, "lenses": " ".join(lenses),
                         "values": " ".join(f"{v:.6g}" for v in values), "lows": " ".join(f"{v:.6g}" for v in lows),
                         "highs": " ".join(f"{v:.6g}" for v in highs), "units": units, "amplitude_name": label,
                         "shared": shared_amp, "chi2_shared": fit_s.chi2, "chi2_split": fit_p.chi2,
                         "dof_split": fit_p.dof, "n_params": k, "p_value": p_value, "p_value_model": p_model,
                         "p_value_block": p_block, "n_blocks": n_blocks})
    out = pd.DataFrame(rows, columns=[c for c in LENS_TEST_COLUMNS if c not in ("significant", "message")])
    n_tests = max(len(out), 1)
    out["significant"] = out["p_value"] < cfg["significance_level"] / n_tests
    out["message"] = [lens_sentence(r) for r in out.to_dict("records")]
    return out[list(LENS_TEST_COLUMNS)]


def lens_sentence(r: dict) -> str:
    """One lens-interaction test as a plain sentence.

    Parameters
    ----------
    r : dict
        A row of :func:`lens_interaction_tests` (columns ``LENS_TEST_COLUMNS``).

    Returns
    -------
    str
        The sentence.
    """
    lenses, units = str(r["lenses"]).split(), str(r["units"])
    vals = [float(v) for v in str(r["values"]).split()]
    lows = [float(v) for v in str(r["lows"]).split()]
    highs = [float(v) for v in str(r["highs"]).split()]
    each = ", ".join(f"{lens} {_amount(v, units)} ({_amount(lo, units)} to {_amount(hi, units)})"
                     for lens, v, lo, hi in zip(lenses, vals, lows, highs))
    stat = (f"one shared value ({_amount(float(r['shared']), units)}) leaves chi2 {float(r['chi2_shared']):.1f}, one per "
            f"lens {float(r['chi2_split']):.1f} for {int(r['dof_split'])} dof in {r['experiment']} ({r['level']} level), "
            f"p {float(r['p_value']):.2g}")
    if bool(r["significant"]):
        then = ("each lens's artefact has its own value (every stage fits each lens on its own), as it must"
                if bool(r["in_model"]) else f"add `{r['effect']}` to model.effects: every stage fits each lens on "
                                             "its own, so each lens gets its own value")
        return f"{r['effect']} differs between the lenses: {each} (95 % intervals); {stat}; {then}"
    return f"{r['effect']}: one value shared by the lenses is enough ({each}; {stat})"


def lens_findings(tests: pd.DataFrame) -> list[str]:
    """The sentences of the lens-interaction tests that found the lenses to differ.

    Parameters
    ----------
    tests : pandas.DataFrame
        The lens-interaction tests (:func:`lens_interaction_tests`).

    Returns
    -------
    list of str
        The sentences.
    """
    if not len(tests):
        return []
    return [str(m) for m, s in zip(tests["message"], tests["significant"]) if _truthy(s)]


def _truthy(value) -> bool:
    if isinstance(value, str):
        return value.strip().lower() in ("true", "1", "yes")
    return bool(value)
