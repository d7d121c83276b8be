"""Units in the artefacts: the camera's counting units in a UDUNITS-2 file.

The stages state their units in UDUNITS-2 notation plus four symbols that
UDUNITS-2 does not define and a camera scientist needs: ``DN`` (a digital
number, one step of the analogue-to-digital converter), ``electron`` (one
photo-electron), ``photon`` and ``pixel`` (one band pixel: a position, a distance or a
count on the band image). All four are counts: dimensionless. The stages
and every reader of an artefact in memory use that notation (the camera's);
a file on disk, which claims the CF conventions, holds in ``units`` the same
unit spelled for UDUNITS-2, with ``DN``, ``electron`` and ``photon`` written ``count``
(UDUNITS-2's dimensionless count) and ``pixel`` left out (a dimensionless
factor of one), and keeps the camera's spelling in the attribute
``camera_units`` (docs/artefact-units.md):

- ``DN s-1`` in memory is ``count s-1`` on disk, ``camera_units`` ``DN s-1``;
- ``DN/electron`` is ``1``, ``camera_units`` ``DN/electron``;
- ``W sr-1 m-2 nm-1 s DN-1`` is ``W sr-1 m-2 nm-1 s count-1``;
- ``pixel`` is ``1``, ``camera_units`` ``pixel``.

:func:`encode_units` makes the disk form (the artefact writers call it) and
:func:`decode_units` restores the camera's (the artefact readers call it), so
an artefact read back has the units it was written with. A unit without
those symbols is written as it is.
"""

from __future__ import annotations

import re

import xarray as xr

__all__ = ["COUNTING_UNITS", "CAMERA_UNITS_ATTR", "udunits_spelling", "encode_units", "decode_units"]

#: the camera's counting units that UDUNITS-2 lacks, and the UDUNITS-2 symbol each is written with on disk
#: (None: left out, a dimensionless factor of one)
COUNTING_UNITS = {"DN": "count", "electron": "count", "photon": "count", "pixel": None}
#: the attribute that keeps a variable's units in the camera's notation, beside its UDUNITS-2 ``units``
CAMERA_UNITS_ATTR = "camera_units"

_SYMBOLS = re.compile(r"(?<![A-Za-z_])(" + "|".join(COUNTING_UNITS) + r")(?![A-Za-z_])")
#: one factor of a product: a symbol and its optional integer exponent (``s-1``, ``DN2``, ``pixel^2``)
_FACTOR = re.compile(r"([A-Za-z_]+)(?:\^?(-?\d+))?")


def udunits_spelling(units: str) -> str:
    """``units`` in the camera's notation spelled for UDUNITS-2 (the module's docstring).

    A unit without ``DN``, ``electron`` or ``pixel`` comes back as it is. One with them must be a product of
    symbols with integer exponents, optionally over one ``/`` (``DN s-1``, ``W sr-1 m-2 nm-1 s DN-1``,
    ``DN/electron``, ``pixel^2``); the exponents of ``count`` add up, and a product left with no symbol is ``1``.

    Parameters
    ----------
    units : str
        A unit in the camera's notation.

    Returns
    -------
    str
        The same unit in UDUNITS-2 notation.

    Raises
    ------
    ValueError
        Naming a unit of another form that uses the camera's symbols (a programming error of the stage that
        wrote it).
    """
    text = str(units)
    if not _SYMBOLS.search(text):
        return text
    powers: dict[str, int] = {}
    for side, part in enumerate(text.split("/")):
        if side > 1 or not part.strip():
            raise ValueError(f"units {text!r}: not a product of symbols over at most one '/'")
        for factor in part.split():
            match = _FACTOR.fullmatch(factor)
            if match is None:
                raise ValueError(f"units {text!r}: factor {factor!r} is not a symbol with an integer exponent")
            symbol, power = match.group(1), int(match.group(2) or 1) * (-1 if side else 1)
            symbol = COUNTING_UNITS.get(symbol, symbol)
            if symbol is not None:
                powers[symbol] = powers.get(symbol, 0) + power
    factors = [s if p == 1 else f"{s}{p}" for s, p in powers.items() if p != 0]
    return " ".join(factors) or "1"


def encode_units(ds: xr.Dataset) -> xr.Dataset:
    """A shallow copy of ``ds`` whose variables' ``units`` are spelled for UDUNITS-2, the camera's spelling in
    ``camera_units`` where it differs (the form written to disk).

    Parameters
    ----------
    ds : xarray.Dataset
        Variables (data and coordinates) with units in the camera's notation; left unchanged.

    Returns
    -------
    xarray.Dataset
        The copy to write.
    """
    out = ds.copy()   # new variables with copies of their attributes: ``ds`` keeps its own
    for var in out.variables.values():
        units = var.attrs.get("units")
        if isinstance(units, str) and CAMERA_UNITS_ATTR not in var.attrs:
            spelled = udunits_spelling(units)
            if spelled != units:
                var.attrs.update({"units": spelled, CAMERA_UNITS_ATTR: units})
    return out


def decode_units(ds: xr.Dataset) -> xr.Dataset:
    """``ds`` with the camera's spelling of each variable's units back in ``units`` where the file kept it in
    ``camera_units`` (the form the pipeline reads).

    Parameters
    ----------
    ds : xarray.Dataset
        A file as opened; changed in place.

    Returns
    -------
    xarray.Dataset
        ``ds`` itself.
    """
    for var in ds.variables.values():
        if CAMERA_UNITS_ATTR in var.attrs:
            var.attrs["units"] = var.attrs.pop(CAMERA_UNITS_ATTR)
    return ds
