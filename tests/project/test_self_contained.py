"""The repository is self-contained: no tracked file sends a reader to notes outside it.

Only the tests may name the real data's default folder beside the repository (they read it and skip
without); docs and scripts name the folder by ``$PIPELINE_REALDATA``. The dataset format and the design are in docs/.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: what a tracked file must not mention: the team's notes, or anything beside the repository but its real data
FORBIDDEN = re.compile(r"DESIGN\.md|DATASET\.md|\.\./shared/(?!realdata\b)|/work/shared\b")
#: outside tests/ not even the real data's default folder: docs and scripts name it by $PIPELINE_REALDATA
OUTSIDE = re.compile(r"\.\./shared\b")


def _tracked() -> list[Path]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    return [ROOT / name for name in out.decode().split("\0") if name]


def test_no_tracked_file_points_outside_the_repository():
    me = Path(__file__).resolve()
    hits = []
    for path in _tracked():
        if path.resolve() == me or not path.is_file():
            continue
        in_tests = path.relative_to(ROOT).parts[0] == "tests"
        try:
            text = path.read_text(encoding="utf-8")
        except (UnicodeDecodeError, OSError):
            continue
        for number, line in enumerate(text.splitlines(), start=1):
            if FORBIDDEN.search(line) or (not in_tests and OUTSIDE.search(line)):
                hits.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()[:120]}")
    assert not hits, "cite docs/dataset-format.md or docs/design.md instead:\n" + "\n".join(hits)


@pytest.mark.parametrize("line, bad", [
    ("see ../shared/DATASET.md", True), ("(DESIGN.md, catalogue)", True), ("../shared/papers/", True),
    ("/work/shared/DESIGN.md", True), ("../shared/realdata/dng", False), ("docs/dataset-format.md", False),
])
def test_pattern(line, bad):
    assert bool(FORBIDDEN.search(line)) is bad
