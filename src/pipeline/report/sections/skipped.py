"""Stages not run, each with its reason (an experiment folder the dataset lacks, a failed upstream job)."""

from __future__ import annotations

from pipeline.report.content import Table, Text
from pipeline.report.registry import section


@section("skipped", "Stages not run", order=110)
def skipped_section(inputs) -> list:
    """The "Stages not run" section: each stage not run with its reason, or a line saying all ran.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs (its ``skipped``).

    Returns
    -------
    list
        The section's blocks (:mod:`pipeline.report.content`).
    """
    if not inputs.skipped:
        return [Text("All requested stages ran.")]
    return [Table(["stage", "reason"], [[k, v] for k, v in inputs.skipped.items()], left=2)]
