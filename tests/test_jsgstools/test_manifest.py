"""Manifests: writing (``jsgstools manifest``, and by ``compress``), reading
(``jsgs.base.manifest.load_manifest``),
the round trip, relative paths, distortion recorded for a user's JPEG collection, and a bad document written.
The reader alone (bad manifests, its imports, its point check) is tested in
``tests/test_jsgs/base/test_manifest_reader.py``."""

from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from jsgs.base.errors import JsgsError
from jsgs.base.manifest import load_manifest
from jsgs.jpeg.header_digest import header_digest
from jsgstools.cli import main
from jsgstools.manifest_writer import build_manifest, manifest, write_manifest

ROOT = Path(__file__).resolve().parents[2]


def test_round_trip_of_a_compressed_scene(compressed_scene: Path) -> None:
    import pycolmap

    from jsgstools.dqt import read_header

    m = load_manifest(compressed_scene / "manifest.json")
    rec = pycolmap.Reconstruction(str(compressed_scene / "sparse" / "0"))
    record = json.loads((compressed_scene / "compress.json").read_text())
    assert m.scene.schedule == "gaussian" and m.scene.seed == 0 and m.scene.test_every == 8
    assert m.scene.subsampling == "4:2:0" and m.scene.downscale is None and not m.scene.undistorted
    assert m.producer["tool"] == "jsgstools compress"
    assert [v.name for v in m.views] == sorted(im.name for im in rec.images.values())
    assert len(m.train_views) == 10 and len(m.test_views) == 2
    by_name = {im.name: im for im in rec.images.values()}
    quality = {v["name"]: v["quality"] for v in record["views"]}
    for v in m.views:
        im = by_name[v.name]
        pose = im.cam_from_world()
        assert np.allclose(v.R, pose.rotation.matrix()) and np.allclose(v.t, pose.translation)
        assert np.allclose(v.world_to_camera[:3, :3], v.R)
        assert np.allclose(v.camera_center, im.projection_center())
        assert np.allclose(v.camera.K, rec.cameras[im.camera_id].calibration_matrix())
        assert v.image.is_file() and v.image.parent == compressed_scene / "images"
        assert v.reference == compressed_scene / "reference" / (Path(v.name).stem + ".png")
        if v.split == "test":
            assert v.jpeg is None and v.image.suffix == ".png"
        else:
            assert v.jpeg is not None and v.jpeg.quality == quality[v.name]
            assert v.jpeg.luma_table.shape == (8, 8) and v.jpeg.chroma_table is not None
            state = read_header(v.image).manifest_state()
            assert np.array_equal(v.jpeg.luma_table, state["luma_table"])
            assert np.array_equal(v.jpeg.chroma_table, state["chroma_table"])
            assert v.jpeg.header_sha256 == header_digest(v.image)
    xyz = np.array([rec.points3D[p].xyz for p in sorted(rec.points3D)])
    rgb = np.array([rec.points3D[p].color for p in sorted(rec.points3D)])
    assert np.array_equal(m.points_xyz, xyz) and np.array_equal(m.points_rgb, rgb)
    assert m.points_rgb.dtype == np.uint8 and m.points_xyz.dtype == np.float64


def test_manifest_command_reproduces_compress(compressed_scene: Path, tmp_path: Path) -> None:
    out = tmp_path / "m.json"
    doc = manifest(compressed_scene, out)
    ref = json.loads((compressed_scene / "manifest.json").read_text())
    assert doc["scene"] == ref["scene"] and doc["points"] == ref["points"]
    # the same views, with paths relative to the new manifest's folder
    for a, b in zip(doc["views"], ref["views"], strict=True):
        assert (out.parent / a["image"]).resolve() == (compressed_scene / b["image"]).resolve()
        assert {k: v for k, v in a.items() if k not in ("image", "reference")} == {
            k: v for k, v in b.items() if k not in ("image", "reference")
        }
    assert doc["producer"]["tool"] == "jsgstools manifest"
    assert doc["producer"]["settings"]["compress"]["schedule"] == "gaussian"
    assert (
        load_manifest(out).views[1].image.resolve() == (compressed_scene / ref["views"][1]["image"]).resolve()
    )
    # the split of a compressed scene is fixed
    with pytest.raises(JsgsError, match="compressed with --test-every 8"):
        build_manifest(compressed_scene, tmp_path / "x.json", test_every=4)


def _jpeg_collection(tmp_path: Path) -> Path:
    """A user's own capture: JPEG photos (q=85), a distorted SIMPLE_RADIAL camera at twice the photo size,
    model names ending in .png while the files end in .jpg."""
    from jsgstools.synth import synth

    scene = tmp_path / "mine"
    synth(scene, views=5, size=(48, 36), k1=0.03, camera_scale=2)
    for p in sorted((scene / "images").glob("*.png")):
        Image.open(p).save(p.with_suffix(".jpg"), quality=85)
        p.unlink()
    return scene


def test_users_jpeg_collection_keeps_its_distortion(tmp_path: Path) -> None:
    scene = _jpeg_collection(tmp_path)
    (scene / "reference").mkdir()
    shutil.copy(scene / "images" / "view_001.jpg", scene / "reference" / "view_001.png")  # a "reference" file
    r = CliRunner().invoke(
        main, ["manifest", str(scene), "--out", str(scene / "manifest.json"), "--test-every", "2"]
    )
    assert r.exit_code == 0, r.output
    assert "5 views (2 train, 3 test; 5 JPEG, 0 lossless)" in r.output
    assert "5 view(s) have distorted cameras (recorded" in r.output
    doc = json.loads((scene / "manifest.json").read_text())
    s = doc["scene"]
    assert s["schedule"] is None and s["seed"] is None and s["downscale"] == 2.0 and s["undistorted"] is False
    for i, v in enumerate(doc["views"]):
        assert v["name"] == f"view_{i:03d}.png" and v["image"] == f"images/view_{i:03d}.jpg"
        assert v["split"] == ("test" if i % 2 == 0 else "train")
        cam = v["camera"]
        assert cam["model"] == "SIMPLE_RADIAL" and cam["distortion"] == {
            "model": "SIMPLE_RADIAL",
            "params": [0.03],
        }
        assert (cam["width"], cam["height"]) == (48, 36)
        assert cam["fx"] == cam["fy"] == pytest.approx(0.85 * 48) and cam["cx"] == pytest.approx(24)
        assert v["jpeg"]["quality"] == 85 and v["jpeg"]["quality_exact"]
        assert v["reference"] == ("reference/view_001.png" if i == 1 else None)
    m = load_manifest(scene / "manifest.json")
    assert m.views[0].camera.distortion is not None and m.views[0].camera.distortion.params == (0.03,)
    # manifest refuses to overwrite without --force
    r = CliRunner().invoke(main, ["manifest", str(scene), "--out", str(scene / "manifest.json")])
    assert r.exit_code == 1 and "exists (use --force" in r.output
    r = CliRunner().invoke(main, ["manifest", str(scene), "--out", str(scene / "manifest.json"), "--force"])
    assert r.exit_code == 0
    r = CliRunner().invoke(main, ["manifest", str(scene), "--out", str(scene)])
    assert r.exit_code == 1 and "is a folder" in r.output
    # --force replaces a manifest, never a photo or any other file
    photo = sorted((scene / "images").iterdir())[0]
    before = photo.read_bytes()
    r = CliRunner().invoke(main, ["manifest", str(scene), "--out", str(photo), "--force"])
    assert r.exit_code == 1 and "is not a jsgs manifest" in r.output and photo.read_bytes() == before


def test_relative_paths_resolve_against_the_manifest_folder(
    compressed_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "deep" / "er" / "m.json"
    doc = manifest(compressed_scene, out)
    assert doc["views"][0]["image"].startswith("../")
    monkeypatch.chdir(tmp_path / "deep")  # the reader must not depend on the working directory
    m = load_manifest(Path("er") / "m.json")
    assert all(v.image.is_file() for v in m.views)
    # moving the manifest breaks its relative paths: a clear error, not a late crash
    moved = tmp_path / "m.json"
    shutil.copy(out, moved)
    with pytest.raises(JsgsError, match=r"m.json: view '.*': image .* not found \(looked for"):
        load_manifest(moved)
    assert len(load_manifest(moved, check_files=False).views) == 12


def test_manifest_refuses_a_bad_scene(synth_scene: Path, tmp_path: Path) -> None:
    scene = tmp_path / "s"
    shutil.copytree(synth_scene, scene)
    (scene / "images" / "view_002.png").unlink()
    with pytest.raises(JsgsError, match="view_002.png: registered image not found"):
        manifest(scene, tmp_path / "m.json")
    assert not (tmp_path / "m.json").exists()
    r = CliRunner().invoke(main, ["manifest", str(tmp_path / "none"), "--out", str(tmp_path / "m.json")])
    assert r.exit_code == 1 and r.output.startswith("error: ") and "Traceback" not in r.output
    # a folder of photos (no COLMAP model): the one line says which command makes one
    photos = tmp_path / "photos"
    photos.mkdir()
    shutil.copy(synth_scene / "images" / "view_000.png", photos)
    for args in (["manifest", str(photos), "--out", str(tmp_path / "m.json")], ["validate", str(photos)]):
        r = CliRunner().invoke(main, args)
        assert r.exit_code == 1 and f"`jsgstools sfm {photos} --out SCENE`" in r.output, (args, r.output)
    assert not (tmp_path / "m.json").exists()


def test_write_validates_and_writes_nothing_when_bad(compressed_scene: Path, tmp_path: Path) -> None:
    doc = json.loads((compressed_scene / "manifest.json").read_text())
    bad = copy.deepcopy(doc)
    bad["views"][1]["t"][0] = float("nan")
    with pytest.raises(JsgsError, match="m.json: not a valid manifest file: at views/1: non-finite"):
        write_manifest(bad, tmp_path / "m.json")
    bad = copy.deepcopy(doc)
    del bad["views"][0]["split"]
    with pytest.raises(JsgsError, match="at views/0: 'split' is a required property"):
        write_manifest(bad, tmp_path / "m.json")
    assert list(tmp_path.iterdir()) == []


def test_manifest_of_a_raw_real_scene(tmp_path: Path) -> None:
    """LLFF fern as shipped: distorted SIMPLE_RADIAL at 4032x3024, PNGs at 504x378. The manifest records the
    distortion and the scaled intrinsics; it does not undistort (that is compress's job)."""
    from conftest import shared_scene

    fern = shared_scene("llff_fern")
    doc = manifest(fern, tmp_path / "fern.json")
    assert doc["scene"]["downscale"] == 8.0 and doc["scene"]["undistorted"] is False
    cam = doc["views"][0]["camera"]
    assert cam["model"] == "SIMPLE_RADIAL" and (cam["width"], cam["height"]) == (504, 378)
    assert cam["fx"] == pytest.approx(3260.5263328805895 / 8) and cam["cx"] == pytest.approx(252.0)
    assert cam["distortion"] == {"model": "SIMPLE_RADIAL", "params": [pytest.approx(0.019750463822896944)]}
    assert all(v["jpeg"] is None and v["reference"] is None for v in doc["views"])
    assert doc["points"]["count"] == 10091
    m = load_manifest(tmp_path / "fern.json")
    assert len(m.test_views) == 3 and m.views[0].image.suffix == ".png"
