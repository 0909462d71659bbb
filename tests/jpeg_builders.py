"""Builders of JPEG test files (EXIF segments, segments inserted after SOI, a table of Cr's own, a file with
one scan per component) for the header parser's tests, the fuzz test and benchmarks/bench_dqt.py."""

from __future__ import annotations

import base64
import struct

# --------------------------------------------------------------------------------------------------------
# Building test files (used by the tests, the fuzz test and the benchmark)


def exif_app1(thumbnail: bytes | None = None, maker_note_bytes: int = 0) -> bytes:
    """A complete EXIF APP1 segment (FF E1, length, ``Exif\\0\\0``, big-endian TIFF) built by hand.

    IFD0 holds Orientation and a pointer to an Exif IFD whose MakerNote is ``maker_note_bytes`` bytes of
    filler (cameras' big EXIF blocks are mostly MakerNote); IFD1 points (JPEGInterchangeFormat/Length) at
    ``thumbnail``, a whole JPEG file embedded in the segment, as cameras store their preview.
    """

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


def own_cr_table(jpeg: bytes, table: list[list[int]]) -> bytes:
    """``jpeg`` (three components, 8-bit tables, SOF0/1/2) with its third component (Cr) quantized by a table
    of its own: a DQT segment defining table 2 as ``table`` (natural order, 8x8, entries 1..255) is inserted
    before the frame header, whose Cr entry then names table 2. The scan is left as it is (libjpeg decodes
    Cr's coefficients with the new steps)."""
    from jsgs.jpeg.tables import ZIGZAG

    sof = next(jpeg.find(m) for m in (b"\xff\xc0", b"\xff\xc1", b"\xff\xc2") if jpeg.find(m) > 0)
    if jpeg[sof + 9] != 3:
        raise ValueError("not a three-component JPEG")
    flat = [v for row in table for v in row]
    payload = bytes([2]) + bytes(flat[i] for i in ZIGZAG)
    out = bytearray(jpeg)
    out[sof + 10 + 3 * 2 + 2] = 2  # Cr's Tq
    return bytes(out[:sof]) + b"\xff\xdb" + struct.pack(">H", len(payload) + 2) + payload + bytes(out[sof:])


#: A 16x16 image (``_scan_pattern()`` of tests/test_jsgstools/dqt/test_dqt.py) saved by Pillow (quality 60,
#: 4:2:0), rewritten losslessly by libjpeg-turbo 2.1's ``jpegtran -optimize -scans`` with one sequential
#: scan per component (Y, Cb, Cr).
NON_INTERLEAVED = (
    "/9j/4AAQSkZJRgABAQAAAQABAAD/2wBDAA0JCgsKCA0LCgsODg0PEyAVExISEyccHhcgLikxMC4pLSwzOko+MzZGNywtQFdBRkxO"
    "UlNSMj5aYVpQYEpRUk//2wBDAQ4ODhMREyYVFSZPNS01T09PT09PT09PT09PT09PT09PT09PT09PT09PT09PT09PT09PT09PT09P"
    "T09PT09PT0//wAARCAAQABADASIAAhEBAxEB/8QAFgABAQEAAAAAAAAAAAAAAAAAAQAC/8QAIxAAAgIBAwQDAQAAAAAAAAAAAQID"
    "ESEEEjEAIkFRE2GBof/aAAgBAQAAPwCDxgrA8LOKFadBWe0gEYJ4GfvHkDcQAhV5TFYWmjTAcd17q8kijyOOhRqXU/CtM5O+WNSx"
    "INZWhXNmv7no08TS7RApcbCDIyi2taUi/WPwVfv/xAAUAQEAAAAAAAAAAAAAAAAAAAAD/8QAHREAAQIHAAAAAAAAAAAAAAAAAQIR"
    "ABIhMVGx8P/aAAgBAhEAPwA1LQHmParkuTeP/8QAFAEBAAAAAAAAAAAAAAAAAAAAAP/EABwRAAEDBQAAAAAAAAAAAAAAAAERITEA"
    "IlFx4f/aAAgBAxEAPwAlpIDDEa4HWStf/9k="
)


def non_interleaved_jpeg() -> bytes:
    """``NON_INTERLEAVED`` as bytes: a baseline JPEG whose three components have a sequential scan each."""
    return base64.b64decode(NON_INTERLEAVED)
