"""``jsgstools synth``: layout, exact geometry (points3D lie where the images show them), determinism, CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from jsgs.base.camera import Camera
from jsgs.base.errors import JsgsError
from jsgstools.cli import main
from jsgstools.synth import cast, default_scene, look_at, parse_size, pixel_rays, synth


def test_layout(synth_scene: Path) -> None:
    import pycolmap

    names = sorted(p.name for p in (synth_scene / "images").iterdir())
    assert names == [f"view_{i:03d}.png" for i in range(12)]
    for n in names:
        with Image.open(synth_scene / "images" / n) as im:
            assert (im.format, im.mode, im.size) == ("PNG", "RGB", (64, 48))
    rec = pycolmap.Reconstruction(str(synth_scene / "sparse" / "0"))
    assert {p.name for p in (synth_scene / "sparse" / "0").iterdir()} >= {
        "cameras.bin",
        "images.bin",
        "points3D.bin",
    }
    assert rec.num_reg_images() == 12 and rec.num_cameras() == 1
    cam = rec.cameras[1]
    assert cam.model_name == "PINHOLE" and (cam.width, cam.height) == (64, 48)
    assert np.allclose(cam.params, [0.85 * 64, 0.85 * 64, 32, 24])
    assert rec.num_points3D() > 1000
    assert not [p for p in synth_scene.rglob("*") if ".part" in p.name]


def test_geometry_is_exact(synth_scene: Path) -> None:
    """Project points3D with pycolmap; the ray through that image point (this module's pixel convention) hits
    the very same point when it is visible, and its colour is the point's colour."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(synth_scene / "sparse" / "0"))
    c = rec.cameras[1]
    cam = Camera("PINHOLE", c.width, c.height, *c.params)
    boxes = default_scene(np.random.default_rng(0))
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    rgb = np.array([p.color for p in rec.points3D.values()])
    for iid in (1, 6, 11):
        pose = rec.images[iid].cam_from_world()
        R, t = pose.rotation.matrix(), pose.translation
        xc = xyz @ R.T + t
        front = xc[:, 2] > 0
        uv = c.img_from_cam(xc[front])
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
        origin, dirs = pixel_rays(cam, R, t, uv[inside])
        hit, colour, _ = cast(boxes, origin, dirs)
        visible = np.linalg.norm(hit - xyz[front][inside], axis=1) < 1e-6
        assert visible.mean() > 0.25  # the rest are behind a box, or on a wall behind the camera's view
        assert np.array_equal(np.clip(np.round(colour[visible] * 255), 0, 255), rgb[front][inside][visible])


def test_look_at_convention() -> None:
    R, t = look_at(np.array([0.0, -3.0, 0.0]), np.zeros(3))
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(R @ np.zeros(3) + t, [0, 0, 3])  # the target is straight ahead (z forward)
    assert (R @ np.array([0, 0, 1.0]))[1] < 0  # world up is image up (y down)


def test_deterministic(tmp_path: Path) -> None:
    a = synth(tmp_path / "a", views=4, size=(40, 30), seed=5)
    b = synth(tmp_path / "b", views=4, size=(40, 30), seed=5)
    synth(tmp_path / "c", views=4, size=(40, 30), seed=6)
    assert a.points == b.points
    for n in ("view_000.png", "view_003.png"):
        assert (tmp_path / "a/images" / n).read_bytes() == (tmp_path / "b/images" / n).read_bytes()
        assert (tmp_path / "a/images" / n).read_bytes() != (tmp_path / "c/images" / n).read_bytes()
    for f in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (tmp_path / "a/sparse/0" / f).read_bytes() == (tmp_path / "b/sparse/0" / f).read_bytes()


def _high_band_share(png: Path) -> float:
    """Median over the 8x8 blocks of the share of DCT magnitude in the high band (u, v >= 4)."""
    import cv2

    img = np.asarray(Image.open(png).convert("L"), dtype=np.float32)
    h, w = img.shape
    hi = []
    for y in range(0, h - h % 8, 8):
        for x in range(0, w - w % 8, 8):
            d = np.abs(cv2.dct(img[y : y + 8, x : x + 8] - 128))
            hi.append(d[4:, 4:].sum() / (d.sum() + 1e-6))
    return float(np.median(hi))


def test_high_frequency_content_and_texture_scale(synth_scene: Path, tmp_path: Path) -> None:
    """The default textures put energy where JPEG quantizes hardest (many 8x8 blocks with strong high-band
    DCT terms); ``texture_scale`` 8 makes every period 8x longer, and the high-band share falls to well under
    half of it in the same view."""
    default = _high_band_share(synth_scene / "images" / "view_000.png")
    synth(tmp_path / "coarse", views=12, size=(64, 48), seed=0, texture_scale=8.0)
    coarse = _high_band_share(tmp_path / "coarse" / "images" / "view_000.png")
    assert default > 0.05
    assert coarse < 0.5 * default, (coarse, default)
    with pytest.raises(JsgsError, match="--texture-scale 0.01: must be within 0.1..100"):
        synth(tmp_path / "bad", views=2, size=(16, 12), texture_scale=0.01)


def test_refuses_and_validates_arguments(tmp_path: Path) -> None:
    synth(tmp_path / "s", views=2, size=(16, 12))
    with pytest.raises(JsgsError, match="not empty"):
        synth(tmp_path / "s", views=2, size=(16, 12))
    synth(tmp_path / "s", views=3, size=(16, 12), force=True)
    assert len(list((tmp_path / "s" / "images").iterdir())) == 3  # --force leaves no stale views
    with pytest.raises(JsgsError, match="--views 1"):
        synth(tmp_path / "t", views=1)
    for bad in ("160", "ax b", "4x4", "160x120x3"):
        with pytest.raises(JsgsError, match="--size"):
            parse_size(bad)
    assert parse_size("160x120") == (160, 120)


def test_cli(tmp_path: Path) -> None:
    r = CliRunner().invoke(main, ["synth", str(tmp_path / "s"), "--views", "3", "--size", "32x24"])
    assert r.exit_code == 0, r.output
    assert "synth: 3 views of 32x24 (PINHOLE fx=27.2 cx=16 cy=12)" in r.output
    r = CliRunner().invoke(main, ["synth", str(tmp_path / "s"), "--views", "3", "--size", "32x24"])
    assert r.exit_code == 1 and "error:" in r.output and "--force" in r.output
    r = CliRunner().invoke(main, ["synth", str(tmp_path / "u"), "--size", "big"])
    assert r.exit_code == 1 and "error: --size 'big'" in r.output
