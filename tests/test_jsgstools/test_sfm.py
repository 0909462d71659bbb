"""Real photo collections in: ``jsgstools sfm`` on camera-like JPEGs (non-IJG tables, EXIF) made from a shared
capture, photos kept byte for byte, then validate, manifest and a short JSGS training evaluated against the
JPEGs; validate naming photos the model left out, other models, EXIF orientations; one-line errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner
from conftest import SHARED
from PIL import Image

from jsgs.base.errors import JsgsError
from jsgstools.cli import main as tools

CUP = SHARED / "scenes" / "custom_kwrous_cup" / "images"
#: camera-like quantization tables (a ramp, not IJG's at any quality)
LUMA = [min(255, 2 + (i // 8 + i % 8)) for i in range(64)]
CHROMA = [min(255, 3 + 2 * (i // 8 + i % 8)) for i in range(64)]


#: the cup's focal length in pixels at the shared images' size (its COLMAP cameras: about 590 at 800×600)
CUP_FOCAL = 295.0


def _distort(im: Image.Image, k1: float) -> Image.Image:
    """``im`` as a lens with SIMPLE_RADIAL distortion ``k1`` (focal CUP_FOCAL, centred) would have seen it:
    each output pixel samples the undistorted image where OpenCV's undistortion of its position falls."""
    import cv2
    import numpy as np

    a = np.asarray(im)
    h, w = a.shape[:2]
    K = np.array([[CUP_FOCAL, 0, w / 2], [0, CUP_FOCAL, h / 2], [0, 0, 1.0]])
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    pix = np.stack([xs.ravel(), ys.ravel()], 1)[:, None, :]
    src = cv2.undistortPoints(pix, K, np.array([k1, 0.0, 0.0, 0.0]), P=K).reshape(h, w, 2)
    out = cv2.remap(a, src[..., 0], src[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return Image.fromarray(out)


def _photos(dst: Path, n: int = 12, orientation: int = 1, k1: float = 0.0) -> Path:
    dst.mkdir(parents=True)
    for i in range(1, n + 1):
        im = Image.open(CUP / f"{i}.png").convert("RGB")
        if k1:
            im = _distort(im, k1)
        exif = Image.Exif()
        exif[0x010F] = "JSGS test camera"
        exif[0x0112] = orientation
        im.save(dst / f"{i}.jpg", qtables=[LUMA, CHROMA], exif=exif.tobytes(), subsampling=2)
    return dst


@pytest.fixture(scope="module")
def jpeg_scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    if not CUP.is_dir():
        pytest.skip("../shared/scenes/custom_kwrous_cup is absent")
    root = tmp_path_factory.mktemp("sfm")
    photos = _photos(root / "photos")
    r = CliRunner().invoke(tools, ["sfm", str(photos), "--out", str(root / "scene")])
    assert r.exit_code == 0, r.output
    return photos, root / "scene"


def test_sfm_keeps_the_photos_and_registers_them(jpeg_scene: tuple[Path, Path]) -> None:
    from jsgs.base.schema import validate

    photos, scene = jpeg_scene
    for p in photos.iterdir():
        assert (scene / "images" / p.name).read_bytes() == p.read_bytes()  # never re-encoded
    rec = json.loads((scene / "sfm.json").read_text())
    validate(rec, "sfm", "sfm.json")
    assert rec["photos"] == 12 and rec["registered"] >= 11 and rec["settings"]["single_camera"] is True
    assert set(rec["seconds"]) == {"features", "matching", "mapping"} and rec["points3D"] > 50


def test_jpeg_only_scene_end_to_end(jpeg_scene: tuple[Path, Path], tmp_path: Path) -> None:
    from jsgs.cli import main as jsgs_main

    _, scene = jpeg_scene
    r = CliRunner().invoke(tools, ["validate", str(scene), "--test-every", "4"])
    assert r.exit_code == 0 and "test views are JPEGs with no lossless copy" in r.output, r.output
    man = tmp_path / "manifest.json"
    r = CliRunner().invoke(tools, ["manifest", str(scene), "--out", str(man), "--test-every", "4"])
    assert r.exit_code == 0, r.output
    doc = json.loads(man.read_text())
    assert all(v["jpeg"] is not None and v["reference"] is None for v in doc["views"])
    assert not doc["views"][0]["jpeg"]["quality_exact"]  # the camera-like tables went through as they are
    assert doc["views"][0]["jpeg"]["luma_table"][0][:3] == LUMA[:3]
    args = ["train", str(man), "--out", str(tmp_path / "run"), "--method", "jsgs", "--iterations", "30",
            "--eval-at", "30", "--device", "cpu", "--quiet"]  # fmt: skip
    r = CliRunner().invoke(jsgs_main, args)
    assert r.exit_code == 0 and "test views against their JPEGs" in r.output, r.output
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["reference"] == "jpeg" and metrics["evals"][0]["psnr"] > 0
    # --test-every 0: every view trains
    args = ["manifest", str(scene), "--out", str(tmp_path / "a.json"), "--test-every", "0"]
    r = CliRunner().invoke(tools, args)
    assert r.exit_code == 0, r.output
    assert all(v["split"] == "train" for v in json.loads((tmp_path / "a.json").read_text())["views"])


def test_validate_names_what_the_model_leaves_out(jpeg_scene: tuple[Path, Path], tmp_path: Path) -> None:
    _, scene = jpeg_scene
    copy = tmp_path / "s"
    shutil.copytree(scene, copy)
    shutil.copy(copy / "images" / "1.jpg", copy / "images" / "extra.jpg")
    shutil.copytree(copy / "sparse" / "0", copy / "sparse" / "1")
    r = CliRunner().invoke(tools, ["validate", str(copy)])
    assert r.exit_code == 0, r.output
    assert "1 image file(s) not in the model" in r.output and "extra.jpg" in r.output
    assert "sparse/1: another COLMAP model" in r.output


def test_exif_orientation_is_reported(jpeg_scene: tuple[Path, Path], tmp_path: Path) -> None:
    _, scene = jpeg_scene
    copy = tmp_path / "s"
    shutil.copytree(scene, copy)
    p = copy / "images" / "2.jpg"
    im = Image.open(p)
    exif = im.getexif()
    exif[0x0112] = 6
    im.save(p, qtables=[LUMA, CHROMA], exif=exif.tobytes(), subsampling=2)
    r = CliRunner().invoke(tools, ["validate", str(copy)])
    assert r.exit_code == 0 and "EXIF Orientation other than 1: 2.jpg (6)" in r.output, r.output
    r = CliRunner().invoke(tools, ["manifest", str(copy), "--out", str(tmp_path / "m.json")])
    assert r.exit_code == 0 and "EXIF Orientation" in r.output
    # the pixels stored turned: the size error says a rotation would explain it
    im.transpose(Image.Transpose.ROTATE_90).save(p, qtables=[LUMA, CHROMA], exif=exif.tobytes())
    r = CliRunner().invoke(tools, ["validate", str(copy)])
    assert r.exit_code == 1 and "rotated by 90° it would match" in r.output, r.output


def test_sfm_bad_input(tmp_path: Path) -> None:
    from jsgstools.sfm import sfm

    (tmp_path / "one").mkdir()
    Image.new("RGB", (8, 8)).save(tmp_path / "one" / "a.jpg")
    with pytest.raises(JsgsError, match="1 photo"):
        sfm(tmp_path / "one", tmp_path / "out")
    r = CliRunner().invoke(tools, ["sfm", str(tmp_path / "none"), "--out", str(tmp_path / "o2")])
    assert r.exit_code != 0 and "Traceback" not in r.output


def test_distorted_camera_trains_on_the_photos_grid(jpeg_scene: tuple[Path, Path], tmp_path: Path) -> None:
    """Photos taken through a lens with barrel distortion: ``sfm --camera-model SIMPLE_RADIAL`` finds it (the
    photos stay as they are), validate and the manifest record it, and a short JSGS run renders through it."""
    from jsgs.cli import main as jsgs_main

    def k_of(photos: Path, scene: Path) -> float:
        args = ["sfm", str(photos), "--out", str(scene), "--camera-model", "SIMPLE_RADIAL"]
        r = CliRunner().invoke(tools, args)
        assert r.exit_code == 0, r.output
        r = CliRunner().invoke(tools, ["validate", str(scene)])
        assert r.exit_code == 0 and "SIMPLE_RADIAL" in r.output, r.output
        man = scene.parent / f"{scene.name}.json"
        r = CliRunner().invoke(tools, ["manifest", str(scene), "--out", str(man), "--test-every", "4"])
        assert r.exit_code == 0 and "distorted cameras" in r.output, r.output
        views = json.loads(man.read_text())["views"]
        assert all(v["camera"]["distortion"]["model"] == "SIMPLE_RADIAL" for v in views)
        return float(views[0]["camera"]["distortion"]["params"][0])

    plain, _ = jpeg_scene
    bent = _photos(tmp_path / "bent", k1=-0.1)
    k_plain, k_bent = k_of(plain, tmp_path / "plain"), k_of(bent, tmp_path / "scene")
    # the shared cup's own images were undistorted; with 12 photos SfM trades some focal length for k1, so
    # the distortion added is compared with what SfM finds without it (about -0.035 here)
    assert -0.15 < k_bent - k_plain < -0.05 and k_bent < -0.08, (k_bent, k_plain)
    args = ["train", str(tmp_path / "scene.json"), "--out", str(tmp_path / "run"), "--method", "jsgs",
            "--iterations", "30", "--eval-at", "30", "--device", "cpu", "--quiet"]  # fmt: skip
    r = CliRunner().invoke(jsgs_main, args)
    assert r.exit_code == 0, r.output
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["reference"] == "jpeg" and metrics["evals"][0]["psnr"] > 0
