"""Provenance: per artefact its file, versions, creation time, model effects, inputs and configuration."""

from __future__ import annotations

import json
from pathlib import Path

from pipeline.report.content import Details, Table
from pipeline.report.inputs import input_count
from pipeline.report.registry import section


@section("provenance", "Provenance", order=120,
         intro="Where every number above comes from: the artefacts read, the pipeline and artefact versions that "
               "wrote them, when, with which model effects, how many input files and which configuration "
               "(SHA-256 of each stage's configuration subset).")
def provenance_section(inputs) -> list:
    """The "Provenance" section: every artefact read and where it comes from.

    Each artefact's versions, creation time, model effects, input count and configuration digest, the
    calibration bundle's (when given), and each artefact's configuration subset.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs.

    Returns
    -------
    list
        The section's blocks (:mod:`pipeline.report.content`).
    """
    arts = list(inputs.all_artefacts())
    rows = [[st, lens, Path(p).name, str(ds.attrs.get("artefact_version", "?")),
             str(ds.attrs.get("pipeline_version", "?")), str(ds.attrs.get("created", "?")),
             str(ds.attrs.get("model_effects", "")).replace(",", ", ") or "(none)",
             input_count(ds), str(ds.attrs.get("config_sha256", "?"))]
            for st, lens, p, ds in arts]
    out = [Table(["stage", "lens", "file", "artefact version", "pipeline version", "created",
                  "model effects", "input files", "config sha256"], rows, left=3)]
    if inputs.calibration is not None:
        attrs = inputs.calibration.attrs
        out.append(Table(["artefact", "artefact version", "pipeline version", "created", "config sha256"],
                         [["calibration bundle", str(attrs.get("artefact_version", "?")),
                           str(attrs.get("pipeline_version", "?")), str(attrs.get("created", "?")),
                           str(attrs.get("config_sha256", "?"))]], left=1))
    for st, lens, _path, ds in arts:
        cfg = ds.attrs.get("config")
        if cfg:
            try:
                cfg = json.dumps(json.loads(cfg), indent=2, sort_keys=True)
            except ValueError:
                pass
            out.append(Details(f"Config subset of {st} / {lens}", pre=cfg))
    return out
