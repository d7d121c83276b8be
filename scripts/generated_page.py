"""The ``--check`` / ``--write`` ending shared by the scripts that generate part of a docs page."""

from __future__ import annotations

from pathlib import Path


def check_or_write(argv: list[str], doc: Path, new: str, how_to_write: str, usage: str) -> int:
    """``--check``: 1 (saying how to refresh it) when ``doc`` is not ``new``; ``--write``: write ``new`` to
    ``doc``; anything else prints ``usage`` and returns 2."""
    import sys

    if argv == ["--check"]:
        if new != doc.read_text(encoding="utf-8"):
            print(f"{doc} is stale: run {how_to_write}", file=sys.stderr)
            return 1
        return 0
    if argv == ["--write"]:
        doc.write_text(new, encoding="utf-8")
        return 0
    print(usage)
    return 2
