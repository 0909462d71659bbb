"""Marker-level JPEG header parser: quantization tables, frame, components, sampling, restart interval.

In the style of Pillow's ``JpegImagePlugin``: it walks the marker segments from SOI to the first SOS and
never decodes pixels. Unlike Pillow it reads only what it needs, segment by segment from the file object,
never past the first SOS segment: APPn payloads (beyond the first 32 bytes, which name them) and other
uninterpreted segments over 1 KiB are skipped by their length (a seek, not a read). A 4000x3000 photo with
a 60 KB EXIF block costs about 700 bytes, and the DQT of an EXIF thumbnail (which lives *inside* APP1) is
never seen.

Rules, stated once:

* Frame types (SOFn): SOF0 baseline, SOF1 extended, SOF2 progressive, SOF3 lossless (Huffman coding) and
  SOF9/10/11 the same three with arithmetic coding are reported. Hierarchical frames (SOF5-7, SOF13-15, DHP,
  EXP), JPEG-LS (SOF55) and the reserved JPG marker are refused with an "unsupported frame type" error.
  Lossless frames use no quantization tables: they get ``quality = None`` and ``manifest_state()`` refuses.
* Tables: every table defined before the first SOS, with the definition in force at SOS (a later DQT with
  the same id replaces an earlier one, as in libjpeg). Values are converted from the file's zigzag order to
  natural row-major 8x8 order, entry ``[v][u]`` (v = vertical frequency). Tables may come after SOF; every
  table a component uses must be defined before the first SOS (tables defined between scans are refused).
* Colour space (libjpeg's ``default_decompress_parms``): 1 component -> gray; 3 components -> YCbCr when a
  JFIF APP0 is present, else per the Adobe APP14 transform (0 -> RGB, otherwise YCbCr), else by component
  ids (1,2,3 -> YCbCr; 'R','G','B' -> RGB; anything else -> YCbCr, libjpeg's assumption); 4 components ->
  CMYK without Adobe APP14 or with transform 0, YCCK otherwise; 2 components -> unknown (named C1, C2).
* Sampling name: gray for one component; 4:4:4 when all components share their factors; otherwise, for
  3 components (or YCCK with K sampled like Y) whose two chroma components agree, the luma/chroma ratio
  (1,1) 4:4:4, (2,1) 4:2:2, (2,2) 4:2:0, (1,2) 4:4:0, (4,1) 4:1:1; everything else is "other".
* Quality: ``estimate_quality`` on the first component's table (luma) and, with two or more components,
  the second component's table (chroma).

Every failure is a ``JsgsError("<name>: <what>")`` on one line; nothing else escapes (see the fuzz test).
"""

from __future__ import annotations

import io
import json
import os
import re
import stat
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, BinaryIO

import numpy as np

from jsgs import __version__
from jsgs.errors import JsgsError
from jsgs.jpeg.tables import QualityEstimate, estimate_quality, ijg_tables, zigzag_to_natural

# SOFn marker code -> (frame type, entropy coding).
SUPPORTED_SOF: dict[int, tuple[str, str]] = {
    0xC0: ("baseline", "huffman"),
    0xC1: ("extended", "huffman"),
    0xC2: ("progressive", "huffman"),
    0xC3: ("lossless", "huffman"),
    0xC9: ("extended", "arithmetic"),
    0xCA: ("progressive", "arithmetic"),
    0xCB: ("lossless", "arithmetic"),
}
UNSUPPORTED_FRAME: dict[int, str] = {
    0xC5: "hierarchical (differential sequential DCT)",
    0xC6: "hierarchical (differential progressive DCT)",
    0xC7: "hierarchical (differential lossless)",
    0xCD: "hierarchical (differential sequential DCT, arithmetic)",
    0xCE: "hierarchical (differential progressive DCT, arithmetic)",
    0xCF: "hierarchical (differential lossless, arithmetic)",
    0xDE: "hierarchical (DHP marker)",
    0xDF: "hierarchical (EXP marker)",
    0xC8: "reserved JPEG extension (JPG marker)",
    0xF7: "JPEG-LS (SOF55)",
}
# Markers without a length field (T.81 B.1.1.3): RSTn and TEM; SOI/EOI are handled on their own.
_STANDALONE = frozenset([0x01, *range(0xD0, 0xD8)])
# Segments skipped by length without interpretation.
_SKIPPED = frozenset(
    [0xC4, 0xCC, 0xDC, 0xFE, 0xF0, 0xF1, 0xF2, 0xF3, 0xF4, 0xF5, 0xF6, 0xF8, 0xF9, 0xFA, 0xFB, 0xFC, 0xFD]
)
_APP_PEEK = 32  # bytes of an APPn payload read to name it (and to parse JFIF/Adobe, which need 14 and 12)
_READ_THROUGH = 1024  # uninterpreted non-APP segments up to this size are read through rather than skipped
_PRINTABLE = re.compile(rb"[\x20-\x7e]*")
_MAX_JUNK = 1024  # non-marker bytes tolerated between segments (libjpeg warns and skips them too)

_NAMES = {
    0xC4: "DHT",
    0xC8: "JPG",
    0xCC: "DAC",
    0xD8: "SOI",
    0xD9: "EOI",
    0xDA: "SOS",
    0xDB: "DQT",
    0xDC: "DNL",
    0xDD: "DRI",
    0xDE: "DHP",
    0xDF: "EXP",
    0xFE: "COM",
    0x01: "TEM",
}

_COMPONENT_NAMES = {
    "gray": ("gray",),
    "YCbCr": ("Y", "Cb", "Cr"),
    "RGB": ("R", "G", "B"),
    "CMYK": ("C", "M", "Y", "K"),
    "YCCK": ("Y", "Cb", "Cr", "K"),
}
_RATIO_NAMES = {(1, 1): "4:4:4", (2, 1): "4:2:2", (2, 2): "4:2:0", (1, 2): "4:4:0", (4, 1): "4:1:1"}
SAMPLING_NAMES = ("4:4:4", "4:2:2", "4:2:0", "4:4:0", "4:1:1", "gray", "other")

TABLE_ORDER_NOTE = (
    "Quantization tables are 8x8 in natural row-major order: values[v][u], v = vertical frequency (row), "
    "u = horizontal frequency (column); the file stores them in zigzag order."
)


def marker_name(code: int) -> str:
    """Human name of marker ``0xFF<code>``: SOF0, DQT, APP1, RST3, ... or ``0xFFxx``."""
    if code in _NAMES:
        return _NAMES[code]
    if 0xC0 <= code <= 0xCF:
        return f"SOF{code - 0xC0}"
    if 0xD0 <= code <= 0xD7:
        return f"RST{code - 0xD0}"
    if 0xE0 <= code <= 0xEF:
        return f"APP{code - 0xE0}"
    if code == 0xF7:
        return "SOF55"
    if 0xF0 <= code <= 0xFD:
        return f"JPG{code - 0xF0}"
    return f"0xFF{code:02X}"


_MARKER_NAMES = [marker_name(c) for c in range(256)]
# Markers that begin a segment with a length field and that the parser accepts before SOS.
_SEGMENT_MARKERS = frozenset([*SUPPORTED_SOF, *_SKIPPED, 0xDA, 0xDB, 0xDD, *range(0xE0, 0xF0)])


# The result classes are plain slotted dataclasses (cheap to build: this is a hot path); treat them as
# read-only. QuantTable is frozen and its array read-only because headers share them through a cache.


@dataclass(frozen=True, slots=True)
class QuantTable:
    """One DQT table: ``values`` is a read-only (8, 8) int64 array in natural row-major order [v, u],
    entries in quantization steps (1..255 for 8-bit tables, 1..65535 for 16-bit ones)."""

    id: int
    precision: int  # bits per entry: 8 (Pq=0) or 16 (Pq=1)
    values: np.ndarray


@dataclass(slots=True)
class Component:
    """One frame component: id byte from SOF, name (Y, Cb, ...), sampling factors, quantization table id
    (None in lossless frames, which use none)."""

    id: int
    name: str
    h: int
    v: int
    table: int | None


@dataclass(slots=True)
class AppSegment:
    """An APPn segment seen (and skipped) in the header: offset of its marker, total length in bytes
    including the marker, and the printable identifier it starts with (Exif, JFIF, ICC_PROFILE, MPF, ...)."""

    marker: str
    offset: int
    length: int
    identifier: str


@dataclass(slots=True)
class JpegHeader:
    """Everything the header says about a JPEG file up to its first scan.

    Sizes are in bytes; ``header_size`` is the offset of the first entropy-coded byte (end of the first SOS
    segment); ``bytes_read`` is how many bytes the parser actually read (skipped segments cost nothing).
    """

    path: str
    file_size: int
    header_size: int
    bytes_read: int
    sof: str  # marker name, e.g. "SOF2"
    frame: str  # baseline | extended | progressive | lossless
    coding: str  # huffman | arithmetic
    sample_precision: int  # bits per sample (8, 12; 2..16 for lossless)
    width: int
    height: int
    color_space: str  # gray | YCbCr | RGB | CMYK | YCCK | unknown
    components: tuple[Component, ...]
    tables: dict[int, QuantTable]
    sampling: str
    restart_interval: int  # MCUs between restart markers; 0 = none
    quality: QualityEstimate | None
    jfif: bool
    adobe_transform: int | None
    app_segments: tuple[AppSegment, ...] = ()
    warnings: tuple[str, ...] = field(default=())

    @property
    def frame_name(self) -> str:
        """``frame`` with ``-arithmetic`` appended for arithmetic coding, e.g. "progressive-arithmetic"."""
        return self.frame if self.coding == "huffman" else f"{self.frame}-arithmetic"

    @property
    def sampling_factors(self) -> str:
        """Per-component HxV factors, e.g. "2x2,1x1,1x1"."""
        return ",".join(f"{c.h}x{c.v}" for c in self.components)

    @property
    def luma_table(self) -> QuantTable | None:
        """Table of the first component (None in lossless frames)."""
        t = self.components[0].table
        return None if t is None else self.tables[t]

    @property
    def chroma_table(self) -> QuantTable | None:
        """Table of the second component (Cb), None for gray and lossless frames."""
        if len(self.components) < 2 or self.components[1].table is None:
            return None
        return self.tables[self.components[1].table]

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict (the per-file object of ``jsgs/schemas/dqt_report.schema.json``)."""
        used: dict[int, list[str]] = {t: [] for t in self.tables}
        for c in self.components:
            if c.table is not None:
                used[c.table].append(c.name)
        q = self.quality
        return {
            "path": self.path,
            "file_size": self.file_size,
            "header_size": self.header_size,
            "bytes_read": self.bytes_read,
            "frame": {
                "marker": self.sof,
                "type": self.frame,
                "coding": self.coding,
                "name": self.frame_name,
                "sample_precision": self.sample_precision,
            },
            "width": self.width,
            "height": self.height,
            "color_space": self.color_space,
            "components": [
                {"id": c.id, "name": c.name, "h": c.h, "v": c.v, "table": c.table} for c in self.components
            ],
            "sampling": self.sampling,
            "sampling_factors": self.sampling_factors,
            "restart_interval": self.restart_interval,
            "tables": [
                {"id": t.id, "precision": t.precision, "used_by": used[t.id], "values": t.values.tolist()}
                for t in self.tables.values()
            ],
            "quality": None
            if q is None
            else {"estimate": q.quality, "exact": q.exact, "mean_abs_error": round(q.error, 4)},
            "jfif": self.jfif,
            "adobe_transform": self.adobe_transform,
            "app_segments": [
                {"marker": a.marker, "offset": a.offset, "length": a.length, "identifier": a.identifier}
                for a in self.app_segments
            ],
            "warnings": list(self.warnings),
        }

    def manifest_state(self) -> dict[str, Any]:
        """The manifest's ``jpeg`` object (jsgs/schemas/manifest.schema.json, ``$defs/jpeg``).

        ``precision`` is 16 when the luma or chroma table is 16-bit. Raises JsgsError for lossless frames.
        """
        luma, chroma = self.luma_table, self.chroma_table
        if luma is None or self.quality is None:
            raise JsgsError(f"{self.path}: {self.frame_name} JPEG ({self.sof}) has no quantization tables")
        precision = max(luma.precision, chroma.precision if chroma is not None else 8)
        return {
            "luma_table": luma.values.tolist(),
            "chroma_table": None if chroma is None else chroma.values.tolist(),
            "sampling": self.sampling,
            "quality": self.quality.quality,
            "quality_exact": self.quality.exact,
            "precision": precision,
            "frame": self.frame_name,
        }


# Exact IJG tables -> quality, so the common case skips ``estimate_quality``'s 100-level search (~70 us, more
# than the rest of the parse). Built in ascending q, so identical tables map to the highest q, which is
# ``estimate_quality``'s tie rule; the test suite checks the two agree.
_EXACT_PAIR: dict[bytes, int] = {}
_EXACT_LUMA: dict[bytes, int] = {}
for _q in range(1, 101):
    _l, _c = ijg_tables(_q)
    _EXACT_PAIR[_l.astype(np.int64).tobytes() + _c.astype(np.int64).tobytes()] = _q
    _EXACT_LUMA[_l.astype(np.int64).tobytes()] = _q
del _q, _l, _c


def quality_of(luma: np.ndarray, chroma: np.ndarray | None) -> QualityEstimate:
    """``estimate_quality(luma, chroma)`` with a dictionary fast path for tables that are exactly IJG's.

    ``luma``/``chroma``: (8, 8) int64 natural-order tables as stored in ``QuantTable.values``.
    """
    key = luma.tobytes() if chroma is None else luma.tobytes() + chroma.tobytes()
    q = (_EXACT_LUMA if chroma is None else _EXACT_PAIR).get(key)
    if q is not None:
        return QualityEstimate(quality=q, exact=True, error=0.0)
    key += b"gray" if chroma is None else b""  # 512 bytes of luma alone never equal 1024 of luma+chroma
    est = _ESTIMATE_CACHE.get(key)
    if est is None:
        est = estimate_quality(luma, chroma)
        if len(_ESTIMATE_CACHE) >= _CACHE_MAX:
            _ESTIMATE_CACHE.clear()
        _ESTIMATE_CACHE[key] = est
    return est


# Decoded tables by their DQT bytes (Pq/Tq byte + entries) and non-IJG quality estimates by table bytes: a
# folder of photos repeats a handful of tables, and decoding/estimating them again costs more than parsing
# the rest of the header. Bounded; ``clear_caches`` empties them (the benchmark's cold-cache column).
_CACHE_MAX = 4096
_TABLE_CACHE: dict[bytes, QuantTable] = {}
_ESTIMATE_CACHE: dict[bytes, QualityEstimate] = {}


def clear_caches() -> None:
    """Forget every cached table and quality estimate."""
    _TABLE_CACHE.clear()
    _ESTIMATE_CACHE.clear()


# --------------------------------------------------------------------------------------------------------
# The parser


class _Reader:
    """Reads a binary file object of known size segment by segment, counting the bytes it takes.

    ``read(n, ahead=k)`` may take up to ``k`` more bytes in the same call (the next marker and length, which
    are header bytes too); they wait in ``pending`` and are served first. ``seek`` skips without reading.
    ``pos`` is the logical position: the offset of the next byte a caller gets.
    """

    __slots__ = ("f", "size", "name", "pos", "nread", "pending")

    def __init__(self, f: BinaryIO, size: int, name: str) -> None:
        self.f = f
        self.size = size
        self.name = name
        self.pos = 0
        self.nread = 0
        self.pending = b""

    def read(self, n: int, ahead: int = 0) -> bytes:
        """Exactly ``n`` bytes; callers check ``pos + n <= size`` first (a short read means the file
        shrank under us). The hot path of the parser, hence the plain arithmetic."""
        p = self.pending
        lp = len(p)
        if n <= lp:
            self.pending = p[n:]
            self.pos += n
            return p[:n]
        end = self.pos + n
        extra = self.size - end
        if extra > ahead:
            extra = ahead
        k = n - lp + extra
        data = self.f.read(k)
        if len(data) != k:
            data = self._read_rest(data, k)
        self.nread += k
        self.pos = end
        if extra > 0:
            self.pending = data[k - extra :]
            data = data[: k - extra]
        else:
            self.pending = b""
        return p + data if lp else data

    def _read_rest(self, data: bytes, k: int) -> bytes:
        while len(data) < k:
            more = self.f.read(k - len(data))
            if not more:
                raise JsgsError(f"{self.name}: file shrank while being read (at offset {self.pos})")
            data += more
        return data

    def seek(self, pos: int) -> None:
        """Move to absolute offset ``pos`` (forward skips within ``pending`` cost nothing)."""
        if self.pos <= pos <= self.pos + len(self.pending):
            self.pending = self.pending[pos - self.pos :]
        else:
            self.f.seek(pos)
            self.pending = b""
        self.pos = pos

    def ends_with_eoi(self) -> bool:
        """Whether the file's last two bytes are EOI (only used to word an error message)."""
        if self.size < 4:
            return False
        self.f.seek(self.size - 2)
        tail = self.f.read(2)
        self.f.seek(self.pos + len(self.pending))
        return tail == b"\xff\xd9"


def _fail(name: str, what: str) -> JsgsError:
    return JsgsError(f"{name}: {what}")


def _not_jpeg(name: str, head: bytes) -> JsgsError:
    kinds = {
        b"\x89PNG": "a PNG image",
        b"GIF8": "a GIF image",
        b"II*\x00": "a TIFF image",
        b"MM\x00*": "a TIFF image",
        b"BM": "a BMP image",
        b"RIFF": "a RIFF (WebP?) file",
        b"\xff\x4f\xff\x51": "a JPEG 2000 codestream",
        b"\x00\x00\x00\x0cjP": "a JPEG 2000 file",
    }
    kind = next((k for magic, k in kinds.items() if head.startswith(magic)), None)
    shown = " ".join(f"{b:02X}" for b in head[:4])
    extra = f" (looks like {kind})" if kind else ""
    return _fail(name, f"not a JPEG file: starts with {shown}{extra}, a JPEG starts with FF D8 (SOI)")


def _next_marker(r: _Reader, warnings: list[str]) -> tuple[int, int]:
    """Find the next marker as libjpeg's ``next_marker`` does (skip junk, fill bytes and stuffed FF00).
    The parser's slow path: used when the pending bytes do not already hold a valid marker and length.

    Returns (marker code, offset of its 0xFF byte). Junk is scanned byte by byte but only up to
    ``_MAX_JUNK`` bytes, so a corrupt length cannot send us through the scan. No byte is read twice.
    """
    start = r.pos
    first = b""
    if start + 2 <= r.size:
        first = r.read(2, ahead=2)  # with the length field behind it, usually already pending
        if first[0] == 0xFF and first[1] not in (0x00, 0xFF):
            return first[1], start
    pos = start  # offset of the next byte to examine

    def take() -> int:
        nonlocal pos
        if pos < start + len(first):
            c = first[pos - start]
        elif r.pos >= r.size:
            raise _fail(r.name, f"truncated file: it ends at offset {r.pos} before the start of scan (SOS)")
        else:
            c = r.read(1)[0]
        pos += 1
        return c

    discarded = 0
    while True:
        c = take()
        if c != 0xFF:
            discarded += 1
            if discarded > _MAX_JUNK:
                raise _fail(
                    r.name,
                    f"no JPEG marker in the {_MAX_JUNK} bytes after offset {start}, where a segment should "
                    "begin (a corrupt segment length?)",
                )
            continue
        ff_at = pos - 1
        c = take()
        while c == 0xFF:  # fill bytes: any number of FF before the marker code
            ff_at = pos - 1
            c = take()
        if c != 0x00:
            if discarded:
                warnings.append(
                    f"{discarded} extraneous bytes before marker {_MARKER_NAMES[c]} at offset {ff_at}"
                )
            return c, ff_at
        discarded += 2  # FF 00 is a stuffed byte, not a marker


def _marker_error(name: str, code: int, at: int) -> JsgsError:
    """The error for a marker that cannot start a header segment here."""
    mname = _MARKER_NAMES[code]
    if code == 0xD8:
        return _fail(name, f"a second start of image (SOI) at offset {at}, before any scan")
    if code == 0xD9:
        return _fail(name, f"end of image (EOI) at offset {at} before any scan: no image data")
    if code in UNSUPPORTED_FRAME:
        return _fail(name, f"unsupported frame type {mname} at offset {at}: {UNSUPPORTED_FRAME[code]}")
    return _fail(name, f"unknown marker {mname} at offset {at}")


def _overrun_error(r: _Reader, code: int, at: int, length: int) -> JsgsError:
    """The error for a segment that does not fit in the file: a truncated file, or (when the file still
    ends with EOI, i.e. is complete) a corrupt length field."""
    mname = _MARKER_NAMES[code]
    left = r.size - r.pos
    if r.ends_with_eoi():
        return _fail(
            r.name,
            f"the {mname} segment at offset {at} declares length {length}, which runs past the end "
            f"of the file ({left} bytes left)",
        )
    return _fail(
        r.name,
        f"truncated file: it ends inside the {mname} segment at offset {at} (the segment needs "
        f"{length - 2} bytes, {left} are left)",
    )


def _parse(r: _Reader) -> JpegHeader:
    name, size = r.name, r.size
    if size == 0:
        raise _fail(name, "empty file (0 bytes)")
    if size < 2:
        raise _not_jpeg(name, r.read(size))
    head = r.read(2, ahead=4)
    if head != b"\xff\xd8":
        raise _not_jpeg(name, head + r.read(min(size - 2, 10)))

    warnings: list[str] = []
    tables: dict[int, QuantTable] = {}
    apps: list[AppSegment] = []
    sof: tuple[int, int, bytes] | None = None  # (marker code, offset, payload)
    restart_interval = 0
    jfif = False
    adobe_transform: int | None = None

    while True:
        # Marker and length: normally both are already pending from the previous read's look-ahead.
        p = r.pending
        if len(p) >= 4 and p[0] == 0xFF and p[1] in _SEGMENT_MARKERS:
            code, at, length = p[1], r.pos, (p[2] << 8) | p[3]
            r.pending = p[4:]
            r.pos = at + 4
        else:
            code, at = _next_marker(r, warnings)
            if code in _STANDALONE:
                continue
            if code not in _SEGMENT_MARKERS:
                raise _marker_error(name, code, at)
            if r.pos + 2 > size:
                raise _fail(
                    name,
                    f"truncated file: it ends inside the length field of the {_MARKER_NAMES[code]} segment "
                    f"at offset {at}",
                )
            b = r.read(2)
            length = (b[0] << 8) | b[1]
        if length < 2:
            raise _fail(
                name,
                f"the {_MARKER_NAMES[code]} segment at offset {at} has an invalid length {length} "
                "(minimum 2)",
            )
        n = length - 2
        if r.pos + n > size:
            raise _overrun_error(r, code, at, length)

        if code == 0xC4 and n <= _READ_THROUGH:  # DHT, the most frequent segment: header bytes anyway,
            r.read(n, ahead=4)  # and one read beats a seek plus a read
        elif code == 0xDB:
            _read_dqt(name, at, r.read(n, ahead=4), tables, warnings)
        elif code == 0xDA:
            payload = r.read(n)
            if sof is None:
                raise _fail(name, f"start of scan (SOS) at offset {at} before any frame header (SOF)")
            return _finish(
                r, sof, payload, at, tables, apps, restart_interval, jfif, adobe_transform, warnings
            )
        elif code in SUPPORTED_SOF:
            if sof is not None:
                raise _fail(name, f"a second frame header ({_MARKER_NAMES[code]}) at offset {at}")
            sof = (code, at, r.read(n, ahead=4))
        elif 0xE0 <= code <= 0xEF:
            peek = r.read(min(n, _APP_PEEK), ahead=4 if n <= _APP_PEEK else 0)
            apps.append(AppSegment(_MARKER_NAMES[code], at, length + 2, _identifier(peek)))
            # libjpeg's examine_app0/app14: JFIF needs 14 data bytes, Adobe 12.
            if code == 0xE0 and n >= 14 and peek.startswith(b"JFIF\x00"):
                jfif = True
            elif code == 0xEE and n >= 12 and peek.startswith(b"Adobe"):
                adobe_transform = peek[11]
            if n > len(peek):
                r.seek(r.pos + n - len(peek))
        elif code == 0xDD:
            if n != 2:
                raise _fail(name, f"the DRI segment at offset {at} has length {length} (must be 4)")
            b = r.read(2, ahead=4)
            restart_interval = (b[0] << 8) | b[1]
        else:
            if 0xF0 <= code <= 0xFD:
                warnings.append(f"skipped extension marker {_MARKER_NAMES[code]} at offset {at}")
            if n <= _READ_THROUGH:
                r.read(n, ahead=4)
            else:
                r.seek(r.pos + n)


def _identifier(peek: bytes) -> str:
    """The printable ASCII prefix of an APPn payload: "JFIF", "Exif", "ICC_PROFILE", "MPF", ..."""
    m = _PRINTABLE.match(peek)
    return m.group().decode("ascii") if m else ""


def _read_dqt(name: str, at: int, p: bytes, tables: dict[int, QuantTable], warnings: list[str]) -> None:
    off = 0
    while off < len(p):
        pq, tq = p[off] >> 4, p[off] & 15
        if pq > 1:
            raise _fail(
                name, f"the DQT segment at offset {at} has table precision code {pq} (must be 0 or 1)"
            )
        if tq > 3:
            raise _fail(name, f"the DQT segment at offset {at} defines table id {tq} (must be 0..3)")
        need = 1 + 64 * (pq + 1)
        if off + need > len(p):
            raise _fail(
                name,
                f"the DQT segment at offset {at} is shorter than its table {tq} ({len(p) - off} of {need} "
                "bytes; segment length inconsistent with its content)",
            )
        raw = p[off : off + need]
        table = _TABLE_CACHE.get(raw)
        if table is None:
            zz = np.frombuffer(raw, dtype=">u2" if pq else np.uint8, count=64, offset=1)
            if (not zz.all()) if pq else (0 in raw[1:]):
                raise _fail(
                    name, f"quantization table {tq} (DQT at offset {at}) has a zero entry (must be >= 1)"
                )
            values = zigzag_to_natural(zz)
            values.flags.writeable = False  # shared by every header with the same table bytes
            table = QuantTable(tq, 16 if pq else 8, values)
            if len(_TABLE_CACHE) >= _CACHE_MAX:
                _TABLE_CACHE.clear()
            _TABLE_CACHE[raw] = table
        if tq in tables:
            warnings.append(f"quantization table {tq} redefined at offset {at}")
        tables[tq] = table
        off += need


def _color_space(ids: Sequence[int], jfif: bool, adobe_transform: int | None) -> str:
    n = len(ids)
    if n == 1:
        return "gray"
    if n == 3:
        if jfif:
            return "YCbCr"
        if adobe_transform is not None:
            return "RGB" if adobe_transform == 0 else "YCbCr"
        if tuple(ids) == (82, 71, 66):  # 'R', 'G', 'B'
            return "RGB"
        return "YCbCr"
    if n == 4:
        return "CMYK" if adobe_transform in (None, 0) else "YCCK"
    return "unknown"


def sampling_name(factors: Sequence[tuple[int, int]], color_space: str) -> str:
    """Name of a component sampling layout given per-component (h, v) factors (see module docstring)."""
    if len(factors) == 1:
        return "gray"
    if all(f == factors[0] for f in factors):
        return "4:4:4"
    n = len(factors)
    if n == 3 or (n == 4 and color_space == "YCCK" and factors[3] == factors[0]):
        (h, v), (ch, cv), cr = factors[0], factors[1], factors[2]
        if cr != (ch, cv) or h % ch or v % cv:
            return "other"
        return _RATIO_NAMES.get((h // ch, v // cv), "other")
    return "other"


def _finish(
    r: _Reader,
    sof: tuple[int, int, bytes],
    sos: bytes,
    sos_at: int,
    tables: dict[int, QuantTable],
    apps: list[AppSegment],
    restart_interval: int,
    jfif: bool,
    adobe_transform: int | None,
    warnings: list[str],
) -> JpegHeader:
    name = r.name
    code, at, p = sof
    mname = _MARKER_NAMES[code]
    frame, coding = SUPPORTED_SOF[code]
    lossless = frame == "lossless"
    if len(p) < 6:
        raise _fail(name, f"the {mname} segment at offset {at} is too short ({len(p) + 2} bytes, minimum 8)")
    precision, height, width, nf = p[0], (p[1] << 8) | p[2], (p[3] << 8) | p[4], p[5]
    if len(p) != 6 + 3 * nf:
        raise _fail(
            name,
            f"the {mname} segment at offset {at} has length {len(p) + 2}, but its {nf} components need "
            f"{8 + 3 * nf}",
        )
    if not 1 <= nf <= 4:
        raise _fail(name, f"the frame header ({mname}) declares {nf} components (supported: 1 to 4)")
    allowed = range(2, 17) if lossless else ((8,) if frame == "baseline" else (8, 12))
    if precision not in allowed:
        raise _fail(name, f"{precision}-bit samples are not valid in a {frame} frame ({mname})")
    if width == 0:
        raise _fail(name, f"the frame header ({mname}) declares width 0")
    if height == 0:
        raise _fail(
            name, f"the frame header ({mname}) declares height 0 (height set by a DNL marker: not supported)"
        )

    ids = list(p[6::3])
    if len(set(ids)) != nf:
        raise _fail(name, f"the frame header ({mname}) repeats a component id: {ids}")
    color_space = _color_space(ids, jfif, adobe_transform)
    names = _COMPONENT_NAMES.get(color_space) or tuple(f"C{i + 1}" for i in range(nf))
    components: list[Component] = []
    for i in range(nf):
        cid, hv, tq = p[6 + 3 * i], p[7 + 3 * i], p[8 + 3 * i]
        h, v = hv >> 4, hv & 15
        if not (1 <= h <= 4 and 1 <= v <= 4):
            raise _fail(name, f"component {names[i]} has invalid sampling factors {h}x{v} (must be 1..4)")
        if lossless:
            tq = None
        elif tq > 3:
            raise _fail(name, f"component {names[i]} uses quantization table id {tq} (must be 0..3)")
        components.append(Component(cid, names[i], h, v, tq))

    # The first scan: it must fit its length and name frame components.
    ns = sos[0] if sos else 0
    if not 1 <= ns <= 4 or len(sos) != 4 + 2 * ns:
        raise _fail(
            name, f"the SOS segment at offset {sos_at} is malformed ({ns} components, length {len(sos) + 2})"
        )
    for i in range(ns):
        if sos[1 + 2 * i] not in ids:
            raise _fail(
                name,
                f"the first scan (SOS at offset {sos_at}) names component id {sos[1 + 2 * i]}, "
                "which is not in the frame",
            )

    quality: QualityEstimate | None = None
    if not lossless:
        if not tables:
            raise _fail(
                name,
                "no quantization table (DQT) before the first scan: an abbreviated JPEG stream whose tables "
                "are stored elsewhere",
            )
        for c in components:
            if c.table not in tables:
                raise _fail(
                    name,
                    f"component {c.name} uses quantization table {c.table}, which is not defined before "
                    "the first scan",
                )
        luma = tables[components[0].table].values  # type: ignore[index]
        chroma = tables[components[1].table].values if nf >= 2 else None  # type: ignore[index]
        quality = quality_of(luma, chroma)
        if precision == 8 and any(t.precision == 16 for t in tables.values()):
            warnings.append(
                "16-bit quantization tables with 8-bit samples (T.81 allows only 8-bit tables here)"
            )

    return JpegHeader(
        path=name,
        file_size=r.size,
        header_size=r.pos,
        bytes_read=r.nread,
        sof=mname,
        frame=frame,
        coding=coding,
        sample_precision=precision,
        width=width,
        height=height,
        color_space=color_space,
        components=tuple(components),
        tables=dict(sorted(tables.items())),
        sampling=sampling_name([(c.h, c.v) for c in components], color_space),
        restart_interval=restart_interval,
        quality=quality,
        jfif=jfif,
        adobe_transform=adobe_transform,
        app_segments=tuple(apps),
        warnings=tuple(warnings),
    )


def read_header_from(f: BinaryIO, name: str, size: int | None = None) -> JpegHeader:
    """Parse the header of an open binary file object positioned at the start of the JPEG.

    ``size`` is the total size in bytes (found by seeking when not given). Reads segment by segment; an
    unbuffered file object (``open(p, "rb", buffering=0)``) makes ``bytes_read`` the bytes taken from the OS.
    """
    try:
        if size is None:
            size = f.seek(0, os.SEEK_END)
            f.seek(0)
        return _parse(_Reader(f, size, name))
    except OSError as e:
        raise JsgsError(f"{name}: read error: {e.strerror or e}") from None


def read_header(path: str | os.PathLike[str]) -> JpegHeader:
    """Parse the header of the JPEG file at ``path`` (reads only the header bytes; see module docstring)."""
    name = str(path)
    try:
        f = open(path, "rb", buffering=0)  # unbuffered: read only the header bytes, nothing ahead
    except OSError as e:
        raise JsgsError(f"{name}: cannot open: {e.strerror or e}") from None
    with f:
        try:
            st = os.fstat(f.fileno())
        except OSError as e:
            raise JsgsError(f"{name}: cannot stat: {e.strerror or e}") from None
        if not stat.S_ISREG(st.st_mode):
            raise JsgsError(f"{name}: not a regular file")
        return read_header_from(f, name, st.st_size)


def parse_header(data: bytes | bytearray | memoryview, name: str) -> JpegHeader:
    """Parse the header of a JPEG held in memory; ``name`` is used in error messages and ``path``."""
    data = bytes(data)
    return _parse(_Reader(io.BytesIO(data), len(data), name))


# --------------------------------------------------------------------------------------------------------
# Reports over several files (the CLI's logic)


@dataclass
class Inspection:
    """Result of inspecting several files: headers of the good ones, one-line errors of the bad ones,
    in the order given."""

    results: list[tuple[str, JpegHeader | JsgsError]]

    @property
    def headers(self) -> list[JpegHeader]:
        return [h for _, h in self.results if isinstance(h, JpegHeader)]

    @property
    def errors(self) -> list[JsgsError]:
        return [e for _, e in self.results if isinstance(e, JsgsError)]

    def summary(self) -> dict[str, Any]:
        """Counts of files and errors, the quality range, how many tables are exactly IJG, sampling kinds."""
        hs = self.headers
        qs = [h.quality for h in hs if h.quality is not None]
        return {
            "files": len(self.results),
            "ok": len(hs),
            "errors": len(self.errors),
            "quality_min": min((q.quality for q in qs), default=None),
            "quality_max": max((q.quality for q in qs), default=None),
            "quality_exact": sum(q.exact for q in qs),
            "sampling": dict(sorted(Counter(h.sampling for h in hs).items())),
            "frames": dict(sorted(Counter(h.frame_name for h in hs).items())),
        }

    def to_json(self) -> dict[str, Any]:
        """The whole ``--json`` document (``jsgs/schemas/dqt_report.schema.json``)."""
        files: list[dict[str, Any]] = []
        for path, res in self.results:
            if isinstance(res, JpegHeader):
                files.append({"ok": True, **res.to_json()})
            else:
                files.append({"ok": False, "path": path, "error": str(res)})
        return {
            "format": "jsgs-dqt-report",
            "format_version": 1,
            "tool": {"name": "jsgstools", "command": "inspect-dqt", "version": __version__},
            "table_order": "natural-row-major",
            "table_order_note": TABLE_ORDER_NOTE,
            "files": files,
            "summary": self.summary(),
        }


def dumps_json(doc: Any, indent: int = 1, _level: int = 0) -> str:
    """JSON text like ``json.dumps(doc, indent=indent)`` but with lists of numbers on one line, so an 8x8
    table reads as 8 rows."""
    pad, inner = " " * (indent * _level), " " * (indent * (_level + 1))
    if isinstance(doc, dict) and doc:
        items = [f"{inner}{json.dumps(k)}: {dumps_json(v, indent, _level + 1)}" for k, v in doc.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(doc, list) and doc and not all(isinstance(x, (int, float)) for x in doc):
        items = [f"{inner}{dumps_json(v, indent, _level + 1)}" for v in doc]
        return "[\n" + ",\n".join(items) + "\n" + pad + "]"
    return json.dumps(doc)


def inspect_files(paths: Iterable[str | os.PathLike[str]]) -> Inspection:
    """Read every header; a bad file becomes its JsgsError in the results instead of stopping the run."""
    results: list[tuple[str, JpegHeader | JsgsError]] = []
    for p in paths:
        name = str(p)
        try:
            results.append((name, read_header(p)))
        except JsgsError as e:
            results.append((name, e))
        except Exception as e:  # a bug (the fuzz test says there is none): still one line, other files go on
            results.append(
                (name, JsgsError(f"{name}: internal error ({type(e).__name__}: {e}); please report"))
            )
    return Inspection(results)


def _quality_text(h: JpegHeader) -> str:
    if h.quality is None:
        return "-"
    return f"{h.quality.quality}" if h.quality.exact else f"~{h.quality.quality}"


def _tables_text(h: JpegHeader) -> str:
    parts = []
    for t in h.tables.values():
        users = ",".join(c.name for c in h.components if c.table == t.id) or "unused"
        bits = "" if t.precision == 8 else "(16-bit)"
        parts.append(f"{t.id}{bits}:{users}")
    return " ".join(parts) or "-"


def format_table(ins: Inspection, show_tables: bool = False) -> str:
    """Human-readable report: one row per good file, then a summary line (and the 8x8 tables on request)."""
    head = ("FILE", "SIZE", "FRAME", "COLOR", "SAMPLING", "QUALITY", "TABLES (id:components)", "DRI")
    rows = [
        (
            h.path,
            f"{h.width}x{h.height}",
            h.frame_name,
            h.color_space,
            h.sampling,
            _quality_text(h),
            _tables_text(h),
            str(h.restart_interval) if h.restart_interval else "-",
        )
        for h in ins.headers
    ]
    lines: list[str] = []
    if rows:
        widths = [max(len(str(x)) for x in col) for col in zip(head, *rows, strict=True)]
        for row in (head, *rows):
            lines.append("  ".join(str(x).ljust(w) for x, w in zip(row, widths, strict=True)).rstrip())
    s = ins.summary()
    if rows:
        lines.append("")
    errors = f"{s['errors']} error" + ("" if s["errors"] == 1 else "s")
    lines.append(f"summary: {s['files']} file{'' if s['files'] == 1 else 's'}, {s['ok']} ok, {errors}")
    if s["quality_min"] is not None:
        n_q = sum(1 for h in ins.headers if h.quality is not None)
        q_range = f"{s['quality_min']}" + (
            "" if s["quality_min"] == s["quality_max"] else f"..{s['quality_max']}"
        )
        note = "" if s["quality_exact"] == n_q else "; ~Q: not IJG's tables, Q is the closest IJG quality"
        lines.append(f"  IJG quality  {q_range} ({s['quality_exact']} of {n_q} exact{note})")
    if s["sampling"]:
        lines.append("  sampling     " + ", ".join(f"{k} x{v}" for k, v in s["sampling"].items()))
    if s["frames"]:
        lines.append("  frames       " + ", ".join(f"{k} x{v}" for k, v in s["frames"].items()))
    if show_tables:
        for h in ins.headers:
            for t in h.tables.values():
                lines.append("")
                lines.append(f"{h.path}: table {t.id} ({t.precision}-bit), natural row-major [v][u]:")
                width = max(len(str(int(x))) for x in t.values.flat)
                for row in t.values:
                    lines.append("  " + " ".join(str(int(x)).rjust(width) for x in row))
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------------
# Building test files (used by the tests, the fuzz test and the benchmark)


def exif_app1(thumbnail: bytes | None = None, maker_note_bytes: int = 0) -> bytes:
    """A complete EXIF APP1 segment (FF E1, length, ``Exif\\0\\0``, big-endian TIFF) built by hand.

    IFD0 holds Orientation and a pointer to an Exif IFD whose MakerNote is ``maker_note_bytes`` bytes of
    filler (cameras' big EXIF blocks are mostly MakerNote); IFD1 points (JPEGInterchangeFormat/Length) at
    ``thumbnail``, a whole JPEG file embedded in the segment, as cameras store their preview.
    """
    import struct

    def entry(tag: int, typ: int, count: int, value: int) -> bytes:
        if typ == 3:  # SHORT: left-justified in the 4-byte value field
            return struct.pack(">HHIHH", tag, typ, count, value, 0)
        return struct.pack(">HHII", tag, typ, count, value)

    thumb = thumbnail or b""
    ifd0, exif_ifd, ifd1 = 8, 8 + 30, 8 + 30 + 18
    note = ifd1 + (42 if thumb else 0)
    thumb_at = note + maker_note_bytes + (maker_note_bytes & 1)
    tiff = b"MM\x00\x2a" + struct.pack(">I", ifd0)
    tiff += struct.pack(">H", 2) + entry(0x0112, 3, 1, 1) + entry(0x8769, 4, 1, exif_ifd)
    tiff += struct.pack(">I", ifd1 if thumb else 0)
    tiff += struct.pack(">H", 1) + entry(0x927C, 7, maker_note_bytes, note) + struct.pack(">I", 0)
    if thumb:
        tiff += struct.pack(">H", 3) + entry(0x0103, 3, 1, 6)
        tiff += entry(0x0201, 4, 1, thumb_at) + entry(0x0202, 4, 1, len(thumb)) + struct.pack(">I", 0)
    tiff += bytes((i * 7 + 3) & 0xFF for i in range(maker_note_bytes)) + b"\x00" * (maker_note_bytes & 1)
    tiff += thumb
    payload = b"Exif\x00\x00" + tiff
    if len(payload) + 2 > 0xFFFF:
        raise ValueError(f"EXIF payload of {len(payload)} bytes does not fit in one APP1 segment")
    return b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload


def insert_after_soi(jpeg: bytes, segment: bytes) -> bytes:
    """``jpeg`` with ``segment`` (a whole marker segment) inserted right after SOI."""
    if not jpeg.startswith(b"\xff\xd8"):
        raise ValueError("not a JPEG (no SOI)")
    return jpeg[:2] + segment + jpeg[2:]
