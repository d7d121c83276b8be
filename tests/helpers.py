"""Geometry artefacts of the simulator's true optics, and a dataset calibrated by the pipeline, for tests.

Tests that hand a stage the true geometry (instead of the geometry stage's
fit) build it here: the truth comes from :mod:`pipeline.simulate`, the layout
from :func:`pipeline.stages.geometry_maps.maps_dataset`, so that no stage
imports the simulator. :func:`calibrate` runs the pipeline's own lab stages
and gathers their bundle.
"""

from __future__ import annotations

from pathlib import Path

import xarray as xr
import yaml

from pipeline.artefact import write_artefact
from pipeline.calibration import BUNDLE_STAGES, build_bundle
from pipeline.workflow import STAGES, run_stage
from pipeline.bands import BANDS
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
        run_stage(stage, root, config, artefacts[stage], upstream)
    bundle_path = out / "calibration" / f"{meta['camera']['serial']}.nc"
    build_bundle(artefacts, bundle_path, meta["camera"], meta["lenses"], config)
    return artefacts, bundle_path, meta
