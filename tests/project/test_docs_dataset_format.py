"""docs/dataset-format.md names every file, column and key that pipeline.io.dataset defines, so that the page a
lab reads cannot fall behind the reader of its data."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import pytest

from pipeline.io import dataset
from pipeline.io.dataset import (COMMON_COLUMNS, EXPERIMENT_COLUMNS, EXPERIMENTS, OPTIONAL_COLUMNS, PROJECTIONS, SIDECARS,
                              TAG_COLUMNS)

DOC = Path(__file__).resolve().parents[2] / "docs" / "dataset-format.md"


@pytest.fixture(scope="module")
def text() -> str:
    return DOC.read_text(encoding="utf-8")


def _named(text: str, name: str) -> bool:
    """``name`` written as code (between backticks, alone or as the head of a path or key)."""
    return re.search(r"`[^`\n]*\b" + re.escape(name) + r"\b[^`\n]*`", text) is not None


def test_every_sidecar_file_is_named(text):
    missing = [f"{exp}/{name}" for exp, names in SIDECARS.items() for name in names if f"`{exp}/{name}`" not in text]
    assert not missing, f"docs/dataset-format.md does not name the sidecar files {missing}"


def test_every_required_frames_column_is_named(text):
    required = set(COMMON_COLUMNS) | {c for columns in EXPERIMENT_COLUMNS.values() for c in columns}
    missing = sorted(c for c in required if f"`{c}`" not in text)
    assert not missing, f"docs/dataset-format.md does not name the frames.csv columns {missing}"


def test_each_experiment_lists_its_own_columns(text):
    """The row of each experiment in the table of experiment columns names exactly the columns the code requires."""
    for experiment in EXPERIMENTS:
        row = re.search(r"^\| `" + experiment + r"` \| ([^|]*)\|", text, re.MULTILINE)
        assert row, f"no row for {experiment!r} in the table of experiment columns"
        listed = tuple(re.findall(r"`([^`]+)`", row.group(1)))
        assert listed == EXPERIMENT_COLUMNS[experiment], (experiment, listed)


def test_optional_and_tag_columns_experiments_and_projections_are_named(text):
    names = OPTIONAL_COLUMNS + TAG_COLUMNS + PROJECTIONS + tuple(f"{e}/" for e in EXPERIMENTS)
    missing = [n for n in names if n not in text]
    assert not missing, f"docs/dataset-format.md does not name {missing}"


def test_sidecar_columns_and_keys_are_named(text):
    """Every column and key the sidecar readers require (their source names them as string literals)."""
    readers = {
        "_photodiode": ("wavelength_nm", "signal", "signal_std"),
        "_source_spectrum": ("wavelength_nm", "radiance", "radiance_std"),
        "_source_reference": ("wavelength_nm", "radiance_W_sr_m2_nm", "uncertainty_rel"),
        "_water": ("temperature_c", "salinity_psu"),
        "_reference_radiometer": ("time",),
        "_site": ("latitude_deg", "longitude_deg", "camera_clock_utc_offset_h", "name", "channels_nm", "fwhm_nm",
                  "half_fov_deg", "calibration_relative_sigma"),
    }
    for reader, keys in readers.items():
        source = inspect.getsource(getattr(dataset, reader))
        for key in keys:
            assert f'"{key}"' in source, f"{reader} no longer reads {key!r}: update this test and the doc"
            assert _named(text, key), f"docs/dataset-format.md does not name {key!r} ({reader})"


def test_default_reference_calibration_sigma_is_stated(text):
    assert "`reference.calibration_relative_sigma`" in text
    assert f"`{dataset.REFERENCE_CALIBRATION_RELATIVE_SIGMA}`" in text
