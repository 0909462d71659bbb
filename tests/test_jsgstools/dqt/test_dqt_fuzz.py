"""Fuzzing the JPEG header parser: mutated real headers give a consistent report or a JsgsError, nothing else.

The mutations are structural (flipped and overwritten bytes, changed segment lengths, dropped, repeated and
swapped segments, inserted markers and junk, cut files). When a mutant still parses, the report is checked
for internal consistency, against the JSON schemas, and against Pillow's own marker parser whenever Pillow
accepts the mutant too.

CI runs ``JSGS_FUZZ_EXAMPLES`` (default 300) hypothesis examples (derandomized: the same ones every run)
plus a deterministic sweep; a long run is
``JSGS_FUZZ_EXAMPLES=100000 .venv/bin/python -m pytest tests/test_jsgstools/dqt/test_dqt_fuzz.py -k
hypothesis``.
"""

from __future__ import annotations

import io
import os
import warnings
from collections import Counter
from collections.abc import Callable, Iterator
from datetime import timedelta

import jsonschema
import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from jpeg_builders import exif_app1, insert_after_soi, non_interleaved_jpeg
from PIL import Image

from jsgs.base.errors import JsgsError
from jsgs.base.schema import load_schema
from jsgs.jpeg.tables import ZIGZAG, ijg_tables
from jsgstools.dqt import SAMPLING_NAMES, JpegHeader, parse_header

EXAMPLES = int(os.environ.get("JSGS_FUZZ_EXAMPLES", "300"))
NAME = "fuzz.jpg"

_REPORT = load_schema("dqt_report")
HEADER_VALIDATOR = jsonschema.Draft202012Validator({"$ref": "#/$defs/header", "$defs": _REPORT["$defs"]})
MANIFEST_JPEG_VALIDATOR = jsonschema.Draft202012Validator(
    {"$ref": "#/$defs/jpeg", "$defs": load_schema("manifest")["$defs"]}
)


def _encode(im: Image.Image, **kw: object) -> bytes:
    buf = io.BytesIO()
    im.save(buf, "JPEG", **kw)
    return buf.getvalue()


def _seeds() -> dict[str, bytes]:
    """Small real files covering the header features the parser handles."""
    rng = np.random.default_rng(0)
    rgb = Image.fromarray(rng.integers(0, 256, (16, 24, 3), dtype=np.uint8), "RGB")
    seeds = {
        "420": _encode(rgb, quality=75),
        "444-progressive": _encode(rgb, quality=30, subsampling="4:4:4", progressive=True),
        "422-optimized-dri": _encode(
            rgb, quality=95, subsampling="4:2:2", optimize=True, restart_marker_blocks=2
        ),
        "gray": _encode(rgb.convert("L"), quality=50),
        "cmyk-adobe": _encode(rgb.convert("CMYK"), quality=60),
        "rgb-adobe": _encode(rgb, quality=85, keep_rgb=True),
        "exif-thumbnail": insert_after_soi(
            _encode(rgb, quality=90), exif_app1(_encode(rgb.resize((8, 8)), quality=20), maker_note_bytes=40)
        ),
    }
    buf = io.BytesIO()
    rgb.save(buf, "MPO", save_all=True, append_images=[rgb.transpose(Image.Transpose.FLIP_LEFT_RIGHT)])
    seeds["mpo"] = buf.getvalue()
    # 16-bit tables: Pillow's first DQT rewritten with Pq=1 and entries above 255.
    base = seeds["420"]
    s = base.index(b"\xff\xdb")
    zz = (ijg_tables(75)[0] * 257).ravel()[ZIGZAG]
    payload = b"\x10" + b"".join(int(v).to_bytes(2, "big") for v in zz)
    seeds["16bit"] = base[:s] + b"\xff\xdb" + (len(payload) + 2).to_bytes(2, "big") + payload + base[s + 69 :]
    seeds["non-interleaved"] = non_interleaved_jpeg()  # one scan per component: the parser follows the scans
    for name, data in seeds.items():
        parse_header(data, name)  # every seed is valid
    return seeds


SEEDS = _seeds()


def segment_spans(data: bytes) -> list[tuple[int, int]]:
    """(start, end) of SOI and of each segment up to SOS, walking as far as the bytes allow (tolerant:
    mutants may be broken anywhere)."""
    spans = [(0, 2)] if data[:2] == b"\xff\xd8" else []
    p = 2
    while p + 4 <= len(data) and data[p] == 0xFF:
        code = data[p + 1]
        if 0xD0 <= code <= 0xD9 or code == 0x01:
            spans.append((p, p + 2))
            p += 2
            continue
        end = p + 2 + int.from_bytes(data[p + 2 : p + 4], "big")
        if end > len(data) or end <= p + 2:
            break
        spans.append((p, end))
        p = end
        if code == 0xDA:
            break
    return spans


MARKER_CODES = [
    0xC0,
    0xC1,
    0xC2,
    0xC3,
    0xC4,
    0xC5,
    0xC9,
    0xCB,
    0xCC,
    0xD0,
    0xD8,
    0xD9,
    0xDA,
    0xDB,
    0xDC,
    0xDD,
    0xDE,
    0xE0,
    0xE1,
    0xE2,
    0xEE,
    0xF0,
    0xF7,
    0xFE,
    0xFF,
    0x00,
    0x01,
    0x02,
]


@st.composite
def mutants(draw: st.DrawFn) -> bytes:
    """A seed file with 1-4 structural mutations."""
    data = bytearray(SEEDS[draw(st.sampled_from(sorted(SEEDS)))])
    for _ in range(draw(st.integers(1, 4))):
        spans = segment_spans(bytes(data))
        header_end = spans[-1][1] if spans else min(len(data), 64)
        kind = draw(
            st.sampled_from(["flip", "set", "length", "drop", "repeat", "swap", "marker", "junk", "cut"])
        )
        if not data:
            break
        if kind in ("length", "drop", "repeat", "swap") and len(spans) < 3:
            kind = "flip"
        if kind == "flip":
            i = draw(st.integers(0, min(len(data), header_end + 16) - 1))
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif kind == "set":
            i = draw(st.integers(0, min(len(data), header_end + 16) - 1))
            data[i] = draw(st.sampled_from([0x00, 0x01, 0x03, 0x04, 0x10, 0x7F, 0x80, 0xFF, 0xFE]))
        elif kind == "length":
            s, e = spans[draw(st.integers(1, len(spans) - 1))]
            if e - s > 2:
                old = int.from_bytes(data[s + 2 : s + 4], "big")
                new = draw(
                    st.one_of(
                        st.integers(0, 0xFFFF), st.integers(-8, 8).map(lambda d, old=old: (old + d) % 0x10000)
                    )
                )
                data[s + 2 : s + 4] = new.to_bytes(2, "big")
        elif kind == "drop":
            s, e = spans[draw(st.integers(1, len(spans) - 1))]
            del data[s:e]
        elif kind == "repeat":
            s, e = spans[draw(st.integers(1, len(spans) - 1))]
            at = spans[draw(st.integers(1, len(spans) - 1))][0]
            data[at:at] = data[s:e]
        elif kind == "swap":
            k = draw(st.integers(1, len(spans) - 2))
            (s1, e1), (s2, e2) = spans[k], spans[k + 1]
            data[s1:e2] = data[s2:e2] + data[s1:e1]
        elif kind == "marker":
            at = draw(st.sampled_from([s for s, _ in spans] + [header_end]))
            code = draw(st.sampled_from(MARKER_CODES))
            body = draw(st.binary(max_size=12))
            length = draw(st.sampled_from([len(body) + 2, 0, 1, 0xFFFF]))
            data[at:at] = bytes([0xFF, code]) + length.to_bytes(2, "big") + body
        elif kind == "junk":
            at = draw(st.sampled_from([s for s, _ in spans] + [header_end]))
            data[at:at] = draw(st.binary(min_size=1, max_size=8))
        else:  # cut
            del data[draw(st.integers(0, len(data))) :]
    return bytes(data)


def check_outcome(data: bytes, *, thorough: bool, note: Callable[[str], object]) -> None:
    """The property: a consistent report or a one-line JsgsError naming the file; nothing else escapes.
    ``note`` records which outcome it was (hypothesis ``event`` in the property test)."""
    try:
        h = parse_header(data, NAME)
    except JsgsError as e:
        msg = str(e)
        assert msg.startswith(f"{NAME}: ") and "\n" not in msg and len(msg) < 300, msg
        note("outcome: JsgsError")
        return
    note("outcome: report")
    check_report(h, data, thorough=thorough, note=note)


def check_report(h: JpegHeader, data: bytes, *, thorough: bool, note: Callable[[str], object]) -> None:
    assert data[:2] == b"\xff\xd8"
    assert h.file_size == len(data) and 0 < h.header_size <= len(data) and h.scans >= 1
    # past the first scan the coded data is read ahead in chunks, up to the file's end
    assert 0 < h.bytes_read <= (h.header_size if h.scans == 1 else len(data))
    assert h.width >= 1 and h.height >= 1 and 1 <= len(h.components) <= 4
    assert len({c.id for c in h.components}) == len(h.components)
    assert len({c.name for c in h.components}) == len(h.components)
    assert all(1 <= c.h <= 4 and 1 <= c.v <= 4 for c in h.components)
    assert h.sampling in SAMPLING_NAMES and 0 <= h.restart_interval <= 0xFFFF
    for tid, t in h.tables.items():
        assert tid == t.id and 0 <= tid <= 3 and t.precision in (8, 16)
        assert t.values.shape == (8, 8) and t.values.dtype == np.int64
        assert 1 <= t.values.min() and t.values.max() <= (255 if t.precision == 8 else 65535)
    if h.frame == "lossless":
        assert h.quality is None and all(c.table is None for c in h.components)
    else:
        assert all(c.table in h.tables for c in h.components)
        assert h.quality is not None and 1 <= h.quality.quality <= 100
        if h.sample_precision != 8:  # 12-bit samples: no manifest state (neither Pillow nor JO decodes them)
            with pytest.raises(JsgsError, match=rf"^{NAME}: {h.sample_precision}-bit samples"):
                h.manifest_state()
        else:
            state = h.manifest_state()
            assert state["luma_table"] == h.tables[h.components[0].table].values.tolist()
            if thorough:
                MANIFEST_JPEG_VALIDATOR.validate(state)
    if thorough:
        HEADER_VALIDATOR.validate({"ok": True, **h.to_json()})
    note("Pillow: same report" if compare_with_pillow(h, data) else "Pillow: refused the mutant")


def compare_with_pillow(h: JpegHeader, data: bytes) -> bool:
    """Where Pillow's parser also accepts the mutant, it must have read the same tables and frame."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(io.BytesIO(data)) as im:
                if im.format not in ("JPEG", "MPO"):
                    return False
                quant = dict(im.quantization)
                size = im.size
                layers = [tuple(layer) for layer in im.layer]
    except Exception:  # Pillow refusing a mutant is fine; only its accepted reports are compared
        return False
    if h.scans == 1:  # Pillow reads the tables before the first scan only (libjpeg decodes with later ones)
        assert sorted(quant) == sorted(h.tables), (quant.keys(), h.tables.keys())
        for tid, values in quant.items():
            assert np.array_equal(np.array(values).reshape(8, 8), h.tables[tid].values)
    assert size == (h.width, h.height)
    if h.frame != "lossless":
        assert layers == [(c.id, c.h, c.v, c.table) for c in h.components]
    return True


@settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=True,
    database=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(mutants())
def test_hypothesis_mutated_headers(data: bytes) -> None:
    check_outcome(data, thorough=True, note=event)


def _sweep(seed: bytes) -> Iterator[bytes]:
    end = segment_spans(seed)[-1][1]
    for i in range(end + 1):
        yield seed[:i]
    for i in range(end):
        for v in (0x00, 0xFF, seed[i] ^ 0x80):
            yield seed[:i] + bytes([v]) + seed[i + 1 :]


@pytest.mark.parametrize("seed", sorted(SEEDS))
def test_sweep_every_cut_and_byte(seed: str) -> None:
    """Deterministic: every prefix of the header, and every header byte set to 00, FF or flipped."""
    seen: Counter[str] = Counter()
    for data in _sweep(SEEDS[seed]):
        check_outcome(data, thorough=False, note=lambda key: seen.update([key]))
    # Both outcomes occur, and Pillow accepted some mutants we reported, so the comparison did run.
    assert seen["outcome: JsgsError"] and seen["outcome: report"] and seen["Pillow: same report"], seen


@pytest.mark.parametrize("seed", sorted(SEEDS))
def test_twelve_bit_frames(seed: str) -> None:
    """Each seed's frame made 12-bit (SOF0 made SOF1, where 12 bits are valid): a consistent report whose
    manifest state is refused, or a JsgsError (a lossless or 8-bit-only frame)."""
    data = bytearray(SEEDS[seed])
    sof = next(i for i in range(2, len(data) - 1) if data[i] == 0xFF and data[i + 1] in (0xC0, 0xC1, 0xC2))
    data[sof + 1] = 0xC1 if data[sof + 1] == 0xC0 else data[sof + 1]
    data[sof + 4] = 12
    outcomes: Counter[str] = Counter()
    check_outcome(bytes(data), thorough=True, note=lambda key: outcomes.update([key]))
    assert outcomes["outcome: report"], outcomes


@settings(
    max_examples=min(EXAMPLES, 60),
    deadline=timedelta(seconds=20),  # a hang fails the example
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(mutants())
def test_hypothesis_mutated_files_through_the_manifest_reader(
    tmp_path_factory: pytest.TempPathFactory, data: bytes
) -> None:
    """The file reader the manifest writer uses (``jpeg_file_state``): the manifest's ``jpeg`` object, valid
    against the manifest schema and finite, or one JsgsError line naming the file."""
    import json

    from jsgstools.manifest_writer import jpeg_file_state

    path = tmp_path_factory.getbasetemp() / NAME
    path.write_bytes(data)
    try:
        state = jpeg_file_state(path)
    except JsgsError as e:
        assert str(e).startswith(f"{path}: ") and "\n" not in str(e), str(e)
        event("outcome: JsgsError")
        return
    event("outcome: state")
    MANIFEST_JPEG_VALIDATOR.validate(state)
    json.dumps(state, allow_nan=False)
