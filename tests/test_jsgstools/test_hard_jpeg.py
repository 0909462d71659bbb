"""Hard JPEG inputs through dataset preparation: a 12-bit JPEG named as such in one line by every tool that
reads it."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from jsgs.base.errors import JsgsError
from jsgs.base.images import read_rgb8
from jsgstools.cli import main as tools
from jsgstools.dqt import parse_header


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
