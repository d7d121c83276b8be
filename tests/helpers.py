"""Geometry artefacts of the simulator's true optics, for tests of later stages.

Tests that hand a stage the true geometry (instead of the geometry stage's
fit) build it here: the truth comes from :mod:`pipeline.simulate`, the layout
from :func:`pipeline.stages.geometry_maps.maps_dataset`, so that no stage
imports the simulator.
"""

from __future__ import annotations

from pathlib import Path

import xarray as xr

from pipeline.artefact import write_artefact
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
