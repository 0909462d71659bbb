"""benchmarks/bench_double_jpeg.py --write: the corpus's JPEGs and labels.json (schema
jsgs/schemas/double_jpeg_corpus.schema.json), each label what the file holds; a label that is not valid is
refused in one line naming labels.json, nothing written."""

from __future__ import annotations

import io
import json
import os
from pathlib import Path

import numpy as np
import pytest
from conftest import load_benchmark
from PIL import Image, JpegImagePlugin

from jsgs.base.errors import JsgsError
from jsgs.base.schema import validate

_env = dict(os.environ)
bdj = load_benchmark("bench_double_jpeg")
os.environ.clear()
os.environ.update(_env)  # its thread settings are for its own runs, not for this session's subprocesses


def _items() -> list:
    """A single compression in each subsampling, a double one and a camera-like original, of a 40x24 image."""
    rgb = Image.fromarray(np.random.default_rng(0).integers(0, 256, (24, 40, 3), dtype=np.uint8))
    once = Image.open(io.BytesIO(bdj.jpeg(rgb, 30, 2))).convert("RGB")
    return [
        bdj.Item("s/v0/420/q50", bdj.jpeg(rgb, 50, 2), "s", "4:2:0", None, 50, rgb.size),
        bdj.Item("s/v0/444/q90", bdj.jpeg(rgb, 90, 0), "s", "4:4:4", None, 90, rgb.size),
        bdj.Item("s/v0/420/q30-q60", bdj.jpeg(once, 60, 2), "s", "4:2:0", 30, 60, rgb.size),
        bdj.Item("camera/IMG_1.JPG", bdj.jpeg(rgb, 95, 2), "camera", "4:2:0", None, None, rgb.size),
    ]


def test_a_written_corpus_is_labelled_and_valid(tmp_path: Path) -> None:
    items = _items()
    bdj.write_corpus(items, tmp_path / "c", 1, "python benchmarks/bench_double_jpeg.py --write c")
    doc = json.loads((tmp_path / "c" / "labels.json").read_text())
    validate(doc, "double_jpeg_corpus", "labels.json")
    assert doc["format"] == bdj.CORPUS_FORMAT and doc["settings"]["per_scene"] == 1
    names = ["s_v0_420_q50.jpg", "s_v0_444_q90.jpg", "s_v0_420_q30-q60.jpg", "camera_IMG_1.JPG"]
    assert [f["file"] for f in doc["files"]] == names
    assert sorted(p.name for p in (tmp_path / "c").iterdir()) == sorted([*names, "labels.json"])
    sampling = {"4:2:0": 2, "4:4:4": 0}
    for it, label in zip(items, doc["files"], strict=True):
        path = tmp_path / "c" / label["file"]
        assert path.read_bytes() == it.data
        assert (label["q1"], label["q2"], label["scene"]) == (it.q1, it.q2, it.scene)
        with Image.open(path) as im:
            assert JpegImagePlugin.get_sampling(im) == sampling[label["subsampling"]]
            assert im.size == (label["width"], label["height"])


def test_a_label_that_is_not_valid_writes_nothing(tmp_path: Path) -> None:
    items = _items()
    items[1].q2 = 101
    with pytest.raises(JsgsError) as e:
        bdj.write_corpus(items, tmp_path / "c", 1)
    line, labels = str(e.value), tmp_path / "c" / "labels.json"
    assert line.startswith(f"{labels}: not a valid double_jpeg_corpus file: at files/1/q2")
    assert "\n" not in line and not (tmp_path / "c").exists()
