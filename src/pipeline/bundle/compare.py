"""Two calibration bundles compared parameter by parameter: what changed, and by how many sigma.

``python -m pipeline compare BUNDLE_A BUNDLE_B`` reads two calibration bundles
(:mod:`pipeline.bundle.calibration`) of one camera model and lens layout: the same camera
at two dates (drift) or two units of the model (unit-to-unit reproducibility).
Every calibrated parameter is taken per lens, band and medium where it has them
(:data:`QUANTITIES`): R^-1, the effective wavelength, the roll-off g(theta) at the
``compare.rolloff_angles_deg`` inside both calibrated fields, the immersion factor,
the conversion gain, the read noise per ISO, the dark current, the shutter offset
(when both fitted it) and the geometry's field angle at the
``compare.radius_fractions`` of the image-circle radius. For each: value A, value B,
the difference B - A, the relative difference (B - A) / A, the combined standard
uncertainty of the difference and z = difference / sigma.

The uncertainty of a difference
    Each parameter's standard uncertainty is a list of terms (:class:`Term`), each
    with the lab inputs it comes from. The two calibrations are independent unless
    they share an input: the bundle's ``lab_input_sha256`` names the lab files its
    artefacts were made from (the instrument sidecars, each experiment's frames as
    one digest). A term whose inputs have the same sha256 in both bundles is common
    to both: its error moves A and B together and leaves only (u_A - u_B)^2 in the
    difference's variance; the other terms add, u_A^2 + u_B^2. R^-1's budget is
    split this way (``uncertainty_contribution``): the calibration lamp and the
    spectrometer noise come with the source spectrum file, the reference reading
    with its file, the lab's named source terms with both, the image statistics with
    the absolute frames and the response corrections with the linearity frames. A
    stage artefact that is the same file in both bundles (``input_sha256``) makes all
    of its parameters common. A parameter whose bundle states one total sigma that
    mixes shared and unshared causes (the effective wavelength: photodiode file and
    noise; the immersion factor: water file and frames) is taken as independent,
    which its ``uncertainty_split`` attribute says. The read noise's sigma is its
    Gaussian sampling error (the bundle's ``read_noise_dn_sigma``).

Verdict per group
    A group (``responsivity``, ``spectral``, ...) is ``changed`` when a parameter's
    |z| exceeds the group's threshold: ``compare.change_z`` for one parameter, raised
    for a group of n so that the group is called changed by chance no more often
    than one parameter is at ``change_z`` (Sidak: 1 - (1 - p)^(1/n)). Otherwise
    ``consistent``; ``not compared`` when no parameter of the group has a sigma.

:func:`compare_bundles` returns the table as an xarray Dataset (CF attributes;
:func:`write_comparison` writes it), :func:`summary_lines` the plain-text summary,
:func:`render_html` an HTML page. :func:`history` lists a camera's calibrations in a
store (:mod:`pipeline.bundle.store`) with the drift of R^-1 between consecutive ones,
through the same :func:`difference`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np
import xarray as xr
from scipy.stats import norm

from pipeline.io.artefact import sha256_file
from pipeline.io.units import encode_units
from pipeline.io.bands import BANDS
from pipeline.bundle.calibration import read_bundle
from pipeline.config import defaults
from pipeline.errors import InputError
from pipeline.radiometry.rolloff import evaluate_rolloff, rolloff_slope_on_image
from pipeline.bundle.store import TIME_FORMAT, check_entry, read_index

__all__ = ["Term", "Quantity", "GROUPS", "QUANTITIES", "R_INVERSE_TERM_INPUTS", "compare_settings", "shared_inputs",
           "bundle_quantities", "difference", "group_threshold", "compare_bundles", "write_comparison",
           "summary_lines", "render_html", "history", "history_table", "history_lines", "write_history_csv",
           "write_history_figure"]

#: parameter groups by physics, in the order they are printed
GROUPS = ("responsivity", "spectral", "rolloff", "immersion", "gain", "exposure", "dark", "geometry")

#: the lab inputs (keys of the bundle's lab_input_sha256) each term of R^-1's budget comes from
#: (pipeline.stages.absolute.TERMS); a term is common to two bundles when all of its inputs are shared
R_INVERSE_TERM_INPUTS = {
    "lamp_calibration": ("absolute/source_spectrum.csv",),
    "spectrometer_noise": ("absolute/source_spectrum.csv",),
    "reference": ("absolute/source_reference.csv",),
    "extra": ("absolute/source_spectrum.csv", "absolute/source_reference.csv"),
    "image": ("absolute/frames",),
    "response": ("linearity/frames",),
}
SPLIT_BUDGET = "split: each term common when its lab inputs are shared (attribute term_inputs), independent otherwise"
NOT_SPLIT = ("not split: the bundle states one total sigma that mixes causes a shared input would and would not make "
             "common; treated as independent")
FIT_ONLY = "one term, the fit's statistical error from the frames named in term_inputs: common only when they are shared"
NO_SIGMA = "the bundle states no uncertainty: z not computed"


@dataclass(frozen=True)
class Term:
    """One part of a parameter's standard uncertainty (absolute, the parameter's units) and the lab inputs it
    comes from (keys of lab_input_sha256; empty: never common)."""

    name: str
    sigma: np.ndarray
    inputs: tuple[str, ...] = ()


@dataclass
class Quantity:
    """A calibrated parameter over its dims (lens, band, medium, ...) with its uncertainty terms."""

    name: str
    group: str
    stage: str
    long_name: str
    units: str
    value: xr.DataArray
    terms: list[Term] = field(default_factory=list)
    split: str = NOT_SPLIT


#: quantity -> (group, stage that fits it)
QUANTITIES = {
    "inverse_responsivity": ("responsivity", "absolute"),
    "effective_wavelength_nm": ("spectral", "spectral"),
    "rolloff": ("rolloff", "rolloff"),
    "immersion_factor": ("immersion", "immersion"),
    "conversion_gain_dn_per_e": ("gain", "linearity"),
    "shutter_offset_s": ("exposure", "linearity"),
    "read_noise_dn": ("dark", "dark"),
    "dark_current_dn_per_s": ("dark", "dark"),
    "field_angle_deg": ("geometry", "geometry"),
}


#: CF attributes of the comparison's coordinates (long_name, units; None: text, no units)
COORDINATE_ATTRS = {"lens": ("lens of the camera", None), "band": ("colour band of the CFA", None),
                    "medium": ("medium in front of the lens (air or water)", None),
                    "dark_iso": ("ISO of the dark model", "1"), "term": ("term of the uncertainty budget", None)}


def compare_settings(config: dict | None = None) -> dict:
    """The ``compare`` section of the configuration (the schema's defaults without one).

    Parameters
    ----------
    config : dict, optional
        The configuration.

    Returns
    -------
    dict
        The ``compare`` section (``change_z``, ``rolloff_angles_deg``, ``radius_fractions``, ...).
    """
    return (config if config is not None else defaults())["compare"]


# --------------------------------------------------------------------------- reading the bundles
def _open(path: str | Path) -> xr.Dataset:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file (give a calibration bundle, results/calibration/<serial>.nc)")
    return read_bundle(path, load=False)


def _layout(bundle: xr.Dataset) -> dict:
    """What two bundles must have alike to be compared: camera model, lenses and their regions and projections,
    band image size, media."""
    return {"camera model": f"{bundle.attrs.get('camera_make', '')} {bundle.attrs.get('camera_model', '')}".strip(),
            "lenses": list(bundle["lens"].values.astype(str)),
            "projections": list(bundle["projection"].values.astype(str)) if "projection" in bundle else [],
            "lens regions": bundle["lens_region_px"].values.tolist() if "lens_region_px" in bundle else [],
            "band image size": [int(bundle.sizes.get("y", 0)), int(bundle.sizes.get("x", 0))]}


def _check_alike(a: xr.Dataset, b: xr.Dataset, path_b: Path, path_a: Path) -> None:
    la, lb = _layout(a), _layout(b)
    for what in la:
        if la[what] != lb[what]:
            raise InputError(path_b, f"{what} {lb[what]} differ from {path_a}'s {la[what]}: compare calibrations of "
                                     "one camera model and lens layout")


def shared_inputs(a: xr.Dataset, b: xr.Dataset) -> tuple[list[str], list[str]]:
    """(lab inputs, stage artefacts) with the same sha256 in both bundles.

    Parameters
    ----------
    a : xarray.Dataset
        Bundle A.
    b : xarray.Dataset
        Bundle B.

    Returns
    -------
    lab : list of str
        The lab inputs (keys of ``lab_input_sha256``) with the same sha256 in both, sorted.
    artefacts : list of str
        The stage artefacts (keys of ``input_sha256``) with the same sha256 in both, sorted.
    """
    def hashes(ds, attr):
        try:
            return json.loads(ds.attrs.get(attr, "{}"))
        except (TypeError, ValueError):
            return {}
    lab = sorted(k for k, v in hashes(a, "lab_input_sha256").items() if hashes(b, "lab_input_sha256").get(k) == v)
    art_a, art_b = hashes(a, "input_sha256"), hashes(b, "input_sha256")
    artefacts = sorted(k for k, v in art_a.items() if art_b.get(k) == v)
    return lab, artefacts


def _stages_shared(a: xr.Dataset, artefacts: list[str]) -> set[str]:
    """Stages whose every artefact (all lenses) is the same file in both bundles."""
    listed = json.loads(a.attrs.get("input_sha256", "{}"))
    stages = {name.split("/", 1)[0] for name in listed}
    return {s for s in stages if all(name in artefacts for name in listed if name.split("/", 1)[0] == s)}


def _attr(var: xr.DataArray, name: str, default: str = "") -> str:
    return str(var.attrs.get(name, default))


def _field_angle_at_radius(theta: np.ndarray, sigma: np.ndarray | None, cx: float, cy: float, radius_px: float,
                           half_width_px: float) -> tuple[float, float]:
    """Field angle at ``radius_px`` from the circle centre: the straight line theta(r) through the band pixels
    within ``half_width_px`` of that radius, evaluated at it; sigma: the mean theta sigma of those pixels (their
    errors, from one fit, move together)."""
    y, x = np.indices(theta.shape)
    r = np.hypot(x - cx, y - cy)
    ring = (np.abs(r - radius_px) <= half_width_px) & np.isfinite(theta)
    if not np.isfinite(radius_px) or ring.sum() < 2:
        return np.nan, np.nan
    dr = r[ring] - radius_px
    slope, intercept = np.polyfit(dr, theta[ring], 1)
    return float(intercept), float(np.mean(sigma[ring])) if sigma is not None else np.nan


def _theta_sigma_at(bundle: xr.Dataset, sel: dict, angles_deg: np.ndarray, half_width_px: float) -> np.ndarray:
    """The geometry's stated theta uncertainty (mean theta_deg_sigma) of the band pixels within ``half_width_px``
    pixels' worth of field angle (the map's mean degrees per pixel, half_fov / circle radius) of each angle; 0
    without theta_deg_sigma (a geometry written from known optics)."""
    if "theta_deg_sigma" not in bundle:
        return np.zeros(np.shape(angles_deg))
    theta = bundle["theta_deg"].sel(sel).values.astype(float)
    sigma = bundle["theta_deg_sigma"].sel(sel).values.astype(float)
    deg_per_px = float(bundle["half_fov_deg"].sel(sel)) / float(bundle["circle_radius_px"].sel(sel))
    if not np.isfinite(deg_per_px):
        return np.full(np.shape(angles_deg), np.nan)
    out = []
    for angle in np.atleast_1d(angles_deg):
        near = (np.abs(theta - angle) <= half_width_px * deg_per_px) & np.isfinite(sigma)
        out.append(float(np.mean(sigma[near])) if near.any() else np.nan)
    return np.array(out)


def bundle_quantities(bundle: xr.Dataset, cfg: dict) -> dict[str, Quantity]:
    """The compared parameters of one bundle (:data:`QUANTITIES`), those it has.

    Parameters
    ----------
    bundle : xarray.Dataset
        The calibration bundle.
    cfg : dict
        The ``compare`` section of the configuration (:func:`compare_settings`).

    Returns
    -------
    dict[str, Quantity]
        Per parameter name its values over its dims, units and uncertainty terms.
    """
    out: dict[str, Quantity] = {}
    lenses = list(bundle["lens"].values.astype(str))
    bands = list(BANDS)

    def make(name, value, terms, split, long_name=None, units=None):
        group, stage = QUANTITIES[name]
        source = bundle[name] if name in bundle else value
        out[name] = Quantity(name, group, stage, long_name or _attr(source, "long_name", name),
                             units or _attr(source, "units", "1"), value, terms, split)

    r_inv, terms = _responsivity(bundle)
    make("inverse_responsivity", r_inv, terms, SPLIT_BUDGET)

    for name, inputs in (("effective_wavelength_nm", ()), ("conversion_gain_dn_per_e", ("linearity/frames",)),
                         ("dark_current_dn_per_s", ("dark/frames",)), ("shutter_offset_s", ("linearity/frames",))):
        if name not in bundle:
            continue
        value = bundle[name].astype(float)
        value = value.sel(band=bands) if "band" in value.dims else value
        sigma = bundle[f"{name}_sigma"].astype(float) if f"{name}_sigma" in bundle else xr.full_like(value, np.nan)
        sigma = sigma.sel(band=bands) if "band" in sigma.dims else sigma
        make(name, value, [Term("stated", sigma.values, inputs)], FIT_ONLY if inputs else NOT_SPLIT)

    if "immersion_factor" in bundle and "water" in str(bundle.attrs.get("media", "")).split(","):
        value = bundle["immersion_factor"].sel(band=bands).astype(float)
        make("immersion_factor", value, [Term("stated", bundle["immersion_factor_sigma"].sel(band=bands).values)],
             NOT_SPLIT)

    read = bundle["read_noise_dn"].sel(band=bands).astype(float)
    if "read_noise_dn_sigma" in bundle:
        make("read_noise_dn", read, [Term("sampling", bundle["read_noise_dn_sigma"].sel(band=bands).values,
                                          ("dark/frames",))], FIT_ONLY)
    else:
        make("read_noise_dn", read, [Term("stated", np.full(read.shape, np.nan))], NO_SIGMA)

    media = [m for m in bundle["medium"].values.astype(str)]
    angles = sorted({float(a) for m in media for a in cfg["rolloff_angles_deg"].get(m, [])})
    g = np.full((len(lenses), len(media), len(bands), len(angles)), np.nan)
    g_sigma = np.full_like(g, np.nan)
    g_theta_sigma = np.full_like(g, np.nan)
    for i, lens in enumerate(lenses):
        for j, medium in enumerate(media):
            reach = float(bundle["calibrated_field_angle_deg"].sel(lens=lens, medium=medium))
            wanted = [k for k, a in enumerate(angles) if a in cfg["rolloff_angles_deg"].get(medium, []) and a <= reach]
            for m, band in enumerate(bands):
                sel = dict(lens=lens, medium=medium, band=band)
                at = np.array([angles[k] for k in wanted])
                coefficients = bundle["rolloff_coefficients"].sel(sel).values.astype(float)
                value, sigma = evaluate_rolloff(coefficients, at, bundle["rolloff_covariance"].sel(sel).values.astype(float))
                g[i, j, m, wanted], g_sigma[i, j, m, wanted] = value, sigma
                # the chain's field_angle term (measurement.rolloff_map): g read at a field angle the geometry
                # states with theta_deg_sigma
                g_theta_sigma[i, j, m, wanted] = np.abs(rolloff_slope_on_image(coefficients, at)) * \
                    _theta_sigma_at(bundle, sel, at, float(cfg["ring_half_width_px"]))
    coords = {"lens": lenses, "medium": media, "band": bands,
              "rolloff_angle_deg": ("rolloff_angle_deg", angles, {"long_name": "field angle of the roll-off",
                                                                  "units": "degree"})}
    dims = ("lens", "medium", "band", "rolloff_angle_deg")
    make("rolloff", xr.DataArray(g, dims=dims, coords=coords),
         [Term("fit", g_sigma, ("rolloff/frames", "geometry/frames")), Term("field_angle", g_theta_sigma, ("geometry/frames",))],
         "two terms: the coefficients' covariance (roll-off and geometry frames) and the chain's field_angle term "
         "g'(theta) sigma_theta (geometry frames); each common only when its frames are shared",
         long_name="relative roll-off g(theta), Eq. (13), inside the calibrated field angle", units="1")

    fractions = [float(f) for f in cfg["radius_fractions"]]
    theta = np.full((len(lenses), len(media), len(bands), len(fractions)), np.nan)
    theta_sigma = np.full_like(theta, np.nan)
    for i, lens in enumerate(lenses):
        for j, medium in enumerate(media):
            for m, band in enumerate(bands):
                sel = dict(lens=lens, medium=medium, band=band)
                t = bundle["theta_deg"].sel(sel).values.astype(float)
                s = bundle["theta_deg_sigma"].sel(sel).values.astype(float) if "theta_deg_sigma" in bundle else None
                cx, cy = float(bundle["circle_xc_px"].sel(sel)), float(bundle["circle_yc_px"].sel(sel))
                radius = float(bundle["circle_radius_px"].sel(sel))
                for k, f in enumerate(fractions):
                    theta[i, j, m, k], theta_sigma[i, j, m, k] = _field_angle_at_radius(
                        t, s, cx, cy, f * radius, float(cfg["ring_half_width_px"]))
    coords = {"lens": lenses, "medium": media, "band": bands,
              "radius_fraction": ("radius_fraction", fractions, {
                  "long_name": "radius as a fraction of the fitted image-circle radius (a lens without an image "
                               "circle has no value)", "units": "1"})}
    make("field_angle_deg", xr.DataArray(theta, dims=("lens", "medium", "band", "radius_fraction"), coords=coords),
         [Term("fit", theta_sigma, ("geometry/frames",))], FIT_ONLY,
         long_name="field angle of the geometry's theta map at a fraction of the image-circle radius", units="degree")
    return out


# --------------------------------------------------------------------------- the difference and its sigma
def difference(value_a, terms_a: list[Term], value_b, terms_b: list[Term], shared: set[str] | list[str],
               all_common: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """B - A and its standard uncertainty.

    A term whose inputs are all in ``shared`` (or every term, with ``all_common``) is common and adds
    (u_A - u_B)^2, any other u_A^2 + u_B^2 (terms matched by name; a term one side lacks counts as zero there).

    Parameters
    ----------
    value_a : array_like
        The parameter in A, its units.
    terms_a : list of Term
        A's uncertainty terms (absolute, same units).
    value_b : array_like
        The parameter in B, same units and shape.
    terms_b : list of Term
        B's uncertainty terms.
    shared : set of str or list of str
        The lab inputs with the same sha256 in both bundles.
    all_common : bool, default False
        Take every term as common (the same stage artefact in both bundles).

    Returns
    -------
    difference : numpy.ndarray
        B - A, the parameter's units.
    sigma : numpy.ndarray
        Its standard uncertainty, same units.
    """
    value_a, value_b = np.asarray(value_a, float), np.asarray(value_b, float)
    by_a, by_b = {t.name: t for t in terms_a}, {t.name: t for t in terms_b}
    variance = np.zeros(np.broadcast(value_a, value_b).shape)
    for name in list(by_a) + [n for n in by_b if n not in by_a]:
        ua = np.asarray(by_a[name].sigma, float) if name in by_a else 0.0
        ub = np.asarray(by_b[name].sigma, float) if name in by_b else 0.0
        inputs = (by_a.get(name) or by_b[name]).inputs
        common = all_common or (bool(inputs) and all(k in shared for k in inputs))
        variance = variance + ((ua - ub) ** 2 if common else ua**2 + ub**2)
    return value_b - value_a, np.sqrt(variance)


def _z(diff: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        z = diff / sigma
    # identical values with no uncertainty left (a shared artefact): no change
    return np.where((sigma == 0) & (diff == 0), 0.0, z)


def group_threshold(change_z: float, n: int) -> float:
    """The |z| a group of ``n`` parameters exceeds by chance as often as one parameter exceeds ``change_z``.

    Two-sided Gaussian, Sidak correction.

    Parameters
    ----------
    change_z : float
        The threshold of one parameter (``compare.change_z``).
    n : int
        The number of parameters of the group.

    Returns
    -------
    float
        The group's threshold (at least ``change_z``; ``change_z`` itself for one parameter).
    """
    p_one = 2.0 * norm.sf(change_z)
    p_each = -np.expm1(np.log1p(-p_one) / max(n, 1))
    return float(max(change_z, norm.isf(p_each / 2.0)))


# --------------------------------------------------------------------------- the comparison
def compare_bundles(path_a: str | Path, path_b: str | Path, config: dict | None = None) -> xr.Dataset:
    """The comparison table of two bundles (B against A) as a Dataset.

    InputError when a bundle cannot be read or the two are not of one camera model and lens layout.

    Parameters
    ----------
    path_a, path_b : str or pathlib.Path
        Bundles A and B.
    config : dict, optional
        The configuration (its ``compare`` section; the schema's defaults without one).

    Returns
    -------
    xarray.Dataset
        Per quantity ``<q>_a``, ``<q>_b``, ``<q>_difference``, ``<q>_relative_difference``,
        ``<q>_difference_sigma``, ``<q>_z`` (in the quantity's units, the relative difference and z
        dimensionless); per group the number of parameters, the largest |z|, the threshold and the verdict.
    """
    cfg = compare_settings(config)
    path_a, path_b = Path(path_a), Path(path_b)
    a = _open(path_a)
    try:
        b = _open(path_b)
    except BaseException:
        a.close()
        raise
    try:
        _check_alike(a, b, path_b, path_a)
        lab, artefacts = shared_inputs(a, b)
        stages = _stages_shared(a, artefacts)
        qa, qb = bundle_quantities(a, cfg), bundle_quantities(b, cfg)
        attrs_a, attrs_b = dict(a.attrs), dict(b.attrs)
    finally:
        a.close()
        b.close()
    out = xr.Dataset()
    counted: dict[str, list[np.ndarray]] = {g: [] for g in GROUPS}
    notes = []
    for name in QUANTITIES:
        if name not in qa or name not in qb:
            if name in qa or name in qb:
                notes.append(f"{name} only in {'A' if name in qa else 'B'}: not compared")
            continue
        A, B = qa[name], qb[name]
        va, vb = xr.align(A.value, B.value, join="inner")
        keep_a = {d: va[d].values for d in va.dims}
        ta = [Term(t.name, A.value.copy(data=np.broadcast_to(t.sigma, A.value.shape)).sel(keep_a).values, t.inputs)
              for t in A.terms]
        tb = [Term(t.name, B.value.copy(data=np.broadcast_to(t.sigma, B.value.shape)).sel(keep_a).values, t.inputs)
              for t in B.terms]
        diff, sigma = difference(va.values, ta, vb.values, tb, set(lab), all_common=A.stage in stages)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel, rel_sigma = diff / np.abs(va.values), sigma / np.abs(va.values)
        z = _z(diff, sigma)
        common = [t.name for t in A.terms if A.stage in stages or (t.inputs and all(k in lab for k in t.inputs))]
        base = {"group": A.group, "uncertainty_split": A.split,
                "term_inputs": json.dumps({t.name: list(t.inputs) for t in A.terms}),
                "common_terms": ",".join(common) if common else "none"}

        def put(suffix, data, long_name, units):
            out[f"{name}{suffix}"] = xr.DataArray(data, dims=va.dims, coords=va.coords,
                                                  attrs={"long_name": long_name, "units": units, **base})
        put("_a", va.values, f"{A.long_name} (A)", A.units)
        put("_b", vb.values, f"{A.long_name} (B)", A.units)
        put("_difference", diff, f"{A.long_name}: B - A", A.units)
        put("_relative_difference", rel, f"{A.long_name}: (B - A) / |A|", "1")
        put("_difference_sigma", sigma, f"{A.long_name}: combined standard uncertainty of B - A", A.units)
        put("_relative_difference_sigma", rel_sigma, f"{A.long_name}: standard uncertainty of (B - A) / |A|", "1")
        put("_z", z, f"{A.long_name}: (B - A) / its standard uncertainty", "1")
        counted[A.group].append(z[np.isfinite(z)])
    n = np.array([sum(v.size for v in counted[g]) for g in GROUPS])
    max_z = np.array([float(np.max(np.abs(np.concatenate(counted[g])))) if k else np.nan
                      for g, k in zip(GROUPS, n)])
    change_z = float(cfg["change_z"])
    threshold = np.array([group_threshold(change_z, int(k)) if k else np.nan for k in n])
    verdict = np.array(["not compared" if not k else ("changed" if m > t else "consistent")
                        for k, m, t in zip(n, max_z, threshold)])
    n_changed = np.array([int(np.sum(np.abs(np.concatenate(counted[g])) > change_z)) if k else 0
                          for g, k in zip(GROUPS, n)])
    out = out.assign_coords(group=("group", list(GROUPS), {"long_name": "parameter group (physics)"}))
    out["group_n_parameters"] = ("group", n, {"long_name": "parameters of the group with a z", "units": "1"})
    out["group_max_abs_z"] = ("group", max_z, {"long_name": "largest |z| of the group", "units": "1"})
    out["group_n_beyond_change_z"] = ("group", n_changed, {
        "long_name": f"parameters of the group with |z| above compare.change_z ({change_z:g})", "units": "1"})
    out["group_threshold_z"] = ("group", threshold, {
        "long_name": "|z| above which the group is called changed (change_z for one parameter, Sidak-raised for "
                     "the group's number)", "units": "1"})
    out["group_verdict"] = ("group", verdict, {"long_name": "changed, consistent or not compared", "units": "1"})
    out["group_verdict"].attrs.pop("units")  # text: no units (CF)
    for name, (long_name, units) in COORDINATE_ATTRS.items():
        if name in out.coords:
            out[name].attrs.setdefault("long_name", long_name)
            if units is not None:
                out[name].attrs.setdefault("units", units)
    serial_a, serial_b = str(attrs_a.get("camera_serial", "")), str(attrs_b.get("camera_serial", ""))
    out.attrs.update({
        "Conventions": "CF-1.10",
        "title": "comparison of two calibration bundles (B against A)",
        "bundle_a": str(path_a), "bundle_b": str(path_b),
        "bundle_a_sha256": sha256_file(path_a), "bundle_b_sha256": sha256_file(path_b),
        "camera_model": f"{attrs_a.get('camera_make', '')} {attrs_a.get('camera_model', '')}".strip(),
        "camera_serial_a": serial_a, "camera_serial_b": serial_b,
        "comparison": "same camera at two dates (drift)" if serial_a == serial_b
                      else "two units of one model (unit-to-unit)",
        "created_a": str(attrs_a.get("created", "")), "created_b": str(attrs_b.get("created", "")),
        "shared_lab_inputs": ",".join(lab) if lab else "none",
        "shared_artefacts": ",".join(artefacts) if artefacts else "none",
        "lab_inputs_known": "yes" if "lab_input_sha256" in attrs_a and "lab_input_sha256" in attrs_b else
                            "no (a bundle without lab_input_sha256: every term taken as independent)",
        "change_z": change_z,
        "notes": "; ".join(notes) if notes else "none",
    })
    return out


def write_comparison(table: xr.Dataset, path: str | Path) -> Path:
    """Write the comparison table as NetCDF (atomically: a temporary file renamed).

    Parameters
    ----------
    table : xarray.Dataset
        The comparison table (:func:`compare_bundles`).
    path : str or pathlib.Path
        The file to write (its folder is created).

    Returns
    -------
    pathlib.Path
        The file written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    # the units spelled for UDUNITS-2 on disk, the camera's (DN, electron, pixel) in camera_units (pipeline.io.units)
    encode_units(table).to_netcdf(tmp, engine="netcdf4")
    tmp.replace(path)
    return path


def _rows(table: xr.Dataset) -> list[dict]:
    """One row per compared parameter: name, group, where (lens, band, ...), values, difference, sigma, z."""
    rows = []
    for name in QUANTITIES:
        if f"{name}_z" not in table:
            continue
        parts = {s: table[f"{name}{s}"] for s in ("_a", "_b", "_difference", "_relative_difference",
                                                    "_difference_sigma", "_relative_difference_sigma", "_z")}
        z = parts["_z"]
        for index in np.ndindex(z.shape):
            if not np.isfinite(float(parts["_difference"].values[index])):
                continue
            where = ", ".join(f"{d} {z[d].values[i]}" for d, i in zip(z.dims, index))
            rows.append({"quantity": name, "group": z.attrs["group"], "where": where, "units": parts["_a"].attrs["units"],
                         **{s.strip("_"): float(v.values[index]) for s, v in parts.items()}})
    return rows


def summary_lines(table: xr.Dataset) -> list[str]:
    """The plain-text summary of a comparison.

    Per group the number of parameters, the largest |z| and the verdict; the largest relative change of R^-1;
    the shared inputs.

    Parameters
    ----------
    table : xarray.Dataset
        The comparison table (:func:`compare_bundles`).

    Returns
    -------
    list of str
        The lines.
    """
    lines = [f"A: {table.attrs['bundle_a']} (camera {table.attrs['camera_serial_a']})",
             f"B: {table.attrs['bundle_b']} (camera {table.attrs['camera_serial_b']}); "
             f"{table.attrs['comparison']}",
             f"{'group':<14}{'n':>5}{'max |z|':>10}{'limit':>8}  verdict"]
    for i, group in enumerate(table["group"].values):
        n = int(table["group_n_parameters"].values[i])
        m, t = float(table["group_max_abs_z"].values[i]), float(table["group_threshold_z"].values[i])
        lines.append(f"{group:<14}{n:>5}{m:>10.2f}{t:>8.2f}  {table['group_verdict'].values[i]}"
                     if n else f"{group:<14}{n:>5}{'-':>10}{'-':>8}  {table['group_verdict'].values[i]}")
    if "inverse_responsivity_relative_difference" in table:
        rel = table["inverse_responsivity_relative_difference"]
        sig = table["inverse_responsivity_relative_difference_sigma"]
        parts = [f"{lens} {band} {100 * float(rel.sel(lens=lens, band=band)):+.2f} +/- "
                 f"{100 * float(sig.sel(lens=lens, band=band)):.2f} %"
                 for lens in rel["lens"].values for band in rel["band"].values]
        lines.append("R^-1 change (B - A) / A: " + "; ".join(parts))
    lines.append(f"shared inputs (common terms cancel in the difference): {table.attrs['shared_lab_inputs']}"
                 + ("" if table.attrs["shared_artefacts"] == "none"
                    else f"; shared artefacts: {table.attrs['shared_artefacts']}"))
    return lines


def render_html(table: xr.Dataset, path: str | Path) -> Path:
    """The comparison as an HTML page (Jinja2 template ``templates/compare.html.j2``).

    Parameters
    ----------
    table : xarray.Dataset
        The comparison table (:func:`compare_bundles`).
    path : str or pathlib.Path
        The HTML file to write (its folder is created).

    Returns
    -------
    pathlib.Path
        The file written.
    """
    from jinja2 import Environment, PackageLoader, StrictUndefined, select_autoescape

    env = Environment(loader=PackageLoader("pipeline", "templates"), undefined=StrictUndefined,
                      autoescape=select_autoescape(["html", "j2"], default_for_string=True))
    groups = [{"name": str(g), "n": int(table["group_n_parameters"].values[i]),
               "max_z": float(table["group_max_abs_z"].values[i]),
               "threshold": float(table["group_threshold_z"].values[i]),
               "verdict": str(table["group_verdict"].values[i])} for i, g in enumerate(table["group"].values)]
    splits = {name: table[f"{name}_z"].attrs["uncertainty_split"] for name in QUANTITIES if f"{name}_z" in table}
    html = env.get_template("compare.html.j2").render(attrs=table.attrs, groups=groups, rows=_rows(table),
                                                      splits=splits, summary=summary_lines(table))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(html)
    return path


# --------------------------------------------------------------------------- a camera's history in the store
def history(store: str | Path, serial: str, config: dict | None = None) -> list[dict]:
    """The calibrations of camera ``serial`` in ``store`` in validity order, with the drift of R^-1.

    Of two with one start, the earlier published comes first. Each comes with R^-1 per lens and band and its
    change from the one before: relative difference, its sigma and z (:func:`difference`: the inputs the two
    bundles share cancel), and whether |z| exceeds ``compare.change_z``. Each file is checked against the
    store's index before it is read.

    Parameters
    ----------
    store : str or pathlib.Path
        The calibration store (:mod:`pipeline.bundle.store`).
    serial : str
        The camera serial.
    config : dict, optional
        The configuration (its ``compare`` section).

    Returns
    -------
    list of dict
        Per calibration ``valid_from``, ``file``, ``sha256``, ``inverse_responsivity`` (xarray.DataArray over lens
        and band, W sr-1 m-2 nm-1 s DN-1), ``shared_lab_inputs``; from the second on ``relative_difference``,
        ``relative_difference_sigma``, ``z`` and ``changed`` (xarray.DataArray).

    Raises
    ------
    InputError
        When the store holds no calibration of the camera or a file is altered.
    """
    store = Path(store)
    change_z = float(compare_settings(config)["change_z"])
    rows = [(datetime.strptime(r["valid_from"], TIME_FORMAT), i, r) for i, r in enumerate(read_index(store))
            if r["serial"] == serial]
    if not rows:
        raise InputError(store, f"holds no calibration of camera {serial}")
    out, before = [], None
    for _, _, row in sorted(rows, key=lambda e: (e[0], e[1])):
        bundle = read_bundle(check_entry(store, row), load=False)
        try:
            value, terms = _responsivity(bundle)
            lab = json.loads(bundle.attrs.get("lab_input_sha256", "{}"))
        finally:
            bundle.close()
        entry = {"valid_from": row["valid_from"], "file": row["file"], "sha256": row["sha256"],
                 "inverse_responsivity": value, "shared_lab_inputs": []}
        if before is not None:
            entry["shared_lab_inputs"] = sorted(k for k, v in lab.items() if before["lab"].get(k) == v)
            old = before["inverse_responsivity"]
            diff, sigma = difference(old.values, before["terms"], value.values, terms, set(entry["shared_lab_inputs"]),
                                     all_common=before["sha256"] == row["sha256"])
            z = _z(diff, sigma)
            entry.update(relative_difference=value.copy(data=diff / np.abs(old.values)),
                         relative_difference_sigma=value.copy(data=sigma / np.abs(old.values)),
                         z=value.copy(data=z), changed=value.copy(data=np.abs(z) > change_z))
        out.append(entry)
        before = {**entry, "terms": terms, "lab": lab}
    return out


def history_table(entries: list[dict]) -> list[dict]:
    """:func:`history` as flat rows (one per calibration, lens and band) for the CSV and the printed table.

    Parameters
    ----------
    entries : list of dict
        A camera's calibrations (:func:`history`).

    Returns
    -------
    list of dict
        Per calibration, lens and band: ``index``, ``valid_from``, ``file``, ``lens``, ``band``,
        ``inverse_responsivity`` (W sr-1 m-2 nm-1 s DN-1), ``change_percent``, ``change_sigma_percent`` (%), ``z``
        (NaN for the first), ``changed`` ("yes", "no" or ""), ``shared_lab_inputs``.
    """
    rows = []
    for k, entry in enumerate(entries):
        value = entry["inverse_responsivity"]
        for lens in value["lens"].values.astype(str):
            for band in value["band"].values.astype(str):
                sel = dict(lens=lens, band=band)
                row = {"index": k, "valid_from": entry["valid_from"], "file": entry["file"], "lens": lens, "band": band,
                       "inverse_responsivity": float(value.sel(sel)),
                       "change_percent": np.nan, "change_sigma_percent": np.nan, "z": np.nan, "changed": "",
                       "shared_lab_inputs": " ".join(entry["shared_lab_inputs"])}
                if "z" in entry:
                    row.update(change_percent=100 * float(entry["relative_difference"].sel(sel)),
                               change_sigma_percent=100 * float(entry["relative_difference_sigma"].sel(sel)),
                               z=float(entry["z"].sel(sel)), changed="yes" if bool(entry["changed"].sel(sel)) else "no")
                rows.append(row)
    return rows


def history_lines(entries: list[dict], serial: str) -> list[str]:
    """The printed table of :func:`history`: per calibration its file, then R^-1 per lens and band with the
    change from the calibration before.

    Parameters
    ----------
    entries : list of dict
        A camera's calibrations (:func:`history`).
    serial : str
        The camera serial.

    Returns
    -------
    list of str
        The lines.
    """
    lines = [f"camera {serial}: {len(entries)} calibration(s) in validity order",
             f"{'valid from':<21}{'lens':<7}{'band':<6}{'R^-1':>12}{'change %':>10}{'sigma %':>9}{'z':>8}  changed"]
    current = None
    for row in history_table(entries):
        if row["index"] != current:
            current = row["index"]
            lines.append(f"{row['valid_from']}  {row['file']}"
                         + (f"  (shared with the one before: {row['shared_lab_inputs']})" if row["shared_lab_inputs"] else ""))
        change = ("" if not np.isfinite(row["z"]) else
                  f"{row['change_percent']:>+10.2f}{row['change_sigma_percent']:>9.2f}{row['z']:>8.2f}  {row['changed']}")
        lines.append(f"{'':<21}{row['lens']:<7}{row['band']:<6}{row['inverse_responsivity']:>12.4e}{change}")
    return lines


def write_history_csv(entries: list[dict], path: str | Path) -> Path:
    """Write :func:`history_table` as CSV.

    Parameters
    ----------
    entries : list of dict
        A camera's calibrations (:func:`history`).
    path : str or pathlib.Path
        The CSV file to write (its folder is created).

    Returns
    -------
    pathlib.Path
        The file written.
    """
    import csv

    rows = history_table(entries)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    return path


def write_history_figure(entries: list[dict], path: str | Path, serial: str) -> Path:
    """R^-1 per lens and band against the validity start (relative to the first calibration), with the
    difference's sigma from the calibration before as error bars; PNG through the Agg canvas.

    Parameters
    ----------
    entries : list of dict
        A camera's calibrations (:func:`history`).
    path : str or pathlib.Path
        The PNG file to write (its folder is created).
    serial : str
        The camera serial, in the panels' titles.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = history_table(entries)
    lenses = list(dict.fromkeys(r["lens"] for r in rows))
    fig = Figure(figsize=(4.0 * len(lenses), 3.2), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(lenses), squeeze=False)[0]
    first = {(r["lens"], r["band"]): r["inverse_responsivity"] for r in rows if r["index"] == 0}
    for ax, lens in zip(axes, lenses):
        for band in BANDS:
            mine = [r for r in rows if r["lens"] == lens and r["band"] == band]
            when = [datetime.strptime(r["valid_from"], TIME_FORMAT) for r in mine]
            rel = [100 * (r["inverse_responsivity"] / first[(lens, band)] - 1) for r in mine]
            err = [r["change_sigma_percent"] if np.isfinite(r["change_sigma_percent"]) else 0.0 for r in mine]
            ax.errorbar(when, rel, yerr=err, marker="o", capsize=3, label=band, color=BAND_COLOURS[band])
        ax.set_title(f"{serial}, lens {lens}")
        ax.set_ylabel("R^-1 against the first (%)")
        ax.tick_params(axis="x", labelrotation=30)
        ax.legend()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    return path


#: line colours of the bands in the history figure
BAND_COLOURS = {"R": "tab:red", "G": "tab:green", "B": "tab:blue"}


def _responsivity(bundle: xr.Dataset) -> tuple[xr.DataArray, list[Term]]:
    """R^-1 (lens, band) and its budget's terms, absolute (``uncertainty_contribution`` x |R^-1|), each with
    the lab inputs it comes from (:data:`R_INVERSE_TERM_INPUTS`)."""
    bands = list(BANDS)
    r_inv = bundle["inverse_responsivity"].sel(band=bands).astype(float).load()
    contrib = bundle["uncertainty_contribution"].sel(band=bands).astype(float)
    terms = [Term(t, (contrib.sel(term=t) * np.abs(r_inv)).values, R_INVERSE_TERM_INPUTS.get(t, ()))
             for t in contrib["term"].values.astype(str)]
    return r_inv, terms
