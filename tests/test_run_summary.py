"""The lines printed when a run ends: report path, one verdict per experiment, skipped stages."""

from __future__ import annotations

import pandas as pd

from pipeline.run_summary import summarise_run


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
    assert "--config 'model={effects: [dark_current, hot_pixels, shutter_offset]}'" in linearity
    assert "no catalogue effect explains" in rolloff and "theta_deg" in rolloff
    assert lines[-1] == "  skipped: field (the dataset has no field/ folder)"


def test_summary_without_a_report(tmp_path):
    assert summarise_run(tmp_path, [], {}) == ["No report was written."]
