"""The benchmark tables of docs/performance.md, rendered from the CSV files of benchmarks/results/.

Each table of the page sits between two markers that name its file, its run and its columns:

    <!-- bench-table: bench_workflow.csv | run=2026-12-04 02:36 9a23994 | stage lens wall_s cpu_s peak_mib -->
    | stage | lens | ... (generated) |
    <!-- end bench-table -->

``run=latest`` shows the newest run of the file. A context field (date, commit, machine, command) named
among the columns is shown per row instead of above the table. A block

    <!-- bench-index -->
    - `bench_apply.csv`: `2026-12-02 05:00` (7 rows); ... (generated)
    <!-- end bench-index -->

lists, per file, the runs that no table of the page shows, so that every row is either shown or named.
The benchmarks append their rows (``benchmarks/record.py``); this script writes the tables again from them.

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
#: the list of the runs no table shows: every figure of benchmarks/results is either on the page or named here
INDEX = re.compile(r"(<!-- bench-index -->\n)(?P<body>.*?)(?P<end><!-- end bench-index -->)", re.S)


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
    lines = [f"*{_context(chosen[0], columns)}*", "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_cell(r, c) for c in columns) + " |" for r in chosen]
    return "\n".join(lines) + "\n"


def _context(first: dict, columns: list[str]) -> str:
    """The line above a table: the date, commit, machine and command of its run's first row, but those the
    table shows as columns (rows of one run measured at different times or by different commands)."""
    parts = []
    if "date" not in columns:
        parts.append(first["date"] if first["date"] not in ("", "not recorded") else "date not recorded")
    if "commit" not in columns:
        parts.append(f"commit {first['commit'] or 'not recorded'}")
    if "machine" not in columns:
        parts.append(first["machine"])
    text = ", ".join(parts)
    if "command" not in columns:
        text += f": `{first['command']}`" if first["command"] else ": command not recorded"
    return text


def _cell(row: dict, column: str) -> str:
    text = row[column].replace("|", "\\|")
    return f"`{text}`" if column == "command" and text not in ("", "not recorded") else text


def index(shown: set[tuple[str, str]]) -> str:
    """A list, per file of benchmarks/results, of the runs no table of the page shows (``shown``: file, run)."""
    lines = []
    for path in sorted(RESULTS.glob("*.csv")):
        runs = list(dict.fromkeys(r["run"] for r in read_rows(path.name)))
        rest = [r for r in runs if (path.name, r) not in shown and (path.name, "latest") not in shown]
        if rest:
            lines.append(f"- `{path.name}`: " + "; ".join(f"`{r}` ({_count(path.name, r)})" for r in rest))
    return "\n".join(lines) + "\n" if lines else "- none\n"


def _count(name: str, run: str) -> str:
    n = sum(r["run"] == run for r in read_rows(name))
    return f"{n} row" + ("s" if n != 1 else "")


def render(text: str) -> str:
    """``text`` with every bench-table block rendered from its CSV, and the bench-index block listing the
    runs that no table shows."""
    def one(m: re.Match) -> str:
        return m.group(1) + table(m.group("file"), m.group("run").strip(), m.group("columns").split()) + m.group("end")
    text = BLOCK.sub(one, text)
    shown = {(m.group("file"), m.group("run").strip()) for m in BLOCK.finditer(text)}
    return INDEX.sub(lambda m: m.group(1) + index(shown) + m.group("end"), text)


def main(argv: list[str]) -> int:
    from generated_page import check_or_write   # beside this script (run as a script, its folder is on the path)

    new = render(DOC.read_text(encoding="utf-8"))
    return check_or_write(argv, DOC, new, "python scripts/bench_tables.py --write", __doc__)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
