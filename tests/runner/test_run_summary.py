"""The lines printed when a run ends: report path, one verdict per experiment, skipped stages."""

from __future__ import annotations

import pandas as pd

from pipeline.runner.run_summary import summarise_run


def _results(tmp_path):
    diag = tmp_path / "diagnostics"
    diag.mkdir(parents=True)
    (tmp_path / "report").mkdir()
    (tmp_path / "report" / "index.html").write_text("<html></html>")
    pd.DataFrame({"experiment": ["dark", "linearity", "rolloff"], "rms_z": [1.02, 4.1, 1.9],
                  "chi2": [40.0, 600.0, 90.0], "dof": [39, 36, 25], "n_obs": [40, 40, 30]}).to_csv(
        diag / "run_errors.csv", index=False)
    pd.DataFrame({"rank": [1, 2], "effect": ["shutter_offset", "nonlinearity"], "experiment": ["linearity"] * 2,
                  "significant": [True, False], "amplitude": [0.0004, 0.01], "amplitude_low": [0.00035, -0.01],
                  "amplitude_high": [0.00045, 0.03], "units": ["s", "1"]}).to_csv(diag / "missing_effects.csv",
                                                                                 index=False)
    pd.DataFrame({"experiment": ["rolloff"], "rms_z": [1.9], "covariate": ["theta_deg (setting level)"],
                  "association": [0.6], "message": ["..."]}).to_csv(diag / "unexplained.csv", index=False)
    return tmp_path


def test_summary_names_the_report_the_missing_effect_and_the_skipped_stages(tmp_path):
    lines = summarise_run(_results(tmp_path), ["dark_current", "hot_pixels"], {"field": "the dataset has no field/ folder"})
    assert lines[0] == f"Calibration report: {(tmp_path / 'report' / 'index.html').resolve()}"
    dark, linearity, rolloff = lines[1:4]
    assert dark.split() == ["dark", "rms_z", "1.02:", "at", "the", "noise", "floor"]
    assert "shutter_offset is most likely missing, 0.0004 s (95 % interval 0.00035 to 0.00045)" in linearity
    assert "no catalogue effect explains" in rolloff and "theta_deg" in rolloff
    assert "--config 'model={effects: [dark_current, hot_pixels, shutter_offset]}'" in lines[-2]
    assert lines[-1] == "  skipped: field (the dataset has no field/ folder)"


def test_one_line_adds_every_effect_found_and_the_field_scale_comes_first(tmp_path):
    """Two experiments each with its own accepted effect: the last line adds both, in the accepted order; the
    field line opens with its scale closure's departure, size and z, then names the effect that predicts it."""
    results = _results(tmp_path)
    diag = results / "diagnostics"
    pd.DataFrame({"experiment": ["linearity", "field"], "rms_z": [4.1, 12.0], "chi2": [600.0, 3000.0],
                  "dof": [36, 95], "n_obs": [40, 96]}).to_csv(diag / "run_errors.csv", index=False)
    pd.DataFrame({"rank": [1, 2, 3], "effect": ["shutter_offset", "spectral_mismatch", "clock_offset"],
                  "experiment": ["field+linearity", "field", "field"], "significant": [True, True, False],
                  "amplitude": [0.0004, 1.05, 1.0], "amplitude_low": [0.00038, 0.92, -3.0],
                  "amplitude_high": [0.00042, 1.18, 5.0], "units": ["s", "1", "s"],
                  "field_scale_explained": [0.998, -0.2, float("nan")],
                  "field_scale_factor": ["R:2.567 G:2.567 B:2.567", "R:0.99 G:0.99 B:0.99", ""]}).to_csv(diag / "missing_effects.csv",
                                                                                  index=False)
    pd.DataFrame({"lens": ["close"] * 3, "band": ["R", "G", "B"], "k_b": [2.57, 2.60, 2.74],
                  "departure_percent": [157.0, 160.0, 174.0], "sigma_percent": [3.6, 3.6, 3.7],
                  "z": [26.4, 26.7, 27.2], "departs": [True, True, True],
                  "explained_by": ["shutter_offset"] * 3, "predicted_factor": [2.567] * 3,
                  "remaining_percent": [0.3, 1.3, 6.7], "z_remaining": [0.1, 0.35, 1.7],
                  "departs_remaining": [False, False, False]}).to_csv(diag / "field_scale.csv", index=False)
    lines = summarise_run(results, ["dark_current", "hot_pixels"])
    field = next(line for line in lines if line.strip().startswith("field"))
    assert field.index("field scale DEPARTS") < field.index("most likely missing")
    assert "disagree by +174 % at 27.2 sigma (B)" in field and "camera/reference 2.57, 2.6, 2.74 (R/G/B)" in field
    assert "predicted by shutter_offset (0.0004 s as the linearity experiment fits it) x2.57" in field
    assert field.endswith("shutter_offset is most likely missing, 0.0004 s (95 % interval 0.00038 to 0.00042)")
    assert lines[-1] == ("  to add every effect this run found (shutter_offset, spectral_mismatch): --config "
                         "'model={effects: [dark_current, hot_pixels, shutter_offset, spectral_mismatch]}' "
                         "(or model.effects in config/config.yaml)")


def test_summary_without_a_report(tmp_path):
    assert summarise_run(tmp_path, [], {}) == ["No report was written."]


def test_stages_not_finished_reads_this_runs_job_logs(tmp_path):
    """A failed job's error line from its log; a stage that needed it is 'not run'; a log older than the
    run's start (a job of an earlier run) is not this run's error."""
    import os

    from pipeline.runner.run_summary import stages_not_finished

    results = tmp_path / "results"
    (results / "dark").mkdir(parents=True)
    (results / "dark" / "far.nc").write_bytes(b"")
    (results / "dark" / "close.nc").write_bytes(b"")
    (results / "logs" / "linearity").mkdir(parents=True)
    (results / "logs" / "geometry").mkdir(parents=True)
    line = "/data/linearity/raw/a.dng: checksum mismatch (MD5SUMS says 1, file is 2)"
    (results / "logs" / "linearity" / "far.log").write_text(
        f"2026-12-01 10:00:00,000 INFO linearity far: reading\n2026-12-01 10:00:01,000 ERROR {line}\n")
    old = results / "logs" / "geometry" / "far.log"
    old.write_text("2026-11-30 10:00:00,000 ERROR /data/geometry/frames.csv: an error of yesterday\n")
    os.utime(old, (1000.0, 1000.0))
    lenses = {"dark": ["far", "close"], "linearity": ["far", "close"], "geometry": ["far"], "rolloff": ["far"]}
    out = stages_not_finished(results, lenses, since=2000.0)
    assert out["linearity"] == f"failed for lens far: {line} (log: {results / 'logs/linearity/far.log'})"
    assert out["geometry"].startswith("not run: the run stopped at a failed job before it")
    assert out["rolloff"] == "not run: it needs geometry, linearity, which did not finish"
    assert "dark" not in out
