"""Helpers shared by the section modules (no section of its own)."""

from __future__ import annotations

import numpy as np
import xarray as xr

from pipeline.report.content import Group, Markup, Table, Text
from pipeline.report.formatting import fmt_uncertain, units_text
from pipeline.report.inputs import ReportInputs

__all__ = ["z_guides", "not_run", "effects_table", "per_lens", "lens_title"]


def z_guides(ax):
    """Horizontal guides of a normalised-residual plot: 0, ±1 (dotted), ±3 (dashed)."""
    for level, style in ((0, "-"), (1, ":"), (-1, ":"), (3, "--"), (-3, "--")):
        ax.axhline(level, color="grey", lw=0.8, ls=style, zorder=0)


def not_run(stage: str, title: str, skipped: dict[str, str]) -> Text:
    reason = skipped.get(stage)
    why = Markup(": {}").format(reason) if reason else Markup("; no artefacts were given")
    return Text(Markup('The {} stage was not run{} (see <a href="#skipped">Stages not run</a>).').format(title, why),
                "note")


def lens_title(lens: str, suffix: str = "") -> str:
    return f"Lens “{lens}”{suffix}"


def effects_table(ds: xr.Dataset):
    """Fitted effect parameters stored as ``effect_<name>`` (+ ``_sigma``), one row per element."""
    names = [v for v in ds.data_vars if v.startswith("effect_") and not v.endswith("_sigma")]
    rows = []
    for v in names:
        da = ds[v]
        sd = ds[f"{v}_sigma"] if f"{v}_sigma" in ds and ds[f"{v}_sigma"].shape == da.shape else None
        for idx in np.ndindex(da.shape):
            label = ""
            if da.size > 1:
                parts = [f"{d}={da[d].values[i]}" if d in da.coords else f"{d}[{i}]" for d, i in zip(da.dims, idx)]
                label = f" ({', '.join(parts)})"
            val = float(da.values[idx]) if da.ndim else float(da.values)
            sig = (float(sd.values[idx]) if da.ndim else float(sd.values)) if sd is not None else None
            rows.append([v.removeprefix("effect_") + label, da.attrs.get("long_name", ""),
                         f"{fmt_uncertain(val, sig)} {units_text(da.attrs.get('units', ''))}".strip()])
    if not rows:
        return Text("No effect parameters are fitted in this stage for this run.", "note")
    return Table(["effect", "description", "value"], rows, "Fitted effect parameters (± standard error):", left=2)


def per_lens(inputs: ReportInputs, stage: str, title: str, build_lens, anchor: str | None = None) -> list:
    """One :class:`Group` per lens of ``stage`` (``build_lens(lens, ds, inputs)`` gives its blocks),
    or a note that the stage did not run."""
    arts = inputs.stage(stage)
    if not arts:
        return [not_run(stage, title, inputs.skipped)]
    anchor = anchor or stage
    return [Group(lens_title(lens), build_lens(lens, ds, inputs), id=f"{anchor}-{lens}") for lens, ds in arts.items()]
