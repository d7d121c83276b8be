"""HTML from the Jinja2 templates of the package, and the figures as numbered PNG files."""

from __future__ import annotations

import base64
import json
import os
from dataclasses import dataclass
from pathlib import Path

from jinja2 import Environment, PackageLoader, StrictUndefined, select_autoescape

from pipeline.report.content import Details, Figure, Group

__all__ = ["RenderedSection", "number_figures", "render_page", "render_fragment", "write_figures",
           "FIGURE_INDEX", "read_figure_index"]

#: the file beside the PNG figures that names each one's section and caption (read by the workflow's report())
FIGURE_INDEX = "figures.json"


@dataclass
class RenderedSection:
    id: str
    title: str
    intro: str
    blocks: list


def _environment() -> Environment:
    env = Environment(loader=PackageLoader("pipeline.report", "templates"),
                      autoescape=select_autoescape(["html", "j2"], default_for_string=True),
                      undefined=StrictUndefined, trim_blocks=True, lstrip_blocks=True)
    env.filters["b64"] = lambda data: base64.b64encode(data).decode("ascii")
    env.filters["kind"] = lambda b: type(b).__name__
    return env


def _walk(blocks):
    for b in blocks:
        yield b
        if isinstance(b, (Group, Details)):
            yield from _walk(b.blocks)


def number_figures(sections: list[RenderedSection]) -> list[tuple[str, Figure]]:
    """Number the figures in page order (each figure's ``number`` is set).

    Parameters
    ----------
    sections : list[RenderedSection]
        The rendered sections, in page order.

    Returns
    -------
    list[tuple[str, pipeline.report.content.Figure]]
        (category, figure) pairs, the category being the section's number and title as the page shows them.
    """
    out = []
    for i, s in enumerate(sections, start=1):
        for b in _walk(s.blocks):
            if isinstance(b, Figure):
                out.append((f"{i}. {s.title}", b))
                b.number = len(out)
    return out


def write_figures(figures: list[tuple[str, Figure]], folder: Path) -> None:
    """Each figure as ``NN_name.png`` in ``folder``, and :data:`FIGURE_INDEX` with category and caption.

    Files are written to a temporary name and renamed, so a reader never sees half a PNG; PNGs of an
    earlier report in the folder are removed first (their numbering no longer holds).

    Parameters
    ----------
    figures : list[tuple[str, pipeline.report.content.Figure]]
        What :func:`number_figures` returned; each figure's ``file`` is set.
    folder : pathlib.Path
        The figures folder, made if missing.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.png"):
        old.unlink()
    index = {}
    for category, fig in figures:
        fig.file = f"{fig.number:02d}_{fig.name}.png"
        target = folder / fig.file
        tmp = target.with_name(f".{target.name}.tmp")
        tmp.write_bytes(fig.png)
        os.replace(tmp, target)
        index[target.stem] = {"category": category, "number": fig.number, "caption": fig.caption, "alt": fig.alt}
    tmp = folder / f".{FIGURE_INDEX}.tmp"
    tmp.write_text(json.dumps(index, indent=1, ensure_ascii=False), encoding="utf-8")
    os.replace(tmp, folder / FIGURE_INDEX)


def read_figure_index(folder) -> dict:
    """:data:`FIGURE_INDEX` of a figures folder: file stem -> category, number, caption, alt text.

    Parameters
    ----------
    folder : str or pathlib.Path
        A figures folder written by :func:`write_figures`.

    Returns
    -------
    dict
        File stem -> ``category``, ``number``, ``caption`` and ``alt``.

    Raises
    ------
    ValueError
        If the index is missing or not JSON.
    """
    path = Path(folder) / FIGURE_INDEX
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read the report's figure index ({exc})") from exc


def render_page(title: str, sections: list[RenderedSection], written: str, n_figures: int) -> str:
    """The report's whole HTML page from its sections.

    Parameters
    ----------
    title : str
        The page's title.
    sections : list[RenderedSection]
        The rendered sections, figures numbered.
    written : str
        When the report was written (ISO 8601, UTC).
    n_figures : int
        The number of figures.

    Returns
    -------
    str
        The HTML document, self-contained (figures inline).
    """
    return _environment().get_template("report.html.j2").render(title=title, sections=sections, written=written,
                                                               n_figures=n_figures)


def render_fragment(blocks: list) -> str:
    """The HTML of some blocks alone (a section's content without the page around it).

    Parameters
    ----------
    blocks : list
        Blocks of :mod:`pipeline.report.content`.

    Returns
    -------
    str
        Their HTML.
    """
    env = _environment()
    return env.from_string('{% from "blocks.html.j2" import block %}{% for b in blocks %}{{ block(b) }}{% endfor %}'
                           ).render(blocks=blocks)
