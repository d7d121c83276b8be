"""The summary's plausibility block: each fitted quantity outside its physical range, with the value and the range
(``plausibility.csv`` of the diagnostics, :mod:`pipeline.diagnostics.plausibility`); no section of its own."""

from __future__ import annotations

import numpy as np

from pipeline.diagnostics.plausibility import LABELS, findings, range_text, summary_lines
from pipeline.report.content import Markup, Table, Text
from pipeline.report.formatting import fmt_uncertain

__all__ = ["plausibility_blocks"]


def _text(value) -> str:
    return str(value) if isinstance(value, str) and value and value != "nan" else ""


def plausibility_blocks(inputs) -> list:
    """A callout and a table of the values outside their range (status, value ± standard uncertainty, range,
    how far beyond it, how the value was derived, the range's reason), or one line saying every checked value
    is within its range; nothing when the diagnostics wrote no plausibility table.

    Parameters
    ----------
    inputs : pipeline.report.inputs.ReportInputs
        The report's inputs (its ``plausibility`` table).

    Returns
    -------
    list
        The blocks (:mod:`pipeline.report.content`).
    """
    table = inputs.plausibility
    if table is None or table.empty or "status" not in table:
        return []
    bad = findings(table)
    checked = "; ".join(summary_lines(table))
    if not len(bad):
        return [Text(f"Every fitted quantity with a physical range is within it ({checked}).", "ok")]
    rows = []
    for _, r in bad.iterrows():
        units = "" if _text(r["units"]) in ("", "1") else f" {r['units']}"
        departure = float(r["departure_sigma"])
        rows.append([r["lens"], ", ".join(p for p in (_text(r["band"]), _text(r["at"])) if p),
                     LABELS.get(str(r["quantity"]), str(r["quantity"])), str(r["status"]),
                     fmt_uncertain(r["value"], r["sigma"]) + units,
                     f"{range_text(r['low'], r['high'])} (plausibility.{r['range_key']})",
                     f"{departure:.1f}" if np.isfinite(departure) else "—", _text(r["derivation"])])
    reasons = dict(zip(bad["range_key"].astype(str), bad["reason"].astype(str)))
    return [Text(Markup("<b>{} fitted value(s) outside their physical range</b> ({}): a mistake of the lab or of "
                        "the fit that the residuals cannot show (each fits its own data); the calibration is "
                        "reported as fitted.").format(len(bad), ", ".join(sorted(set(bad["status"].astype(str))))),
                 "callout"),
            Table(["lens", "band / where", "quantity", "verdict", "value", "range", "beyond (σ)", "derived from"],
                  rows, "Fitted quantities outside their physical range (src/pipeline/schema.yaml, plausibility: a value "
                        "beyond the range by more than plausibility.margin_sigma of its stated standard "
                        "uncertainty). Why each range: " + " ".join(f"{key}: {why}" for key, why in reasons.items())
                  + f" Checked: {checked}.", left=4, marked=[True] * len(rows))]
