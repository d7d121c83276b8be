"""Helpers shared by the section modules (no section of its own)."""

from __future__ import annotations

import numpy as np
import xarray as xr

from pipeline.report.content import Group, Markup, Table, Text
from pipeline.report.formatting import fmt_uncertain, units_text
from pipeline.report.inputs import ReportInputs

__all__ = ["z_guides", "not_run", "effects_table", "per_lens", "lens_title"]


def z_guides(ax):
    """Horizontal guides of a normalised-residual plot: 0, ±1 (dotted), ±3 (dashed).

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        The plot's axes.
    """
    for level, style in ((0, "-"), (1, ":"), (-1, ":"), (3, "--"), (-3, "--")):
        ax.axhline(level, color="grey", lw=0.8, ls=style, zorder=0)


def not_run(stage: str, title: str, skipped: dict[str, str]) -> Text:
    """The note that a stage was not run, with its reason and a link to the "Stages not run" section.

    Parameters
    ----------
    stage : str
        The stage, e.g. ``"rolloff"``.
    title : str
        The stage's name as the page writes it.
    skipped : dict[str, str]
        Stage -> why it was not run.

    Returns
    -------
    pipeline.report.content.Text
        A note.
    """
    reason = skipped.get(stage)
    why = Markup(": {}").format(reason) if reason else Markup("; no artefacts were given")
    return Text(Markup('The {} stage was not run{} (see <a href="#skipped">Stages not run</a>).').format(title, why),
                "note")


def lens_title(lens: str, suffix: str = "") -> str:
    """The heading of one lens's part of a section.

    Parameters
    ----------
    lens : str
        The lens.
    suffix : str, optional
        Text after the lens's name.

    Returns
    -------
    str
        E.g. ``Lens “front”``.
    """
    return f"Lens “{lens}”{suffix}"


def effects_table(ds: xr.Dataset):
    """Fitted effect parameters stored as ``effect_<name>`` (+ ``_sigma``), one row per element.

    Parameters
    ----------
    ds : xarray.Dataset
        A stage's artefact.

    Returns
    -------
    pipeline.report.content.Table or pipeline.report.content.Text
        The table (effect, description, value ± standard error with units), or a note when the artefact holds
        no effect parameter.
    """
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
    """One :class:`Group` per lens of ``stage``, or a note that the stage did not run.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs.
    stage : str
        The stage whose artefacts are shown.
    title : str
        The stage's name as the page writes it (for the note).
    build_lens : callable
        ``build_lens(lens, ds, inputs)`` -> the lens's blocks.
    anchor : str or None, optional
        The groups' anchor prefix; default ``stage``.

    Returns
    -------
    list
        The groups (anchored ``<anchor>-<lens>``), or the one note of :func:`not_run`.
    """
    arts = inputs.stage(stage)
    if not arts:
        return [not_run(stage, title, inputs.skipped)]
    anchor = anchor or stage
    return [Group(lens_title(lens), build_lens(lens, ds, inputs), id=f"{anchor}-{lens}") for lens, ds in arts.items()]


def residual_figure(tab, x: str, xlabel: str, name: str, caption: str, group: str | None = None,
                    group_label: str = "", logx: bool = False):
    """Where a stage's model fails: the normalised residuals z of its observation table against a covariate.

    One colour per band, one marker per value of ``group`` (e.g. azimuth plane or medium), with the ±1 and
    ±3 guides.

    Parameters
    ----------
    tab : pandas.DataFrame
        The observation table (``z``, the covariate, ``band``; only ``used`` rows are drawn when it has them).
    x : str
        The covariate's column.
    xlabel : str
        The x axis's label (with units).
    name : str
        The figure's short name.
    caption : str
        Its caption.
    group : str or None, optional
        A column whose values get their own marker.
    group_label : str, optional
        What a value of ``group`` is called in the legend.
    logx : bool, default False
        A logarithmic x axis.

    Returns
    -------
    pipeline.report.content.Figure or None
        The figure; None when the table has no z or no ``x``.
    """
    import matplotlib.pyplot as plt

    from pipeline.report.content import draw
    from pipeline.report.palette import BAND_COLOURS, category

    if not len(tab) or "z" not in tab or x not in tab:
        return None
    if "used" in tab:
        tab = tab[tab["used"].astype(bool)]
    fig, ax = plt.subplots(figsize=(9.5, 3.6))
    markers = "osD^v<>P"
    groups = list(dict.fromkeys(tab[group])) if group and group in tab else [None]
    for k, g in enumerate(groups):
        sub = tab if g is None else tab[tab[group] == g]
        for j, (band, sb) in enumerate(sub.groupby("band", sort=False) if "band" in sub else [("", sub)]):
            label = f"{band}" + (f", {group_label} {g}" if g is not None else "")
            ax.plot(sb[x], sb["z"], markers[k % len(markers)], ms=4, mfc="none",
                    color=BAND_COLOURS.get(str(band), category(j)), label=label)
    z_guides(ax)
    if logx:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("residual z (data − model)/σ [1]")
    n_entries = len(ax.get_legend_handles_labels()[1])
    ax.legend(fontsize=6, ncol=1 if n_entries <= 9 else 2, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    return draw(fig, name, caption, alt=f"normalised residuals against {xlabel}")
