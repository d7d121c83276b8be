"""A stage's code fingerprint (a rule param): the modules it runs, and a change to one of them."""

from __future__ import annotations

import shutil

from pipeline.runner import workflow


def test_a_stage_runs_its_module_its_physics_and_the_runner_not_other_stages():
    modules = workflow.stage_code_modules("rolloff")
    assert {"pipeline.stages.rolloff", "pipeline.radiometry.rolloff", "pipeline.runner.workflow", "pipeline.effects",
            "pipeline.stages.observations", "pipeline.io.frames"} <= set(modules)
    assert not any(m.startswith(("pipeline.simulate", "pipeline.report", "pipeline.diagnostics.missing_effects")) for m in modules)
    assert "pipeline.stages.dark" not in modules
    # absolute reduces its frames with the spectral stage's central-mask functions
    assert "pipeline.stages.spectral" in workflow.stage_code_modules("absolute")


def test_editing_a_physics_module_changes_only_the_stages_that_run_it(tmp_path, monkeypatch):
    copy = tmp_path / "pipeline"
    shutil.copytree(workflow.PACKAGE_ROOT, copy, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(workflow, "PACKAGE_ROOT", copy)
    before = {stage: workflow.stage_code_sha256(stage) for stage in ("dark", "rolloff", "immersion")}
    path = copy / "radiometry" / "rolloff.py"
    path.write_text(path.read_text() + "\n# an edit\n")
    after = {stage: workflow.stage_code_sha256(stage) for stage in before}
    assert after["rolloff"] != before["rolloff"]
    assert after["dark"] == before["dark"]
    assert (after["immersion"] != before["immersion"]) == ("pipeline.radiometry.rolloff" in
                                                           workflow.stage_code_modules("immersion"))
