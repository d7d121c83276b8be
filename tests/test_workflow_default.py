"""What `python -m pipeline simulate --scale tiny` writes by default calibrates end to end through the
workflow, field hour included, and new field data reruns the field job only."""

from __future__ import annotations

import subprocess
import sys

import pandas as pd
import xarray as xr

from workflow_runs import LENSES, planned_rules, snakemake


def test_the_default_tiny_simulation_runs_through_the_whole_workflow(tmp_path):
    """What `python -m pipeline simulate --scale tiny` writes by default (every experiment,
    the command line's default seed) calibrates end to end."""
    dataset = tmp_path / "tiny"
    proc = subprocess.run([sys.executable, "-m", "pipeline", "simulate", "--out", str(dataset), "--scale", "tiny",
                           "--no-progress"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    run = snakemake(tmp_path, dataset)
    for stage in ("dark", "linearity", "geometry", "rolloff", "spectral", "absolute", "immersion"):
        for lens in LENSES:
            with xr.open_dataset(tmp_path / f"results/{stage}/{lens}.nc") as ds:
                assert ds.attrs["artefact"] == stage
    assert (tmp_path / "results/report/index.html").exists()
    assert "Calibration report:" in run.stdout + run.stderr
    # the field hour: one job for the lens at the zenith, its section in the report, its row in the error history
    assert (tmp_path / "results/field/close.nc").exists() and not (tmp_path / "results/field/far.nc").exists()
    html = (tmp_path / "results/report/index.html").read_text()
    assert 'id="field-close"' in html and "MUPD" in html
    history = pd.read_csv(tmp_path / "results/diagnostics/error_history.csv")
    assert "field" in set(history["experiment"])
    # new field data only: the field job, the diagnostics and the report rerun, no lab stage
    from pipeline.dataset import write_md5sums

    reference = dataset / "field/reference_radiometer.csv"
    lines = reference.read_text().splitlines()
    reference.write_text("\n".join(lines[:-1]) + "\n")       # the last reading dropped
    write_md5sums(dataset)
    assert planned_rules(tmp_path, dataset) == {"field", "diagnostics", "report", "all"}
