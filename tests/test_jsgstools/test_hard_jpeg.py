"""Hard JPEG inputs through dataset preparation: a 12-bit JPEG named as such in one line by every tool that
reads it; a view whose Cr has a table of its own recorded in the manifest and refused by JSGS; views whose
sizes are not multiples of 8 or 16 compressed, recorded in the manifest and reproduced bit for bit by the
observation operator from the manifest's JPEG state and the view's lossless reference; EXIF orientations 2-8
reported and ignored (the stored pixels everywhere); a file without its EOI named where it is decoded."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from jpeg_builders import own_cr_table
from PIL import Image

from jsgs.base.errors import JsgsError
from jsgs.base.images import read_rgb8
from jsgs.jpeg.observe import jpeg_observe
from jsgstools.cli import main as tools
from jsgstools.compress import SUBSAMPLING, compress
from jsgstools.dqt import parse_header
from jsgstools.synth import synth


def _twelve_bit(data: bytes) -> bytes:
    """``data`` (a baseline JPEG) with its frame header made SOF1 with 12-bit samples."""
    b = bytearray(data)
    sof = b.find(b"\xff\xc0")
    b[sof + 1], b[sof + 4] = 0xC1, 12
    return bytes(b)


def test_twelve_bit_jpeg_is_named_in_one_line(compressed_scene: Path, tmp_path: Path) -> None:
    scene = tmp_path / "s"
    shutil.copytree(compressed_scene, scene)
    img = scene / "images" / "view_001.jpg"
    img.write_bytes(_twelve_bit(img.read_bytes()))
    for args in (["validate", str(scene)], ["manifest", str(scene), "--out", str(tmp_path / "m.json")]):
        r = CliRunner().invoke(tools, args)
        assert r.exit_code == 1 and "Traceback" not in r.output, r.output
        line = next(x for x in r.output.splitlines() if "view_001.jpg" in x)
        assert "a 12-bit JPEG (extended, SOF1): Pillow decodes 8-bit JPEGs only" in line, r.output
        assert "_io." not in r.output
    assert not (tmp_path / "m.json").exists()
    # the header parser reads it; its manifest state is refused, naming the precision
    h = parse_header(img.read_bytes(), str(img))
    assert h.sample_precision == 12
    with pytest.raises(JsgsError, match=r"view_001.jpg: 12-bit samples \(extended JPEG, SOF1\)"):
        h.manifest_state()
    # the image reader (the trainer's) names the file, not Pillow's file object
    with pytest.raises(JsgsError, match=r"view_001.jpg: cannot decode image \(Pillow cannot identify") as e:
        read_rgb8(img)
    assert "_io." not in str(e.value)


@pytest.mark.parametrize("subsampling", sorted(SUBSAMPLING))
def test_odd_sizes_through_dataset_preparation_are_bit_exact(subsampling: str, tmp_path: Path) -> None:
    """37x23 views (neither side a multiple of 8 or 16) compressed at several qualities: the manifest's tables
    and sampling are the file's, and JO "exact" on the lossless reference reproduces Pillow's decode of each
    JPEG view bit for bit."""
    synth(tmp_path / "scene", views=6, size=(37, 23), seed=0)
    compress(tmp_path / "scene", tmp_path / "data", "gaussian", seed=0, jobs=1, subsampling=subsampling)
    doc = json.loads((tmp_path / "data" / "manifest.json").read_text())
    views = [v for v in doc["views"] if v["jpeg"] is not None]
    assert len(views) >= 4 and len({v["jpeg"]["quality"] for v in views}) >= 3
    for v in views:
        j = v["jpeg"]
        with Image.open(tmp_path / "data" / v["image"]) as im:
            decoded = np.asarray(im.convert("RGB"))
            assert np.array_equal(np.asarray(im.quantization[0]).reshape(8, 8), j["luma_table"])
        assert decoded.shape == (23, 37, 3) and j["sampling"] == SUBSAMPLING[subsampling][0]
        ref = np.asarray(Image.open(tmp_path / "data" / v["reference"]).convert("RGB"))
        x = torch.from_numpy(ref.copy()).permute(2, 0, 1)[None].float() / 255
        out = jpeg_observe(x, np.array(j["luma_table"]), np.array(j["chroma_table"]), j["sampling"], "exact")
        got = (out[0] * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
        assert np.array_equal(got, decoded), (v["name"], j["quality"])


def test_cr_table_of_its_own_is_recorded_and_refused(compressed_scene: Path, tmp_path: Path) -> None:
    from jsgs.cli import main as jsgs_main
    from jsgs.jpeg.tables import ijg_tables

    scene = tmp_path / "s"
    shutil.copytree(compressed_scene, scene)
    img = scene / "images" / "view_001.jpg"
    img.write_bytes(own_cr_table(img.read_bytes(), ijg_tables(5)[1].tolist()))
    r = CliRunner().invoke(tools, ["manifest", str(scene), "--out", str(tmp_path / "m.json")])
    assert r.exit_code == 0, r.output
    views = {v["name"]: v for v in json.loads((tmp_path / "m.json").read_text())["views"]}
    assert views["view_001.jpg"]["jpeg"]["cr_table"] == ijg_tables(5)[1].tolist()
    assert "cr_table" not in views["view_002.jpg"]["jpeg"]
    args = ["train", str(tmp_path / "m.json"), "--out", str(tmp_path / "run"), "--iterations", "1",
            "--device", "cpu", "--quiet"]
    r = CliRunner().invoke(jsgs_main, args)
    assert r.exit_code == 1 and "Traceback" not in r.output, r.output
    assert r.output.strip().count("\n") == 0
    assert "view 'view_001.jpg' quantizes Cr with a table of its own" in r.output, r.output
    # DS and GC work on JO's output (quantized with both chroma tables), so they need JO: without JO, DS or GC
    # nothing reads the chroma tables and the view trains
    bare = [*args[:3], str(tmp_path / "bare"), *args[4:], "--eval-at", "", "--no-jo"]
    r = CliRunner().invoke(jsgs_main, bare)
    assert r.exit_code == 1 and "need JO" in r.output and "view_001" not in r.output, r.output
    r = CliRunner().invoke(jsgs_main, [*bare, "--no-ds", "--no-gc"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "bare" / "point_cloud.ply").is_file()


def _with_orientation(jpeg: bytes, orientation: int) -> bytes:
    """``jpeg`` with an EXIF APP1 holding only ``Orientation`` inserted after SOI (pixels and the decoding
    header unchanged)."""
    exif = Image.Exif()
    exif[0x0112] = orientation
    payload = exif.tobytes()
    assert payload.startswith(b"Exif\x00\x00")
    return jpeg[:2] + b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload + jpeg[2:]


def test_exif_orientations_2_to_8_keep_the_stored_pixels(compressed_scene: Path, tmp_path: Path) -> None:
    """Every EXIF Orientation is reported (one warning line naming the photos) and ignored, as COLMAP does:
    the manifest's camera size and JPEG state are the stored image's, and the image the trainer reads is the
    stored pixels, not turned."""
    scene = tmp_path / "s"
    shutil.copytree(compressed_scene, scene)
    names = [f"view_00{k - 1}.jpg" for k in range(2, 9)]  # view_001 .. view_007: orientations 2 .. 8
    stored = {}
    for k, name in zip(range(2, 9), names, strict=True):
        p = scene / "images" / name
        stored[name] = read_rgb8(p)
        p.write_bytes(_with_orientation(p.read_bytes(), k))
        with Image.open(p) as im:
            assert im.getexif()[0x0112] == k
    r = CliRunner().invoke(tools, ["manifest", str(scene), "--out", str(tmp_path / "m.json")])
    assert r.exit_code == 0, r.output
    warning = next(x for x in r.output.splitlines() if "EXIF Orientation" in x)
    assert "7 photo(s) with an EXIF Orientation other than 1: view_001.jpg (2)" in warning, warning
    assert "view_004.jpg (5), view_005.jpg (6) ...;" in warning
    before = {v["name"]: v for v in json.loads((compressed_scene / "manifest.json").read_text())["views"]}
    for v in json.loads((tmp_path / "m.json").read_text())["views"]:
        if v["name"] in stored:
            assert v["camera"]["width"] == 64 and v["camera"]["height"] == 48  # not swapped by 5..8
            assert v["jpeg"] == before[v["name"]]["jpeg"]  # APP1 is not part of the decoding header
            assert np.array_equal(read_rgb8(tmp_path / v["image"]), stored[v["name"]])


def test_missing_eoi_is_one_line_where_pixels_are_decoded(compressed_scene: Path, tmp_path: Path) -> None:
    """A JPEG whose last two bytes (EOI) are cut: the header parser and the manifest (header only) take it;
    validate and the trainer, which decode it, name the file in one line (Pillow: truncated)."""
    from jsgs.cli import main as jsgs_main

    scene = tmp_path / "s"
    shutil.copytree(compressed_scene, scene)
    img = scene / "images" / "view_001.jpg"
    img.write_bytes(img.read_bytes()[:-2])
    assert parse_header(img.read_bytes(), str(img)).quality is not None
    r = CliRunner().invoke(tools, ["validate", str(scene)])
    assert r.exit_code == 1 and f"{img}: cannot decode image (image file is truncated" in r.output, r.output
    r = CliRunner().invoke(tools, ["manifest", str(scene), "--out", str(tmp_path / "m.json")])
    assert r.exit_code == 0, r.output
    args = ["train", str(tmp_path / "m.json"), "--out", str(tmp_path / "run"), "--iterations", "1",
            "--device", "cpu", "--quiet"]
    r = CliRunner().invoke(jsgs_main, args)
    assert r.exit_code == 1 and "Traceback" not in r.output and r.output.strip().count("\n") == 0, r.output
    assert f"{img}: cannot decode training image of view 'view_001.jpg' (image file is truncated" in r.output


def _two_components(jpeg: bytes) -> bytes:
    """A 4:4:4 Pillow JPEG's header with its third component dropped from the frame and the scan (a
    two-component file: the header parser reads it, Pillow does not)."""
    d = bytearray(jpeg)
    sof = d.find(b"\xff\xc0")
    d[sof + 3], d[sof + 9] = 14, 2
    del d[sof + 16 : sof + 19]
    sos = d.find(b"\xff\xda")
    d[sos + 3], d[sos + 4] = 10, 2
    del d[sos + 9 : sos + 11]
    return bytes(d)


def _segment(data: bytes, code: int) -> tuple[int, int]:
    """(offset, length field) of the first segment with marker ``code``."""
    at = data.find(bytes([0xFF, code]))
    return at, int.from_bytes(data[at + 2 : at + 4], "big")


def test_jpegs_pillow_cannot_open_are_explained(tmp_path: Path) -> None:
    from jsgstools.scene import _probe_image

    img = tmp_path / "two.jpg"
    buf = io.BytesIO()
    Image.fromarray(np.full((16, 16, 3), 90, np.uint8)).save(buf, "JPEG", quality=70, subsampling=0)
    img.write_bytes(_two_components(buf.getvalue()))
    assert [c.name for c in parse_header(img.read_bytes(), str(img)).components] == ["C1", "C2"]
    assert _probe_image(img)[2] == "cannot read image: a JPEG with 2 components: Pillow decodes 1, 3 or 4"
    data = bytearray(img.read_bytes())
    data[data.find(b"\xff\xda") + 5] = 9  # the scan names a component the frame lacks: the parser's message
    img.write_bytes(bytes(data))
    why = _probe_image(img)[2]
    assert why is not None and why.startswith("cannot read image: a damaged JPEG: the first scan (SOS at")
    assert why.endswith("names component id 9, which is not in the frame")
    # a header cut short (Pillow: "Truncated File Read") and one without a frame header, in the parser's words
    img.write_bytes(buf.getvalue()[:300])
    assert _probe_image(img)[2] == (
        "cannot read image: a damaged JPEG: truncated file: it ends inside the DHT segment at offset 210 "
        "(the segment needs 179 bytes, 86 are left)"
    )
    data = buf.getvalue()
    sof, _ = _segment(data, 0xC0)
    img.write_bytes(data[:sof] + data[sof + 2 + int.from_bytes(data[sof + 2 : sof + 4], "big") :])
    why = _probe_image(img)[2]
    assert why is not None and why.startswith("cannot read image: a damaged JPEG: start of scan (SOS) at")


def test_jsgs_trains_440_and_411_views(compressed_scene: Path, tmp_path: Path) -> None:
    """Views recorded as 4:4:0 / 4:1:1 (files Pillow cannot write; the manifest's sampling set by hand, the
    files' headers unchanged) train with JO, DS and GC: a complete run whose final evaluation's training
    terms are finite and hold L_obs, L_low, L_mid and L_fro; the same first step's L_obs under the two
    samplings differs (JO codes each view at the manifest's sampling) where its photometric term agrees."""
    import math

    from jsgs.cli import main as jsgs_main

    settings = tmp_path / "settings.json"  # one evaluation at the end, no FPS passes nor renders beyond it
    settings.write_text(json.dumps({"eval": {"fps_passes": 1, "fps_warmup": 0, "save_renders": False}}))
    first_step = {}
    for sampling in ("4:4:0", "4:1:1"):
        doc = json.loads((compressed_scene / "manifest.json").read_text())
        for v in doc["views"]:
            for key in ("image", "reference"):
                if v.get(key):
                    v[key] = str(compressed_scene / v[key])
            if v["jpeg"] is not None:
                v["jpeg"]["sampling"] = sampling
        manifest = tmp_path / f"m{sampling[-1]}.json"
        manifest.write_text(json.dumps(doc))
        run = tmp_path / f"run{sampling[-1]}"
        args = ["train", str(manifest), "--out", str(run), "--iterations", "2", "--device", "cpu",
                "--quiet", "--method", "jsgs", "--config", str(settings)]  # fmt: skip
        r = CliRunner().invoke(jsgs_main, args)
        assert r.exit_code == 0, r.output
        metrics = json.loads((run / "metrics.json").read_text())
        assert metrics["status"] == "complete"
        train = metrics["evals"][-1]["train"]
        assert train["steps"] == 2 and {"obs", "low", "mid", "fro"} <= train["terms"].keys()
        assert all(math.isfinite(t) for t in (train["loss"], *train["terms"].values()))
        # the first step's view: GC runs on step 0 of every gc_every (4), so on it alone of the two
        first_step[sampling] = next(v["terms"] for v in train["per_view"].values() if "fro" in v["terms"])
    a, b = first_step.values()
    assert a["photometric"] == b["photometric"] and a["obs"] != b["obs"]
