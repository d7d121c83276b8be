"""Raw frame input and output: DNG pixels from the file's bytes or with rawpy, tags with tifffile.

``read_raw`` reads one raw file into a :class:`RawFrame` (the visible CFA
mosaic, not demosaiced, plus the tags the pipeline needs). An uncompressed CFA
DNG (strips or tiles, 8 to 16 bits a sample) is read straight from the file's
bytes, with the same values as LibRaw's; compressed DNG and every other raw
format go through rawpy.  ``read_tags`` reads
only the tags, for quick validation.  ``write_dng`` writes the minimal DNG 1.4
that the simulator produces and that rawpy/LibRaw can open.

Every bad-input condition raises :class:`pipeline.errors.InputError` with a
one-line message naming the file and the problem.
"""

from __future__ import annotations

import hashlib
import io
import os
from dataclasses import dataclass
from datetime import datetime
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import rawpy
import tifffile

from pipeline.errors import InputError

__all__ = ["RawFrame", "read_raw", "read_tags", "missing_tags", "write_dng", "TAG_NAMES", "tag_problem"]

# TIFF / EXIF / DNG tag codes used here.
_IMAGE_WIDTH, _IMAGE_LENGTH = 256, 257
_MAKE, _MODEL = 271, 272
_STRIP_OFFSETS, _STRIP_COUNTS = 273, 279
_TILE_OFFSETS, _TILE_COUNTS = 324, 325
_PHOTOMETRIC, _NEW_SUBFILE = 262, 254
_CFA_DIM, _CFA_PATTERN = 33421, 33422
_EXPOSURE, _ISO = 33434, 34855
_EXIF_IFD = 34665
_DATETIME_ORIGINAL, _SUBSEC_ORIGINAL = 36867, 37521
_DNG_VERSION, _DNG_BACKWARD, _UNIQUE_MODEL = 50706, 50707, 50708
_CFA_PLANE_COLOR, _CFA_LAYOUT = 50710, 50711
_BLACK_DIM, _BLACK, _WHITE = 50713, 50714, 50717
_COLOR_MATRIX1, _AS_SHOT_NEUTRAL = 50721, 50728
_SERIAL, _ILLUMINANT1 = 50735, 50778
_BODY_SERIAL = 42033
_ACTIVE_AREA, _MASKED_AREAS = 50829, 50830
_BITS, _COMPRESSION, _SAMPLES, _ROWS_PER_STRIP = 258, 259, 277, 278
_FILL_ORDER, _SAMPLE_FORMAT = 266, 339
_TILE_WIDTH, _TILE_LENGTH = 322, 323
_LINEARIZATION, _OPCODE_LIST1 = 50712, 51008

_PHOTOMETRIC_CFA = 32803
_PHOTOMETRIC_LINEAR_RAW = 34892

# RawFrame attribute -> human tag name (used in error messages and missing_tags).
TAG_NAMES = {
    "exposure_s": "ExposureTime",
    "iso": "ISOSpeedRatings",
    "time": "DateTimeOriginal",
    "make": "Make",
    "model": "Model",
    "black_level": "BlackLevel",
    "white_level": "WhiteLevel",
    "cfa_pattern": "CFAPattern",
}
#: what is wrong with a tag the reader could not take (absent, unreadable, or a value no camera writes)
_TAG_PROBLEM = {"exposure_s": "is missing or not a positive number of seconds",
                "iso": "is missing or not a positive number",
                "time": "is missing or not a date and time (YYYY:MM:DD HH:MM:SS)"}


def tag_problem(key: str) -> str:
    """One line: the tag's name and what is wrong with it.

    Parameters
    ----------
    key : str
        A field of :class:`RawFrame` named in :data:`TAG_NAMES`, e.g. ``"exposure_s"``.

    Returns
    -------
    str
        E.g. ``"ExposureTime tag is missing or not a positive number of seconds"``.
    """
    return f"{TAG_NAMES[key]} tag {_TAG_PROBLEM.get(key, 'is missing')}"


# Tags a calibration frame needs, in report order.
_REQUIRED_FOR_REPORT = ("exposure_s", "iso", "time", "make", "model",
                        "black_level", "white_level", "cfa_pattern")

# CFAPlaneColor / CFAPattern colour codes (TIFF/EP).
_COLOUR_LETTERS = {0: "R", 1: "G", 2: "B", 3: "C", 4: "M", 5: "Y", 6: "W"}
_LETTER_CODES = {"R": 0, "G": 1, "B": 2}


@dataclass(frozen=True)
class RawFrame:
    """One raw exposure: the visible CFA mosaic and the tags the pipeline uses."""

    path: Path
    cfa: np.ndarray
    exposure_s: float | None
    iso: float | None
    time: datetime | None
    black_level: float
    white_level: float
    cfa_pattern: str
    make: str | None
    model: str | None
    md5: str
    sha256: str = ""     # sha256 hex of the same bytes (artefact provenance)
    serial: str | None = None   # camera serial number (DNG CameraSerialNumber)
    #: mean raw value (DN) of the optically black pixels the DNG declares (see
    #: :func:`optical_black_rectangles`), None when it declares none
    optical_black_dn: float | None = None
    optical_black_count: int = 0   # number of raw pixels averaged in optical_black_dn
    #: sample variance (DN^2, ddof 1) of those pixels' raw values, None when the DNG declares none
    optical_black_var_dn2: float | None = None
    #: how the mosaic was read: ``"direct"`` (an uncompressed DNG's strips or tiles, from the file's bytes)
    #: or ``"rawpy"`` (LibRaw)
    decoder: str = "rawpy"


# ---------------------------------------------------------------------------
# helpers


def _short_reason(exc: BaseException) -> str:
    """First line of a library exception, trimmed, for a one-line message."""
    text = str(exc).strip()
    if text.startswith(("b'", 'b"')) and text.endswith(("'", '"')):
        text = text[2:-1]
    text = text.splitlines()[0] if text else type(exc).__name__
    if len(text) > 120:
        text = text[:117] + "..."
    return text or type(exc).__name__


def _read_buffer(path: Path, mapped: bool) -> np.ndarray:
    """The file's bytes as a uint8 array: read into one allocation, or memory-mapped (read-only) when ``mapped``."""
    if not path.exists():
        raise InputError(path, "file not found")
    if not path.is_file():
        raise InputError(path, "not a file")
    try:
        if mapped and path.stat().st_size:
            return np.memmap(path, dtype=np.uint8, mode="r").view(np.ndarray)
        with open(path, "rb", buffering=0) as fh:
            buffer = np.empty(os.fstat(fh.fileno()).st_size, np.uint8)
            view, done = memoryview(buffer), 0
            while done < buffer.size:
                got = fh.readinto(view[done:])
                if not got:
                    return buffer[:done]   # the file shrank while it was read
                done += got
            return buffer
    except OSError as exc:
        raise InputError(path, f"cannot read file ({_short_reason(exc)})") from None


class _BufferStream(io.RawIOBase):
    """A read-only binary stream over an array's bytes, without copying them (``io.BytesIO`` copies any
    buffer but a ``bytes`` object); closing it releases the array."""

    def __init__(self, buffer: np.ndarray):
        super().__init__()
        self._view, self._pos = memoryview(buffer).cast("B"), 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: len(self._view)}[whence]
        self._pos = max(base + int(offset), 0)
        return self._pos

    def readinto(self, target) -> int:
        n = max(min(len(target), len(self._view) - self._pos), 0)
        memoryview(target).cast("B")[:n] = self._view[self._pos:self._pos + n]
        self._pos += n
        return n

    def close(self) -> None:
        if not self.closed:
            self._view.release()
        super().close()


def _values(tag: tifffile.TiffTag | None) -> list[float] | None:
    """Numeric tag value as a flat list of floats (rationals divided out)."""
    if tag is None:
        return None
    value = tag.value
    if isinstance(value, (bytes, str)):
        return None
    if isinstance(value, np.ndarray):
        value = value.ravel().tolist()
    if not isinstance(value, (tuple, list)):
        value = [value]
    value = list(value)
    if tag.dtype in (5, 10):  # RATIONAL, SRATIONAL: flattened (num, den) pairs
        if len(value) % 2:
            return None
        out = []
        for num, den in zip(value[0::2], value[1::2]):
            if den == 0:
                return None
            out.append(num / den)
        return out
    try:
        return [float(v) for v in value]
    except (TypeError, ValueError):
        return None


def _positive_number(value: Any) -> float | None:
    """First value of a tag as a positive float, or None (missing, zero, junk)."""
    if value is None:
        return None
    if isinstance(value, tuple) and len(value) == 2 and all(isinstance(v, int) for v in value):
        num, den = value
        value = num / den if den else 0.0
    elif isinstance(value, (tuple, list, np.ndarray)):
        if len(value) == 0:
            return None
        value = value[0]
    try:
        value = float(value)
    except (TypeError, ValueError):
        return None
    if not np.isfinite(value) or value <= 0:
        return None
    return value


def _text(value: Any) -> str | None:
    if value is None:
        return None
    if isinstance(value, bytes):
        value = value.decode("ascii", "replace")
    value = str(value).strip().strip("\x00").strip()
    return value or None


def _parse_time(value: Any, subsec: Any) -> datetime | None:
    text = _text(value)
    if text is None:
        return None
    try:
        stamp = datetime.strptime(text[:19], "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None  # e.g. "0000:00:00 00:00:00" or junk: treated as absent
    digits = _text(subsec)
    if digits is not None:
        digits = "".join(ch for ch in digits if ch.isdigit())
        if digits:
            micro = int(round(int(digits) * 10 ** (6 - len(digits)))) if len(digits) <= 6 \
                else int(round(int(digits[:7]) / 10))
            micro = min(micro, 999_999)
            stamp = stamp.replace(microsecond=micro)
    return stamp


class _TagSource:
    """Tags from the raw IFD, IFD0 and the EXIF sub-IFD, looked up in that order."""

    def __init__(self, tif: tifffile.TiffFile):
        self.ifd0 = tif.pages[0]
        self.raw = self._find_raw_ifd(self.ifd0)
        exif = self.ifd0.tags.get(_EXIF_IFD)
        if exif is None and self.raw is not self.ifd0:
            exif = self.raw.tags.get(_EXIF_IFD)
        self.exif = exif.value if exif is not None and isinstance(exif.value, dict) else {}

    @staticmethod
    def _find_raw_ifd(ifd0):
        def is_raw(page) -> bool:
            photometric = page.tags.get(_PHOTOMETRIC)
            subfile = page.tags.get(_NEW_SUBFILE)
            return (photometric is not None
                    and photometric.value in (_PHOTOMETRIC_CFA, _PHOTOMETRIC_LINEAR_RAW)
                    and (subfile is None or subfile.value == 0))

        if is_raw(ifd0):
            return ifd0
        try:  # camera DNGs often keep the raw image in a SubIFD behind a preview
            for page in tifffile.TiffPages(ifd0):
                if page is not None and is_raw(page):
                    return page
        except Exception:  # noqa: BLE001 - no usable SubIFDs: fall back to IFD0
            pass
        return ifd0

    def tag(self, code: int) -> tifffile.TiffTag | None:
        for page in (self.raw, self.ifd0):
            tag = page.tags.get(code)
            if tag is not None:
                return tag
        return None

    def value(self, code: int) -> Any:
        tag = self.tag(code)
        if tag is not None:
            return tag.value
        name = tifffile.TIFF.TAGS.get(code)
        for key in (name, name.replace("Subsec", "SubSec") if name else None):
            if key and key in self.exif:
                return self.exif[key]
        return None

    def data_end(self) -> int | None:
        """End offset of the raw image data (strips or tiles), if it is known."""
        for off_code, cnt_code in ((_STRIP_OFFSETS, _STRIP_COUNTS), (_TILE_OFFSETS, _TILE_COUNTS)):
            offs, cnts = self.raw.tags.get(off_code), self.raw.tags.get(cnt_code)
            if offs is not None and cnts is not None:
                o = np.atleast_1d(np.asarray(offs.value, dtype=np.int64))
                c = np.atleast_1d(np.asarray(cnts.value, dtype=np.int64))
                if o.size and o.size == c.size:
                    return int((o + c).max())
        return None

    def cfa_pattern(self) -> str | None:
        dim = _values(self.raw.tags.get(_CFA_DIM))
        pattern = self.raw.tags.get(_CFA_PATTERN)
        if pattern is None or (dim is not None and [int(d) for d in dim] != [2, 2]):
            return None
        codes = list(pattern.value) if isinstance(pattern.value, (bytes, tuple, list, np.ndarray)) else []
        if len(codes) != 4:
            return None
        plane = self.raw.tags.get(_CFA_PLANE_COLOR)
        plane_codes = list(plane.value) if plane is not None else [0, 1, 2]
        try:
            letters = [_COLOUR_LETTERS[int(plane_codes[int(c)])] for c in codes]
        except (IndexError, KeyError):
            return None
        # The pattern is given at the origin of the full raw image; rawpy's visible
        # image starts at ActiveArea (top, left): shift the phase when odd.
        area = _values(self.raw.tags.get(_ACTIVE_AREA))
        top, left = (int(area[0]) % 2, int(area[1]) % 2) if area and len(area) == 4 else (0, 0)
        grid = np.array(letters).reshape(2, 2)
        grid = np.roll(grid, (-top, -left), axis=(0, 1))
        return "".join(grid.ravel())

    def rectangles(self, code: int) -> list[tuple[int, int, int, int]]:
        """A DNG rectangle tag (ActiveArea, MaskedAreas) as (top, left, bottom, right) tuples."""
        values = _values(self.raw.tags.get(code))
        if not values or len(values) % 4:
            return []
        out = []
        for k in range(0, len(values), 4):
            top, left, bottom, right = (int(v) for v in values[k:k + 4])
            if bottom > top >= 0 and right > left >= 0:
                out.append((top, left, bottom, right))
        return out

    def visible_shape(self) -> tuple[int, int] | None:
        """(rows, cols) of the raw image inside ActiveArea: the mosaic ``read_raw`` returns."""
        area = _values(self.raw.tags.get(_ACTIVE_AREA))
        if area and len(area) == 4:
            top, left, bottom, right = (int(v) for v in area)
            return (bottom - top, right - left) if bottom > top and right > left else None
        length = _values(self.raw.tags.get(_IMAGE_LENGTH))
        width = _values(self.raw.tags.get(_IMAGE_WIDTH))
        if length and width and length[0] > 0 and width[0] > 0:
            return int(length[0]), int(width[0])
        return None


def _tags_from_tiff(path: Path, tif: tifffile.TiffFile, file_size: int, src: _TagSource | None = None) -> dict:
    src = _TagSource(tif) if src is None else src
    end = src.data_end()
    if end is not None and end > file_size:
        raise InputError(path, f"truncated file: image data ends at byte {end} but the file has {file_size} bytes")
    black = _values(src.tag(_BLACK))
    white = _values(src.tag(_WHITE))
    return {
        "path": path,
        "exposure_s": _positive_number(src.value(_EXPOSURE)),
        "iso": _positive_number(src.value(_ISO)),
        "time": _parse_time(src.value(_DATETIME_ORIGINAL), src.value(_SUBSEC_ORIGINAL)),
        "black_level": float(np.mean(black)) if black else None,
        "white_level": float(max(white)) if white else None,
        "cfa_pattern": src.cfa_pattern(),
        "make": _text(src.value(_MAKE)),
        "model": _text(src.value(_MODEL)),
        "serial": _text(src.value(_SERIAL)) or _text(src.value(_BODY_SERIAL)),
        "shape": src.visible_shape(),
        "active_area": (src.rectangles(_ACTIVE_AREA) or [None])[0],
        "masked_areas": src.rectangles(_MASKED_AREAS),
    }


def _empty_tags(path: Path) -> dict:
    return {"path": path, "exposure_s": None, "iso": None, "time": None, "black_level": None,
            "white_level": None, "cfa_pattern": None, "make": None, "model": None, "serial": None, "shape": None,
            "active_area": None, "masked_areas": []}


@dataclass(frozen=True)
class _Layout:
    """Where an uncompressed CFA image's samples lie in the file: strips (``tile_cols`` None) or tiles."""

    rows: int
    cols: int
    bits: int
    big_endian: bool
    offsets: np.ndarray
    counts: np.ndarray
    block_rows: int                 # rows of one strip (RowsPerStrip) or of one tile (TileLength)
    tile_cols: int | None = None    # TileWidth; None for strips


def _tag_ints(page, code: int) -> list[int] | None:
    tag = page.tags.get(code)
    if tag is None:
        return None
    values = np.atleast_1d(np.asarray(tag.value)).ravel()
    if values.size == 0 or not np.issubdtype(values.dtype, np.integer):
        return None
    return [int(v) for v in values]


def _direct_layout(src: _TagSource, byteorder: str, tags: dict) -> _Layout | None:
    """The raw IFD's layout when it is a plain uncompressed CFA image that :func:`_direct_mosaic` reads with
    LibRaw's values: one 8..16-bit unsigned sample a pixel, MSB-first fill, a 2x2 R, G, G, B pattern, black and
    white levels given, no linearisation table or raw opcodes (LibRaw would change the values); None for
    anything else, which rawpy then reads."""
    page = src.raw
    single = {code: _tag_ints(page, code) for code in (_PHOTOMETRIC, _COMPRESSION, _SAMPLES, _BITS, _FILL_ORDER,
                                                       _SAMPLE_FORMAT, _IMAGE_WIDTH, _IMAGE_LENGTH)}
    if single[_PHOTOMETRIC] != [_PHOTOMETRIC_CFA] or single[_COMPRESSION] not in (None, [1]):
        return None
    if single[_SAMPLES] not in (None, [1]) or single[_FILL_ORDER] not in (None, [1]):
        return None
    if single[_SAMPLE_FORMAT] not in (None, [1]) or single[_BITS] is None or len(set(single[_BITS])) != 1:
        return None
    if _LINEARIZATION in page.tags or _OPCODE_LIST1 in page.tags:
        return None
    if tags["black_level"] is None or tags["white_level"] is None or tags["cfa_pattern"] is None \
            or sorted(tags["cfa_pattern"]) != ["B", "G", "G", "R"]:
        return None
    bits = single[_BITS][0]
    if not 8 <= bits <= 16 or single[_IMAGE_WIDTH] is None or single[_IMAGE_LENGTH] is None:
        return None
    rows, cols = single[_IMAGE_LENGTH][0], single[_IMAGE_WIDTH][0]
    tile_cols, tile_rows = _tag_ints(page, _TILE_WIDTH), _tag_ints(page, _TILE_LENGTH)
    if tile_cols is not None and tile_rows is not None:
        offsets, counts = _tag_ints(page, _TILE_OFFSETS), _tag_ints(page, _TILE_COUNTS)
        block_rows, tile = tile_rows[0], tile_cols[0]
    else:
        offsets, counts = _tag_ints(page, _STRIP_OFFSETS), _tag_ints(page, _STRIP_COUNTS)
        block_rows, tile = min((_tag_ints(page, _ROWS_PER_STRIP) or [rows])[0], rows), None
    if offsets is None or counts is None or len(offsets) != len(counts) or rows <= 0 or cols <= 0 \
            or block_rows <= 0 or (tile is not None and tile <= 0):
        return None
    return _Layout(rows=rows, cols=cols, bits=bits, big_endian=byteorder == ">",
                   offsets=np.asarray(offsets, np.int64), counts=np.asarray(counts, np.int64),
                   block_rows=block_rows, tile_cols=tile)


def _samples(block: np.ndarray, count: int, bits: int, big_endian: bool) -> np.ndarray:
    """The first ``count`` samples of each row of ``block`` (uint8, rows x row bytes), as uint16: a view for
    native-order 16-bit samples, else one decoded copy (8-bit widened; other depths unpacked MSB first, as
    TIFF packs them, each row starting on a byte)."""
    if bits == 16:
        words = block[:, :2 * count].view(">u2" if big_endian else "<u2")
        return words.view(np.uint16) if words.dtype == np.dtype(np.uint16) else words.astype(np.uint16)
    if bits == 8:
        return block[:, :count].astype(np.uint16)
    padded = np.zeros((block.shape[0], block.shape[1] + 2), np.uint8)
    padded[:, :block.shape[1]] = block
    position = np.arange(count, dtype=np.int64) * bits
    first = position >> 3
    word = (padded[:, first].astype(np.uint32) << 16) | (padded[:, first + 1].astype(np.uint32) << 8) \
        | padded[:, first + 2]
    shift = (24 - bits - (position & 7)).astype(np.uint32)
    return ((word >> shift) & np.uint32((1 << bits) - 1)).astype(np.uint16)


def _direct_mosaic(buffer: np.ndarray, lay: _Layout) -> np.ndarray | None:
    """The full raw image (rows x cols, uint16) of an uncompressed layout, from the file's bytes: a view on them
    for native 16-bit samples in strips that follow each other in order (LibRaw reads such strips as one run
    from the first), else one decoded copy; None when the strips are not one ordered run or a strip or tile
    is short (rawpy then decides)."""
    if lay.tile_cols is None:
        row_bytes = (lay.cols * lay.bits + 7) // 8
        start = int(lay.offsets[0])
        firsts = np.arange(lay.offsets.size, dtype=np.int64) * lay.block_rows
        need = np.minimum(lay.block_rows, lay.rows - firsts) * row_bytes
        if firsts[-1] >= lay.rows or lay.rows > firsts[-1] + lay.block_rows \
                or np.any(lay.offsets != start + firsts * row_bytes) or np.any(lay.counts < need) \
                or start + lay.rows * row_bytes > buffer.size:
            return None
        block = buffer[start:start + lay.rows * row_bytes].reshape(lay.rows, row_bytes)
        return _samples(block, lay.cols, lay.bits, lay.big_endian)
    across = -(-lay.cols // lay.tile_cols)
    if lay.offsets.size != across * -(-lay.rows // lay.block_rows):
        return None
    row_bytes = (lay.tile_cols * lay.bits + 7) // 8
    full = np.empty((lay.rows, lay.cols), np.uint16)
    for k, (offset, count) in enumerate(zip(lay.offsets.tolist(), lay.counts.tolist())):
        top, left = (k // across) * lay.block_rows, (k % across) * lay.tile_cols
        height, width = min(lay.block_rows, lay.rows - top), min(lay.tile_cols, lay.cols - left)
        if count < height * row_bytes or offset + height * row_bytes > buffer.size:
            return None
        block = buffer[offset:offset + height * row_bytes].reshape(height, row_bytes)
        full[top:top + height, left:left + width] = _samples(block, lay.tile_cols, lay.bits, lay.big_endian)[:, :width]
    return full


def _visible(full: np.ndarray, tags: dict) -> np.ndarray | None:
    """The ActiveArea of the full raw image (all of it without one), as rawpy's ``raw_image_visible``; None when
    the area does not fit the image or starts on an odd row or column (LibRaw then moves its start to keep
    the Bayer phase: rawpy reads those files)."""
    if tags["active_area"] is None:
        return full
    top, left, bottom, right = tags["active_area"]
    if bottom > full.shape[0] or right > full.shape[1] or top % 2 or left % 2:
        return None
    return full[top:bottom, left:right]


def _rawpy_mosaic(path: Path, buffer: np.ndarray, tags: dict, tiff_problem: str | None):
    """LibRaw's visible mosaic (a copy), the optically black pixels' sums, the pattern and LibRaw's levels."""
    raw_buffer = io.BytesIO(buffer)
    try:
        with rawpy.imread(raw_buffer) as raw:
            cfa = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
            black_sums = _black_sums(raw.raw_image, tags)
            raw_pattern = raw.raw_pattern
            colour_desc = raw.color_desc.decode("ascii", "replace")
            black_per_channel = list(raw.black_level_per_channel)
            white_rawpy = float(raw.white_level)
    except (rawpy.LibRawError, rawpy.NotSupportedError, ValueError, OSError) as exc:
        if tiff_problem:
            raise InputError(path, f"not a readable DNG/TIFF file ({tiff_problem})") from None
        raise InputError(path, f"unreadable or truncated raw file ({_short_reason(exc)})") from None
    finally:
        raw_buffer.close()
    if raw_pattern is None or np.shape(raw_pattern) != (2, 2):
        raise InputError(path, "not a 2x2 Bayer CFA image (rawpy gives no 2x2 raw_pattern)")
    pattern = "".join(colour_desc[int(i)] for i in np.asarray(raw_pattern).ravel())
    return cfa, black_sums, pattern, float(np.mean(black_per_channel)), white_rawpy


def _black_sums(full: np.ndarray, tags: dict) -> tuple[int, float, float]:
    """Count, sum and sum of squares (DN, DN^2) of the optically black pixels of the full raw image."""
    pixels = [full[t:b, left:r] for t, left, b, r in optical_black_rectangles(tags, full.shape)]
    pixels = [p for p in pixels if p.size]
    return (int(sum(p.size for p in pixels)), float(sum(p.sum(dtype=np.float64) for p in pixels)),
            float(sum(np.square(p, dtype=np.float64).sum() for p in pixels)))


def _check_require(path: Path, tags: dict, require) -> None:
    unknown = [name for name in require if name not in TAG_NAMES]
    if unknown:
        raise ValueError(f"unknown required field(s) {unknown}; known: {sorted(TAG_NAMES)}")
    absent = [name for name in require if tags.get(name) is None]
    if absent:
        more = f" (also: {', '.join(TAG_NAMES[name] for name in absent[1:])})" if len(absent) > 1 else ""
        raise InputError(path, f"{tag_problem(absent[0])}{more}")


# ---------------------------------------------------------------------------
# public API


def optical_black_rectangles(tags: dict, full_shape: tuple[int, int]) -> list[tuple[int, int, int, int]]:
    """The optically black (masked) pixels of a raw frame as (top, left, bottom, right) rectangles.

    The DNG's MaskedAreas when it declares them (DNG 1.4 specification: fully masked
    pixels, for measuring the black level). Otherwise, when an ActiveArea is declared,
    the margins of the full raw image above and to the left of it: sensors put their
    masked rows and columns there (the Canon 550D file in the project's real-data folder
    reads about 2050 DN over its 152 left columns against a black level of 2056, where
    the lit image reads 2466); margins below and to the right are often unread and are
    not used. No declaration: no rectangles.

    Parameters
    ----------
    tags : dict
        The frame's tags as :func:`read_tags` gives them (``masked_areas`` and ``active_area`` are used).
    full_shape : tuple[int, int]
        (rows, columns) of the full raw image, masked margins included, in raw pixels.

    Returns
    -------
    list[tuple[int, int, int, int]]
        The rectangles as (top, left, bottom, right) raw pixel indices, bottom and right exclusive; empty when
        the file declares neither.
    """
    if tags.get("masked_areas"):
        return list(tags["masked_areas"])
    area = tags.get("active_area")
    if not area:
        return []
    top, left, bottom, right = area
    out = []
    if top > 0:
        out.append((0, 0, top, full_shape[1]))
    if left > 0:
        out.append((top, 0, full_shape[0], left))
    return out


def read_tags(path) -> dict:
    """Tags of one raw file without decoding pixels.

    Keys: path, exposure_s, iso, time, black_level, white_level, cfa_pattern,
    make, model, serial (CameraSerialNumber or the EXIF BodySerialNumber) and
    shape ((rows, cols) of the visible mosaic), active_area ((top, left, bottom,
    right) or None) and masked_areas (a list of such rectangles, DNG MaskedAreas).
    Absent, empty or zero tags are None.

    Parameters
    ----------
    path : str or pathlib.Path
        The raw (DNG/TIFF) file.

    Returns
    -------
    dict
        The tags by the keys above: ``exposure_s`` in s, ``iso``, ``time`` a :class:`datetime.datetime`,
        ``black_level`` and ``white_level`` in DN, ``cfa_pattern`` e.g. ``"RGGB"``, the rest text or pixel
        indices.

    Raises
    ------
    pipeline.errors.InputError
        If the file is missing or is not a readable DNG/TIFF file.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    if not path.is_file():
        raise InputError(path, "not a file")
    try:
        with tifffile.TiffFile(path) as tif:
            return _tags_from_tiff(path, tif, path.stat().st_size)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - any tifffile failure is a bad file here
        raise InputError(path, f"not a readable DNG/TIFF file ({_short_reason(exc)})") from None


def read_raw(path, require=("exposure_s", "iso", "time"), *, checksums: bool = True,
             decoder: str = "auto", mapped: bool | None = None) -> RawFrame:
    """Read one raw file: visible CFA mosaic (from the file's bytes, or rawpy) and tags (tifffile).

    The file is read once; the MD5 is computed from those bytes and the tags and
    pixels are decoded from the same bytes. An uncompressed CFA DNG in strips or
    tiles (8 to 16 bits a sample, no linearisation table) is read directly: the
    mosaic is a view on the bytes (native-order 16-bit strips) or one decoded
    copy, with the values rawpy's ``raw_image_visible`` gives; anything else goes
    through rawpy. ``require`` lists RawFrame fields that must be present and
    non-zero (see ``TAG_NAMES``). With ``checksums=False`` (a reader that neither
    checks MD5SUMS nor records the frame's sha256, as ``apply``) ``md5`` and
    ``sha256`` are empty and the file is memory-mapped instead of read (unless
    ``mapped`` says otherwise): the two hashes of a 48 MB frame cost more CPU
    than its decode, and a mapped frame is never copied whole.

    Parameters
    ----------
    path : str or pathlib.Path
        The raw file.
    require : sequence of str, default ("exposure_s", "iso", "time")
        The fields whose tags must be present and valid.
    checksums : bool, default True
        Compute the MD5 and sha256 of the file's bytes.
    decoder : {"auto", "rawpy"}, default "auto"
        ``"auto"`` reads an uncompressed CFA DNG directly and the rest with rawpy; ``"rawpy"`` reads every file
        with rawpy.
    mapped : bool or None, optional
        Memory-map the file (read-only) instead of reading it into memory; ``None`` (default) maps it when
        ``checksums`` is False. A mapped frame's mosaic reads the file's pages: the file must not be rewritten
        while the frame is in use.

    Returns
    -------
    RawFrame
        The visible mosaic (uint16, DN, black level not subtracted; possibly a read-only view), its tags, its
        checksums, the mean and variance of its optically black pixels (:func:`optical_black_rectangles`) and
        the decoder used. Where the file lacks BlackLevel or WhiteLevel, LibRaw's values are used.

    Raises
    ------
    pipeline.errors.InputError
        If the file cannot be read or decoded, is not a 2x2 R, G, G, B Bayer image, or lacks a required tag.
    ValueError
        If ``decoder`` is not one of the two names.
    """
    if decoder not in ("auto", "rawpy"):
        raise ValueError(f"decoder must be 'auto' or 'rawpy', not {decoder!r}")
    path = Path(path)
    buffer = _read_buffer(path, mapped=not checksums if mapped is None else bool(mapped))
    md5 = hashlib.md5(buffer).hexdigest() if checksums else ""
    sha256 = hashlib.sha256(buffer).hexdigest() if checksums else ""

    # tifffile's objects form reference cycles that hold its file object; the cycle lives until the
    # garbage collector's next full pass, which comes rarely in a loop that allocates few objects: closing
    # the stream releases the file's bytes at once (each frame's 48 MB piled up otherwise, a peak that grew
    # with the number of frames read)
    tiff_stream, layout = _BufferStream(buffer), None
    try:
        with tifffile.TiffFile(io.BufferedReader(tiff_stream)) as tif:
            src = _TagSource(tif)
            tags = _tags_from_tiff(path, tif, buffer.size, src)
            if decoder == "auto":
                layout = _direct_layout(src, tif.byteorder, tags)
        tiff_problem = None
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - tifffile's errors vary; rawpy decides below
        tags, tiff_problem = _empty_tags(path), _short_reason(exc)
    finally:
        tiff_stream.close()

    full = _direct_mosaic(buffer, layout) if layout is not None else None
    cfa = _visible(full, tags) if full is not None else None
    if cfa is not None:
        black_sums, pattern, used = _black_sums(full, tags), tags["cfa_pattern"], "direct"
        black, white = tags["black_level"], tags["white_level"]
    else:
        cfa, black_sums, pattern, black, white = _rawpy_mosaic(path, buffer, tags, tiff_problem)
        black = tags["black_level"] if tags["black_level"] is not None else black
        white = tags["white_level"] if tags["white_level"] is not None else white
        used = "rawpy"
    del buffer, full
    if sorted(pattern) != ["B", "G", "G", "R"]:
        raise InputError(path, f"unsupported CFA pattern {pattern!r} (need R, G, G, B)")
    if cfa.ndim != 2 or cfa.size == 0:
        raise InputError(path, f"raw image has unexpected shape {cfa.shape}")

    _check_require(path, tags, require)

    black_count, black_sum, black_sumsq = black_sums
    return RawFrame(
        path=path, cfa=cfa, exposure_s=tags["exposure_s"], iso=tags["iso"], time=tags["time"],
        black_level=float(black), white_level=float(white), cfa_pattern=pattern,
        make=tags["make"], model=tags["model"], md5=md5, sha256=sha256, serial=tags.get("serial"),
        optical_black_dn=black_sum / black_count if black_count else None, optical_black_count=black_count,
        optical_black_var_dn2=(max(black_sumsq - black_sum**2 / black_count, 0.0) / (black_count - 1)
                               if black_count > 1 else None),
        decoder=used,
    )


def missing_tags(frame_or_tags) -> list[str]:
    """Human names of the tags a calibration frame needs but this one lacks.

    Parameters
    ----------
    frame_or_tags : RawFrame or dict
        A decoded frame, or the tags of :func:`read_tags`.

    Returns
    -------
    list[str]
        The tag names (:data:`TAG_NAMES`) that are absent, in report order; empty when none is.
    """
    if isinstance(frame_or_tags, RawFrame):
        get = lambda name: getattr(frame_or_tags, name)  # noqa: E731
    else:
        get = frame_or_tags.get
    return [TAG_NAMES[name] for name in _REQUIRED_FOR_REPORT if get(name) is None]


def _rational(value: float, what: str) -> tuple[int, int]:
    if not np.isfinite(value) or value <= 0:
        raise ValueError(f"{what} must be a positive finite number, got {value!r}")
    limit = max(1, min(2**32 - 1, int((2**32 - 1) / max(value, 1.0))))
    frac = Fraction(value).limit_denominator(limit)
    if frac.numerator == 0 or frac.numerator > 2**32 - 1:
        raise ValueError(f"{what} {value!r} cannot be written as a TIFF rational")
    return frac.numerator, frac.denominator


def write_dng(path, cfa: np.ndarray, *, exposure_s: float, iso: float, time: datetime,
              black_level: float, white_level: float = 16383, cfa_pattern: str = "RGGB",
              make: str = "Insta360", model: str = "ONE", serial: str = "SIM-0001",
              active_area: tuple[int, int, int, int] | None = None) -> None:
    """Write a minimal uncompressed 16-bit CFA DNG 1.4 (one IFD), deterministically.

    Parameters
    ----------
    path : str or pathlib.Path
        The file to write.
    cfa : numpy.ndarray
        The 2-D mosaic of raw values in DN, integers within 0..65535 (written as uint16).
    exposure_s : float
        Exposure time in s, > 0 (written as a rational).
    iso : float
        ISO speed, a whole number in 1..65535.
    time : datetime.datetime
        The capture time (DateTimeOriginal, with sub-seconds).
    black_level : float
        The black level in DN, within 0..65535.
    white_level : float, default 16383
        The white (saturation) level in DN, within 1..65535.
    cfa_pattern : str, default "RGGB"
        The 2x2 Bayer cell read row-major, four letters from R, G, B.
    make : str, default "Insta360"
        Camera make, non-empty ASCII.
    model : str, default "ONE"
        Camera model, non-empty ASCII.
    serial : str, default "SIM-0001"
        Camera serial number, non-empty ASCII.
    active_area : tuple[int, int, int, int] or None, optional
        The DNG ActiveArea as (top, left, bottom, right) pixel indices: the pixels outside it are the sensor's
        masked (optically black) margins; ``None`` (default) writes none.

    Raises
    ------
    ValueError
        If a value cannot be written as the DNG requires.
    """
    cfa = np.asarray(cfa)
    if cfa.ndim != 2 or cfa.size == 0:
        raise ValueError(f"cfa must be a non-empty 2-D array, got shape {cfa.shape}")
    if cfa.dtype != np.uint16:
        if not np.issubdtype(cfa.dtype, np.integer):
            raise ValueError(f"cfa must hold integers, got dtype {cfa.dtype}")
        if cfa.min() < 0 or cfa.max() > 65535:
            raise ValueError("cfa values must fit in 16 bits")
        cfa = cfa.astype(np.uint16)
    pattern = cfa_pattern.upper()
    if len(pattern) != 4 or any(ch not in _LETTER_CODES for ch in pattern):
        raise ValueError(f"cfa_pattern must be 4 letters from R, G, B, got {cfa_pattern!r}")
    iso_int = int(round(iso))
    if abs(iso - iso_int) > 1e-9 or not 0 < iso_int <= 65535:
        raise ValueError(f"iso must be a whole number in 1..65535, got {iso!r}")
    if not 0 <= black_level < 65536 or not 0 < white_level <= 65535:
        raise ValueError("black_level and white_level must be within 0..65535")
    for name, text in (("make", make), ("model", model), ("serial", serial)):
        if not text or not str(text).isascii():
            raise ValueError(f"{name} must be a non-empty ASCII string")

    if float(black_level).is_integer():
        black_tag = (_BLACK, "I", 1, int(black_level), True)
    else:
        black_tag = (_BLACK, "2I", 1, _rational(float(black_level), "black_level"), True)
    neutral = (1, 2, 1, 1, 1, 2)  # AsShotNeutral 0.5, 1, 0.5: a plausible white balance
    # sRGB-ish XYZ(D65)->camera matrix, x10000 as signed rationals.
    matrix = (32404, -15371, -4985, -9692, 18760, 416, 556, -2040, 10572)
    matrix_rational = tuple(v for m in matrix for v in (m, 10000))
    stamp = time.strftime("%Y:%m:%d %H:%M:%S")
    camera_model = f"{make} {model}"
    extratags = [
        (_CFA_DIM, "H", 2, (2, 2), True),
        (_CFA_PATTERN, "B", 4, bytes(_LETTER_CODES[ch] for ch in pattern), True),
        (_EXPOSURE, "2I", 1, _rational(float(exposure_s), "exposure_s"), True),
        (_ISO, "H", 1, iso_int, True),
        (_DATETIME_ORIGINAL, "s", 0, stamp, True),
        (_SUBSEC_ORIGINAL, "s", 0, f"{time.microsecond:06d}", True),
        (_DNG_VERSION, "B", 4, bytes((1, 4, 0, 0)), True),
        (_DNG_BACKWARD, "B", 4, bytes((1, 4, 0, 0)), True),
        (_UNIQUE_MODEL, "s", 0, camera_model, True),
        (_CFA_PLANE_COLOR, "B", 3, bytes((0, 1, 2)), True),
        (_CFA_LAYOUT, "H", 1, 1, True),
        (_BLACK_DIM, "H", 2, (1, 1), True),
        black_tag,
        (_WHITE, "I", 1, int(round(white_level)), True),
        (_COLOR_MATRIX1, "2i", 9, matrix_rational, True),
        (_AS_SHOT_NEUTRAL, "2I", 3, neutral, True),
    ]
    if active_area is not None:
        top, left, bottom, right = (int(v) for v in active_area)
        if not (0 <= top < bottom <= cfa.shape[0] and 0 <= left < right <= cfa.shape[1]):
            raise ValueError(f"active_area {active_area!r} does not fit the {cfa.shape} mosaic")
        extratags.append((_ACTIVE_AREA, "I", 4, (top, left, bottom, right), True))
    extratags += [
        (_SERIAL, "s", 0, str(serial), True),
        (_ILLUMINANT1, "H", 1, 21, True),  # D65
        (_MAKE, "s", 0, str(make), True),
        (_MODEL, "s", 0, str(model), True),
    ]
    rows = cfa.shape[0]
    with tifffile.TiffWriter(path, bigtiff=False, byteorder="<") as tw:
        tw.write(
            np.ascontiguousarray(cfa),
            photometric=_PHOTOMETRIC_CFA,
            planarconfig="contig",
            compression=None,
            rowsperstrip=rows,
            subfiletype=0,
            software=False,
            datetime=None,
            description=None,
            metadata=None,
            resolution=None,
            extratags=extratags,
        )
