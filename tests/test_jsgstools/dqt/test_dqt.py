"""jsgstools.dqt and ``jsgstools inspect-dqt``: agreement with Pillow/libjpeg, EXIF thumbnails, MPO, 16-bit
tables, other frame types and colour spaces, every bad input through the CLI, the JSON schema."""

from __future__ import annotations

import io
import json
import struct
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from click.testing import CliRunner
from jpeg_builders import exif_app1, insert_after_soi, non_interleaved_jpeg, own_cr_table
from PIL import ExifTags, Image, JpegImagePlugin

from jsgs.base.errors import JsgsError
from jsgs.base.schema import load_schema
from jsgs.jpeg.tables import BASE_LUMA, ZIGZAG, estimate_quality, ijg_tables
from jsgstools.cli.inspect_dqt import inspect_dqt
from jsgstools.dqt import (
    JpegHeader,
    clear_caches,
    parse_header,
    quality_of,
    read_header,
    read_header_from,
)

ROOT = Path(__file__).resolve().parents[3]
SHARED_SCENES = ROOT.parent / "shared" / "scenes"


# ---------------------------------------------------------------------------------------------------------
# Helpers: small images, encoding, a minimal independent segment walker, byte surgery


def image(w: int = 32, h: int = 24, mode: str = "RGB", seed: int = 0) -> Image.Image:
    """Smooth gradient plus noise (uint8), enough detail for libjpeg to use every table."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.stack([xx * 255 / w, yy * 255 / h, (xx + yy) * 127 / (w + h)], axis=-1)
    arr = np.clip(base + rng.normal(0, 20, base.shape), 0, 255).astype(np.uint8)
    im = Image.fromarray(arr, "RGB")
    return im if mode == "RGB" else im.convert(mode)


def encode(im: Image.Image, **kw: object) -> bytes:
    buf = io.BytesIO()
    im.save(buf, "JPEG", **kw)
    return buf.getvalue()


def segments(data: bytes) -> list[tuple[int, int, int]]:
    """(marker code, offset of its FF, end offset) for SOI and every segment up to SOS, for the well-formed
    files these tests build (independent of the parser under test)."""
    out = [(0xD8, 0, 2)]
    p = 2
    while True:
        assert data[p] == 0xFF, p
        code = data[p + 1]
        length = int.from_bytes(data[p + 2 : p + 4], "big")
        out.append((code, p, p + 2 + length))
        p += 2 + length
        if code == 0xDA:
            return out


def find(data: bytes, code: int, k: int = 0) -> tuple[int, int]:
    """(start, end) of the k-th segment with ``code``."""
    return [(s, e) for c, s, e in segments(data) if c == code][k]


def drop(data: bytes, code: int, k: int | None = None) -> bytes:
    """``data`` without the segments with ``code`` (only the k-th when given)."""
    spans = [(s, e) for c, s, e in segments(data) if c == code]
    if k is not None:
        spans = [spans[k]]
    for s, e in reversed(spans):
        data = data[:s] + data[e:]
    return data


def put(data: bytes, offset: int, *values: int) -> bytes:
    """``data`` with bytes from ``offset`` replaced by ``values``."""
    b = bytearray(data)
    b[offset : offset + len(values)] = bytes(values)
    return bytes(b)


def sof_component_offset(data: bytes, i: int) -> int:
    """Offset of component i's id byte in the SOF segment (its HV byte follows, then its Tq)."""
    s = [s for c, s, _ in segments(data) if c in (0xC0, 0xC1, 0xC2)][0]
    return s + 10 + 3 * i


def dqt_segment(*tables: tuple[int, np.ndarray, int]) -> bytes:
    """One DQT segment holding ``(id, natural-order 8x8 table, bits)`` tables, written in zigzag order."""
    payload = b""
    for tq, t, bits in tables:
        zz = np.asarray(t).ravel()[ZIGZAG]
        if bits == 8:
            payload += bytes([tq]) + bytes(int(x) for x in zz)
        else:
            payload += bytes([0x10 | tq]) + struct.pack(">64H", *(int(x) for x in zz))
    return b"\xff\xdb" + struct.pack(">H", len(payload) + 2) + payload


def pillow_agrees(data: bytes, h: JpegHeader) -> None:
    """Our report says what Pillow's marker parser says: tables (natural order), size, components."""
    with Image.open(io.BytesIO(data)) as im:
        assert isinstance(im, JpegImagePlugin.JpegImageFile)
        assert sorted(im.quantization) == sorted(h.tables)
        for tid, values in im.quantization.items():
            np.testing.assert_array_equal(np.array(values).reshape(8, 8), h.tables[tid].values)
        assert im.size == (h.width, h.height)
        assert [tuple(layer) for layer in im.layer] == [(c.id, c.h, c.v, c.table) for c in h.components]
        assert bool(im.info.get("progressive")) == (h.frame == "progressive")
        if len(h.components) == 3:
            expected = {0: "4:4:4", 1: "4:2:2", 2: "4:2:0"}.get(JpegImagePlugin.get_sampling(im))
            if expected is not None:
                assert h.sampling == expected


def highest_equivalent_quality(q: int, gray: bool) -> int:
    """The highest q2 whose IJG tables equal those of q (estimate_quality's tie rule)."""
    luma, chroma = ijg_tables(q)
    best = q
    for q2 in range(q, 101):
        l2, c2 = ijg_tables(q2)
        if np.array_equal(l2, luma) and (gray or np.array_equal(c2, chroma)):
            best = q2
    return best


# ---------------------------------------------------------------------------------------------------------
# Agreement with Pillow and libjpeg on Pillow-made files


def test_pillow_quantization_is_natural_order() -> None:
    """Pillow >= 8.3 converts DQT to natural order; check it rather than trust it (the tables are not
    symmetric, so zigzag order would differ)."""
    data = encode(image(), quality=50)
    with Image.open(io.BytesIO(data)) as im:
        luma = np.array(im.quantization[0]).reshape(8, 8)
    np.testing.assert_array_equal(luma, BASE_LUMA)  # q=50 scales by 100 %: T.81's table K.1, natural order
    assert not np.array_equal(luma.ravel(), luma.ravel()[ZIGZAG])


VARIANTS: dict[str, tuple[str, dict[str, object], str, str]] = {
    # name: (mode, save options, expected sampling, expected frame)
    "444": ("RGB", {"subsampling": "4:4:4"}, "4:4:4", "baseline"),
    "422": ("RGB", {"subsampling": "4:2:2"}, "4:2:2", "baseline"),
    "420": ("RGB", {"subsampling": "4:2:0"}, "4:2:0", "baseline"),
    "progressive": ("RGB", {"progressive": True}, "4:2:0", "progressive"),
    "optimized": ("RGB", {"optimize": True, "subsampling": "4:4:4"}, "4:4:4", "baseline"),
    "gray": ("L", {}, "gray", "baseline"),
}


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_agrees_with_pillow_and_libjpeg_every_quality(variant: str) -> None:
    mode, options, sampling, frame = VARIANTS[variant]
    im = image(mode=mode)
    gray = mode == "L"
    for q in range(1, 101):
        data = encode(im, quality=q, **options)
        h = parse_header(data, f"{variant}-q{q}.jpg")
        pillow_agrees(data, h)
        # libjpeg's jpeg_set_quality(q, force_baseline=TRUE) is what Pillow wrote.
        luma, chroma = ijg_tables(q)
        np.testing.assert_array_equal(h.luma_table.values, luma)
        if gray:
            assert h.chroma_table is None and len(h.tables) == 1 and h.color_space == "gray"
        else:
            np.testing.assert_array_equal(h.chroma_table.values, chroma)
            assert [c.name for c in h.components] == ["Y", "Cb", "Cr"]
        assert h.sampling == sampling and h.frame == frame and h.coding == "huffman"
        assert (h.width, h.height, h.sample_precision, h.restart_interval) == (32, 24, 8, 0)
        assert h.quality is not None and h.quality.exact and h.quality.error == 0.0
        assert h.quality.quality == highest_equivalent_quality(q, gray)
        assert h.jfif and all(t.precision == 8 for t in h.tables.values())
        assert h.bytes_read <= h.header_size < len(data)


def test_custom_tables_get_the_closest_quality() -> None:
    """Camera-like tables (not IJG's at any quality): closest IJG quality, exact=False; cached estimates
    and decoded tables change nothing, and the shared arrays are read-only."""
    luma, chroma = ijg_tables(85)
    luma = luma.copy()
    luma[0, 0], luma[7, 7] = 3, 20
    data = encode(image(), qtables=[luma.ravel().tolist(), chroma.ravel().tolist()])
    first = parse_header(data, "cam.jpg")
    assert first.quality == estimate_quality(luma, chroma) and not first.quality.exact
    assert first.quality.quality == 85
    with pytest.raises(ValueError):
        first.tables[0].values[0, 0] = 1
    again = parse_header(data, "cam.jpg")
    clear_caches()
    fresh = parse_header(data, "cam.jpg")
    assert first.to_json() == again.to_json() == fresh.to_json()


def test_quality_fast_path_matches_estimate_quality() -> None:
    rng = np.random.default_rng(1)
    for q in range(1, 101):
        luma, chroma = ijg_tables(q)
        assert quality_of(luma, chroma) == estimate_quality(luma, chroma)
        assert quality_of(luma, None) == estimate_quality(luma, None)
        noisy = np.clip(luma + rng.integers(-2, 3, luma.shape), 1, 255)
        assert quality_of(noisy, chroma) == estimate_quality(noisy, chroma)


# ---------------------------------------------------------------------------------------------------------
# EXIF thumbnail, MPO, 16-bit tables


def test_exif_thumbnail_tables_are_not_the_images(tmp_path: Path) -> None:
    """APP1 holds a whole thumbnail JPEG (q=20, gray) before the image's own DQT (q=90): only q=90 counts."""
    thumb = encode(image(16, 12, "L", seed=3), quality=20)
    app1 = exif_app1(thumb, maker_note_bytes=60_000)
    data = insert_after_soi(encode(image(), quality=90), app1)
    # The thumbnail really is where EXIF IFD1 says (read back with Pillow's EXIF reader).
    with Image.open(io.BytesIO(data)) as im:
        exif = im.getexif()
        assert len(exif.get_ifd(ExifTags.IFD.Exif)[0x927C]) == 60_000  # the MakerNote filler
        ifd1 = exif.get_ifd(ExifTags.IFD.IFD1)
    tiff = data.index(b"Exif\x00\x00") + 6
    assert data[tiff + ifd1[0x201] : tiff + ifd1[0x201] + ifd1[0x202]] == thumb
    assert parse_header(thumb, "thumb").quality.quality == 20

    h = parse_header(data, "exif.jpg")
    pillow_agrees(data, h)
    assert h.quality.quality == 90 and h.quality.exact and h.color_space == "YCbCr"
    assert h.app_segments[0].identifier == "Exif" and h.app_segments[0].length == len(app1)

    path = tmp_path / "exif.jpg"
    path.write_bytes(data)
    hf = read_header(path)
    assert hf.to_json() == {**h.to_json(), "path": str(path)}
    assert hf.header_size > 60_000 and hf.bytes_read < 1_000  # the 60 KB APP1 was skipped, not read


def test_mpo_reports_the_first_picture() -> None:
    first = image()
    second = image(seed=5)
    second.encoderinfo = {"quality": 20}  # Pillow lets an appended frame override the encoder options
    buf = io.BytesIO()
    first.save(buf, "MPO", save_all=True, append_images=[second], quality=90)
    data = buf.getvalue()
    with Image.open(io.BytesIO(data)) as im:
        assert im.format == "MPO" and im.n_frames == 2
        im.seek(1)
        np.testing.assert_array_equal(np.array(im.quantization[0]).reshape(8, 8), ijg_tables(20)[0])
    h = parse_header(data, "pair.mpo")
    assert [a.identifier for a in h.app_segments if a.marker == "APP2"] == ["MPF"]
    assert h.quality.quality == 90 and h.quality.exact
    with Image.open(io.BytesIO(data)) as im:  # frame 0, as Pillow reports it
        for tid, values in im.quantization.items():
            np.testing.assert_array_equal(np.array(values).reshape(8, 8), h.tables[tid].values)


def test_handmade_16bit_tables() -> None:
    base = encode(image(), quality=50)
    luma16 = ijg_tables(50)[0] * 300 + 7  # entries up to ~36000: needs 16 bits
    chroma8 = ijg_tables(50)[1]
    # One DQT segment with both tables (table 0 16-bit, table 1 8-bit) replacing Pillow's two segments.
    s0, _ = find(base, 0xDB, 0)
    data = drop(base, 0xDB)
    data = data[:s0] + dqt_segment((0, luma16, 16), (1, chroma8, 8)) + data[s0:]
    h = parse_header(data, "sixteen.jpg")
    pillow_agrees(data, h)
    assert h.tables[0].precision == 16 and h.tables[1].precision == 8
    np.testing.assert_array_equal(h.tables[0].values, luma16)
    assert h.luma_table.values.max() > 255
    assert h.quality is not None and not h.quality.exact
    assert any("16-bit" in w for w in h.warnings)
    state = h.manifest_state()
    assert state["precision"] == 16 and state["luma_table"] == luma16.tolist()
    validate_manifest_jpeg(state)


# ---------------------------------------------------------------------------------------------------------
# Frame types, sampling names, restart interval, colour spaces, segment order


@pytest.mark.parametrize(
    ("code", "frame", "coding"),
    [(0xC1, "extended", "huffman"), (0xC9, "extended", "arithmetic"), (0xCA, "progressive", "arithmetic")],
)
def test_other_dct_frames_are_reported(code: int, frame: str, coding: str) -> None:
    data = encode(image(), quality=60)
    s, _ = find(data, 0xC0)
    h = parse_header(put(data, s + 1, code), "f.jpg")
    assert (h.frame, h.coding) == (frame, coding)
    assert h.frame_name == (frame if coding == "huffman" else f"{frame}-arithmetic")
    assert h.quality.quality == 60 and h.manifest_state()["frame"] == h.frame_name


@pytest.mark.parametrize("code", [0xC3, 0xCB])
def test_lossless_frames_have_no_quality(code: int) -> None:
    data = encode(image(), quality=60)
    s, _ = find(data, 0xC0)
    h = parse_header(put(data, s + 1, code), "lossless.jpg")
    assert h.frame == "lossless" and h.quality is None and h.to_json()["quality"] is None
    assert all(c.table is None for c in h.components)
    with pytest.raises(JsgsError, match="^lossless.jpg: lossless.* has no quantization tables$"):
        h.manifest_state()
    # A lossless frame needs no DQT at all.
    no_dqt = drop(data, 0xDB)
    h = parse_header(put(no_dqt, find(no_dqt, 0xC0)[0] + 1, code), "noq.jpg")
    assert h.tables == {} and h.frame == "lossless"


@pytest.mark.parametrize(
    ("factors", "name"),
    [
        ([0x11, 0x11, 0x11], "4:4:4"),
        ([0x22, 0x22, 0x22], "4:4:4"),
        ([0x21, 0x11, 0x11], "4:2:2"),
        ([0x22, 0x11, 0x11], "4:2:0"),
        ([0x12, 0x11, 0x11], "4:4:0"),
        ([0x41, 0x11, 0x11], "4:1:1"),
        ([0x42, 0x21, 0x21], "4:2:0"),
        ([0x22, 0x21, 0x21], "4:4:0"),
        ([0x31, 0x11, 0x11], "other"),
        ([0x22, 0x11, 0x21], "other"),
        ([0x32, 0x21, 0x21], "other"),
    ],
)
def test_sampling_names(factors: list[int], name: str) -> None:
    data = encode(image(), quality=70, subsampling="4:4:4")
    for i, hv in enumerate(factors):
        data = put(data, sof_component_offset(data, i) + 1, hv)
    h = parse_header(data, "s.jpg")
    assert h.sampling == name
    assert h.sampling_factors == ",".join(f"{f >> 4}x{f & 15}" for f in factors)


def test_gray_with_factors_is_still_gray() -> None:
    data = encode(image(mode="L"), quality=70)
    h = parse_header(put(data, sof_component_offset(data, 0) + 1, 0x22), "g.jpg")
    assert h.sampling == "gray" and [c.name for c in h.components] == ["gray"]


@pytest.mark.parametrize(
    ("option", "expected"), [({"restart_marker_blocks": 3}, 3), ({"restart_marker_rows": 1}, 2)]
)
def test_restart_interval(option: dict[str, int], expected: int) -> None:
    data = encode(image(), quality=80, **option)  # 32 px wide at 4:2:0: 2 MCUs per row
    h = parse_header(data, "dri.jpg")
    assert h.restart_interval == expected
    pillow_agrees(data, h)


def test_color_spaces() -> None:
    cmyk = encode(image(mode="CMYK"), quality=80)
    h = parse_header(cmyk, "cmyk.jpg")
    assert (h.color_space, [c.name for c in h.components], h.adobe_transform) == ("CMYK", list("CMYK"), 0)
    assert h.sampling == "4:4:4"
    pillow_agrees(cmyk, h)
    adobe = find(cmyk, 0xEE)[0]
    ycck = put(cmyk, adobe + 4 + 11, 2)  # Adobe transform byte: 2 = YCCK
    assert [c.name for c in parse_header(ycck, "ycck.jpg").components] == ["Y", "Cb", "Cr", "K"]

    rgb = encode(image(), quality=80, keep_rgb=True)
    h = parse_header(rgb, "rgb.jpg")
    assert (h.color_space, [c.name for c in h.components]) == ("RGB", ["R", "G", "B"])
    assert not h.quality.exact  # every component uses the luma table: not IJG's luma+chroma pair
    # Without the Adobe marker libjpeg still says RGB from the component ids 'R', 'G', 'B'.
    assert parse_header(drop(rgb, 0xEE), "rgb2.jpg").color_space == "RGB"
    # Without JFIF, ids 1, 2, 3 mean YCbCr.
    plain = drop(encode(image(), quality=80), 0xE0)
    h = parse_header(plain, "nojfif.jpg")
    assert not h.jfif and h.color_space == "YCbCr"


def test_dqt_after_sof_and_redefinition() -> None:
    data = encode(image(), quality=40)
    d0 = data[slice(*find(data, 0xDB, 0))]
    d1 = data[slice(*find(data, 0xDB, 1))]
    moved = drop(data, 0xDB)
    _, sof_end = find(moved, 0xC0)
    moved = moved[:sof_end] + d0 + d1 + moved[sof_end:]
    h = parse_header(moved, "late.jpg")
    assert h.quality.quality == 40 and h.quality.exact
    pillow_agrees(moved, h)
    # A second definition of table 0 before SOS replaces the first (libjpeg and Pillow agree).
    sos = find(moved, 0xDA)[0]
    redefined = moved[:sos] + dqt_segment((0, ijg_tables(10)[0], 8)) + moved[sos:]
    h = parse_header(redefined, "redef.jpg")
    np.testing.assert_array_equal(h.tables[0].values, ijg_tables(10)[0])
    assert any("redefined" in w for w in h.warnings)
    pillow_agrees(redefined, h)


def test_fill_bytes_and_junk_between_segments() -> None:
    data = encode(image(), quality=55)
    s, _ = find(data, 0xDB, 1)
    filled = data[:s] + b"\xff\xff\xff" + data[s:]
    h = parse_header(filled, "fill.jpg")
    assert h.quality.quality == 55 and h.warnings == ()
    junk = data[:s] + b"\x00\x12\xff\x00" + data[s:]
    h = parse_header(junk, "junk.jpg")
    assert h.quality.quality == 55 and any("extraneous" in w for w in h.warnings)
    pillow_agrees(junk, h)


def test_rst_and_tem_markers_are_tolerated() -> None:
    data = encode(image(), quality=55)
    s, _ = find(data, 0xDB, 1)
    h = parse_header(data[:s] + b"\xff\xd0\xff\x01" + data[s:], "rst.jpg")
    assert h.quality.quality == 55


# ---------------------------------------------------------------------------------------------------------
# Components outside the first scan: tables latched at each component's own first scan

def _scan_pattern() -> np.ndarray:
    yy, xx = np.mgrid[0:16, 0:16]
    planes = [(xx * 29 + yy * 47 + c * 83 + (xx * yy % 17) * 9) % 256 for c in range(3)]
    return np.stack(planes, -1).astype(np.uint8)


def _decode(data: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(data)) as im:
        return np.asarray(im.convert("RGB"))


def _sos_offsets(data: bytes) -> list[int]:
    return [i for i in range(len(data) - 1) if data[i : i + 2] == b"\xff\xda"]  # FF is stuffed in coded data


def test_tables_latched_at_each_components_first_scan() -> None:
    """libjpeg takes a component's table when the component's first scan begins: a DQT between scans decides
    the tables of the components not yet scanned. JO "exact" with the parser's tables reproduces libjpeg's
    decode; Pillow's ``quantization`` (read before the first scan only) does not see such a table."""
    import torch

    from jsgs.jpeg.observe import jpeg_observe

    data = non_interleaved_jpeg()
    arr = torch.from_numpy(_scan_pattern()).permute(2, 0, 1)[None].float() / 255

    def exact(h: JpegHeader) -> np.ndarray:
        s = h.manifest_state()
        luma, chroma = np.array(s["luma_table"]), np.array(s["chroma_table"])
        out = jpeg_observe(arr, luma, chroma, s["sampling"], "exact")
        return (out[0] * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()

    h = parse_header(data, "n.jpg")
    assert h.scans == 3 and (h.quality.quality, h.quality.exact) == (60, True)
    assert np.array_equal(exact(h), _decode(data))
    sos = _sos_offsets(data)
    assert len(sos) == 3
    other = ijg_tables(10)[1]
    # the chroma table redefined before Cb's first scan: libjpeg decodes Cb and Cr with it
    mod = data[: sos[1]] + dqt_segment((1, other, 8)) + data[sos[1] :]
    h = parse_header(mod, "m.jpg")
    np.testing.assert_array_equal(h.tables[1].values, other)
    assert h.scans == 3 and not np.array_equal(_decode(mod), _decode(data))
    # a decoy chroma table before the first scan, the file's own defined again before Cb's first scan: the
    # decode is the file's, and so is JO's with the parser's tables (Pillow's ``quantization`` says the decoy)
    s0, e0 = find(data, 0xDB, 1)
    decoy = data[:s0] + dqt_segment((1, other, 8)) + data[e0 : sos[1]]
    decoy += dqt_segment((1, ijg_tables(60)[1], 8)) + data[sos[1] :]
    assert np.array_equal(_decode(decoy), _decode(data))
    with Image.open(io.BytesIO(decoy)) as im:
        assert np.array_equal(np.array(im.quantization[1]).reshape(8, 8), other)
    h = parse_header(decoy, "decoy.jpg")
    np.testing.assert_array_equal(h.tables[1].values, ijg_tables(60)[1])
    assert np.array_equal(exact(h), _decode(decoy))
    # the chroma table defined only between the scans
    late = drop(data, 0xDB, 1)
    at = _sos_offsets(late)[1]
    late = late[:at] + dqt_segment((1, ijg_tables(60)[1], 8)) + late[at:]
    h = parse_header(late, "late.jpg")
    assert sorted(h.tables) == [0, 1] and h.quality.exact and np.array_equal(_decode(late), _decode(data))
    # never defined for the components outside the first scan: named with the offset of Cb's first scan, in
    # the words of a single-scan file's refusal (the first scan, every component's first)
    undefined = drop(data, 0xDB, 1)
    single = drop(_base(), 0xDB, 1)
    for what, file, at in (("u.jpg", undefined, _sos_offsets(undefined)[1]), ("one.jpg", single, None)):
        at = _sos_offsets(file)[0] if at is None else at
        with pytest.raises(JsgsError) as info:
            parse_header(file, what)
        assert str(info.value) == (f"{what}: component Cb uses quantization table 1, which is not defined "
                                   f"before its first scan (SOS at offset {at})")  # fmt: skip
    # a file that ends, or whose image ends, before Cb and Cr have a scan
    with pytest.raises(JsgsError, match=r"^c.jpg: truncated file: it ends in a scan's coded data before any "
                                        r"scan of component\(s\) Cb, Cr$"):
        parse_header(data[: sos[0] + 20], "c.jpg")
    with pytest.raises(JsgsError, match=r"^e.jpg: end of image \(EOI\) at offset \d+ before any scan of "
                                        r"component\(s\) Cb, Cr$"):
        parse_header(data[: sos[1]] + b"\xff\xd9", "e.jpg")
    # or inside the length field of the segment after the first scan, named as before the first scan
    with pytest.raises(JsgsError, match=rf"^l.jpg: truncated file: it ends inside the length field of the "
                                        rf"SOS segment at offset {sos[1]}$"):
        parse_header(data[: sos[1] + 3], "l.jpg")


def test_table_redefined_between_cb_and_crs_first_scans_is_crs_own(tmp_path: Path) -> None:
    """Table 1 (Cb's and Cr's) redefined between Cb's and Cr's first scans: libjpeg decodes Cr with the new
    table, so the file quantizes Cr with a table of its own. The header records it as ``cr_table``; libjpeg
    decodes the file exactly as the file whose Cr names a table of its own with the recorded values (no DQT
    between scans), and not as the file without the redefinition. The report lists table 1 twice."""
    data = non_interleaved_jpeg()
    sos = _sos_offsets(data)
    other = ijg_tables(10)[1]
    split = data[: sos[2]] + dqt_segment((1, other, 8)) + data[sos[2] :]
    h = parse_header(split, "s.jpg")
    s = h.manifest_state()
    assert s["luma_table"] == ijg_tables(60)[0].tolist() and s["chroma_table"] == ijg_tables(60)[1].tolist()
    assert s["cr_table"] == other.tolist() and (s["quality"], s["quality_exact"]) == (60, True)
    explicit = own_cr_table(data, s["cr_table"])
    assert np.array_equal(_decode(split), _decode(explicit))
    assert not np.array_equal(_decode(split), _decode(data))
    assert parse_header(explicit, "s.jpg").manifest_state() == s
    assert any("Cr decodes with another table than Cb" in w for w in h.warnings), h.warnings
    luma60, chroma60 = (t.tolist() for t in ijg_tables(60))
    got = [(t["id"], t["used_by"], t["values"]) for t in h.to_json()["tables"]]
    assert got == [(0, ["Y"], luma60), (1, ["Cb"], chroma60), (1, ["Cr"], other.tolist())]
    (tmp_path / "s.jpg").write_bytes(split)
    r = CliRunner().invoke(inspect_dqt, [str(tmp_path / "s.jpg"), "--json"])
    assert r.exit_code == 0, r.output
    jsonschema.validate(json.loads(r.output), load_schema("dqt_report"))
    r = CliRunner().invoke(inspect_dqt, [str(tmp_path / "s.jpg")])
    assert r.exit_code == 0 and "0:Y 1:Cb 1:Cr" in r.output, r.output
    # redefined with the same values: one chroma table
    same = data[: sos[2]] + dqt_segment((1, ijg_tables(60)[1], 8)) + data[sos[2] :]
    assert "cr_table" not in parse_header(same, "same.jpg").manifest_state()


# ---------------------------------------------------------------------------------------------------------
# Reading only the header; manifest state


class CountingFile(io.FileIO):
    """An unbuffered file that records every read: how many bytes, and the furthest offset reached."""

    def __init__(self, path: Path) -> None:
        super().__init__(path, "rb")
        self.bytes = 0
        self.furthest = 0

    def read(self, size: int = -1) -> bytes:  # type: ignore[override]
        data = super().read(size)
        self.bytes += len(data)
        self.furthest = max(self.furthest, self.tell())
        return data


def test_reads_only_the_header(tmp_path: Path) -> None:
    """A large image with a 60 KB EXIF block: the parser never reads past SOS, nor the APP1 payload."""
    big = image(1024, 768, seed=2)
    data = insert_after_soi(
        encode(big, quality=92), exif_app1(encode(big.resize((160, 120)), quality=70), 60_000)
    )
    path = tmp_path / "big.jpg"
    path.write_bytes(data)
    with CountingFile(path) as f:
        h = read_header_from(f, str(path), len(data))
        assert f.bytes == h.bytes_read < 1_000
        assert f.furthest == h.header_size == find(data, 0xDA)[1]
    assert h.file_size == len(data) > 100_000 and (h.width, h.height) == (1024, 768)


MANIFEST_JPEG = {"$ref": "#/$defs/jpeg", "$defs": load_schema("manifest")["$defs"]}


def validate_manifest_jpeg(state: dict[str, object]) -> None:
    jsonschema.Draft202012Validator(MANIFEST_JPEG).validate(state)


@pytest.mark.parametrize("mode", ["RGB", "L"])
def test_manifest_state(mode: str) -> None:
    h = parse_header(encode(image(mode=mode), quality=33, subsampling="4:2:0"), "m.jpg")
    state = h.manifest_state()
    validate_manifest_jpeg(state)
    assert set(state) == {
        "luma_table",
        "chroma_table",
        "sampling",
        "quality",
        "quality_exact",
        "precision",
        "frame",
        "color_space",
    }
    assert state["color_space"] == ("gray" if mode == "L" else "YCbCr")
    assert state["luma_table"] == ijg_tables(33)[0].tolist() and state["quality"] == 33
    assert state["quality_exact"] is True and state["precision"] == 8 and state["frame"] == "baseline"
    if mode == "L":
        assert state["chroma_table"] is None and state["sampling"] == "gray"
    else:
        assert state["chroma_table"] == ijg_tables(33)[1].tolist() and state["sampling"] == "4:2:0"


def test_manifest_state_records_a_cr_table_of_its_own() -> None:
    """A file whose Cr component names a third table: libjpeg decodes Cr with it, so the manifest records it
    (``cr_table``) rather than letting Cb's table stand for both; files with one chroma table have none."""
    base = encode(image(), quality=60, subsampling="4:2:0")
    own = ijg_tables(5)[1]
    data = own_cr_table(base, own.tolist())
    h = parse_header(data, "cr.jpg")
    assert [c.table for c in h.components] == [0, 1, 2]
    pillow_agrees(data, h)
    with Image.open(io.BytesIO(data)) as a, Image.open(io.BytesIO(base)) as b:  # table 2 is used
        assert not np.array_equal(np.asarray(a.convert("RGB")), np.asarray(b.convert("RGB")))
    state = h.manifest_state()
    validate_manifest_jpeg(state)
    assert state["cr_table"] == own.tolist() and state["chroma_table"] == ijg_tables(60)[1].tolist()
    # a third table equal to Cb's in value is one chroma table
    same = parse_header(own_cr_table(base, ijg_tables(60)[1].tolist()), "same.jpg").manifest_state()
    assert "cr_table" not in same


# ---------------------------------------------------------------------------------------------------------
# The CLI: table, --json against the schema, bad inputs


def run(args: list[str]) -> tuple[int, str, str]:
    result = CliRunner().invoke(inspect_dqt, args, catch_exceptions=False)
    return result.exit_code, result.stdout, result.stderr


@pytest.fixture()
def good_files(tmp_path: Path) -> tuple[Path, Path]:
    a = tmp_path / "a.jpg"
    b = tmp_path / "b.jpg"
    a.write_bytes(encode(image(), quality=75))
    b.write_bytes(encode(image(mode="L"), quality=30, progressive=True))
    return a, b


def test_cli_table(good_files: tuple[Path, Path]) -> None:
    a, b = good_files
    code, out, err = run([str(a), str(b), "--tables"])
    assert code == 0 and err == ""
    lines = out.splitlines()
    assert lines[0].split()[:4] == ["FILE", "SIZE", "FRAME", "COLOR"]
    row_a = next(line for line in lines if line.startswith(str(a)))
    assert "32x24" in row_a and "baseline" in row_a and "4:2:0" in row_a and " 75 " in row_a
    assert "0:Y 1:Cb,Cr" in row_a
    row_b = next(line for line in lines if line.startswith(str(b)))
    assert "progressive" in row_b and "gray" in row_b and " 30 " in row_b
    assert "summary: 2 files, 2 ok, 0 errors\n  IJG quality  30..75 (2 of 2 exact)\n" in out
    assert "  sampling     4:2:0 x1, gray x1\n  frames       baseline x1, progressive x1\n" in out
    assert f"{a}: table 0 (8-bit), natural row-major [v][u]:" in out
    first_row = lines[lines.index(f"{a}: table 0 (8-bit), natural row-major [v][u]:") + 1].split()
    assert [int(x) for x in first_row] == ijg_tables(75)[0][0].tolist()


def test_cli_table_names_12_bit_frames(tmp_path: Path) -> None:
    """The FRAME column says the sample precision when it is not 8 (such files have no manifest state)."""
    data = bytearray(encode(image(), quality=75))
    s, _ = find(bytes(data), 0xC0)
    data[s + 1], data[s + 4] = 0xC1, 12
    path = tmp_path / "twelve.jpg"
    path.write_bytes(bytes(data))
    code, out, _ = run([str(path)])
    assert code == 0 and "  extended 12-bit  " in out.splitlines()[1], out


def test_cli_json_validates_against_schema(good_files: tuple[Path, Path], tmp_path: Path) -> None:
    a, b = good_files
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"hello")
    thumb = tmp_path / "exif.jpg"
    thumb.write_bytes(
        insert_after_soi(encode(image(), quality=88), exif_app1(encode(image(), quality=10), 100))
    )
    code, out, err = run([str(a), str(bad), str(b), str(thumb), "--json"])
    assert code == 1
    assert err.splitlines() == [
        f"error: {bad}: not a JPEG file: starts with 68 65 6C 6C, a JPEG starts with FF D8 (SOI)"
    ]
    doc = json.loads(out)
    jsonschema.Draft202012Validator(load_schema("dqt_report")).validate(doc)
    from jsgs import __version__

    assert doc["tool"] == {"name": "jsgstools", "command": "inspect-dqt", "version": __version__}
    assert doc["table_order"] == "natural-row-major"
    assert [f["ok"] for f in doc["files"]] == [True, False, True, True]
    assert doc["files"][1] == {"ok": False, "path": str(bad), "error": err.splitlines()[0][len("error: ") :]}
    assert doc["files"][0]["tables"][0]["values"] == ijg_tables(75)[0].tolist()
    assert doc["files"][3]["quality"]["estimate"] == 88
    assert ", ".join(str(x) for x in ijg_tables(75)[0][0]) in out  # a table row is one line of the JSON
    assert doc["summary"] == {
        "files": 4,
        "ok": 3,
        "errors": 1,
        "quality_min": 30,
        "quality_max": 88,
        "quality_exact": 3,
        "sampling": {"4:2:0": 2, "gray": 1},
        "frames": {"baseline": 2, "progressive": 1},
    }


def test_cli_help_states_natural_order() -> None:
    result = CliRunner().invoke(inspect_dqt, ["--help"])
    assert result.exit_code == 0
    assert "NATURAL ROW-MAJOR" in result.stdout and "--json" in result.stdout


def _base() -> bytes:
    return encode(image(), quality=75)


def _sof_start(d: bytes) -> int:
    return find(d, 0xC0)[0]


BAD_INPUTS: dict[str, tuple[Callable[[], bytes], str]] = {
    "empty": (lambda: b"", "empty file (0 bytes)"),
    "one_byte": (lambda: b"\xff", "not a JPEG file"),
    "png": (
        lambda: b"\x89PNG\r\n\x1a\n" + b"\x00" * 20,
        "not a JPEG file: starts with 89 50 4E 47 (looks like a PNG image)",
    ),
    "text": (lambda: b"just some text\n", "not a JPEG file"),
    "truncated_in_dqt": (
        lambda: _base()[: find(_base(), 0xDB)[0] + 30],
        "truncated file: it ends inside the DQT segment",
    ),
    "truncated_in_sos": (
        lambda: _base()[: find(_base(), 0xDA)[1] - 3],
        "truncated file: it ends inside the SOS segment",
    ),
    "truncated_in_length": (
        lambda: _base()[: find(_base(), 0xDB)[0] + 3],
        "ends inside the length field of the DQT",
    ),
    "truncated_at_boundary": (lambda: _base()[: find(_base(), 0xC0)[1]], "truncated file: it ends at offset"),
    "length_past_end": (
        lambda: put(_base(), find(_base(), 0xE0)[0] + 2, 0xFF, 0xF0),
        "the APP0 segment at offset 2 declares length 65520, which runs past the end of the file",
    ),
    "dht_length_past_end": (
        lambda: put(_base(), find(_base(), 0xC4)[0] + 2, 0x7F, 0xFF),
        "the DHT segment at offset",
    ),
    "length_below_two": (
        lambda: put(_base(), find(_base(), 0xDB)[0] + 2, 0, 1),
        "invalid length 1 (minimum 2)",
    ),
    "no_dqt_abbreviated": (lambda: drop(_base(), 0xDB), "no quantization table (DQT) before the first scan"),
    "undefined_table": (
        lambda: drop(_base(), 0xDB, 1),
        "component Cb uses quantization table 1, which is not defined before its first scan (SOS at offset ",
    ),
    "sof5_hierarchical": (lambda: put(_base(), _sof_start(_base()) + 1, 0xC5), "unsupported frame type SOF5"),
    "sof14_hierarchical": (
        lambda: put(_base(), _sof_start(_base()) + 1, 0xCE),
        "unsupported frame type SOF14",
    ),
    "jpeg_ls": (
        lambda: put(_base(), _sof_start(_base()) + 1, 0xF7),
        "unsupported frame type SOF55 at offset",
    ),
    "dhp": (lambda: put(_base(), _sof_start(_base()) + 1, 0xDE), "unsupported frame type DHP"),
    "no_sof": (lambda: drop(_base(), 0xC0), "start of scan (SOS) at offset"),
    "eoi_before_scan": (
        lambda: _base()[: find(_base(), 0xC0)[0]] + b"\xff\xd9",
        "end of image (EOI) at offset",
    ),
    "second_soi": (lambda: insert_after_soi(_base(), b"\xff\xd8"), "a second start of image (SOI)"),
    "second_sof": (
        lambda: (
            _base()[: find(_base(), 0xC0)[1]]
            + _base()[slice(*find(_base(), 0xC0))]
            + _base()[find(_base(), 0xC0)[1] :]
        ),
        "a second frame header (SOF0)",
    ),
    "dqt_precision_2": (lambda: put(_base(), find(_base(), 0xDB)[0] + 4, 0x20), "table precision code 2"),
    "dqt_table_id_5": (
        lambda: put(_base(), find(_base(), 0xDB)[0] + 4, 0x05),
        "defines table id 5 (must be 0..3)",
    ),
    "dqt_short": (lambda: put(_base(), find(_base(), 0xDB)[0] + 4, 0x10), "is shorter than its table 0"),
    "dqt_zero_entry": (lambda: put(_base(), find(_base(), 0xDB)[0] + 5, 0), "has a zero entry"),
    "twelve_bit_baseline": (
        lambda: put(_base(), _sof_start(_base()) + 4, 12),
        "12-bit samples are not valid in a baseline frame",
    ),
    "width_zero": (lambda: put(_base(), _sof_start(_base()) + 7, 0, 0), "declares width 0"),
    "height_zero": (lambda: put(_base(), _sof_start(_base()) + 5, 0, 0), "declares height 0"),
    "sof_length_mismatch": (lambda: put(_base(), _sof_start(_base()) + 9, 4), "but its 4 components need 20"),
    "bad_sampling_factor": (
        lambda: put(_base(), sof_component_offset(_base(), 1) + 1, 0x51),
        "invalid sampling factors 5x1",
    ),
    "table_id_out_of_range": (
        lambda: put(_base(), sof_component_offset(_base(), 0) + 2, 7),
        "quantization table id 7",
    ),
    "duplicate_component_ids": (
        lambda: put(_base(), sof_component_offset(_base(), 1), 1),
        "repeats a component id",
    ),
    "unknown_marker": (lambda: put(_base(), find(_base(), 0xDB)[0] + 1, 0x02), "unknown marker 0xFF02"),
    "no_marker_found": (
        lambda: put(_base(), find(_base(), 0xDB)[0], *([0x00] * 1100)),
        "no JPEG marker in the 1024 bytes",
    ),
    "sos_bad_component": (lambda: put(_base(), find(_base(), 0xDA)[0] + 5, 9), "names component id 9"),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_cli_bad_input(case: str, good_files: tuple[Path, Path], tmp_path: Path) -> None:
    """Each bad file: one line naming it on stderr, exit 1, no traceback, the good files still reported."""
    build, expected = BAD_INPUTS[case]
    bad = tmp_path / f"{case}.jpg"
    bad.write_bytes(build())
    a, b = good_files
    code, out, err = run([str(a), str(bad), str(b)])
    assert code == 1
    assert "Traceback" not in out + err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {bad}: "), err
    assert expected in lines[0], lines[0]
    assert str(a) in out and str(b) in out and "summary: 3 files, 2 ok, 1 error\n" in out
    with pytest.raises(JsgsError) as info:  # the library says the same
        parse_header(bad.read_bytes(), str(bad))
    assert f"error: {info.value}" == lines[0]


def test_cli_missing_file_and_directory(good_files: tuple[Path, Path], tmp_path: Path) -> None:
    a, _ = good_files
    missing = tmp_path / "nope.jpg"
    code, out, err = run([str(missing), str(tmp_path), str(a)])
    assert code == 1 and "Traceback" not in out + err
    assert err.splitlines() == [
        f"error: {missing}: cannot open: No such file or directory",
        f"error: {tmp_path}: is a folder, not a regular file",
    ]
    assert "summary: 3 files, 1 ok, 2 errors\n" in out


def test_cli_unexpected_exception_is_one_line(
    good_files: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Even a bug in the parser must not print a traceback or stop the other files."""
    import jsgstools.dqt.report as dqt  # inspect_files reads each file through this name

    a, b = good_files
    real = dqt.read_header

    def flaky(path: str | Path) -> JpegHeader:
        if Path(path) == b:
            raise RuntimeError("boom")
        return real(path)

    monkeypatch.setattr(dqt, "read_header", flaky)
    code, out, err = run([str(a), str(b)])
    assert code == 1 and "Traceback" not in out + err
    assert err.splitlines() == [f"error: {b}: internal error (RuntimeError: boom); please report"]
    assert str(a) in out


def test_console_script_end_to_end(good_files: tuple[Path, Path], tmp_path: Path) -> None:
    """Through the installed entry point (the group registration included), in a real process."""
    a, _ = good_files
    bad = tmp_path / "cut.jpg"
    bad.write_bytes(a.read_bytes()[:100])
    proc = subprocess.run(
        [sys.executable, "-c", "from jsgstools.cli import main; main()", "inspect-dqt", str(a), str(bad)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {bad}: truncated file: it ends inside the DQT")
    assert str(a) in proc.stdout


# ---------------------------------------------------------------------------------------------------------
# Real photographs (the shared scenes, encoded to JPEG here)


def shared_images(per_scene: int = 2) -> list[Path]:
    if not SHARED_SCENES.is_dir():
        pytest.skip(f"shared scenes not found at {SHARED_SCENES} (../shared is absent on this machine)")
    paths: list[Path] = []
    for scene in sorted(SHARED_SCENES.iterdir()):
        paths += sorted((scene / "images").glob("*.png"))[:per_scene]
    if not paths:
        pytest.skip(f"no PNG images under {SHARED_SCENES}/*/images")
    return paths


@pytest.mark.parametrize(
    "options",
    [
        {"quality": 10, "subsampling": "4:2:0"},
        {"quality": 50, "subsampling": "4:4:4"},
        {"quality": 90, "subsampling": "4:2:2", "progressive": True},
        {"quality": 97, "subsampling": "4:2:0", "optimize": True},
    ],
    ids=["q10-420", "q50-444", "q90-422-progressive", "q97-420-optimized"],
)
def test_real_photos(options: dict[str, object], tmp_path: Path) -> None:
    for png in shared_images():
        with Image.open(png) as im:
            data = encode(im.convert("RGB"), **options)
        path = tmp_path / f"{png.parent.parent.name}_{png.stem}.jpg"
        path.write_bytes(data)
        h = read_header(path)
        pillow_agrees(data, h)
        assert h.quality.quality == options["quality"] and h.quality.exact
        assert (h.width, h.height) == Image.open(png).size


def test_camera_originals() -> None:
    """The four unchanged camera JPEGs of ../shared/jpeg_samples (4032x3024, the camera's own tables, DRI 252,
    EXIF with a thumbnail, XMP, IPTC, ICC): Pillow's tables, size and components; a header of under 1 KiB read
    of a ~6 KB one, one scan; the closest IJG quality 92, not exact; a valid manifest state."""
    originals = SHARED_SCENES.parent / "jpeg_samples" / "camera_originals"
    files = sorted(originals.glob("*.JPG")) if originals.is_dir() else []
    if not files:
        pytest.skip(f"no camera JPEGs: {originals} is absent (../shared not beside the checkout)")
    for path in files:
        h = read_header(path)
        pillow_agrees(path.read_bytes(), h)
        assert (h.width, h.height, h.sampling, h.restart_interval, h.scans) == (4032, 3024, "4:2:0", 252, 1)
        assert h.bytes_read < 1024 < h.header_size and h.frame_name == "baseline"
        assert (h.quality.quality, h.quality.exact) == (92, False)
        assert {"Exif", "ICC_PROFILE"} <= {a.identifier for a in h.app_segments}
        validate_manifest_jpeg(h.manifest_state())
