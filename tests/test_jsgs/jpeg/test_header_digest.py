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
    assert header_digest_bytes(data) == hashlib.sha256(_kept_segments(data, _sos_end(data))).hexdigest()


def _kept_segments(data: bytes, end: int) -> bytes:
    """An independent walk of a well-formed ``data`` up to offset ``end``: the segments after SOI but the
    APPn (n != 0, 14) and COM ones, each scan's coded data (up to the next FF that is not 00, FF or RSTn)
    left out."""
    kept, p = b"", 2
    while p < end:
        code, length = data[p + 1], int.from_bytes(data[p + 2 : p + 4], "big")
        if not (0xE1 <= code <= 0xED or code in (0xEF, 0xFE)):
            kept += data[p : p + 2 + length]
        p += 2 + length
        if code == 0xDA and p < end:
            while not (data[p] == 0xFF and data[p + 1] not in (0x00, 0xFF, *range(0xD0, 0xD8))):
                p += 1
    return kept


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


# ---------------------------------------------------------------------------------------------------------
# Scheme 2: a DQT between scans (a file whose first scan leaves components out) is covered


def _sos_offsets(data: bytes) -> list[int]:
    return [i for i in range(len(data) - 1) if data[i : i + 2] == b"\xff\xda"]  # FF is stuffed in coded data


def _dqt(table_id: int, values: list[int]) -> bytes:
    return b"\xff\xdb" + (67).to_bytes(2, "big") + bytes([table_id, *values])


def test_scheme_2_covers_a_dqt_between_scans() -> None:
    """One sequential scan per component (Y, Cb, Cr): a DQT before Cb's or Cr's first scan decides their
    table. Scheme 1 stops at the first scan and misses it; scheme 2 (what manifests record) reads on to the
    scan header by which every component has begun a scan, the header parser's ``header_size``, and is the
    SHA-256 of the decoding segments up to there, the coded data left out. A file whose first scan codes every
    component gets one digest under both schemes."""
    import hashlib

    from jpeg_builders import non_interleaved_jpeg

    data = non_interleaved_jpeg()
    sos = _sos_offsets(data)
    assert len(sos) == 3 and parse_header(data, "n.jpg").scans == 3
    end = _sos_end(data)
    assert end > sos[2]
    # independently: the segments from SOI on, each scan's coded data cut
    assert header_digest_bytes(data) == hashlib.sha256(_kept_segments(data, end)).hexdigest()
    first = header_digest_bytes(data, scheme=1)
    assert first != header_digest_bytes(data) and first == header_digest_bytes(data[: sos[0] + 12], scheme=1)
    # a chroma table redefined before Cr's first scan, or before Cb's: only scheme 2 sees it
    for at in sos[1:]:
        changed = data[:at] + _dqt(1, [7] * 64) + data[at:]
        assert header_digest_bytes(changed, scheme=1) == first
        assert header_digest_bytes(changed) != header_digest_bytes(data)
    # what comes after Cr's first scan header is not read (a cut file keeps its digest)
    assert header_digest_bytes(data[:end]) == header_digest_bytes(data)
    with pytest.raises(JsgsError, match=r"^n.jpg: truncated JPEG \(the file ends before every component's"):
        header_digest_bytes(data[: sos[0] + 12], "n.jpg")
    with pytest.raises(JsgsError, match=r"^n.jpg: EOI marker before every component's first scan$"):
        header_digest_bytes(data[: sos[1]] + b"\xff\xd9", "n.jpg")
    # one interleaved scan: the schemes agree
    single = _jpeg(_img(4), quality=70)
    assert header_digest_bytes(single, scheme=1) == header_digest_bytes(single, scheme=2)


def test_manifests_record_scheme_2_and_older_ones_still_train(tmp_path: Path) -> None:
    """A scene with a multi-scan training JPEG: ``jsgstools manifest`` records its scheme-2 digest, so a DQT
    changed between its scans is refused by name before training; a manifest as written before the scheme
    was recorded (the scheme-1 digest, no scheme) still validates and trains, checked with scheme 1."""
    import json

    from click.testing import CliRunner
    from jpeg_builders import non_interleaved_jpeg

    from jsgs.cli import main as jsgs_main
    from jsgstools.cli import main as tools
    from jsgstools.compress import compress
    from jsgstools.synth import synth

    synth(tmp_path / "scene", views=4, size=(16, 16), seed=0)
    compress(tmp_path / "scene", tmp_path / "data", "gaussian", seed=0, jobs=1)
    doc = json.loads((tmp_path / "data" / "manifest.json").read_text())
    view = next(v for v in doc["views"] if v["jpeg"] is not None and v["split"] == "train")
    img = tmp_path / "data" / view["image"]
    data = non_interleaved_jpeg()
    img.write_bytes(data)
    manifest = tmp_path / "m.json"
    r = CliRunner().invoke(tools, ["manifest", str(tmp_path / "data"), "--out", str(manifest)])
    assert r.exit_code == 0, r.output
    doc = json.loads(manifest.read_text())
    jpegs = {v["name"]: v["jpeg"] for v in doc["views"] if v["jpeg"] is not None}
    assert {j["header_digest_scheme"] for j in jpegs.values()} == {2}
    assert jpegs[view["name"]]["header_sha256"] == header_digest_bytes(data)
    train = ["train", "--iterations", "1", "--eval-at", "", "--device", "cpu", "--quiet", "--method",
             "gsplat"]  # fmt: skip
    # Cr's table redefined between the scans: the header before the first scan is the same, the file is not
    at = _sos_offsets(data)[2]
    img.write_bytes(data[:at] + _dqt(1, [7] * 64) + data[at:])
    r = CliRunner().invoke(jsgs_main, [train[0], str(manifest), *train[1:], "--out", str(tmp_path / "run")])
    assert r.exit_code == 1 and f"{img}: changed since" in r.output, r.output
    # the manifest as written before the scheme was recorded, on the file it was written for
    img.write_bytes(data)
    for v in doc["views"]:
        if v["jpeg"] is not None:
            v["jpeg"]["header_sha256"] = header_digest(tmp_path / v["image"], scheme=1)  # relative to m.json
            del v["jpeg"]["header_digest_scheme"]
    assert header_digest(img, scheme=1) != header_digest(img)
    manifest.write_text(json.dumps(doc))
    r = CliRunner().invoke(jsgs_main, [train[0], str(manifest), *train[1:], "--out", str(tmp_path / "old")])
    assert r.exit_code == 0 and "no header digest" not in r.output, r.output
    assert (tmp_path / "old" / "point_cloud.ply").is_file()
