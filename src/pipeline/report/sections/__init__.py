"""One module per report section; each registers its builder with :func:`pipeline.report.registry.section`."""

from __future__ import annotations

import importlib
import pkgutil

from pipeline.report.registry import SectionSpec, sections_in_order


def registered_sections() -> list[SectionSpec]:
    """Every section of the report, in page order: each module of this package is imported, so it registers.

    Returns
    -------
    list[pipeline.report.registry.SectionSpec]
        The sections, sorted by their order.
    """
    for info in pkgutil.iter_modules(__path__):
        importlib.import_module(f"{__name__}.{info.name}")
    return sections_in_order()
