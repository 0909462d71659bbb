"""Images every tool decodes the same way (``jsgs.base.images.read_rgb8``): 16-bit greyscale by value,
truncated files and images over the pixel limit as one line naming the file in validate, compress and train;
an unreadable compress.json and a camera that sees no point reported by validate."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from jsgs.base.errors import JsgsError
from jsgs.base.images import read_rgb8
from jsgstools.cli import main as tools


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_16_bit_grey_is_scaled_by_value(tmp_path: Path) -> None:
    a = (np.arange(48 * 64).reshape(48, 64) * 21).astype(np.uint16)
    Image.fromarray(a).save(tmp_path / "g16.png")
    assert Image.open(tmp_path / "g16.png").mode.startswith("I;16")
    got = read_rgb8(tmp_path / "g16.png")
    want = np.round(a.astype(np.float64) * 255.0 / 65535.0).astype(np.uint8)
    assert got.shape == (48, 64, 3) and (got == want[..., None]).all()
    assert got.max() < 255 and len(np.unique(got)) > 100  # Pillow's convert("RGB") would make it all white


def _first_image(scene: Path) -> Path:
    return sorted((scene / "images").iterdir())[0]


def test_16_bit_scene_trains_and_compresses_like_its_8_bit_values(synth_scene: Path, tmp_path: Path) -> None:
    from jsgstools.compress import compress

    scene = _copy(synth_scene, tmp_path / "s")
    img = _first_image(scene)
    grey8 = np.asarray(Image.open(img).convert("L")).astype(np.uint16)
    Image.fromarray(grey8 * 257).save(img)  # the same grey values, 16 bits
    r = CliRunner().invoke(tools, ["validate", str(scene)])
    assert r.exit_code == 0, r.output
    compress(scene, tmp_path / "c", "clean", jobs=1)
    ref = np.asarray(Image.open(tmp_path / "c" / "reference" / f"{img.stem}.png").convert("RGB"))
    assert (ref == grey8.astype(np.uint8)[..., None]).all()


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def test_truncated_image_is_one_line_everywhere(synth_scene: Path, tmp_path: Path) -> None:
    from jsgs.cli import main as jsgs_main

    scene = _copy(synth_scene, tmp_path / "s")
    img = _first_image(scene)
    _truncate(img)
    r = CliRunner().invoke(tools, ["validate", str(scene)])
    assert r.exit_code == 1 and f"{img.name}: cannot decode image" in r.output, r.output
    args = ["compress", str(scene), "--out", str(tmp_path / "c"), "--schedule", "uniform", "--jobs", "1"]
    r = CliRunner().invoke(tools, args)
    assert r.exit_code == 1 and "Traceback" not in r.output and str(img) in r.output, r.output
    assert not (tmp_path / "c" / "manifest.json").exists()
    # the trainer: a manifest of the scene as it is (PNG training views), the bad one named
    r = CliRunner().invoke(tools, ["manifest", str(scene), "--out", str(tmp_path / "m.json")])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(jsgs_main, ["train", str(tmp_path / "m.json"), "--out", str(tmp_path / "run"),
                                       "--iterations", "2", "--device", "cpu", "--quiet"])  # fmt: skip
    assert r.exit_code == 1 and "cannot decode" in r.output and str(img.name) in r.output, r.output
    assert r.output.strip().count("\n") == 0 and "Traceback" not in r.output


def test_pixel_limit_is_a_setting(synth_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from PIL import Image as PILImage

    monkeypatch.setattr(PILImage, "MAX_IMAGE_PIXELS", PILImage.MAX_IMAGE_PIXELS)  # restored after the test
    img = _first_image(synth_scene)
    monkeypatch.setenv("JSGS_MAX_IMAGE_PIXELS", "100")
    with pytest.raises(JsgsError, match=r"exceeds the pixel limit .*JSGS_MAX_IMAGE_PIXELS"):
        read_rgb8(img)
    r = CliRunner().invoke(tools, ["validate", str(synth_scene)])
    assert r.exit_code == 1 and "exceeds the pixel limit" in r.output
    monkeypatch.setenv("JSGS_MAX_IMAGE_PIXELS", "lots")
    with pytest.raises(JsgsError, match="JSGS_MAX_IMAGE_PIXELS='lots': must be a positive whole number"):
        read_rgb8(img)
    monkeypatch.setenv("JSGS_MAX_IMAGE_PIXELS", "100000000")
    assert read_rgb8(img).ndim == 3


def test_validate_reports_a_broken_record_and_a_blind_camera(compressed_scene: Path, tmp_path: Path) -> None:
    import pycolmap

    scene = _copy(compressed_scene, tmp_path / "s")
    (scene / "compress.json").write_text("{not json")
    r = CliRunner().invoke(tools, ["validate", str(scene)])
    assert r.exit_code == 1 and "compress.json: unreadable" in r.output
    (scene / "compress.json").write_text((compressed_scene / "compress.json").read_text())
    model = scene / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    im = next(iter(rec.images.values()))
    frame = rec.frames[im.frame_id]
    # move every point 1000 units behind the camera (the synthetic room surrounds its cameras)
    identity = pycolmap.Rotation3d(np.array([0.0, 0.0, 0.0, 1.0]))
    back = pycolmap.Rigid3d(identity, np.array([0.0, 0.0, -1000.0]))
    frame.rig_from_world = back * frame.rig_from_world
    rec.write_binary(str(model))
    r = CliRunner().invoke(tools, ["validate", str(scene)])
    assert "sees none of the" in r.output, r.output
    assert json.loads((scene / "compress.json").read_text())["settings"]
