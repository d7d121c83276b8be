"""The benchmark tables of docs/performance.md, rendered from the CSV files of benchmarks/results/.

Each table of the page sits between two markers that name its file, its run and its columns:

    <!-- bench-table: bench_workflow.csv | run=2026-12-04 02:36 9a23994 | stage lens wall_s cpu_s peak_mib -->
    | stage | lens | ... (generated) |
    <!-- end bench-table -->

``run=latest`` shows the newest run of the file. The benchmarks append their rows
(``benchmarks/record.py``); this script writes the tables again from them.

    python scripts/bench_tables.py --write    # render every table of docs/performance.md
    python scripts/bench_tables.py --check    # exit 1 when a table differs from its CSV
"""

from __future__ import annotations

import csv
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DOC = ROOT / "docs" / "performance.md"
BLOCK = re.compile(r"(<!-- bench-table: (?P<file>[\w.-]+) \| run=(?P<run>[^|]*?) \| (?P<columns>[^>]*?) -->\n)"
                   r"(?P<body>.*?)(?P<end><!-- end bench-table -->)", re.S)


def read_rows(name: str) -> list[dict]:
    path = RESULTS / name
    if not path.exists():
        raise SystemExit(f"{path}: no such results file (named by a bench-table marker of {DOC.name})")
    with path.open(newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def table(name: str, run: str, columns: list[str]) -> str:
    """The rows of ``run`` (``latest``: the file's last run) as a Markdown table of ``columns``."""
    rows = read_rows(name)
    if run == "latest" and rows:
        run = rows[-1]["run"]
    chosen = [r for r in rows if r["run"] == run]
    if not chosen:
        raise SystemExit(f"{RESULTS / name}: no rows of run {run!r} (named by a bench-table marker of {DOC.name})")
    unknown = [c for c in columns if c not in chosen[0]]
    if unknown:
        raise SystemExit(f"{RESULTS / name}: no column {', '.join(unknown)} (named by a bench-table marker of {DOC.name})")
    first = chosen[0]
    command = "" if "command" in columns else f": `{first['command']}`"
    lines = [f"*{first['date']}, commit {first['commit'] or 'not recorded'}, {first['machine']}{command}*",
             "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_cell(r, c) for c in columns) + " |" for r in chosen]
    return "\n".join(lines) + "\n"


def _cell(row: dict, column: str) -> str:
    text = row[column].replace("|", "\\|")
    return f"`{text}`" if column == "command" and text else text


def render(text: str) -> str:
    """``text`` with every bench-table block rendered from its CSV."""
    def one(m: re.Match) -> str:
        return m.group(1) + table(m.group("file"), m.group("run").strip(), m.group("columns").split()) + m.group("end")
    return BLOCK.sub(one, text)


def main(argv: list[str]) -> int:
    from generated_page import check_or_write   # beside this script (run as a script, its folder is on the path)

    new = render(DOC.read_text(encoding="utf-8"))
    return check_or_write(argv, DOC, new, "python scripts/bench_tables.py --write", __doc__)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
