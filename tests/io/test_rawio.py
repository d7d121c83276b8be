"""Tests for pipeline.io.rawio: DNG round trip, tag reading, error messages, real files."""

from __future__ import annotations

import hashlib
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
import rawpy
import tifffile

from pipeline.errors import InputError
from pipeline.io.rawio import RawFrame, missing_tags, read_raw, read_tags, write_dng
from real_dng import BLACKMAGIC, CANON, needs_real, strip_tag

T0 = datetime(2021, 3, 18, 16, 2, 0, 123456)


def _mosaic(rows=64, cols=32, seed=0):
    return np.random.default_rng(seed).integers(0, 16384, (rows, cols), dtype=np.uint16)


def _write(path, cfa=None, **kw):
    args = dict(exposure_s=1 / 250, iso=200, time=T0, black_level=512)
    args.update(kw)
    write_dng(path, _mosaic() if cfa is None else cfa, **args)
    return path


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_round_trip_pixels_pattern_and_tags(tmp_path, pattern):
    cfa = _mosaic(seed=hash(pattern) % 1000)
    path = _write(tmp_path / "a.dng", cfa, cfa_pattern=pattern, exposure_s=1 / 3, iso=800,
                  black_level=2048, white_level=16000)
    frame = read_raw(path)
    assert isinstance(frame, RawFrame)
    assert frame.cfa.dtype == np.uint16 and frame.cfa.shape == cfa.shape
    np.testing.assert_array_equal(frame.cfa, cfa)
    assert frame.cfa_pattern == pattern
    assert frame.black_level == 2048.0 and frame.white_level == 16000.0
    assert frame.exposure_s == 1 / 3
    assert frame.iso == 800.0
    assert frame.time == T0  # sub-seconds kept
    assert (frame.make, frame.model) == ("Insta360", "ONE")
    assert frame.md5 == hashlib.md5(path.read_bytes()).hexdigest()
    assert missing_tags(frame) == []
    # rawpy itself agrees with the file
    with rawpy.imread(str(path)) as raw:
        np.testing.assert_array_equal(raw.raw_image_visible, cfa)
        assert list(raw.black_level_per_channel) == [2048] * 4
    tags = read_tags(path)
    assert tags["cfa_pattern"] == pattern
    assert tags["exposure_s"] == 1 / 3 and tags["iso"] == 800.0 and tags["time"] == T0
    assert set(tags) == {"path", "exposure_s", "iso", "time", "black_level", "white_level",
                         "cfa_pattern", "make", "model", "serial", "shape", "active_area", "masked_areas"}
    assert tags["serial"] == "SIM-0001" and tags["shape"] == cfa.shape
    # no ActiveArea or MaskedAreas written: no optically black pixels
    assert tags["active_area"] is None and tags["masked_areas"] == []
    assert frame.optical_black_dn is None and frame.optical_black_count == 0


def test_without_checksums_the_same_frame_and_no_hashes(tmp_path):
    """apply's read: the same mosaic and tags, md5 and sha256 left empty (the hashes are not taken)."""
    path = _write(tmp_path / "a.dng")
    full, bare = read_raw(path), read_raw(path, checksums=False)
    np.testing.assert_array_equal(bare.cfa, full.cfa)
    assert (bare.exposure_s, bare.iso, bare.time, bare.cfa_pattern, bare.serial) == (
        full.exposure_s, full.iso, full.time, full.cfa_pattern, full.serial)
    assert (bare.md5, bare.sha256) == ("", "")
    assert full.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()


def test_dng_structure(tmp_path):
    path = _write(tmp_path / "a.dng", serial="SN-42")
    with tifffile.TiffFile(path) as tif:
        assert len(tif.pages) == 1
        tags = tif.pages[0].tags
        assert tags["NewSubfileType"].value == 0
        assert tags["PhotometricInterpretation"].value == 32803
        assert tags["Compression"].value == 1
        assert tags["BitsPerSample"].value == 16
        assert bytes(tags["DNGVersion"].value) == bytes((1, 4, 0, 0))
        assert tags["CameraSerialNumber"].value == "SN-42"
        assert tags["SubsecTimeOriginal"].value == "123456"
        assert "Software" not in tags and "DateTime" not in tags


def test_write_is_deterministic(tmp_path):
    a = _write(tmp_path / "a.dng").read_bytes()
    b = _write(tmp_path / "b.dng").read_bytes()
    assert a == b
    c = _write(tmp_path / "c.dng", exposure_s=1 / 125).read_bytes()
    assert a != c


def test_fractional_black_level_and_whole_second_time(tmp_path):
    t = datetime(2020, 1, 2, 3, 4, 5)
    path = _write(tmp_path / "a.dng", black_level=511.5, time=t, exposure_s=2.5)
    frame = read_raw(path)
    assert frame.black_level == 511.5
    assert frame.time == t and frame.exposure_s == 2.5


def test_write_rejects_bad_arguments(tmp_path):
    with pytest.raises(ValueError):
        _write(tmp_path / "a.dng", cfa=np.zeros((4, 4, 3), np.uint16))
    with pytest.raises(ValueError):
        _write(tmp_path / "a.dng", cfa_pattern="RGGX")
    with pytest.raises(ValueError):
        _write(tmp_path / "a.dng", exposure_s=0)
    with pytest.raises(ValueError):
        _write(tmp_path / "a.dng", cfa=np.full((4, 4), 70000, np.int64))


def test_full_size_frame_round_trip(tmp_path):
    """A frame of the real camera's size (both lenses stacked, 6912 x 3456) reads back exactly (the write and
    decode times are measured by the benchmarks, not here)."""
    cfa = _mosaic(6912, 3456, seed=1)
    _write(tmp_path / "big.dng", cfa)
    frame = read_raw(tmp_path / "big.dng")
    np.testing.assert_array_equal(frame.cfa, cfa)


def test_missing_file(tmp_path):
    for fn in (read_raw, read_tags):
        with pytest.raises(InputError) as err:
            fn(tmp_path / "nope.dng")
        assert str(err.value) == f"{tmp_path / 'nope.dng'}: file not found"


def test_truncated_dng(tmp_path):
    data = _write(tmp_path / "a.dng").read_bytes()
    bad = tmp_path / "cut.dng"
    bad.write_bytes(data[: len(data) // 2])
    for fn in (read_raw, read_tags):
        with pytest.raises(InputError) as err:
            fn(bad)
        msg = str(err.value)
        assert msg.startswith(f"{bad}: ") and "truncated" in msg and "\n" not in msg
    tiny = tmp_path / "tiny.dng"
    tiny.write_bytes(data[:60])
    with pytest.raises(InputError) as err:
        read_raw(tiny)
    assert str(err.value).startswith(f"{tiny}: ") and "\n" not in str(err.value)


def test_not_a_dng(tmp_path):
    bad = tmp_path / "notes.dng"
    bad.write_bytes(b"this is a text file, not a raw image\n" * 20)
    for fn in (read_raw, read_tags):
        with pytest.raises(InputError) as err:
            fn(bad)
        msg = str(err.value)
        assert msg.startswith(f"{bad}: ") and "not a readable DNG" in msg and "\n" not in msg


def test_plain_tiff_is_not_a_raw(tmp_path):
    path = tmp_path / "rgb.tif"
    tifffile.imwrite(path, np.zeros((8, 8, 3), np.uint8), photometric="rgb")
    with pytest.raises(InputError) as err:
        read_raw(path, require=())
    assert str(err.value).startswith(f"{path}: ") and "\n" not in str(err.value)


def test_missing_exposure_time(tmp_path):
    path = _write(tmp_path / "a.dng")
    strip_tag(path, 33434)
    with pytest.raises(InputError) as err:
        read_raw(path)
    assert str(err.value) == f"{path}: ExposureTime tag is missing or not a positive number of seconds"
    frame = read_raw(path, require=("iso", "time"))
    assert frame.exposure_s is None
    assert missing_tags(frame) == ["ExposureTime"]
    assert missing_tags(read_tags(path)) == ["ExposureTime"]


def test_tags_in_exif_subifd(tmp_path):
    """Exposure, ISO and time may live in the EXIF sub-IFD instead of IFD0."""
    path = _write(tmp_path / "exif.dng", cfa_pattern="BGGR", black_level=100, time=datetime(2000, 1, 1))
    for number, code in enumerate((33434, 34855, 36867, 37521)):
        strip_tag(path, code, 65000 + number)  # hide the IFD0 copies
    assert read_tags(path)["exposure_s"] is None
    exif = {"ExposureTime": (1, 60), "ISOSpeedRatings": 400,
            "DateTimeOriginal": "2022:05:06 07:08:09", "SubsecTimeOriginal": "25"}
    _append_exif(path, exif)
    tags = read_tags(path)
    assert tags["exposure_s"] == 1 / 60 and tags["iso"] == 400.0
    assert tags["time"] == datetime(2022, 5, 6, 7, 8, 9, 250000)
    assert tags["cfa_pattern"] == "BGGR" and tags["black_level"] == 100.0
    frame = read_raw(path)
    assert frame.cfa_pattern == "BGGR" and frame.exposure_s == 1 / 60
    assert frame.time == datetime(2022, 5, 6, 7, 8, 9, 250000)


def _append_exif(path: Path, exif: dict) -> None:
    """Append an EXIF IFD to a little-endian classic TIFF and point IFD0 at it."""
    import struct

    data = bytearray(path.read_bytes())
    entries = []
    blobs = bytearray()
    base = len(data)
    n = 4
    ifd_size = 2 + 12 * n + 4
    def blob(b: bytes) -> int:
        off = base + ifd_size + len(blobs)
        blobs.extend(b + (b"\0" if len(b) % 2 else b""))
        return off
    num, den = exif["ExposureTime"]
    entries.append(struct.pack("<HHII", 33434, 5, 1, blob(struct.pack("<II", num, den))))
    entries.append(struct.pack("<HHIHH", 34855, 3, 1, exif["ISOSpeedRatings"], 0))
    dto = exif["DateTimeOriginal"].encode() + b"\0"
    entries.append(struct.pack("<HHII", 36867, 2, len(dto), blob(dto)))
    sub = exif["SubsecTimeOriginal"].encode() + b"\0"
    entries.append(struct.pack("<HHI4s", 37521, 2, len(sub), sub.ljust(4, b"\0")))
    exif_ifd = struct.pack("<H", n) + b"".join(entries) + struct.pack("<I", 0)
    data.extend(exif_ifd)
    data.extend(blobs)
    # rewrite IFD0 with one more entry (ExifIFD) at the end of the file
    ifd0 = int.from_bytes(data[4:8], "little")
    count = int.from_bytes(data[ifd0:ifd0 + 2], "little")
    old = [bytes(data[ifd0 + 2 + 12 * i: ifd0 + 14 + 12 * i]) for i in range(count)]
    old.append(struct.pack("<HHII", 34665, 4, 1, base))
    old.sort(key=lambda e: struct.unpack("<H", e[:2])[0])
    new_ifd0 = len(data)
    data.extend(struct.pack("<H", len(old)) + b"".join(old) + struct.pack("<I", 0))
    data[4:8] = struct.pack("<I", new_ifd0)
    path.write_bytes(bytes(data))


@needs_real
def test_real_canon():
    frame = read_raw(CANON, require=())
    assert frame.cfa.shape == (1156, 1734) and frame.cfa.dtype == np.uint16
    assert frame.cfa_pattern == "RGGB"
    assert frame.black_level == 2056.0 and frame.white_level == 15000.0
    assert frame.make == "Canon" and frame.model == "Canon EOS Kiss X4"
    assert frame.exposure_s is None and frame.iso is None and frame.time is None
    assert frame.cfa.max() > frame.black_level  # real pixels, not zeros
    assert missing_tags(frame) == ["ExposureTime", "ISOSpeedRatings", "DateTimeOriginal"]
    tags = read_tags(CANON)
    assert tags["cfa_pattern"] == "RGGB" and tags["black_level"] == 2056.0
    assert tags["shape"] == frame.cfa.shape  # the visible mosaic, from the tags alone
    assert missing_tags(tags) == ["ExposureTime", "ISOSpeedRatings", "DateTimeOriginal"]
    with pytest.raises(InputError) as err:
        read_raw(CANON)
    msg = str(err.value)
    assert msg.startswith(f"{CANON}: ExposureTime tag is missing or not a positive number of seconds") and "\n" not in msg


@needs_real
def test_real_blackmagic():
    frame = read_raw(BLACKMAGIC, require=())
    assert frame.cfa.shape == (2176, 4128) and frame.cfa.dtype == np.uint16
    assert frame.cfa_pattern == "RGGB"
    assert frame.black_level == 512.0 and frame.white_level == 65535.0
    assert frame.make is None and frame.model is None
    tags = read_tags(BLACKMAGIC)
    assert tags["shape"] == frame.cfa.shape and tags["serial"] == "f6845270-68de-40e7-9688-2492e35e94c0"
    assert missing_tags(frame) == ["ExposureTime", "ISOSpeedRatings", "DateTimeOriginal", "Make", "Model"]
    with pytest.raises(InputError) as err:
        read_raw(BLACKMAGIC)
    assert str(err.value).startswith(f"{BLACKMAGIC}: ExposureTime tag is missing or not a positive number of seconds")
    with pytest.raises(InputError) as err:
        read_raw(BLACKMAGIC, require=("make",))
    assert str(err.value) == f"{BLACKMAGIC}: Make tag is missing"


@needs_real
def test_canon_active_area_and_optically_black_pixels():
    """The Canon 550D file declares ActiveArea (26, 152, 1182, 1886) and no MaskedAreas: the margins above
    and left of it are its optically black pixels. Their mean must sit near the BlackLevel tag (2056 DN;
    a masked pixel holds the black level plus read noise, and its mean over 2e5 pixels is read-noise
    limited to well under 1 DN, so the 10 DN tolerance leaves room only for the tag being a nominal
    value), far below the lit image (its mean is hundreds of DN above)."""
    tags = read_tags(CANON)
    assert tags["active_area"] == (26, 152, 1182, 1886)
    assert tags["masked_areas"] == []
    frame = read_raw(CANON, require=())
    # top margin 26 x 1888 plus left margin (1182 - 26) x 152
    assert frame.optical_black_count == 26 * 1888 + (1182 - 26) * 152
    assert abs(frame.optical_black_dn - frame.black_level) < 10
    assert frame.cfa.mean() > frame.optical_black_dn + 300


def test_read_raw_leaves_no_buffer_of_the_file_for_the_garbage_collector(tmp_path):
    """tifffile's objects form reference cycles around the file object they are given; an open
    BytesIO in such a cycle kept each frame's bytes (48 MB at full scale) alive until the collector's
    next full pass, and the peak memory of a stage grew with its frame count. With the collector off,
    no file object read_raw made may still hold the bytes when it returns."""
    import gc
    import io

    path = _write(tmp_path / "f.dng")
    gc.collect()
    before = {id(o) for o in gc.get_objects() if isinstance(o, io.BytesIO)}
    gc.disable()
    try:
        frame = read_raw(path)
        left = [o for o in gc.get_objects()
                if isinstance(o, io.BytesIO) and id(o) not in before and not o.closed]
    finally:
        gc.enable()
    assert frame.cfa.shape == (64, 32)
    assert left == [], f"{len(left)} open BytesIO holding {[len(o.getbuffer()) for o in left]} bytes"
