"""Every ``units`` attribute of a NetCDF file, checked with UDUNITS-2 itself (cf-units bundles the C library).

An artefact claims ``Conventions: CF-1.10``, so each of its ``units`` must be a unit UDUNITS-2 parses (not
the unknown unit). Where a variable also keeps the camera's spelling (``camera_units``: UDUNITS-2 with the
dimensionless counts DN, electron, photon and pixel, docs/artefact-units.md), that spelling with each of the four
written as UDUNITS-2's ``count`` must be the same unit as ``units`` (UDUNITS-2 compares them: same
dimension and scale). The substitution here is the documented rule, written independently of
``pipeline.io.units``, whose spelling of the product the check does not read.
"""

from __future__ import annotations

import re
from pathlib import Path

import cf_units
import netCDF4

#: the camera's counting units (docs/artefact-units.md), each a dimensionless count
CAMERA_COUNTS = re.compile(r"(?<![A-Za-z_])(DN|electron|photon|pixel)(?![A-Za-z_])")


def udunits(text: str) -> cf_units.Unit | None:
    """``text`` as a UDUNITS-2 unit, or None where UDUNITS-2 does not parse it (or gives the unknown unit)."""
    try:
        unit = cf_units.Unit(text)
    except ValueError:
        return None
    return None if unit.is_unknown() else unit


def camera_unit(text: str) -> cf_units.Unit | None:
    """A unit in the camera's notation (DN, electron, photon and pixel counted) as a UDUNITS-2 unit, or None."""
    return udunits(CAMERA_COUNTS.sub("count", text))


def units_problems(path: Path) -> list[str]:
    """One line per variable of ``path`` (groups included) whose units do not parse, or whose camera_units
    disagree with them; a file without the CF Conventions attribute is one line too."""
    problems = []
    with netCDF4.Dataset(path) as ds:
        if not str(getattr(ds, "Conventions", "")).startswith("CF-"):
            problems.append(f"{path}: no CF Conventions attribute")
        groups = [ds]
        while groups:
            group = groups.pop()
            groups.extend(group.groups.values())
            for name, var in group.variables.items():
                attrs = {k: var.getncattr(k) for k in var.ncattrs()}
                if "units" not in attrs:
                    continue
                units, camera = str(attrs["units"]), attrs.get("camera_units")
                where = f"{path.parent.name}/{path.name}:{group.path.rstrip('/')}/{name}"
                if udunits(units) is None:
                    problems.append(f"{where}: units {units!r} is not a UDUNITS-2 unit")
                elif camera is not None and camera_unit(str(camera)) != udunits(units):
                    problems.append(f"{where}: camera_units {camera!r} is not the unit {units!r}")
    return problems


def count_units(path: Path) -> int:
    """How many ``units`` attributes ``path`` holds (that a check saw something)."""
    with netCDF4.Dataset(path) as ds:
        return sum("units" in var.ncattrs() for var in ds.variables.values())
