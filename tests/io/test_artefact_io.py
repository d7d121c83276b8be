"""How an artefact's variables are stored: compressed by default, uncompressed where a stage says so."""

from __future__ import annotations

import netCDF4
import numpy as np
import xarray as xr

from pipeline.io.artefact import ARTEFACT_COMPRESSION_LEVEL, write_artefact


def test_a_variable_whose_encoding_says_no_zlib_is_stored_uncompressed(tmp_path):
    rng = np.random.default_rng(0)
    ds = xr.Dataset({"pattern": (("y", "x"), rng.normal(size=(64, 64)).astype(np.float32)),
                     "noisy": (("y", "x"), rng.normal(size=(64, 64)).astype(np.float32))})
    ds["noisy"].encoding["zlib"] = False
    path = write_artefact(ds, tmp_path / "a.nc", stage="linearity", inputs={}, config_subset={}, effects=[])
    with netCDF4.Dataset(path) as nc:
        assert nc["pattern"].filters()["zlib"] and nc["pattern"].filters()["complevel"] == ARTEFACT_COMPRESSION_LEVEL
        assert not nc["noisy"].filters()["zlib"]
    with xr.open_dataset(path) as back:
        for name in ds.data_vars:
            np.testing.assert_array_equal(back[name].values, ds[name].values)
