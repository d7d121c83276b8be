"""What a report section returns: figures and tables with their captions, as data.

A section builder returns a list of blocks (:class:`Text`, :class:`Items`, :class:`Table`,
:class:`Figure`, :class:`Group`, :class:`Details`); the templates turn them into HTML, and the report
numbers the figures and writes each as a PNG file. Text is escaped when rendered; a string built as
:class:`markupsafe.Markup` (its arguments escaped by ``Markup.format``) keeps its links and emphasis.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from typing import Union

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.layout_engine import PlaceHolderLayoutEngine  # noqa: E402
from markupsafe import Markup  # noqa: E402

__all__ = ["Text", "Items", "Table", "Figure", "Group", "Details", "Block", "draw", "Markup", "FIGURE_DPI"]

#: resolution of the PNG figures; at 90 dpi an 11-inch figure is 990 px, inside a 1280 px page
FIGURE_DPI = 90


@dataclass
class Text:
    """A paragraph; ``kind`` is "p", "note" (grey), "callout" (act on it) or "ok" (all is well)."""

    text: str
    kind: str = "p"


@dataclass
class Items:
    """A bulleted list."""

    items: list


@dataclass
class Table:
    """A table with a caption above it; the first ``left`` columns are left-aligned; ``marked`` (one
    flag per row, optional) highlights the rows a reader should look at (class ``flag``).

    Rendered inside a scrolling box so that a wide table never widens the page.
    """

    header: list
    rows: list
    caption: str = ""
    left: int = 1
    marked: list = field(default_factory=list)


@dataclass
class Figure:
    """One PNG figure; ``name`` becomes its file name, ``alt`` its alternative text."""

    name: str
    caption: str
    png: bytes
    alt: str = ""
    number: int = 0
    file: str = ""


@dataclass
class Group:
    """A subsection (one lens, one topic) with an ``<h3>`` and an anchor."""

    title: str
    blocks: list = field(default_factory=list)
    id: str | None = None


@dataclass
class Details:
    """A collapsed block: tables or a preformatted text a reader opens on demand."""

    summary: str
    blocks: list = field(default_factory=list)
    pre: str | None = None


Block = Union[Text, Items, Table, Figure, Group, Details]


def draw(fig, name: str, caption: str, alt: str | None = None) -> Figure:
    """The matplotlib figure ``fig`` as a :class:`Figure` (PNG bytes); the figure is closed.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure, drawn; closed after.
    name : str
        The figure's short name (its file name in the figures folder, without number).
    caption : str
        The caption under it.
    alt : str or None, optional
        Its alternative text; default the name with spaces for underscores.

    Returns
    -------
    Figure
        The figure as PNG bytes, at ``FIGURE_DPI``.
    """
    buf = io.BytesIO()
    # a figure laid out once by ``tight_layout`` keeps a placeholder layout engine, for which savefig draws
    # the whole figure once more before drawing it into the PNG; the placeholder lays nothing out, so it
    # is dropped: the same pixels at about half the cost
    if isinstance(fig.get_layout_engine(), PlaceHolderLayoutEngine):
        fig.set_layout_engine(None)
    try:
        fig.savefig(buf, format="png", dpi=FIGURE_DPI)
    finally:
        plt.close(fig)
    return Figure(name=name, caption=str(caption), png=buf.getvalue(), alt=alt or name.replace("_", " "))
