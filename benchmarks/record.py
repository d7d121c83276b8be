"""Benchmark results as data: each ``benchmarks/bench_*.py`` appends its figures to
``benchmarks/results/<bench>.csv``, one row per measured thing, with the date, the commit, the machine and the
command that gave them; the docs pages (``docs/performance.md``, ``docs/effects-and-diagnostics.md`` and
every other page with a ``bench-table`` marker) render their tables from these files (``scripts/bench_tables.py``),
so that no timing is typed by hand. The ``runs_<page>.csv`` files hold the runs a page reported in its prose
before there was a benchmark to append them (a test, a scratch script or a workflow run, as each row's command
says), transcribed with their date where the page gave one; a run's figures go there, or to its benchmark's
file, never into the prose.

A file's columns are the union of its rows' columns: a benchmark that reports a new figure adds a column,
and the older rows leave it empty.
"""

from __future__ import annotations

import csv
import os
import platform
import shlex
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
#: the columns every row starts with
CONTEXT = ("date", "commit", "machine", "command", "run")


def commit() -> str:
    """The checked-out commit (short hash), with ``+changes`` when the work tree differs from it."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=HERE,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+changes" if dirty else "")


def machine() -> str:
    """Cores, memory and CPU of this machine, e.g. ``2 cores, 24 GB, x86_64``."""
    try:
        pages = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        memory = f", {pages / 2**30:.0f} GB"
    except (ValueError, OSError, AttributeError):
        memory = ""
    return f"{os.cpu_count()} cores{memory}, {platform.machine()}"


def command() -> str:
    """The command line that runs this benchmark, as typed from the repository's root."""
    return shlex.join(["python", *[os.path.relpath(a, HERE.parent) if a == sys.argv[0] else a for a in sys.argv]])


def append_rows(bench: str, rows: list[dict], *, run: str = "", results: Path = RESULTS) -> Path:
    """Append ``rows`` (figure name -> value) to ``results/<bench>.csv`` after the context columns.

    ``run`` names the run the rows belong to (default: the date and commit), so that a table of
    the docs can show one run's rows.
    """
    when = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M")
    head = commit()
    context = {"date": when, "commit": head, "machine": machine(), "command": command(), "run": run or f"{when} {head}"}
    new = [{**context, **{k: _text(v) for k, v in row.items()}} for row in rows]
    path = results / f"{bench}.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    old: list[dict] = []
    columns = list(CONTEXT)
    if path.exists():
        with path.open(newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            columns = list(reader.fieldnames or CONTEXT)
            old = list(reader)
    for row in new:
        columns += [k for k in row if k not in columns]
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows(old + new)
    print(f"appended {len(new)} rows to {os.path.relpath(path)}")
    return path


def _text(value) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)
