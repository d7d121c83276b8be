"""The benchmark tables of the docs pages, rendered from the CSV files of benchmarks/results/.

Each table of a page (any ``docs/*.md``) sits between two markers that name its file, its run and its columns:

    <!-- bench-table: bench_workflow.csv | run=2026-12-04 02:36 9a23994 | stage lens wall_s cpu_s peak_mib -->
    | stage | lens | ... (generated) |
    <!-- end bench-table -->

``run=latest`` shows the newest run of the file, ``run=all`` every row of it. A context field (date, commit,
machine, command, run) named among the columns is shown per row instead of above the table, and so is one
that differs between the table's rows. A marker indented under a list item has its table indented as far.
A block

    <!-- bench-index -->
    - `bench_apply.csv`: `2026-12-02 05:00` (7 rows); ... (generated)
    <!-- end bench-index -->

(in docs/performance.md) lists, per file, the runs that no table of any page shows, so that every row is either
shown or named. The benchmarks append their rows (``benchmarks/record.py``); this script writes the tables
again from them.

    python scripts/bench_tables.py --write    # render every table of every docs page
    python scripts/bench_tables.py --check    # exit 1 when a table differs from its CSV
"""

from __future__ import annotations

import csv
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DOCS = ROOT / "docs"
BLOCK = re.compile(r"(?P<indent>^[ ]*)(?P<head><!-- bench-table: (?P<file>[\w.-]+) \| run=(?P<run>[^|]*?) \| "
                   r"(?P<columns>[^>]*?) -->\n)(?P<body>.*?)(?P<end><!-- end bench-table -->)", re.S | re.M)
#: the list of the runs no table shows: every figure of benchmarks/results is either on the page or named here
INDEX = re.compile(r"(<!-- bench-index -->\n)(?P<body>.*?)(?P<end><!-- end bench-index -->)", re.S)


def read_rows(name: str) -> list[dict]:
    """The rows of ``benchmarks/results/<name>``.

    Parameters
    ----------
    name : str
        The file's name, e.g. ``bench_workflow.csv``.

    Returns
    -------
    list of dict
        One dict per row, column name to text.
    """
    path = RESULTS / name
    if not path.exists():
        raise SystemExit(f"{path}: no such results file (named by a bench-table marker of docs/)")
    with path.open(newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def table(name: str, run: str, columns: list[str]) -> str:
    """The rows of one run of a results file as a Markdown table, with its context line above.

    Parameters
    ----------
    name : str
        The results file's name.
    run : str
        The run whose rows to show; ``latest`` the file's last run, ``all`` every row.
    columns : list of str
        The columns to show, in order.

    Returns
    -------
    str
        The context line, a blank line and the table, ending in a newline.
    """
    rows = read_rows(name)
    if run == "latest" and rows:
        run = rows[-1]["run"]
    chosen = rows if run == "all" else [r for r in rows if r["run"] == run]
    if not chosen:
        raise SystemExit(f"{RESULTS / name}: no rows of run {run!r} (named by a bench-table marker of docs/)")
    # a context field that differs between the rows is shown per row, whatever the marker names
    columns = columns + [c for c in ("date", "commit", "machine", "command")
                         if c not in columns and len({r[c] for r in chosen}) > 1]
    unknown = [c for c in columns if c not in chosen[0]]
    if unknown:
        raise SystemExit(f"{RESULTS / name}: no column {', '.join(unknown)} (named by a bench-table marker of docs/)")
    context = _context(chosen[0], columns)      # empty when every context field is a column
    lines = ([f"*{context}*", ""] if context else []) + ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
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
        parts.append(first["machine"] if first["machine"] not in ("", "not recorded") else "machine not recorded")
    text = ", ".join(parts)
    if "command" not in columns:
        text += f": `{first['command']}`" if first["command"] else ": command not recorded"
    return text


def _cell(row: dict, column: str) -> str:
    text = row[column].replace("|", "\\|")
    if column == "commit" and not text:
        return "not recorded"
    return f"`{text}`" if column == "command" and text not in ("", "not recorded") else text


def index(shown: set[tuple[str, str]]) -> str:
    """A list, per file of benchmarks/results, of the runs that no table of the docs shows.

    Parameters
    ----------
    shown : set of (str, str)
        The (file, run) pairs the pages' markers name (run ``latest`` or ``all`` as written).

    Returns
    -------
    str
        One Markdown list item per file with runs not shown (``- none`` when every run is shown).
    """
    lines = []
    for path in sorted(RESULTS.glob("*.csv")):
        runs = list(dict.fromkeys(r["run"] for r in read_rows(path.name)))
        if (path.name, "all") in shown:
            continue
        rest = [r for r in runs if (path.name, r) not in shown and (path.name, "latest") not in shown]
        if rest:
            lines.append(f"- `{path.name}`: " + "; ".join(f"`{r}` ({_count(path.name, r)})" for r in rest))
    return "\n".join(lines) + "\n" if lines else "- none\n"


def _count(name: str, run: str) -> str:
    n = sum(r["run"] == run for r in read_rows(name))
    return f"{n} row" + ("s" if n != 1 else "")


def pages() -> list[Path]:
    """The docs pages with a bench-table or bench-index marker.

    Returns
    -------
    list of Path
        The pages under ``docs/`` (not its build folder), sorted.
    """
    return sorted(p for p in DOCS.rglob("*.md")
                  if "_build" not in p.parts and "<!-- bench-" in p.read_text(encoding="utf-8"))


def shown_runs(texts: list[str]) -> set[tuple[str, str]]:
    """The (file, run) pairs that the bench-table markers of ``texts`` name.

    Parameters
    ----------
    texts : list of str
        Page texts.

    Returns
    -------
    set of (str, str)
        File name and run as the markers write them.
    """
    return {(m.group("file"), m.group("run").strip()) for text in texts for m in BLOCK.finditer(text)}


def render(text: str, shown: set[tuple[str, str]] | None = None) -> str:
    """A page with every bench-table block rendered from its CSV and the bench-index block listing the runs that
    no table shows.

    Parameters
    ----------
    text : str
        The page's text.
    shown : set of (str, str), optional
        The runs the docs show (:func:`shown_runs`); by default those of every page of :func:`pages` and of
        ``text``.

    Returns
    -------
    str
        The page rendered.
    """
    def one(m: re.Match) -> str:
        # a block indented under a list item: its table indented as far
        rendered = table(m.group("file"), m.group("run").strip(), m.group("columns").split())
        body = "".join(m.group("indent") + line if line.strip() else line for line in rendered.splitlines(True))
        return m.group("indent") + m.group("head") + body + m.group("indent") + m.group("end")
    text = BLOCK.sub(one, text)
    if shown is None:
        shown = shown_runs([p.read_text(encoding="utf-8") for p in pages()] + [text])
    return INDEX.sub(lambda m: m.group(1) + index(shown) + m.group("end"), text)


def render_all() -> dict[Path, str]:
    """Every page with markers, rendered.

    Returns
    -------
    dict of Path to str
        Each page of :func:`pages` and its rendered text.
    """
    texts = {p: p.read_text(encoding="utf-8") for p in pages()}
    shown = shown_runs(list(texts.values()))
    return {p: render(t, shown) for p, t in texts.items()}


def main(argv: list[str]) -> int:
    """``--write`` renders every page's tables, ``--check`` returns 1 when one is stale.

    Parameters
    ----------
    argv : list of str
        The command-line arguments.

    Returns
    -------
    int
        The exit status.
    """
    from generated_page import check_or_write   # beside this script (run as a script, its folder is on the path)

    status = 0
    for path, new in render_all().items():
        status = max(status, check_or_write(argv, path, new, "python scripts/bench_tables.py --write", __doc__))
        if status == 2:
            break
    return status


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
