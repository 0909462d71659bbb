"""benchmarks/bench_double_jpeg.py --write: the corpus's JPEGs and labels.json (schema
jsgs/schemas/double_jpeg_corpus.schema.json), each label what the file holds; a label that is not valid is
refused in one line naming labels.json, nothing written."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
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


def _one_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    (line,) = err.splitlines()
    assert line.startswith("error: ") and "Traceback" not in err
    return line


def test_the_command_refuses_bad_input_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A label failing its schema, an --md that cannot be written (a folder, or under a file) and a
    --per-scene below 1: one line and exit code 1, no traceback; nothing written."""
    items = _items()
    items[1].q2 = 101
    monkeypatch.setattr(bdj, "corpus", lambda per_scene: items)
    out = tmp_path / "c"
    assert bdj.main(["--per-scene", "1", "--write", str(out)]) == 1
    assert f"{out / 'labels.json'}: not a valid double_jpeg_corpus file: at files/1/q2" in _one_error(capsys)
    assert not out.exists()
    (tmp_path / "file").write_text("mine")
    assert bdj.main(["--md", str(tmp_path / "file" / "sub" / "r.md")]) == 1
    assert _one_error(capsys) == f"error: {tmp_path / 'file' / 'sub' / 'r.md'}: cannot be written: " + (
        f"{tmp_path / 'file'} is not a folder")  # fmt: skip
    assert bdj.main(["--md", str(tmp_path)]) == 1
    assert _one_error(capsys) == f"error: {tmp_path}: is a folder; --md takes a file name"
    assert bdj.main(["--per-scene", "0"]) == 1
    assert "--per-scene: at least 1" in _one_error(capsys)
    assert (tmp_path / "file").read_text() == "mine"


def test_write_goes_only_into_a_folder_of_its_own(tmp_path: Path) -> None:
    """--write DIR: a folder holding anything but a corpus of this tool is refused and left as it is (a file
    of the same name as a corpus file included); a corpus it wrote is replaced whole, files the new one
    lacks removed; a folder another writer holds (its output lock) is refused."""
    from jsgs.base.io import LOCK_NAME

    items = _items()
    out = tmp_path / "c"
    out.mkdir()
    (out / "s_v0_420_q50.jpg").write_bytes(b"not ours")
    with pytest.raises(JsgsError, match=r"not empty and not a corpus of this tool \(.*json: is missing"):
        bdj.write_corpus(items, out, 1)
    assert [p.name for p in out.iterdir()] == ["s_v0_420_q50.jpg"]
    assert (out / "s_v0_420_q50.jpg").read_bytes() == b"not ours"
    (out / "s_v0_420_q50.jpg").unlink()
    bdj.write_corpus(items, out, 1)  # an empty folder
    (out / "notes.txt").write_text("mine")
    with pytest.raises(JsgsError, match="holds notes.txt, not part of the corpus its labels.json lists"):
        bdj.write_corpus(items, out, 1)
    assert (out / "notes.txt").read_text() == "mine" and (out / "labels.json").exists()
    (out / "notes.txt").unlink()
    bdj.write_corpus(items[:2], out, 1)  # its own corpus: replaced whole
    labels = json.loads((out / "labels.json").read_text())
    listed = [f["file"] for f in labels["files"]]
    assert sorted(p.name for p in out.iterdir()) == sorted(["labels.json", *listed])
    assert len(labels["files"]) == 2
    other = tmp_path / "held"
    code = (f"from jsgs.base.io import OutputLock; lock = OutputLock({str(other)!r}, 'another writer'); "
            "print('held', flush=True); input(); lock.release()")  # fmt: skip
    holder = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True)  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        with pytest.raises(JsgsError, match="in use by another writer"):
            bdj.write_corpus(items, other, 1)
        assert [p.name for p in other.iterdir()] == [LOCK_NAME]
    finally:
        holder.communicate("\n", timeout=60)
