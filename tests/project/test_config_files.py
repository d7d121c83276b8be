"""Config files read strictly: a key written twice (YAML and Snakemake keep the last without a word) stops
the run at start-up with one line naming the file and both lines, config/config.yaml and any --configfile."""

from __future__ import annotations

import pytest

from pipeline.config import load_config
from pipeline.errors import InputError
from pipeline.runner.workflow import check_config
from workflow_runs import REPO, snakemake

#: a lab's edit: the dark section copied below to try a threshold, the old one left above it
TWICE = "dataset: data/x\ndark:\n  hot_pixel_threshold_sigma: 6\nlinearity: {}\ndark:\n  hot_pixel_threshold_sigma: 8\n"


def test_load_config_refuses_a_key_written_twice(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text(TWICE)
    with pytest.raises(InputError) as err:
        load_config(path)
    assert str(err.value) == (f"{path}: line 5: key 'dark' appears twice (first on line 2); keep one of the two "
                              "(YAML would silently use the last)")


def test_check_config_reads_every_config_file_again(tmp_path):
    """The start-up check (the Snakefile passes workflow.configfiles) names the file with the duplicate,
    also in a nested mapping; a file without one passes."""
    nested = tmp_path / "lab.yaml"
    nested.write_text("field:\n  reference_window_s: 20\n  min_reference_samples: 4\n  reference_window_s: 30\n")
    config = load_config()
    with pytest.raises(InputError, match=r"lab.yaml: line 4: key 'reference_window_s' appears twice \(first on "
                                         r"line 2\)"):
        check_config(config, REPO / "config" / "config.yaml", config_files=[REPO / "config" / "config.yaml", nested])
    check_config(load_config(), REPO / "config" / "config.yaml", config_files=[REPO / "config" / "config.yaml"])


def test_a_configfile_with_a_key_twice_stops_the_workflow(tmp_path):
    """Through Snakemake (a dry run): exit 1, one error line naming the --configfile, no results/. The
    config is checked before the dataset is looked at, so no dataset is needed."""
    lab = tmp_path / "lab.yaml"
    lab.write_text(TWICE.split("\n", 1)[1])
    proc = snakemake(tmp_path, tmp_path / "no-dataset", "--configfile", str(lab), "-n", check=False)
    errors = [line for line in (proc.stdout + proc.stderr).splitlines() if line.startswith("error:")]
    assert proc.returncode == 1 and errors == [
        f"error: {lab}: line 4: key 'dark' appears twice (first on line 1); keep one of the two (YAML would "
        "silently use the last)"], proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and not (tmp_path / "results").exists()


def test_an_angle_outside_its_range_is_refused_at_start_up():
    """Another instance of the schema's ranges: the field mask's half angle past 90 deg (a full width
    written for the half) names the key, the value and the range."""
    config = load_config()
    config["field"] = {**config["field"], "mask_half_angle_deg": 120.0}
    with pytest.raises(InputError) as err:
        check_config(config, "config/config.yaml")
    assert str(err.value) == "config/config.yaml: config field.mask_half_angle_deg: 120.0 is outside its range (0, 90]"
