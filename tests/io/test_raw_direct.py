"""The direct read of uncompressed DNG against rawpy: bit for bit on every kind of raw file the tests have.

``read_raw`` reads an uncompressed CFA DNG (strips or tiles, 8 to 16 bits a sample) straight from the file's
bytes and every other raw file through rawpy; ``decoder="rawpy"`` forces rawpy. Both must give the same
mosaic, band images, saturation maps, levels, pattern, optically black statistics and tags, exactly (integer
data: no tolerance), on: the simulated camera's frames of every experiment, the smartphone's (12-bit, GRBG,
optically black margins declared by ActiveArea), a light-field bracket, the EMVA1288 frames wrapped as DNG,
the two real-camera DNG files, and DNG layouts written here that the simulator does not write (8, 10, 12 and
14-bit packed samples, big-endian 16-bit, several strips, tiles cut at the image's edges, an even
ActiveArea), and files it leaves to rawpy (a LinearizationTable, strips not in one run, an odd ActiveArea).
"""

from __future__ import annotations

import struct
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.io.bands import split_bands, split_saturation
from pipeline.io.rawio import RawFrame, read_raw
from pipeline.simulate.brackets import render_bracket
from pipeline.simulate.dataset import EXPERIMENTS
from pipeline.simulate.smartphone import simulate_smartphone_dataset
from real_dng import BLACKMAGIC, CANON, needs_real
from realdata import emva1288_descriptor_or_skip

#: RawFrame fields both decoders must give alike (all but the decoder's name)
COMPARED = [f.name for f in fields(RawFrame) if f.name not in ("cfa", "decoder")]


def assert_same_as_rawpy(path: Path, checksums: bool = True) -> str:
    """Read ``path`` both ways, assert every output equal, and return the decoder ``read_raw`` chose."""
    auto = read_raw(path, require=(), checksums=checksums)
    ref = read_raw(path, require=(), checksums=checksums, decoder="rawpy")
    assert ref.decoder == "rawpy"
    assert auto.cfa.dtype == ref.cfa.dtype == np.uint16
    np.testing.assert_array_equal(auto.cfa, ref.cfa, err_msg=str(path))
    for name in COMPARED:
        assert getattr(auto, name) == getattr(ref, name), (path, name)
    bands_auto, bands_ref = split_bands(auto.cfa, auto.cfa_pattern), split_bands(ref.cfa, ref.cfa_pattern)
    sat_auto = split_saturation(auto.cfa, auto.cfa_pattern, auto.white_level - 1)
    sat_ref = split_saturation(ref.cfa, ref.cfa_pattern, ref.white_level - 1)
    for band in "RGB":
        np.testing.assert_array_equal(bands_auto[band], bands_ref[band])
        np.testing.assert_array_equal(sat_auto[band], sat_ref[band])
    return auto.decoder


def test_every_simulated_experiment_reads_directly_as_rawpy(make_dataset):
    """Every frame of every experiment of the tiny simulated camera (16-bit strips, 14-bit values)."""
    root, _ = make_dataset(seed=5, experiments=EXPERIMENTS)
    paths = sorted(root.rglob("*.dng"))
    assert len({p.parent.parent.name for p in paths}) == len(EXPERIMENTS)
    for path in paths:
        assert assert_same_as_rawpy(path) == "direct", path
    # apply's read (memory-mapped, no checksums) gives the same on a sample of them
    for path in paths[::max(1, len(paths) // 8)]:
        assert assert_same_as_rawpy(path, checksums=False) == "direct"


def test_smartphone_frames_read_directly_as_rawpy(tmp_path):
    """The smartphone (one rectilinear region, 12-bit values, GRBG, ActiveArea margins)."""
    root = simulate_smartphone_dataset(tmp_path / "phone", scale="tiny", seed=6, experiments=("dark", "geometry"))
    paths = sorted(root.rglob("*.dng"))
    assert paths
    for path in paths:
        assert assert_same_as_rawpy(path) == "direct"
    frame = read_raw(paths[0], require=())
    assert frame.cfa_pattern == "GRBG" and frame.optical_black_count > 0


def test_bracket_frames_read_directly_as_rawpy(tmp_path):
    render_bracket(tmp_path / "field", seed=3, scale="tiny")
    paths = sorted((tmp_path / "field").rglob("*.dng"))
    assert paths
    for path in paths:
        assert assert_same_as_rawpy(path) == "direct"


def test_emva1288_frames_wrapped_as_dng_read_directly_as_rawpy(tmp_path):
    """The EMVA1288 reference set's 12-bit frames wrapped by init's EMVA1288 folder (skipped when absent)."""
    from pipeline.scaffold import emva1288_raw_folder

    descriptor = emva1288_descriptor_or_skip()
    emva1288_raw_folder(descriptor, tmp_path / "raw", make="Basler", model="EMVA1288 set 001",
                        serial="set001", crop_px=(64, 64))
    paths = sorted((tmp_path / "raw").rglob("*.dng"))
    assert paths
    for path in paths[::max(1, len(paths) // 12)]:
        assert assert_same_as_rawpy(path) == "direct"


@needs_real
def test_real_camera_files_take_the_path_their_compression_decides():
    """The Canon 550D file (Magic Lantern: uncompressed, 14-bit packed strip, ActiveArea) is read directly;
    the Blackmagic file (lossless-JPEG tiles with a LinearizationTable) goes through rawpy. Both give rawpy's
    values, optically black statistics included."""
    assert assert_same_as_rawpy(CANON) == "direct"
    assert assert_same_as_rawpy(CANON, checksums=False) == "direct"
    assert assert_same_as_rawpy(BLACKMAGIC) == "rawpy"
    assert read_raw(CANON, require=()).optical_black_count == 26 * 1888 + (1182 - 26) * 152


# ---------------------------------------------------------------- DNG layouts the simulator does not write

def _pack(values: np.ndarray, bits: int) -> bytes:
    """Rows of samples packed MSB first at ``bits`` bits, each row padded to a whole byte (TIFF's packing)."""
    if bits in (8, 16):
        raise ValueError("whole-byte samples are not packed")
    out = []
    for row in values:
        b = ((row[:, None].astype(np.uint32) >> np.arange(bits - 1, -1, -1, dtype=np.uint32)) & 1).astype(np.uint8)
        out.append(np.packbits(b.ravel()).tobytes())
    return b"".join(out)


def _encode(values: np.ndarray, bits: int, order: str) -> bytes:
    if bits == 16:
        return values.astype(order + "u2").tobytes()
    if bits == 8:
        return values.astype(np.uint8).tobytes()
    return _pack(values, bits)


def write_layout_dng(path: Path, cfa: np.ndarray, *, bits: int, order: str = "<", rows_per_strip=None,
                     tile=None, active_area=None, pattern=(0, 1, 1, 2), black=64, white=None,
                     linearization=None, blocks_reversed=False, gap=0) -> None:
    """A minimal uncompressed CFA DNG 1.4 written field by field: ``bits`` per sample, ``order`` byte order,
    strips of ``rows_per_strip`` rows or ``tile`` (rows, cols) tiles (edge tiles padded), optional ActiveArea
    and LinearizationTable; ``blocks_reversed`` stores the strips or tiles last first and ``gap`` leaves that many
    bytes after each (the offsets still right)."""
    rows, cols = cfa.shape
    blocks = []
    if tile is None:
        rps = rows if rows_per_strip is None else rows_per_strip
        for r in range(0, rows, rps):
            blocks.append(_encode(cfa[r:r + rps], bits, order))
        layout = {"rps": rps}
    else:
        tl, tw = tile
        for r in range(0, rows, tl):
            for c in range(0, cols, tw):
                padded = np.zeros((tl, tw), cfa.dtype)
                part = cfa[r:r + tl, c:c + tw]
                padded[:part.shape[0], :part.shape[1]] = part
                if r + tl > rows:      # the last row of tiles holds only the image's rows (as LibRaw reads them)
                    padded = padded[:rows - r]
                blocks.append(_encode(padded, bits, order))
        layout = {"tile": tile}
    white = (1 << bits) - 1 if white is None else white
    entries = [(254, 4, [0]), (256, 4, [cols]), (257, 4, [rows]), (258, 3, [bits]), (259, 3, [1]),
               (262, 3, [32803]), (277, 3, [1]), (284, 3, [1]),
               (33421, 3, [2, 2]), (33422, 1, list(pattern)), (50706, 1, [1, 4, 0, 0]),
               (50708, 2, b"Layout test\0"), (50710, 1, [0, 1, 2]), (50711, 3, [1]), (50714, 4, [black]),
               (50717, 4, [white])]
    if active_area is not None:
        entries.append((50829, 4, list(active_area)))
    if linearization is not None:
        entries.append((50712, 3, [int(v) for v in linearization]))
    count = len(blocks)
    if tile is None:
        entries += [(273, 4, [0] * count), (278, 4, [layout["rps"]]), (279, 4, [len(b) for b in blocks])]
    else:
        entries += [(322, 4, [tile[1]]), (323, 4, [tile[0]]), (324, 4, [0] * count),
                    (325, 4, [len(b) for b in blocks])]
    entries.sort(key=lambda e: e[0])
    size = {1: 1, 2: 1, 3: 2, 4: 4}
    fmt = {1: "B", 3: "H", 4: "I"}
    ifd_size = 2 + 12 * len(entries) + 4
    extra_at = 8 + ifd_size
    # the data blocks follow the IFD and its out-of-line values (each padded to an even length)
    data_at = extra_at + sum(-(-len(v) * size[t] // 2) * 2 for _, t, v in entries if len(v) * size[t] > 4)
    offsets, at = [0] * len(blocks), data_at
    for k in (reversed(range(len(blocks))) if blocks_reversed else range(len(blocks))):
        offsets[k] = at
        at += len(blocks[k]) + gap
    extra = bytearray()
    ifd = bytearray(struct.pack(order + "H", len(entries)))
    for code, typ, value in entries:
        if code in (273, 324):
            value = offsets
        raw = value if isinstance(value, bytes) else struct.pack(order + fmt[typ] * len(value), *value)
        if len(raw) <= 4:
            ifd += struct.pack(order + "HHI", code, typ, len(value)) + raw.ljust(4, b"\0")
        else:
            ifd += struct.pack(order + "HHII", code, typ, len(value), extra_at + len(extra))
            extra += raw + b"\0" * (len(raw) % 2)
    ifd += struct.pack(order + "I", 0)
    header = (b"II" if order == "<" else b"MM") + struct.pack(order + "HI", 42, 8)
    body = header + bytes(ifd) + bytes(extra)
    assert len(body) == data_at
    body += b"".join(b + b"\0" * gap for b in (blocks[::-1] if blocks_reversed else blocks))
    path.write_bytes(body)


LAYOUTS = {
    "16-bit little-endian, one strip": dict(bits=16),
    "16-bit big-endian, one strip": dict(bits=16, order=">"),
    "16-bit, strips of 7 rows": dict(bits=16, rows_per_strip=7),
    "8-bit": dict(bits=8),
    "10-bit packed": dict(bits=10),
    "12-bit packed, strips of 5 rows": dict(bits=12, rows_per_strip=5),
    "14-bit packed, big-endian": dict(bits=14, order=">"),
    "16-bit tiles, edge tiles cut": dict(bits=16, tile=(16, 16)),
    "12-bit packed tiles": dict(bits=12, tile=(16, 32)),
    "14-bit packed, even ActiveArea, GBRG": dict(bits=14, active_area=(2, 4, 38, 44), pattern=(1, 2, 0, 1)),
}


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_uncompressed_layouts_read_directly_as_rawpy(tmp_path, name):
    """Each layout, with values over the whole range of its bits and odd image sizes (a partial last strip
    and partial edge tiles), reads directly with rawpy's values, and as the values written."""
    kw = LAYOUTS[name]
    bits = kw["bits"]
    cfa = np.random.default_rng(len(name)).integers(0, 1 << bits, (41, 50), dtype=np.uint32).astype(np.uint16)
    cfa[0, :4] = (0, (1 << bits) - 1, 1, 1 << (bits - 1))      # both ends of the range
    path = tmp_path / "layout.dng"
    write_layout_dng(path, cfa, **kw)
    assert assert_same_as_rawpy(path) == "direct"
    assert assert_same_as_rawpy(path, checksums=False) == "direct"
    frame = read_raw(path, require=())
    area = kw.get("active_area")
    expected = cfa if area is None else cfa[area[0]:area[2], area[1]:area[3]]
    np.testing.assert_array_equal(frame.cfa, expected)


def test_unusual_files_go_through_rawpy(tmp_path):
    """What the direct read declines, rawpy reads as before: a LinearizationTable (LibRaw maps the values through
    it); strips with a gap between them (LibRaw reads strips as one run from the first, so its values differ
    from the written ones there, and the direct read, whose contract is rawpy's values, leaves them to it);
    strips stored last first (LibRaw then reads past the file's end: the one-line error as before)."""
    cfa = np.random.default_rng(1).integers(0, 4096, (41, 50), dtype=np.uint16)
    table = (np.arange(4096, dtype=np.int64) * 3 // 2).astype(np.uint16)
    path = tmp_path / "linear.dng"
    write_layout_dng(path, cfa, bits=16, linearization=table, white=6142)
    frame = read_raw(path, require=())
    assert frame.decoder == "rawpy"
    np.testing.assert_array_equal(frame.cfa, table[cfa])
    path = tmp_path / "gap.dng"
    write_layout_dng(path, cfa, bits=12, rows_per_strip=5, gap=1)
    assert assert_same_as_rawpy(path) == "rawpy"
    path = tmp_path / "reversed.dng"
    write_layout_dng(path, cfa, bits=16, rows_per_strip=5, blocks_reversed=True)
    with pytest.raises(InputError, match="unreadable or truncated raw file"):
        read_raw(path, require=())
    write_layout_dng(path, cfa, bits=16, rows_per_strip=5)
    assert read_raw(path, require=()).decoder == "direct"
    with pytest.raises(ValueError):
        read_raw(path, decoder="libraw")
    # an ActiveArea starting on an odd row and column: LibRaw starts the visible mosaic one row and one column
    # further in (33 x 39 here, not 34 x 40) to keep the Bayer phase; rawpy reads it
    path = tmp_path / "odd.dng"
    write_layout_dng(path, cfa, bits=16, active_area=(3, 5, 37, 45))
    assert assert_same_as_rawpy(path) == "rawpy"
    np.testing.assert_array_equal(read_raw(path, require=()).cfa, cfa[4:37, 6:45])
