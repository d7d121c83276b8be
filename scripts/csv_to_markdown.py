"""Render columns of a results CSV (one row per run and band) as a Markdown table for the docs.

    python scripts/csv_to_markdown.py docs/figures-data/field_scale_default.csv band k_b departure_percent z
"""

from __future__ import annotations

import sys

import pandas as pd


def render(path: str, columns: list[str]) -> str:
    table = pd.read_csv(path)[columns]
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for _, row in table.iterrows():
        cells = [f"{v:.4g}" if isinstance(v, float) else str(v) for v in row]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(render(sys.argv[1], sys.argv[2:]))
