"""The report's sections, registered by the module that builds each one.

A section module decorates its builder with :func:`section`;
:func:`pipeline.report.sections.registered_sections` imports every module of :mod:`pipeline.report.sections`
and returns the sections in page order. A new stage adds its section
by adding one module there: no list, no dispatch to edit elsewhere.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

__all__ = ["SectionSpec", "section", "sections_in_order"]


@dataclass(frozen=True)
class SectionSpec:
    """One section: its anchor ``id``, its ``title``, its place on the page and its builder.

    ``build(inputs)`` takes the :class:`pipeline.report.inputs.ReportInputs` and returns the
    section's blocks (:mod:`pipeline.report.content`).
    """

    id: str
    title: str
    order: int
    build: Callable
    intro: str = ""


_REGISTRY: dict[str, SectionSpec] = {}


def section(id: str, title: str, order: int, intro: str = ""):
    """Register the decorated function as the builder of section ``id``.

    Parameters
    ----------
    id : str
        The section's anchor on the page.
    title : str
        Its heading.
    order : int
        Its place on the page (ascending).
    intro : str, optional
        A paragraph under the heading.

    Returns
    -------
    callable
        The decorator: it registers the builder (``build(inputs)`` -> blocks) and returns it unchanged.

    Raises
    ------
    ValueError
        When the decorator is applied, if another module already registered ``id``.
    """
    def register(build: Callable) -> Callable:
        if id in _REGISTRY and _REGISTRY[id].build.__module__ != build.__module__:
            raise ValueError(f"report section {id!r} is registered twice ({_REGISTRY[id].build.__module__}, "
                             f"{build.__module__})")
        _REGISTRY[id] = SectionSpec(id, title, order, build, intro)
        return build
    return register


def sections_in_order() -> list[SectionSpec]:
    """The sections registered so far, in page order (:func:`pipeline.report.sections.registered_sections` imports
    them all first).

    Returns
    -------
    list[SectionSpec]
        The sections, sorted by ``order``.
    """
    return sorted(_REGISTRY.values(), key=lambda s: s.order)
