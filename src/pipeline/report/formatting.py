"""Formatting of numbers for the report: one value with its uncertainty and units, from a number or an artefact.

One set of helpers for every section: :func:`fmt_value` (significant figures), :func:`fmt_uncertain`
(value rounded to its uncertainty), :func:`units_text` (CF units written with superscripts) and
:func:`quantity` (an artefact variable with its ``_sigma``, its 95 % interval and its units).
"""

from __future__ import annotations

import math
import re

import numpy as np
import xarray as xr

__all__ = ["finite", "fmt_value", "fmt_uncertain", "units_text", "var_units", "quantity", "pct", "bands", "media"]

_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def finite(x) -> bool:
    """Whether ``x`` is a finite number (False for None, text and NaN).

    Parameters
    ----------
    x : object
        Any value.

    Returns
    -------
    bool
        True when ``float(x)`` is finite.
    """
    try:
        return math.isfinite(float(x))
    except (TypeError, ValueError):
        return False


def fmt_value(value, digits: int = 4) -> str:
    """A number with ``digits`` significant figures (plain notation unless very large or small).

    Parameters
    ----------
    value : object
        A number (or None, or anything else, shown as its text).
    digits : int, default 4
        Significant figures.

    Returns
    -------
    str
        The text: ``"—"`` for None, ``"n/a"`` for NaN, an integer as it is, else plain notation, or
        scientific below 1e-3 and from 1e6.
    """
    if value is None:
        return "—"
    try:
        v = float(value)
    except (TypeError, ValueError):
        return str(value)
    if math.isnan(v):
        return "n/a"
    if math.isinf(v):
        return "∞" if v > 0 else "−∞"
    if v == 0:
        return "0"
    if v == int(v) and abs(v) < 1e9 and isinstance(value, (int, np.integer)):
        return str(int(v))
    mag = math.floor(math.log10(abs(v)))
    if mag < -3 or mag >= 6:
        return f"{v:.{digits - 1}e}"
    decimals = max(digits - 1 - mag, 0)
    return f"{v:.{decimals}f}"


def fmt_uncertain(value, sigma, digits: int = 4) -> str:
    """``value ± sigma``, sigma to two significant figures and the value to the same decimal place.

    Falls back to :func:`fmt_value` (``digits`` significant figures) when sigma is missing, zero or
    not finite.

    Parameters
    ----------
    value : object
        The value.
    sigma : object
        Its standard uncertainty, same units.
    digits : int, default 4
        Significant figures of the fallback.

    Returns
    -------
    str
        E.g. ``"1.234 ± 0.012"``, or ``"(1.23 ± 0.12)×10^-5"`` below 1e-3 and from 1e6.
    """
    if not finite(value):
        return fmt_value(value, digits)
    v = float(value)
    if not finite(sigma) or float(sigma) <= 0:
        return fmt_value(v, digits)
    s = float(sigma)
    ref = max(abs(v), s)
    mag = math.floor(math.log10(ref))
    if mag < -3 or mag >= 6:
        scale = 10.0 ** mag
        vs, ss = v / scale, s / scale
        dec = max(1 - math.floor(math.log10(ss)), 0)
        return f"({vs:.{dec}f} ± {ss:.{dec}f})×10^{mag}"
    dec = max(1 - math.floor(math.log10(s)), 0)
    return f"{v:.{dec}f} ± {s:.{dec}f}"


def units_text(units) -> str:
    """CF units as a reader writes them: "W sr-1 m-2" -> "W sr⁻¹ m⁻²", "DN2" -> "DN²", "degree" -> "°".

    A dimensionless "1" and an empty string give "".

    Parameters
    ----------
    units : str or None
        The units as the artefact writes them.

    Returns
    -------
    str
        The units for the page.
    """
    if units is None:
        return ""
    u = str(units).strip()
    if u in ("", "1"):
        return ""
    u = re.sub(r"(?<=[A-Za-z])\^?\(?(-?\d+)\)?(?=$|\s)", lambda m: m.group(1).translate(_SUPERSCRIPT), u)
    u = re.sub(r"\bdn(?=$|\s|[⁻⁰¹²³⁴⁵⁶⁷⁸⁹])", "DN", u)
    return u.replace("degree_C", "°C").replace("degC", "°C").replace("degree", "°")


def _sel(da: xr.DataArray, sel: dict) -> xr.DataArray:
    return da.sel(**{k: v for k, v in sel.items() if k in da.dims})


def quantity(ds: xr.Dataset, name: str, sigma: str | None = None, digits: int = 4, units: bool = True,
             interval: bool = True, **sel) -> str:
    """The artefact variable ``name`` (selected by ``sel``) with its uncertainty, interval and units.

    The uncertainty is ``sigma`` when given, else the first of ``name_sigma`` and
    ``<name without _dn>_sigma_dn`` the artefact holds; ``name_low``/``name_high`` add the 95 %
    interval. "n/a" when the variable is absent or the selection is not one value.

    Parameters
    ----------
    ds : xarray.Dataset
        The artefact.
    name : str
        The variable.
    sigma : str or None, optional
        The variable holding its uncertainty.
    digits : int, default 4
        Significant figures when there is no uncertainty.
    units : bool, default True
        Append the variable's units (:func:`units_text`).
    interval : bool, default True
        Append the 95 % interval when the artefact has it.
    **sel
        Coordinates that select one value (``band="G"``, ``medium="air"``...); a dimension the variable
        lacks is ignored.

    Returns
    -------
    str
        E.g. ``"2056.3 ± 0.2 DN"``.
    """
    if name not in ds:
        return "n/a"
    da = _sel(ds[name], sel)
    if da.size != 1:
        return "n/a"
    sig = None
    candidates = [sigma] if sigma else [f"{name}_sigma", f"{name.removesuffix('_dn')}_sigma_dn"]
    for cand in candidates:
        if cand in ds:
            sd = _sel(ds[cand], sel)
            sig = float(sd) if sd.size == 1 else None
            break
    text = fmt_uncertain(da.values.item(), sig, digits)
    lo, hi = f"{name}_low", f"{name}_high"
    if interval and lo in ds and hi in ds:
        text += f" [95 %: {fmt_value(float(_sel(ds[lo], sel)))}, {fmt_value(float(_sel(ds[hi], sel)))}]"
    if not units:
        return text
    return f"{text} {units_text(ds[name].attrs.get('units', ''))}".strip()


def pct(x, decimals: int = 2) -> str:
    """A fraction as a percentage, "n/a" when not finite.

    Parameters
    ----------
    x : object
        A fraction (0.01 is 1 %).
    decimals : int, default 2
        Decimals of the percentage.

    Returns
    -------
    str
        E.g. ``"1.00 %"``.
    """
    return f"{100 * float(x):.{decimals}f} %" if finite(x) else "n/a"


def bands(ds: xr.Dataset) -> list[str]:
    """The artefact's bands, in its order (empty without a ``band`` coordinate).

    Parameters
    ----------
    ds : xarray.Dataset
        An artefact.

    Returns
    -------
    list[str]
        E.g. ``["R", "G", "B"]``.
    """
    return [str(b) for b in ds["band"].values] if "band" in ds.coords else []


def media(ds: xr.Dataset) -> list[str]:
    """The artefact's media, in its order (empty without a ``medium`` coordinate).

    Parameters
    ----------
    ds : xarray.Dataset
        An artefact.

    Returns
    -------
    list[str]
        E.g. ``["air", "water"]``.
    """
    return [str(m) for m in ds["medium"].values] if "medium" in ds.coords else []


def var_units(ds: xr.Dataset, name: str) -> str:
    """The units of artefact variable ``name`` as :func:`units_text` writes them ("" when absent).

    Parameters
    ----------
    ds : xarray.Dataset
        An artefact.
    name : str
        The variable.

    Returns
    -------
    str
        The units for the page.
    """
    return units_text(ds[name].attrs.get("units", "")) if name in ds else ""


def bias_drift_text(ds: xr.Dataset) -> str:
    """The bias drift, or why it could not be tested (no unlit corners, no optically black pixels).

    Parameters
    ----------
    ds : xarray.Dataset
        A dark or linearity artefact.

    Returns
    -------
    str
        ``bias_drift_dn`` with its uncertainty, interval and units (:func:`quantity`), or the artefact's note on
        why it is not testable.
    """
    if not int(ds.attrs.get("bias_drift_testable", 1)):
        return ds.attrs.get("bias_drift_note", "not testable")
    return quantity(ds, "bias_drift_dn")
