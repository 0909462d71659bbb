"""The header parser: a reader that fetches only the header bytes, a marker table dispatching each segment
before the first SOS to a small handler that fills a parse state, and the frame / first-scan checks at SOS."""

from __future__ import annotations

import io
import os
import stat
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import BinaryIO

import numpy as np

from jsgs.base.errors import JsgsError
from jsgs.jpeg.header_digest import SCAN_CHUNK, coded_data_end
from jsgs.jpeg.tables import QualityEstimate, zigzag_to_natural
from jsgstools.dqt.cache import _CACHE_MAX, _TABLE_CACHE
from jsgstools.dqt.header import (
    AppSegment,
    Component,
    JpegHeader,
    QuantTable,
    _color_space,
    quality_of,
    sampling_name,
)
from jsgstools.dqt.markers import (
    _APP_PEEK,
    _BETWEEN_SCANS,
    _COMPONENT_NAMES,
    _MARKER_NAMES,
    _MAX_JUNK,
    _PRINTABLE,
    _READ_THROUGH,
    _SEGMENT_MARKERS,
    _STANDALONE,
    APP0,
    APP14,
    APP15,
    DQT,
    DRI,
    EOI,
    SOS,
    SUPPORTED_SOF,
    UNSUPPORTED_FRAME,
)

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


def _undefined_table(name: str, c: Component, sos_at: int) -> JsgsError:
    """A component whose table id has no table when its first scan (SOS at ``sos_at``) begins."""
    return _fail(
        name,
        f"component {c.name} uses quantization table {c.table}, which is not defined before its first scan "
        f"(SOS at offset {sos_at})",
    )


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


@dataclass(slots=True)
class ParseState:
    """What the segments before the first SOS have said so far (filled by the marker handlers)."""

    name: str
    tables: dict[int, QuantTable] = field(default_factory=dict)
    apps: list[AppSegment] = field(default_factory=list)
    sof: tuple[int, int, bytes] | None = None  # (marker code, offset, payload)
    restart_interval: int = 0
    jfif: bool = False
    adobe_transform: int | None = None
    warnings: list[str] = field(default_factory=list)
    scans: int = 0  # scan headers (SOS) read


#: A marker handler: (reader positioned after the length field, state, marker code, offset of the marker,
#: payload size n, the length field) -> the header when the walk ends there (SOS), else None. Each handler
#: consumes exactly the n payload bytes.
Handler = Callable[[_Reader, ParseState, int, int, int, int], "JpegHeader | None"]


def _on_skip(r: _Reader, st: ParseState, code: int, at: int, n: int, length: int) -> None:
    """DHT, DAC, COM and the other uninterpreted segments: read through when small (one read beats a seek plus
    a read; most are header bytes anyway), else skipped by their length."""
    if 0xF0 <= code <= 0xFD:
        st.warnings.append(f"skipped extension marker {_MARKER_NAMES[code]} at offset {at}")
    if n <= _READ_THROUGH:
        r.read(n, ahead=4)
    else:
        r.seek(r.pos + n)


def _on_dqt(r: _Reader, st: ParseState, code: int, at: int, n: int, length: int) -> None:
    _read_dqt(st.name, at, r.read(n, ahead=4), st.tables, st.warnings)


def _on_sof(r: _Reader, st: ParseState, code: int, at: int, n: int, length: int) -> None:
    if st.sof is not None:
        raise _fail(st.name, f"a second frame header ({_MARKER_NAMES[code]}) at offset {at}")
    st.sof = (code, at, r.read(n, ahead=4))


def _on_app(r: _Reader, st: ParseState, code: int, at: int, n: int, length: int) -> None:
    """APPn: the first bytes name the segment; JFIF (APP0) and Adobe (APP14) set the colour space."""
    peek = r.read(min(n, _APP_PEEK), ahead=4 if n <= _APP_PEEK else 0)
    st.apps.append(AppSegment(_MARKER_NAMES[code], at, length + 2, _identifier(peek)))
    # libjpeg's examine_app0/app14: JFIF needs 14 data bytes, Adobe 12.
    if code == APP0 and n >= 14 and peek.startswith(b"JFIF\x00"):
        st.jfif = True
    elif code == APP14 and n >= 12 and peek.startswith(b"Adobe"):
        st.adobe_transform = peek[11]
    if n > len(peek):
        r.seek(r.pos + n - len(peek))


def _on_dri(r: _Reader, st: ParseState, code: int, at: int, n: int, length: int) -> None:
    if n != 2:
        raise _fail(st.name, f"the DRI segment at offset {at} has length {length} (must be 4)")
    b = r.read(2, ahead=4)
    st.restart_interval = (b[0] << 8) | b[1]


def _on_sos(r: _Reader, st: ParseState, code: int, at: int, n: int, length: int) -> JpegHeader:
    payload = r.read(n)
    if st.sof is None:
        raise _fail(st.name, f"start of scan (SOS) at offset {at} before any frame header (SOF)")
    return _finish(r, st, payload, at)


#: The marker table: segment marker -> its handler (anything else in ``_SEGMENT_MARKERS``: ``_on_skip``).
HANDLERS: dict[int, Handler] = {
    DQT: _on_dqt,
    DRI: _on_dri,
    SOS: _on_sos,
    **{c: _on_sof for c in SUPPORTED_SOF},
    **{c: _on_app for c in range(APP0, APP15 + 1)},
}


def _parse(r: _Reader) -> JpegHeader:
    name, size = r.name, r.size
    if size == 0:
        raise _fail(name, "empty file (0 bytes)")
    if size < 2:
        raise _not_jpeg(name, r.read(size))
    head = r.read(2, ahead=4)
    if head != b"\xff\xd8":
        raise _not_jpeg(name, head + r.read(min(size - 2, 10)))

    st = ParseState(name)
    handlers, skip = HANDLERS, _on_skip
    while True:
        # Marker and length: normally both are already pending from the previous read's look-ahead.
        p = r.pending
        if len(p) >= 4 and p[0] == 0xFF and p[1] in _SEGMENT_MARKERS:
            code, at, length = p[1], r.pos, (p[2] << 8) | p[3]
            r.pending = p[4:]
            r.pos = at + 4
        else:
            code, at = _next_marker(r, st.warnings)
            if code in _STANDALONE:
                continue
            if code not in _SEGMENT_MARKERS:
                raise _marker_error(name, code, at)
            length = _read_length(r, code, at)
        n = _payload_size(r, code, at, length)
        header = handlers.get(code, skip)(r, st, code, at, n, length)
        if header is not None:
            return header


def _read_length(r: _Reader, code: int, at: int) -> int:
    """The length field of the segment whose marker ``code`` is at offset ``at`` (the reader just after the
    marker, then after the field). JsgsError where the file ends inside it."""
    if r.pos + 2 > r.size:
        raise _fail(
            r.name,
            f"truncated file: it ends inside the length field of the {_MARKER_NAMES[code]} segment "
            f"at offset {at}",
        )
    b = r.read(2)
    return (b[0] << 8) | b[1]


def _payload_size(r: _Reader, code: int, at: int, length: int) -> int:
    """A segment's payload size in bytes (``length`` less its own 2 bytes), the reader after the length
    field. JsgsError for a length below 2 or a payload running past the end of the file."""
    if length < 2:
        raise _fail(
            r.name,
            f"the {_MARKER_NAMES[code]} segment at offset {at} has an invalid length {length} (minimum 2)",
        )
    if r.pos + length - 2 > r.size:
        raise _overrun_error(r, code, at, length)
    return length - 2


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



def _finish(r: _Reader, st: ParseState, sos: bytes, sos_at: int) -> JpegHeader:
    """The frame header and the first scan checked against each other and the tables: the header."""
    name = r.name
    assert st.sof is not None
    code, at, p = st.sof
    tables, warnings = st.tables, st.warnings
    mname = _MARKER_NAMES[code]
    frame, coding = SUPPORTED_SOF[code]
    lossless = frame == "lossless"
    precision, height, width, nf = _frame_fields(name, mname, at, p, frame)
    ids = list(p[6::3])
    if len(set(ids)) != nf:
        raise _fail(name, f"the frame header ({mname}) repeats a component id: {ids}")
    color_space = _color_space(ids, st.jfif, st.adobe_transform)
    components = _components(name, p, nf, color_space, lossless)
    _check_first_scan(name, sos, sos_at, ids)
    st.scans = 1
    first_scan = {sos[1 + 2 * i] for i in range(sos[0])}
    relatched: dict[int, QuantTable] = {}
    if not lossless and len(first_scan) < nf:
        tables, relatched = _follow_scans(r, st, components, first_scan, sos_at)
    quality = None if lossless else _quality(name, tables, warnings, components, precision, relatched, sos_at)
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
        restart_interval=st.restart_interval,
        quality=quality,
        jfif=st.jfif,
        adobe_transform=st.adobe_transform,
        app_segments=tuple(st.apps),
        scans=st.scans,
        warnings=tuple(warnings),
        relatched=relatched,
    )


def _frame_fields(name: str, mname: str, at: int, p: bytes, frame: str) -> tuple[int, int, int, int]:
    """The frame header's sample precision, height, width and component count, checked (its length, the
    count, the precision its frame allows, a size that is not 0)."""
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
    allowed = range(2, 17) if frame == "lossless" else ((8,) if frame == "baseline" else (8, 12))
    if precision not in allowed:
        raise _fail(name, f"{precision}-bit samples are not valid in a {frame} frame ({mname})")
    if width == 0:
        raise _fail(name, f"the frame header ({mname}) declares width 0")
    if height == 0:
        raise _fail(
            name, f"the frame header ({mname}) declares height 0 (height set by a DNL marker: not supported)"
        )
    return precision, height, width, nf


def _components(name: str, p: bytes, nf: int, color_space: str, lossless: bool) -> list[Component]:
    """The frame's components with their sampling factors and table ids (none in a lossless frame)."""
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
    return components


def _check_first_scan(name: str, sos: bytes, sos_at: int, ids: list[int], which: str = "first") -> None:
    """The first (or a later, ``which``) scan must fit its length and name frame components."""
    ns = sos[0] if sos else 0
    if not 1 <= ns <= 4 or len(sos) != 4 + 2 * ns:
        raise _fail(
            name, f"the SOS segment at offset {sos_at} is malformed ({ns} components, length {len(sos) + 2})"
        )
    for i in range(ns):
        if sos[1 + 2 * i] not in ids:
            raise _fail(
                name,
                f"the {which} scan (SOS at offset {sos_at}) names component id {sos[1 + 2 * i]}, "
                "which is not in the frame",
            )


def _follow_scans(
    r: _Reader, st: ParseState, components: list[Component], first_scan: set[int], sos_at: int
) -> tuple[dict[int, QuantTable], dict[int, QuantTable]]:
    """The tables of a frame whose first scan does not code every component. libjpeg takes a component's
    table when the component's first scan begins (``latch_quant_tables``), and a DQT between scans may
    define or redefine it for a later component; so the scans are followed (their entropy-coded data skipped
    by its markers) until every component has begun one. Returns table id -> the table its first component
    decodes with, and component index -> its table where it differs from that (the id redefined between the
    two components' first scans: the component decodes with the new table, as libjpeg does)."""
    name, tables = r.name, st.tables
    latched: dict[int, QuantTable] = {}  # component index -> its table

    def latch(scan_ids: set[int], at: int) -> None:
        for i, c in enumerate(components):
            if c.id in scan_ids and i not in latched:
                if c.table not in tables:
                    raise _undefined_table(name, c, at)
                latched[i] = tables[c.table]  # type: ignore[index]

    latch(first_scan, sos_at)
    ids = [c.id for c in components]
    while len(latched) < len(components):
        waiting = ", ".join(c.name for i, c in enumerate(components) if i not in latched)
        code, at, n = _next_scan_segment(r, st, waiting)
        if code == DQT:
            _read_dqt(name, at, r.read(n), tables, st.warnings)
        elif code == SOS:
            payload = r.read(n)
            st.scans += 1
            _check_first_scan(name, payload, at, ids, "next")
            latch({payload[1 + 2 * i] for i in range(payload[0])}, at)
        else:
            r.seek(r.pos + n)
    by_id: dict[int, QuantTable] = {}
    relatched: dict[int, QuantTable] = {}
    for i, c in enumerate(components):
        first = by_id.setdefault(c.table, latched[i])  # type: ignore[arg-type]
        if first is not latched[i] and not np.array_equal(first.values, latched[i].values):
            relatched[i] = latched[i]
            st.warnings.append(
                f"quantization table {c.table} is redefined between the first scans of the components that "
                f"use it: {c.name} decodes with another table than "
                f"{next(o.name for o in components if o.table == c.table)}"
            )
    return {**tables, **by_id}, relatched


def _next_scan_segment(r: _Reader, st: ParseState, waiting: str) -> tuple[int, int, int]:
    """The next segment after a scan's entropy-coded data: (marker code, offset, payload size), the reader
    after its length field. JsgsError at the end of the file or image, or at a marker that has no place
    between scans."""
    name = r.name
    while True:
        _skip_entropy_coded(r, waiting)
        code, at = _next_marker(r, st.warnings)
        if code in _STANDALONE:
            continue
        if code == EOI:
            raise _fail(name, f"end of image (EOI) at offset {at} before any scan of component(s) {waiting}")
        if code not in _BETWEEN_SCANS:
            raise _fail(name, f"marker {_MARKER_NAMES[code]} at offset {at} between scans")
        return code, at, _payload_size(r, code, at, _read_length(r, code, at))


def _skip_entropy_coded(r: _Reader, waiting: str) -> None:
    """Move ``r`` over entropy-coded data (bytes, stuffed FF 00, RSTn markers) to the FF of the next marker,
    reading ``SCAN_CHUNK`` bytes at a time (what is read past the marker stays pending;
    :func:`jsgs.jpeg.header_digest.coded_data_end` finds it)."""
    while True:
        if r.pos + 2 > r.size:
            raise _fail(
                r.name,
                f"truncated file: it ends in a scan's coded data before any scan of component(s) {waiting}",
            )
        start = r.pos
        chunk = r.read(min(SCAN_CHUNK, r.size - start))
        keep, found = coded_data_end(chunk)
        if keep < len(chunk):
            r.pending = chunk[keep:] + r.pending
            r.pos = start + keep
        if found:
            return


def _quality(
    name: str,
    tables: dict[int, QuantTable],
    warnings: list[str],
    components: list[Component],
    precision: int,
    relatched: dict[int, QuantTable],
    sos_at: int,
) -> QualityEstimate:
    """The quality estimate of a DCT frame from its luma (and chroma) tables, which must all be defined
    (``relatched``: component index -> its table where it is not ``tables``' of its id; ``sos_at``: the
    first scan's offset, every component's first where one is not defined); a warning for 16-bit tables
    with 8-bit samples."""
    if not tables:
        raise _fail(
            name,
            "no quantization table (DQT) before the first scan: an abbreviated JPEG stream whose tables "
            "are stored elsewhere",
        )
    for c in components:
        if c.table not in tables:
            raise _undefined_table(name, c, sos_at)
    own = [relatched.get(i) or tables[c.table] for i, c in enumerate(components[:2])]  # type: ignore[index]
    quality = quality_of(own[0].values, own[1].values if len(own) == 2 else None)
    if precision == 8 and any(t.precision == 16 for t in [*tables.values(), *relatched.values()]):
        warnings.append("16-bit quantization tables with 8-bit samples (T.81 allows only 8-bit tables here)")
    return quality


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
    from jsgs.base.io import open_regular

    name = str(path)
    try:
        # unbuffered: read only the header bytes, nothing ahead; a FIFO or a device is refused at once
        f = open_regular(path, buffering=0)
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


