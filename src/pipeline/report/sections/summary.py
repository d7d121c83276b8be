"""Results first: what a reader can act on (Larouche et al. 2024, Tables 1 and 2 in one layout).

The camera and dataset; what did not run and why (at the top when an experiment folder is missing);
the calibration per lens and band: R⁻¹ with its relative uncertainty and largest budget term,
effective wavelength and half bandwidth, immersion factor, half field of view, roll-off at the
configured field angles, noise-equivalent radiance and limit of detection; the field agreement;
and one verdict per experiment: at the noise floor, or which effect is missing; each fitted
quantity outside its physical range (an implied window index, a conversion gain, a roll-off above 1, a
negative dark current), with the value and the range.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.diagnostics.missing_effects import accepted_effects, field_scale_sentence
from pipeline.stages.observations import dataset_to_table
from pipeline.radiometry.rolloff import evaluate_rolloff, rolloff_slope
from pipeline.report.content import Markup, Table, Text
from pipeline.report.formatting import bands as band_list
from pipeline.report.formatting import finite, fmt_uncertain, fmt_value, pct, quantity, var_units
from pipeline.report.formatting import media as media_list
from pipeline.report.registry import section
from pipeline.report.sections.diagnostics import amplitude_text, as_bool, top_effect
from pipeline.report.sections.field import field_agreement_rows
from pipeline.report.sections._plausibility import plausibility_blocks
from pipeline.report.sections.noise_floor import RADIANCE_UNITS, operating_point

__all__ = ["calibration_rows", "stage_verdicts"]


def _top_of_page(inputs) -> list:
    out = []
    if inputs.failed:
        out.append(Text(Markup("This run failed: {}. This report covers the stages that finished.").format(
            Markup("; ").join(Markup("<b>{}</b> {}").format(s, why) for s, why in inputs.failed.items())), "callout"))
    not_run = {s: why for s, why in inputs.skipped.items() if s not in inputs.failed}
    if not_run:
        out.append(Text(Markup("Not in this report: {}. Every other stage is shown below "
                               '(see <a href="#skipped">Stages not run</a>).').format(
            Markup("; ").join(Markup("<b>{}</b>: {}").format(s, why) for s, why in not_run.items())), "callout"))
    return out


def _camera_table(inputs) -> Table | None:
    rows = []
    ds_info = inputs.dataset or {}
    camera = ds_info.get("camera") or {}
    if camera:
        rows.append(["camera", " ".join(str(camera.get(k, "")) for k in ("make", "model")).strip()
                     + (f", serial {camera['serial']}" if camera.get("serial") else "")])
    if ds_info.get("path"):
        rows.append(["dataset", str(ds_info["path"])])
    if ds_info.get("experiments") is not None:
        rows.append(["experiments in the dataset", ", ".join(ds_info["experiments"]) or "(none)"])
    arts = list(inputs.all_artefacts())
    if arts:
        rows.append(["lenses", ", ".join(dict.fromkeys(lens for _, lens, _, _ in arts))])
        effects = sorted({str(ds.attrs.get("model_effects", "")) for _, _, _, ds in arts})
        rows.append(["model effects", " | ".join(e.replace(",", ", ") or "(none)" for e in effects)])
        rows.append(["stages with artefacts", ", ".join(dict.fromkeys(st for st, _, _, _ in arts))])
    return Table(["item", "value"], rows, left=2) if rows else None


def _theta_sigma_at(geo, medium: str, band: str, angle: float) -> float:
    """The geometry's stated uncertainty of the field angle (deg) at ``angle``: its azimuthal RMS at the
    summary angles (``theta_deg_sigma_at_field_angle``), linear between them; NaN without it, outside them
    or beyond the half field of view."""
    if geo is None or "theta_deg_sigma_at_field_angle" not in geo or medium not in media_list(geo):
        return float("nan")
    at = np.asarray(geo["theta_summary_deg"].values, dtype=float)
    sigma = np.asarray(geo["theta_deg_sigma_at_field_angle"].sel(medium=medium, band=band).values, dtype=float)
    if not at.min() <= angle <= at.max():
        return float("nan")
    return float(np.interp(angle, at, sigma))


def rolloff_at_angle(ds, medium: str, band: str, angle: float, geo=None) -> tuple[float, float]:
    """g(angle) of the roll-off artefact ``ds`` and its standard uncertainty at the field angle ``angle``
    (NaN without a covariance).

    The uncertainty is the curve's own (its coefficients' covariance) and, where the lens's geometry
    artefact ``geo`` states it, that of the field angles the curve was fitted on, |dg/dtheta| sigma_theta:
    the curve was fitted against the fitted geometry's angles (on the tiny simulated camera 0.5 to 0.7 deg
    low at 60 deg, within their stated sigma), and with the curve's sigma alone the curves missed the
    simulator's truth at 60 deg by 3 to 4 of it over 8 seeds, while they matched it pixel by pixel, each on
    its own geometry.

    Parameters
    ----------
    ds : xarray.Dataset
        The lens's roll-off artefact.
    medium : str
        ``"air"`` or ``"water"``.
    band : str
        ``"R"``, ``"G"`` or ``"B"``.
    angle : float
        The field angle, degree.
    geo : xarray.Dataset or None, optional
        The lens's geometry artefact (its theta uncertainty).

    Returns
    -------
    g : float
        The relative illumination at ``angle`` (1 on the axis).
    sigma : float
        Its standard uncertainty.
    """
    coef = ds["rolloff_coefficients"].sel(medium=medium, band=band).values
    if "rolloff_covariance" not in ds:
        return float(evaluate_rolloff(coef, angle)), float("nan")
    g, sg = evaluate_rolloff(coef, angle, ds["rolloff_covariance"].sel(medium=medium, band=band).values)
    sigma_theta = _theta_sigma_at(geo, medium, band, angle)
    if np.isfinite(sigma_theta):
        sg = np.hypot(sg, float(rolloff_slope(coef, angle)) * sigma_theta)
    return float(g), float(sg)


def _rolloff_at(ds, medium: str, band: str, angle: float, geo=None) -> str:
    """:func:`rolloff_at_angle` as the summary shows it, or n/a beyond the largest measured field angle of the
    medium."""
    if ds is None or "rolloff_coefficients" not in ds or medium not in media_list(ds):
        return "n/a"
    coef = ds["rolloff_coefficients"].sel(medium=medium, band=band).values
    if not np.all(np.isfinite(coef)):
        return "n/a"
    if "obs_setting" in ds.dims:
        tab = dataset_to_table(ds, "obs_setting")
        tab = tab[tab["medium"] == medium] if "medium" in tab else tab
        if len(tab) and angle > float(tab["theta_deg"].max()) + 1e-9:
            return f"beyond θ max {fmt_value(float(tab['theta_deg'].max()), 3)}°"
    g, sg = rolloff_at_angle(ds, medium, band, angle, geo)
    return fmt_uncertain(g, sg) if np.isfinite(sg) else fmt_value(g, 3)


def _budget(a, band: str) -> str:
    if "relative_sigma" not in a:
        return "n/a"
    text = pct(a["relative_sigma"].sel(band=band), 1)
    if "uncertainty_contribution" in a and "term" in a.coords:
        contrib = a["uncertainty_contribution"].sel(band=band)
        i = int(np.nanargmax(contrib.values)) if np.any(np.isfinite(contrib.values)) else None
        if i is not None:
            text += f" (largest: {str(a['term'].values[i]).replace('_', ' ')} {pct(contrib.values[i], 1)})"
    return text


def calibration_rows(inputs, angles: list[float]) -> tuple[tuple[list[str], list[list[str]]], tuple[list[str], list[list[str]]]]:
    """The summary's two calibration tables, one row per lens and band.

    Radiometry (the layout of Table 1: effective wavelength, half bandwidth, R⁻¹ with its relative
    uncertainty and largest budget term, NER, limit of detection) and optics (Table 2: immersion factor, half
    field of view, roll-off at ``angles`` per medium).

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs.
    angles : list[float]
        The field angles the roll-off is given at, degree (``report.rolloff_summary_angles_deg``).

    Returns
    -------
    radiometry : tuple[list[str], list[list[str]]]
        (header, rows) of the radiometry table.
    optics : tuple[list[str], list[list[str]]]
        (header, rows) of the optics table; both without rows when there are no absolute or immersion
        artefacts.
    """
    absolute, immersion = inputs.stage("absolute"), inputs.stage("immersion")
    spectral, geometry, rolloff = inputs.stage("spectral"), inputs.stage("geometry"), inputs.stage("rolloff")
    bundle = inputs.calibration
    lenses = list(dict.fromkeys(list(absolute) + list(immersion)))
    r_units = next((var_units(a, "inverse_responsivity") for a in absolute.values() if "inverse_responsivity" in a), "")
    rolloff_media = sorted({m for ds in rolloff.values() for m in media_list(ds)}) or ["air"]
    radiometry_header = ["lens", "band", "λ_eff [nm]", "Λ/2 [nm]", f"R⁻¹ [{r_units}]", "u(R⁻¹), largest term",
                         f"NER [{RADIANCE_UNITS}]", f"LoD [{RADIANCE_UNITS}]"]
    optics_header = (["lens", "band", "I (immersion factor)", "half FOV air [°]", "half FOV water [°]"]
                     + [f"g({a:g}°) {m}" for a in angles for m in rolloff_media])
    radiometry, optics = [], []
    for lens in lenses:
        a, im, sp = absolute.get(lens), immersion.get(lens), spectral.get(lens)
        geo, ro = geometry.get(lens), rolloff.get(lens)
        bands = band_list(a) if a is not None else band_list(im)
        for b in bands:
            wl = quantity(sp, "effective_wavelength_nm", units=False, band=b) if sp is not None else (
                quantity(im, "effective_wavelength_nm", units=False, band=b) if im is not None else "n/a")
            hb = quantity(sp, "half_bandwidth_nm", units=False, band=b) if sp is not None else "n/a"
            r_inv = quantity(a, "inverse_responsivity", units=False, band=b) if a is not None else "n/a"
            budget = _budget(a, b) if a is not None else "n/a"
            ner = lod = "n/a"
            if bundle is not None and "noise_equivalent_radiance" in bundle and lens in bundle["lens"].values:
                ner = fmt_value(float(bundle["noise_equivalent_radiance"].sel(lens=lens, band=b)), 2)
                lod = fmt_value(float(bundle["limit_of_detection"].sel(lens=lens, band=b)), 2)
            radiometry.append([lens, b, wl, hb, r_inv, budget, ner, lod])
            i_f = quantity(im, "immersion_factor", units=False, interval=False, band=b) if im is not None else "n/a"
            fov = [quantity(geo, "half_fov_deg", units=False, digits=3, medium=m, band=b)
                   if geo is not None and "half_fov_deg" in geo and m in media_list(geo) else "n/a"
                   for m in ("air", "water")]
            g = [_rolloff_at(ro, m, b, ang, geo) for ang in angles for m in rolloff_media]
            optics.append([lens, b, i_f, *fov, *g])
    return (radiometry_header, radiometry), (optics_header, optics)


def _significant_for(missing, experiment: str):
    """The best-ranked significant candidate whose experiment names ``experiment`` (a candidate may be
    tested on several experiments together), or None."""
    if missing.empty or not {"experiment", "significant"} <= set(missing.columns):
        return None
    found = missing[missing["experiment"].astype(str).str.contains(experiment, regex=False)
                    & missing["significant"].map(as_bool)]
    if found.empty:
        return None
    return (found.sort_values("rank") if "rank" in found else found).iloc[0]


def evidence_text(top) -> str:
    """How strongly the residuals ask for a candidate.

    The chi-square it removes for its parameters, with p, and the share of the excess chi-square it explains
    when there is an excess (rms z above 1).

    Parameters
    ----------
    top : pandas.Series
        A row of ``missing_effects.csv`` (``delta_chi2``, ``n_params``, ``p_value``, ``explained_fraction``).

    Returns
    -------
    str
        E.g. ``"it lowers χ² by 412 for 1 parameter, p = 1.0e-12, 93 % of the excess χ²"``.
    """
    text = (f"it lowers χ² by {fmt_value(top.get('delta_chi2'), 3)} for {int(top.get('n_params', 0))} "
            f"parameter{'s' if int(top.get('n_params', 0)) != 1 else ''}, p = {fmt_value(top.get('p_value'), 2)}")
    share = top.get("explained_fraction")
    if finite(share) and float(share) > 0:
        text += f", {100 * float(share):.0f} % of the excess χ²"
    return text


def stage_verdicts(inputs) -> list[list[str]]:
    """One row per experiment of this run: rms z and the verdict.

    The verdict is the missing effect (significant candidate), structure no candidate explains, at the noise
    floor (no table's residual chi-square significant or, without the residual tests, rms z at most the
    diagnostics' ``structured_rms_z``), or above it with no significant candidate.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs (``run_errors``, ``missing_effects``, ``unexplained``, ``residual_tests``,
        ``field_scale``).

    Returns
    -------
    list[list[str]]
        (experiment, rms z, verdict) per row of ``run_errors.csv``; empty without it.
    """
    errors = inputs.run_errors
    if errors.empty or not {"experiment", "rms_z"} <= set(errors.columns):
        return []
    unexp = inputs.unexplained
    limit = float(inputs.settings.get("structured_rms_z", 1.5))
    tests = inputs.residual_tests
    tests = tests if isinstance(tests, pd.DataFrame) and {"experiment", "p_value"} <= set(tests.columns) else None
    rows = []
    for _, r in errors.iterrows():
        exp = str(r["experiment"])
        top = _significant_for(inputs.missing_effects, exp)
        structure = unexp[unexp["experiment"].astype(str) == exp] if not unexp.empty and "experiment" in unexp else []
        scale = (field_scale_sentence(inputs.field_scale, inputs.missing_effects) + ". Match-up: "
                 if exp == "field" and not inputs.field_scale.empty else "")
        if top is not None:
            verdict = (f"missing effect: {top['effect']} ({amplitude_text(top)}); add it to model.effects "
                       "in config/config.yaml and rerun")
        elif len(structure):
            verdict = f"structure no candidate explains: {structure.iloc[0].get('message', '')}"
        elif tests is not None and (tests["experiment"].astype(str) == exp).any():
            mine = tests[tests["experiment"].astype(str) == exp]
            verdict = (f"at the noise floor (no table's residual chi-square significant; smallest p "
                       f"{fmt_value(float(mine['p_value'].min()), 2)})")
        elif finite(r["rms_z"]) and float(r["rms_z"]) <= limit:
            verdict = "at the noise floor"
        else:
            verdict = f"above the noise floor (rms z > {limit:g}) and no significant candidate effect"
        rows.append([exp, fmt_value(r["rms_z"], 3), scale + verdict])
    return rows


@section("summary", "Summary", order=10)
def summary_section(inputs) -> list:
    """The "Summary" section.

    The run's facts, the camera, the calibration tables, the plausibility checks, the field agreement and
    the verdict per experiment.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs.

    Returns
    -------
    list
        The section's blocks (:mod:`pipeline.report.content`).
    """
    out = _top_of_page(inputs)
    camera = _camera_table(inputs)
    if camera is not None:
        out.append(camera)
    angles = [float(a) for a in inputs.settings.get("rolloff_summary_angles_deg", [])]
    (r_header, r_rows), (o_header, o_rows) = calibration_rows(inputs, angles)
    at = (f" at {operating_point(inputs.calibration)[1]}" if inputs.calibration is not None
          and "limit_of_detection" in inputs.calibration else "")
    if r_rows:
        out.append(Table(r_header, r_rows,
                         "Calibration per lens and band, radiometry (± standard uncertainty; the layout of Larouche et "
                         "al. 2024, Table 1): effective wavelength and half bandwidth (Eq. 8), R⁻¹ (Eq. 9) with its "
                         "relative uncertainty and the largest term of its budget, the noise-equivalent radiance and "
                         f"the limit of detection (Section 3.8){at}.", left=2))
        out.append(Table(o_header, o_rows,
                         "Calibration per lens and band, immersion and field of view (the layout of Table 2): the "
                         "immersion factor (Eq. 11), the half field of view in air and water, and the roll-off g(θ) "
                         "of Eq. (13) at report.rolloff_summary_angles_deg per medium (not extrapolated beyond the "
                         "largest measured angle), its uncertainty the curve's and that of the field angle it was "
                         "fitted on, |dg/dθ| times the geometry's stated σθ at that angle.", left=2))
    out += plausibility_blocks(inputs)
    field = [row for lens, ds in inputs.stage("field").items() for row in field_agreement_rows(lens, ds)]
    if not inputs.field_scale.empty:
        departs = inputs.field_scale["departs"].map(as_bool).any()
        out.append(Text(Markup("<b>{}</b>.").format(field_scale_sentence(inputs.field_scale, inputs.missing_effects)),
                        "callout" if departs else "ok"))
    if field:
        out.append(Table(["lens", "band", "camera / reference", "MUPD % (nearest channel)", "MUPD % (band-convolved)",
                          "match-ups", "rms z"], field,
                         Markup('Field agreement at the zenith (<a href="#field">details</a>); the paper reports MUPD '
                                "21.1, 20.3, 18.6 % (R, G, B) for the real camera."), left=2))
    verdicts = stage_verdicts(inputs)
    if verdicts:
        out.append(Table(["experiment", "rms z", "verdict"], verdicts,
                         "Verdict per experiment (rms z = 1 at the noise floor): the missing effect the diagnostics "
                         "find significant, else the residual structure no candidate explains (a chi-square test of "
                         "each experiment's residuals against their degrees of freedom, by frame or setting), else "
                         "the noise floor (without the residual tests: rms z at most "
                         f"{float(inputs.settings.get('structured_rms_z', 1.5)):g}):", left=3))
    top = top_effect(inputs.missing_effects)
    if top is not None and as_bool(top.get("significant")):
        out.append(Text(Markup("The residuals point to a missing effect: <b>{}</b> in the {} experiment ({}; "
                               "{}). Add it to <code>model.effects</code> in <code>config/config.yaml</code> and "
                               "rerun.").format(top["effect"], top["experiment"], amplitude_text(top),
                                                evidence_text(top)), "callout"))
        found = [e for e in accepted_effects(inputs.missing_effects) if e not in inputs.model_effects()]
        if len(found) > 1:
            out.append(Text(Markup("Every effect this run found, in the order the diagnostics accepted them: "
                                   "<code>--config 'model={{effects: [{}]}}'</code>.").format(
                                       ", ".join(inputs.model_effects() + found)), "callout"))
    elif top is not None:
        out.append(Text(Markup("No significant missing effect. The top-ranked candidate, <b>{}</b>, is not "
                               "significant (p = {}).").format(top["effect"], fmt_value(top.get("p_value"), 3)), "ok"))
    else:
        out.append(Text("The missing-effect search returned no candidates.", "ok"))
    return out
