"""``jsgstools downscale``: the pixels are the block means of the cropped view, the written cameras project
every point to 1/F of where the source camera does, the record validates, and nothing that is not its own
is written over."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from jsgs.base.errors import JsgsError
from jsgstools.cli import main
from jsgstools.downscale import downscale
from jsgstools.synth import synth


@pytest.fixture(scope="module")
def odd_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A synthetic scene of odd size (the crop matters) with 4 views."""
    out = tmp_path_factory.mktemp("odd") / "scene"
    synth(out, views=4, size=(35, 27), seed=3, supersample=1)
    return out


def _project(cam: object, xyz: np.ndarray, image: object) -> np.ndarray:
    cam_xyz = np.array([image.cam_from_world() * p for p in xyz])  # type: ignore[attr-defined]
    return np.array(cam.img_from_cam(cam_xyz))  # type: ignore[attr-defined]


def test_pixels_cameras_and_record(odd_scene: Path, tmp_path: Path) -> None:
    import pycolmap

    from jsgs.base.schema import validate

    before = sorted((p.relative_to(odd_scene), p.stat().st_mtime_ns) for p in odd_scene.rglob("*"))
    out = tmp_path / "half"
    record = downscale(odd_scene, out, factor=2)
    validate(json.loads((out / "downscale.json").read_text()), "downscale_record", "downscale.json")
    assert record["settings"]["factor"] == 2 and len(record["views"]) == 4
    for v in record["views"]:
        assert v["source_size"] == [35, 27] and v["size"] == [17, 13]
        src = np.asarray(Image.open(odd_scene / "images" / v["name"]).convert("RGB"), np.float64)
        blocks = src[:26, :34].reshape(13, 2, 17, 2, 3).mean(axis=(1, 3))
        got = np.asarray(Image.open(out / v["image"]), np.float64)
        assert got.shape == (13, 17, 3) and np.abs(got - blocks).max() <= 0.5 + 1e-9

    a = pycolmap.Reconstruction(str(odd_scene / "sparse" / "0"))
    b = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    xyz = np.array([p.xyz for p in a.points3D.values()])[:50]
    for iid, im in a.images.items():
        jm = b.images[iid]
        assert jm.name == Path(im.name).stem + ".png"
        cb = b.cameras[jm.camera_id]
        assert (cb.width, cb.height) == (17, 13)
        # COLMAP's pixel convention: the block mean of source pixels [2u, 2u+2) sits at u + 0.5 = (2u + 1) / 2
        np.testing.assert_allclose(_project(cb, xyz, jm), _project(a.cameras[im.camera_id], xyz, im) / 2)
    assert sorted((p.relative_to(odd_scene), p.stat().st_mtime_ns) for p in odd_scene.rglob("*")) == before


def test_manifest_reads_the_copy_at_its_own_size(odd_scene: Path, tmp_path: Path) -> None:
    out = tmp_path / "half"
    r = CliRunner().invoke(main, ["downscale", str(odd_scene), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "35x27 -> 17x13 (factor 2)" in r.output
    r = CliRunner().invoke(main, ["manifest", str(out), "--out", str(out / "manifest.json")])
    assert r.exit_code == 0, r.output
    assert "no separate lossless references: evaluation compares with the images themselves" in r.output
    doc = json.loads((out / "manifest.json").read_text())
    cams = {(v["camera"]["width"], v["camera"]["height"]) for v in doc["views"]}
    assert cams == {(17, 13)}


def test_refuses_what_is_not_its_own(odd_scene: Path, tmp_path: Path) -> None:
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    for extra in ([], ["--force"]):
        r = CliRunner().invoke(main, ["downscale", str(odd_scene), "--out", str(other), *extra])
        assert r.exit_code != 0 and r.output.count("\n") == 1 and "Traceback" not in r.output, r.output
    assert [p.name for p in other.iterdir()] == ["keep.txt"]
    out = tmp_path / "half"
    assert CliRunner().invoke(main, ["downscale", str(odd_scene), "--out", str(out)]).exit_code == 0
    assert CliRunner().invoke(main, ["downscale", str(odd_scene), "--out", str(out)]).exit_code != 0
    (out / "images" / "stale.png").write_bytes(b"")
    r = CliRunner().invoke(main, ["downscale", str(odd_scene), "--out", str(out), "--force"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (out / "images").iterdir()) == [f"view_{i:03d}.png" for i in range(4)]
    r = CliRunner().invoke(main, ["downscale", str(odd_scene), "--out", str(tmp_path / "x"), "--factor", "5"])
    assert r.exit_code != 0 and "--factor" in r.output


def test_refuses_a_factor_that_leaves_too_little(odd_scene: Path, tmp_path: Path) -> None:
    with pytest.raises(JsgsError, match="smaller than 11 px"):
        downscale(odd_scene, tmp_path / "tiny", factor=4)
    assert not (tmp_path / "tiny").exists() or not any((tmp_path / "tiny").iterdir())


def test_a_failure_leaves_nothing(odd_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import jsgstools.scene

    def fail(*_: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(jsgstools.scene, "write_model_atomic", fail)
    out = tmp_path / "half"
    with pytest.raises(OSError, match="disk full"):
        downscale(odd_scene, out)
    assert not out.exists() or not any(out.iterdir())


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_force_keeps_the_earlier_output_until_the_new_one_is_complete(
    odd_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import jsgstools.scene
    from jsgstools.scene import EARLIER_PREFIX

    out = tmp_path / "half"
    downscale(odd_scene, out)
    (out / "notes.txt").write_text("mine")  # not the tool's: never moved
    (out / "images" / "stale.png").write_bytes(b"earlier")  # in the earlier output only
    before = _tree(out)
    write_model = jsgstools.scene.write_model_atomic

    def interrupted(*_: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(jsgstools.scene, "write_model_atomic", interrupted)
    with pytest.raises(KeyboardInterrupt):  # Ctrl-C after the new images were written
        downscale(odd_scene, out, force=True)
    assert _tree(out) == before and not [p for p in out.iterdir() if p.name.startswith(EARLIER_PREFIX)]
    # a call killed before it could put the earlier output back leaves it aside: the next --force replaces it
    (out / f"{EARLIER_PREFIX}killed").mkdir()
    (out / f"{EARLIER_PREFIX}killed" / "downscale.json").write_text("{}")
    monkeypatch.setattr(jsgstools.scene, "write_model_atomic", write_model)
    downscale(odd_scene, out, force=True)
    after = _tree(out)
    names = [".jsgstools.json", "downscale.json", "images", "notes.txt", "sparse"]
    assert sorted(p.name for p in out.iterdir()) == names
    assert after["notes.txt"] == b"mine" and "images/stale.png" not in after
    assert {k: v for k, v in before.items() if k.startswith(("images/", "sparse/"))} == {
        k: v for k, v in after.items() if k.startswith(("images/", "sparse/"))
    } | {"images/stale.png": b"earlier"}  # the same pixels and model again
