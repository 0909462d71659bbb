"""COLMAP models checked for what they claim: binary files read to their declared end (truncated or padded
copies are one-line errors naming the file), implausible cameras and non-finite points refused, through
``validate``, ``manifest`` and ``compress`` alike; real models pass."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner
from conftest import SHARED

from jsgs.base.errors import JsgsError
from jsgstools.cli import main
from jsgstools.colmap_check import check_binary_model, check_cameras_bin, check_images_bin, check_points_bin


def _copy(synth_scene: Path, dst: Path) -> Path:
    shutil.copytree(synth_scene, dst)
    return dst


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
@pytest.mark.parametrize("cut", [1, 9, "half", "count"])
def test_truncated_files_are_named(synth_scene: Path, tmp_path: Path, name: str, cut: object) -> None:
    scene = _copy(synth_scene, tmp_path / "s")
    f = scene / "sparse" / "0" / name
    data = f.read_bytes()
    keep = {"half": len(data) // 2, "count": 5}[cut] if isinstance(cut, str) else len(data) - int(cut)
    f.write_bytes(data[:keep])
    before = {p: p.read_bytes() for p in scene.rglob("*") if p.is_file()}
    for cmd in (["validate", str(scene)], ["manifest", str(scene), "--out", str(tmp_path / "m.json")]):
        r = CliRunner().invoke(main, cmd)
        assert r.exit_code == 1, r.output
        # validate lists it as its problem, manifest stops with it: one line naming the file either way
        lines = [ln for ln in r.output.splitlines() if str(f) in ln]
        assert len(lines) == 1 and ("truncated" in lines[0] or "declares" in lines[0]), r.output
        assert "Traceback" not in r.output and len(r.output.splitlines()) <= 2, r.output
    assert {p: p.read_bytes() for p in scene.rglob("*") if p.is_file()} == before  # nothing changed
    assert not (tmp_path / "m.json").exists()


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_trailing_bytes_are_refused(synth_scene: Path, tmp_path: Path, name: str) -> None:
    scene = _copy(synth_scene, tmp_path / "s")
    f = scene / "sparse" / "0" / name
    f.write_bytes(f.read_bytes() + b"\0" * 7)
    with pytest.raises(JsgsError, match="7 bytes after the last"):
        check_binary_model(scene / "sparse" / "0")


def _edit_camera(scene: Path, **params: float) -> None:
    import pycolmap

    model = scene / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    for cam in rec.cameras.values():
        p = list(cam.params)
        info = [s.strip() for s in cam.params_info.split(",")]
        for k, v in params.items():
            p[info.index(k)] = v
        cam.params = p
    rec.write_binary(str(model))


@pytest.mark.parametrize(
    ("params", "message"),
    [({"cx": -5.0}, "principal point"), ({"cy": 1e6}, "principal point"), ({"fx": 0.0}, "focal length"),
     ({"fy": float("nan")}, "not finite")],
)  # fmt: skip
def test_implausible_cameras(
    synth_scene: Path, tmp_path: Path, params: dict[str, float], message: str
) -> None:
    scene = _copy(synth_scene, tmp_path / "s")
    _edit_camera(scene, **params)
    r = CliRunner().invoke(main, ["validate", str(scene)])
    assert r.exit_code == 1 and message in r.output and "cameras.bin: camera" in r.output, r.output


def test_implausible_distortion_and_bad_points(synth_scene: Path, tmp_path: Path) -> None:
    import pycolmap

    scene = _copy(synth_scene, tmp_path / "s")
    model = scene / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    cam = next(iter(rec.cameras.values()))
    f, cx, cy = float(cam.params[0]), float(cam.params[2]), float(cam.params[3])
    rec.cameras[cam.camera_id] = pycolmap.Camera.create_from_model_name(
        cam.camera_id, "SIMPLE_RADIAL", f, cam.width, cam.height
    )
    rec.cameras[cam.camera_id].params = [f, cx, cy, 1512.0]
    rec.write_binary(str(model))
    with pytest.raises(JsgsError, match=r"distortion \[1512.0\] is implausible"):
        check_cameras_bin(model / "cameras.bin")
    rec.cameras[cam.camera_id].params = [f, cx, cy, 0.01]
    pid = next(iter(rec.points3D))
    rec.points3D[pid].xyz = [float("inf"), 0.0, 0.0]
    rec.write_binary(str(model))
    check_cameras_bin(model / "cameras.bin")
    check_images_bin(model / "images.bin")
    with pytest.raises(JsgsError, match="1 point"):
        check_points_bin(model / "points3D.bin")


@pytest.mark.skipif(not (SHARED / "scenes").is_dir(), reason="../shared/scenes is absent")
def test_real_models_pass_and_the_truncated_fern_camera_is_caught(tmp_path: Path) -> None:
    for scene in sorted((SHARED / "scenes").iterdir()):
        check_binary_model(scene / "sparse" / "0")
    cams = tmp_path / "cameras.bin"
    cams.write_bytes((SHARED / "scenes" / "llff_fern" / "sparse" / "0" / "cameras.bin").read_bytes()[:56])
    with pytest.raises(JsgsError, match="truncated: the parameters of camera 1"):
        check_cameras_bin(cams)
