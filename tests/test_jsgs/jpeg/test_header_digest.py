"""The JPEG header digest (jsgs.jpeg.header_digest): what changes it (tables, sampling, frame), what does not
(pixels under the same header, Exif, comments), bad files in one line, and agreement with the toolkit's header
parser: every file the parser reads, the digest reads too (the manifest writer needs both)."""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jpeg_builders import exif_app1, insert_after_soi
from PIL import Image

from jsgs.base.errors import JsgsError
from jsgs.jpeg.header_digest import header_digest, header_digest_bytes
from jsgstools.dqt import parse_header


def _img(seed: int, size: tuple[int, int] = (24, 16)) -> Image.Image:
    rng = np.random.default_rng(seed)
    return Image.fromarray(rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8), "RGB")


def _jpeg(im: Image.Image, **kw: object) -> bytes:
    buf = io.BytesIO()
    im.save(buf, "JPEG", **kw)
    return buf.getvalue()


def _sos_end(data: bytes) -> int:
    return parse_header(data, "x.jpg").header_size


def test_the_digest_is_the_decoding_header() -> None:
    a, b = _img(0), _img(1)
    base = header_digest_bytes(_jpeg(a, quality=75))
    # other pixels, the same encoder settings: the same header bytes, the same digest
    assert header_digest_bytes(_jpeg(b, quality=75)) == base
    # metadata the decoder ignores does not count
    assert header_digest_bytes(_jpeg(a, quality=75, comment=b"hello")) == base
    assert header_digest_bytes(insert_after_soi(_jpeg(a, quality=75), exif_app1())) == base
    # what fixes the JPEG state does
    others = {
        "quality": _jpeg(a, quality=74),
        "sampling": _jpeg(a, quality=75, subsampling="4:4:4"),
        "progressive": _jpeg(a, quality=75, progressive=True),
        "huffman": _jpeg(a, quality=75, optimize=True),
        "restart": _jpeg(a, quality=75, restart_marker_blocks=2),
        "gray": _jpeg(a.convert("L"), quality=75),
    }
    digests = {k: header_digest_bytes(v) for k, v in others.items()}
    assert base not in digests.values() and len(set(digests.values())) == len(digests), digests
    # the pixels are not read: cutting the file after the first scan's header leaves the digest
    data = _jpeg(a, quality=75)
    assert header_digest_bytes(data[: _sos_end(data)]) == base


def test_it_is_sha256_of_the_segments_it_keeps() -> None:
    """Against an independent walk: the bytes from SOI to the end of SOS minus the APPn (n != 0, 14) and COM
    segments, SOI itself excluded."""
    import hashlib

    data = insert_after_soi(_jpeg(_img(2), quality=60, comment=b"c"), exif_app1())
    end = _sos_end(data)
    kept, p = b"", 2
    while p < end:
        code, length = data[p + 1], int.from_bytes(data[p + 2 : p + 4], "big")
        if not (0xE1 <= code <= 0xED or code in (0xEF, 0xFE)):
            kept += data[p : p + 2 + length]
        p += 2 + length
    assert header_digest_bytes(data) == hashlib.sha256(kept).hexdigest()


def test_bad_files_are_one_line(tmp_path: Path) -> None:
    data = _jpeg(_img(0), quality=75)
    cases = {
        "png.jpg": b"\x89PNG\r\n\x1a\n" + b"\x00" * 20,
        "empty.jpg": b"",
        "cut.jpg": data[: _sos_end(data) - 3],
        "eoi.jpg": b"\xff\xd8\xff\xd9",
    }
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(JsgsError) as e:
            header_digest(tmp_path / name)
        assert str(e.value).startswith(str(tmp_path / name)) and "\n" not in str(e.value)
    with pytest.raises(JsgsError, match="missing.jpg: cannot read"):
        header_digest(tmp_path / "missing.jpg")
    if hasattr(os, "mkfifo"):
        os.mkfifo(tmp_path / "fifo.jpg")  # no writer: a blocking open would hang
        with pytest.raises(JsgsError, match="not a regular file"):
            header_digest(tmp_path / "fifo.jpg")


SEED = insert_after_soi(_jpeg(_img(3), quality=80, comment=b"x"), exif_app1())


@st.composite
def mutants(draw: st.DrawFn) -> bytes:
    """The seed with 1-3 byte-level changes in and just after its header: flips, overwrites with marker-ish
    bytes, insertions, cuts."""
    data = bytearray(SEED)
    end = _sos_end(SEED) + 8
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["flip", "set", "insert", "cut"]))
        i = draw(st.integers(0, max(0, min(len(data), end) - 1)))
        if not data:
            break
        if kind == "flip":
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif kind == "set":
            data[i] = draw(st.sampled_from([0x00, 0x01, 0x02, 0xD0, 0xD8, 0xD9, 0xDA, 0xE1, 0xFE, 0xFF]))
        elif kind == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=6))
        else:
            del data[i:]
    return bytes(data)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mutants())
def test_mutated_headers_never_escape_and_agree_with_the_parser(data: bytes) -> None:
    try:
        header_digest_bytes(data, "m.jpg")
        ok = True
    except JsgsError as e:
        assert str(e).startswith("m.jpg: ") and "\n" not in str(e)
        ok = False
    try:
        parse_header(data, "m.jpg")
    except JsgsError:
        return
    assert ok, "the toolkit's parser reads this header but the digest does not"
