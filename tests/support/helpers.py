"""Geometry artefacts of the simulator's true optics, and a dataset calibrated by the pipeline, for tests.

Tests that hand a stage the true geometry (instead of the geometry stage's
fit) build it here: the truth comes from :mod:`pipeline.simulate`, the layout
from :func:`pipeline.stages.geometry_maps.maps_dataset`, so that no stage
imports the simulator. :func:`calibrate` runs the pipeline's own lab stages
and gathers their bundle; :func:`key_results` reads its key numbers for the regression
(``tests/regression/``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr
import yaml

from pipeline.io.artefact import write_artefact
from pipeline.bundle.calibration import BUNDLE_STAGES, build_bundle, read_bundle
from pipeline.radiometry.rolloff import evaluate_rolloff
from pipeline.runner.workflow import STAGES, run_stage
from pipeline.io.bands import BANDS
from pipeline.simulate.lens import default_model
from pipeline.simulate.rolloff import true_band_models
from pipeline.stages.geometry_maps import MEDIA, maps_dataset


def default_maps_dataset(lens: str, band_shape: tuple[int, int], media=MEDIA) -> xr.Dataset:
    """Maps of the simulator's nominal camera (published fits, no per-band differences)."""
    return maps_dataset({(m, b): default_model(lens, m, band_shape) for m in media for b in BANDS}, band_shape)


def write_default_geometry(folder, lenses, band_shape: tuple[int, int], media=MEDIA) -> dict:
    """Write geometry artefacts of the nominal camera (see :func:`default_maps_dataset`) into
    ``folder``, one per lens; returns lens -> path."""
    return {lens: write_artefact(default_maps_dataset(lens, band_shape, media=media), Path(folder) / f"{lens}.nc",
                                 stage="geometry", inputs={}, config_subset={}, effects=[])
            for lens in lenses}


def true_geometry_dataset(lens: str, band_px: int) -> xr.Dataset:
    """Geometry artefact maps of the simulator's true optics at each band's CFA site
    (:func:`pipeline.simulate.rolloff.true_band_models`): what a per-band geometry
    calibration finds."""
    return maps_dataset(true_band_models(lens, band_px), (band_px, band_px))


def calibrate(root: Path, config: dict, out: Path) -> tuple[dict, Path, dict]:
    """Every lab stage of the bundle on ``root``, per lens, into ``out``; then the bundle.

    Returns (artefacts {stage: {lens: path}}, bundle path, dataset.yaml).
    """
    meta = yaml.safe_load((root / "dataset.yaml").read_text())
    artefacts = {}
    for stage in BUNDLE_STAGES:
        spec = STAGES[stage]
        upstream = {name: artefacts[name] for name in spec.upstream + spec.optional_upstream if name in artefacts}
        artefacts[stage] = {lens: out / stage / f"{lens}.nc" for lens in meta["lenses"]}
        # as the workflow's jobs run them (checked=True): the simulated datasets' consistency is what
        # test_consistency.py and test_validation.py check, and these stages' numbers what the callers check
        run_stage(stage, root, config, artefacts[stage], upstream, checked=True)
    bundle_path = out / "calibration" / f"{meta['camera']['serial']}.nc"
    build_bundle(artefacts, bundle_path, meta["camera"], meta["lenses"], config)
    return artefacts, bundle_path, meta


#: field angles at which the regression records the roll-off, per medium (inside the tiny camera's
#: calibrated field angle: about 82 degrees in air, 70 in water)
REGRESSION_ROLLOFF_DEG = {"air": (60.0, 80.0), "water": (60.0,)}


def key_results(bundle_path: Path) -> dict[str, dict]:
    """The calibration's key numbers per stage, lens and band, from its bundle: {name: {value, sigma}}.

    ``sigma`` is the pipeline's own stated standard uncertainty of the value, or None where the
    bundle states none. Names are ``stage.quantity.lens[.band][.setting]``. NaN is written as None.
    """
    b = read_bundle(bundle_path)
    out: dict[str, dict] = {}

    def put(name, value, sigma=None):
        value = float(value)
        sigma = None if sigma is None else float(sigma)
        out[name] = {"value": None if np.isnan(value) else value,
                     "sigma": None if sigma is None or np.isnan(sigma) else sigma}

    def with_sigma(stage, var, lens, band=None):
        sel = {"lens": lens} if band is None else {"lens": lens, "band": band}
        sigma = b[f"{var}_sigma"].sel(sel) if f"{var}_sigma" in b else None
        put(".".join([stage, var, lens] + ([band] if band else [])), b[var].sel(sel), sigma)

    for lens in b["lens"].values.astype(str):
        put(f"linearity.conversion_gain_dn_per_e.{lens}", b["conversion_gain_dn_per_e"].sel(lens=lens),
            b["conversion_gain_dn_per_e_sigma"].sel(lens=lens))
        put(f"linearity.saturation_dn.{lens}", b["saturation_dn"].sel(lens=lens))
        with_sigma("dark", "dark_current_dn_per_s", lens)
        for band in BANDS:
            with_sigma("dark", "bias_dn", lens, band)
            for iso in (100.0, 3200.0):
                put(f"dark.read_noise_dn.{lens}.{band}.iso{iso:g}", b["read_noise_dn"].sel(lens=lens, band=band, dark_iso=iso))
            put(f"dark.offset_pattern_dn.{lens}.{band}", b["offset_pattern_dn"].sel(lens=lens, band=band))
            for var in ("xc_px", "yc_px", "half_fov_deg"):
                put(f"geometry.{var}.{lens}.{band}.air", b[var].sel(lens=lens, band=band, medium="air"))
            for medium, angles in REGRESSION_ROLLOFF_DEG.items():
                sel = dict(lens=lens, band=band, medium=medium)
                g, sigma = evaluate_rolloff(b["rolloff_coefficients"].sel(sel).values,
                                            np.array(angles), b["rolloff_covariance"].sel(sel).values)
                for angle, gi, si in zip(angles, g, sigma):
                    put(f"rolloff.g.{lens}.{band}.{medium}.{angle:g}deg", gi, si)
            with_sigma("spectral", "effective_wavelength_nm", lens, band)
            put(f"spectral.half_bandwidth_nm.{lens}.{band}", b["half_bandwidth_nm"].sel(lens=lens, band=band))
            with_sigma("absolute", "inverse_responsivity", lens, band)
            with_sigma("immersion", "immersion_factor", lens, band)
            put(f"calibration.noise_equivalent_radiance.{lens}.{band}",
                b["noise_equivalent_radiance"].sel(lens=lens, band=band))
    return out


def true_and_fitted_theta(truth: dict, art: xr.Dataset, lens: str, medium: str, band: str):
    """The simulator's true band model and theta map beside the fitted ones of a geometry artefact:
    (true model, fitted model, true theta map, fitted theta map)."""
    from pipeline.geometry.maps import theta_phi_maps
    from pipeline.geometry.scaramuzza import FisheyeModel
    from pipeline.stages.geometry_maps import model_from_dataset

    t = FisheyeModel.from_dict(truth["models"][lens][medium][band]["band"])
    th_true, _ = theta_phi_maps(t)
    return t, model_from_dataset(art, medium, band), th_true, art["theta_deg"].sel(medium=medium, band=band).values


def assert_g_theta_within_a_band_pixel(dataset_root, artefacts: dict) -> None:
    """The G theta map of each lens's geometry artefact (``artefacts``: lens -> path) against the simulator's
    truth of ``dataset_root``: the median error over the true image circle within one band pixel's angle on
    the axis (the tiny scale's 2.5 to 3 deg; measured 0.5 to 1.1 deg)."""
    import numpy as np
    import xarray as xr
    import yaml

    from pipeline.geometry.maps import theta_phi_maps
    from pipeline.geometry.scaramuzza import FisheyeModel
    from pipeline.simulate.dataset import truth_dir_for

    truth = yaml.safe_load((truth_dir_for(dataset_root) / "truth.yaml").read_text())["experiments_truth"]["geometry"]
    for lens, path in artefacts.items():
        with xr.open_dataset(path) as art:
            for medium in ("air", "water"):
                t = FisheyeModel.from_dict(truth["models"][lens][medium]["G"]["band"])
                th_true, _ = theta_phi_maps(t)
                fitted = art["theta_deg"].sel(medium=medium, band="G").values
                err = np.abs(fitted - th_true)[th_true <= t.half_fov_deg]
                deg_per_band_px = np.degrees(1.0 / t.poly[0])
                assert np.median(err) < deg_per_band_px, (lens, medium, float(np.median(err)))


#: every lab effect of the catalogue, at the simulator's default (typical) amplitudes (the apply and geometry truth tests)
LAB_EFFECTS = ("dark_current", "hot_pixels", "shutter_offset", "nonlinearity", "iso_gain", "prnu", "bias_drift",
               "temperature", "rolloff_azimuth", "stray_light", "immersion_angle")
