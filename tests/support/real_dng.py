"""The two real-camera DNG files beside a checkout (skipped when absent) and a tag hider for bad-input tests."""

from __future__ import annotations

from pathlib import Path

import pytest

REAL = (Path(__file__).resolve().parents[2] / ".." / "shared" / "realdata" / "dng").resolve()
CANON = REAL / "canon-eos550d-magiclantern_syoyo-tinydng_colorchart.dng"
BLACKMAGIC = REAL / "blackmagic-pocket4k_imageio-test_images_Blackmagic.dng"
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason="shared/realdata/dng not present")


def strip_tag(path: Path, code: int, new_code: int = 65000) -> None:
    """Rename a tag in place (IFD0) so readers no longer see it."""
    data = bytearray(path.read_bytes())
    ifd = int.from_bytes(data[4:8], "little")
    count = int.from_bytes(data[ifd:ifd + 2], "little")
    for i in range(count):
        entry = ifd + 2 + 12 * i
        if int.from_bytes(data[entry:entry + 2], "little") == code:
            data[entry:entry + 2] = new_code.to_bytes(2, "little")
            break
    else:
        raise AssertionError(f"tag {code} not found")
    path.write_bytes(bytes(data))
