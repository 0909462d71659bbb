"""``jsgstools validate``: a good scene passes with a summary; each bad input is one problem line; several
problems are all listed; real scenes' downscale factors are found."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import shared_scene
from PIL import Image

from jsgs.base.errors import JsgsError
from jsgstools.cli import main
from jsgstools.scene import resolve_image
from jsgstools.validate import require_valid, validate_scene


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _edit_model(scene: Path, edit) -> None:  # type: ignore[no-untyped-def]
    """Load sparse/0, apply ``edit(reconstruction)``, write it back (binary)."""
    import pycolmap

    model = scene / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    edit(rec)
    shutil.rmtree(model)
    model.mkdir()
    rec.write_binary(str(model))


def _run(scene: Path) -> tuple[int, str]:
    r = CliRunner().invoke(main, ["validate", str(scene)])
    return r.exit_code, r.output


def test_good_scene(synth_scene: Path) -> None:
    code, out = _run(synth_scene)
    assert code == 0, out
    assert "downscale    1" in out and "points3D" in out and out.rstrip().endswith("ok")
    assert "12 registered, 12 found" in out
    assert "10 train / 2 test" in out


def test_text_model_and_plain_sparse_folder(synth_scene: Path, tmp_path: Path) -> None:
    import pycolmap

    scene = _copy(synth_scene, tmp_path / "s")
    rec = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    shutil.rmtree(scene / "sparse")
    (scene / "sparse").mkdir()
    rec.write_text(str(scene / "sparse"))
    report = validate_scene(scene)
    assert report.ok, report.problems
    assert report.scene is not None and report.scene.model_format == "text"
    assert report.scene.model_dir == scene / "sparse"


@pytest.mark.parametrize(
    ("name", "breaker", "expected"),
    [
        ("missing sparse", lambda s: shutil.rmtree(s / "sparse"), "no COLMAP model"),
        (
            "corrupt model",
            lambda s: (s / "sparse" / "0" / "cameras.bin").write_bytes(b"\x01\x02garbage"),
            "not a COLMAP cameras.bin",
        ),
        ("missing images folder", lambda s: shutil.rmtree(s / "images"), "images folder not found"),
        (
            "missing image",
            lambda s: (s / "images" / "view_003.png").unlink(),
            "view_003.png: registered image not found",
        ),
        (
            "unreadable image",
            lambda s: (s / "images" / "view_003.png").write_bytes(b"not an image"),
            "view_003.png: cannot read image",
        ),
        (
            "size mismatch",
            lambda s: Image.new("RGB", (64, 64)).save(s / "images" / "view_004.png"),
            "view_004.png: size 64x64 does not match its camera 1 (64x48)",
        ),
        (
            "inconsistent factor",
            lambda s: Image.new("RGB", (32, 24)).save(s / "images" / "view_005.png"),
            "view_005.png: downscale factor 2 (32x24 from camera 1 64x48) differs from the scene's 1",
        ),
        (
            "lossy non-JPEG format",
            lambda s: Image.new("RGB", (64, 48)).save(s / "images" / "view_006.png", format="WEBP"),
            "view_006.png: format WEBP is not supported",
        ),
    ],
)
def test_each_bad_input_is_one_problem(
    synth_scene: Path, tmp_path: Path, name: str, breaker, expected: str
) -> None:  # type: ignore[no-untyped-def]
    scene = _copy(synth_scene, tmp_path / "s")
    breaker(scene)
    code, out = _run(scene)
    assert code == 1, (name, out)
    problems = [line for line in out.splitlines() if line.startswith("problem: ")]
    assert len(problems) == 1, (name, out)
    assert expected in problems[0], (name, problems)
    assert f"error: {scene}: 1 problem(s)" in out
    assert "Traceback" not in out


def test_nan_pose(synth_scene: Path, tmp_path: Path) -> None:
    import pycolmap

    def edit(rec):  # type: ignore[no-untyped-def]
        frame = rec.frames[rec.images[2].frame_id]
        frame.rig_from_world = pycolmap.Rigid3d(
            pycolmap.Rotation3d(np.array([0, 0, 0, 1.0])), np.array([np.nan, 0.0, 0.0])
        )

    scene = _copy(synth_scene, tmp_path / "s")
    _edit_model(scene, edit)
    code, out = _run(scene)
    assert code == 1
    assert "image 'view_001.png' has a non-finite pose" in out


def _cancelling_ups(i: int) -> tuple[np.ndarray, np.ndarray]:
    R = np.diag([-1.0, -1.0, 1.0]) if i % 2 else np.eye(3)  # every other camera rolled by half a turn
    return R, -R @ np.array([0.5 * i, 0.0, -4.0])


def _most_on_focus(i: int) -> tuple[np.ndarray, np.ndarray]:
    return np.eye(3), np.array([0.0, 0.0, float(max(0, i - 7))])  # 8 of 12 at the origin, 4 behind it


@pytest.mark.parametrize(
    ("pose", "why"),
    [(_cancelling_ups, "the cameras' up directions cancel out: their mean is zero"),
     (_most_on_focus, "most cameras sit at their common focus point: their median distance from it is 0")],
    ids=["cancelling ups", "most on focus"],
)  # fmt: skip
def test_cameras_the_normalisation_refuses_are_a_warning(
    synth_scene: Path, tmp_path: Path, pose: Callable[[int], tuple[np.ndarray, np.ndarray]], why: str
) -> None:
    """validate and manifest warn with the trainer's own reason, which the trainer's normalisation gives for
    the manifest's poses."""
    import pycolmap

    from jsgs.base.manifest import load_manifest
    from jsgs.train.normalize import normalize_world

    def edit(rec):  # type: ignore[no-untyped-def]
        for i, iid in enumerate(sorted(rec.images)):
            R, t = pose(i)
            rec.frames[rec.images[iid].frame_id].rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(R), t)

    code, out = _run(synth_scene)
    assert code == 0 and "normalize_world" not in out, out
    scene = _copy(synth_scene, tmp_path / "s")
    _edit_model(scene, edit)
    line = f"{scene / 'sparse' / '0'}: {why}: jsgs train refuses the scene unless scene.normalize_world is "
    line += "false"
    code, out = _run(scene)
    assert code == 0 and f"warning: {line}" in out.splitlines() and "one position" not in out, out
    r = CliRunner().invoke(main, ["manifest", str(scene), "--out", str(tmp_path / "m.json")])
    assert r.exit_code == 0 and f"warning: {line}" in r.output.splitlines(), r.output
    views = load_manifest(tmp_path / "m.json").views
    c2w = np.stack([np.linalg.inv(v.world_to_camera) for v in views])
    with pytest.raises(ValueError) as e:
        normalize_world(c2w, np.zeros((0, 3)))
    assert str(e.value) == why


def test_duplicate_names(synth_scene: Path, tmp_path: Path) -> None:
    def edit(rec):  # type: ignore[no-untyped-def]
        rec.images[3].name = "view_001.png"

    scene = _copy(synth_scene, tmp_path / "s")
    _edit_model(scene, edit)
    code, out = _run(scene)
    assert code == 1
    assert "image name 'view_001.png' is used by 2 images (ids 2, 3)" in out


def test_empty_points3D(synth_scene: Path, tmp_path: Path) -> None:
    def edit(rec):  # type: ignore[no-untyped-def]
        for pid in list(rec.points3D):
            rec.delete_point3D(pid)

    scene = _copy(synth_scene, tmp_path / "s")
    _edit_model(scene, edit)
    code, out = _run(scene)
    assert code == 1
    assert "points3D is empty" in out


def test_camera_models(synth_scene: Path, tmp_path: Path) -> None:
    import pycolmap

    def set_model(name: str, params: list[float]):  # type: ignore[no-untyped-def]
        def edit(rec):  # type: ignore[no-untyped-def]
            cam = rec.cameras[1]
            cam.model = getattr(pycolmap.CameraModelId, name)
            cam.params = params

        return edit

    # distorted but undistortable: a warning, exit 0
    scene = _copy(synth_scene, tmp_path / "radial")
    _edit_model(scene, set_model("SIMPLE_RADIAL", [54.4, 32.0, 24.0, 0.01]))
    code, out = _run(scene)
    assert code == 0, out
    assert "warning:" in out and "SIMPLE_RADIAL with distortion [0.01]: compress undistorts it" in out
    assert "a JPEG-only scene trains as it is" in out
    # FULL_OPENCV: compress undistorts it, the trainer does not render it (a JPEG-only scene cannot train)
    scene = _copy(synth_scene, tmp_path / "full")
    _edit_model(scene, set_model("FULL_OPENCV", [54.4, 54.4, 32.0, 24.0, 0.01, 0, 0, 0, 0.001, 0, 0, 0]))
    code, out = _run(scene)
    assert code == 0, out
    assert "FULL_OPENCV with distortion" in out and "a JPEG-only scene cannot train with it" in out
    # a fisheye model: not supported
    scene = _copy(synth_scene, tmp_path / "fisheye")
    _edit_model(scene, set_model("OPENCV_FISHEYE", [54.4, 54.4, 32.0, 24.0, 0.01, 0, 0, 0]))
    code, out = _run(scene)
    assert code == 1
    assert "camera model OPENCV_FISHEYE is not supported" in out
    # manifest accepts it (it records any model); compress does not
    assert require_valid(scene, allow=("camera_model",)).scene is not None
    with pytest.raises(JsgsError, match="OPENCV_FISHEYE"):
        require_valid(scene)
    # bad intrinsics
    scene = _copy(synth_scene, tmp_path / "focal")
    _edit_model(scene, set_model("PINHOLE", [-5.0, 54.4, 32.0, 24.0]))
    code, out = _run(scene)
    assert code == 1 and "focal length [-5.0, 54.4] is not positive" in out


def test_every_problem_is_listed(synth_scene: Path, tmp_path: Path) -> None:
    def edit(rec):  # type: ignore[no-untyped-def]
        rec.images[3].name = "view_001.png"
        for pid in list(rec.points3D):
            rec.delete_point3D(pid)

    scene = _copy(synth_scene, tmp_path / "s")
    _edit_model(scene, edit)
    (scene / "images" / "view_005.png").unlink()
    Image.new("RGB", (64, 64)).save(scene / "images" / "view_006.png")
    Image.new("RGB", (32, 24)).save(scene / "images" / "view_007.png")
    code, out = _run(scene)
    assert code == 1
    problems = [line for line in out.splitlines() if line.startswith("problem: ")]
    assert len(problems) == 5, out
    for what in (
        "used by 2 images",
        "points3D is empty",
        "view_005.png: registered image not found",
        "view_006.png: size 64x64",
        "view_007.png: downscale factor 2",
    ):
        assert sum(what in p for p in problems) == 1, (what, problems)
    assert f"error: {scene}: 5 problem(s)" in out
    with pytest.raises(JsgsError, match=r"\(and 4 more; run `jsgstools validate"):
        require_valid(scene)


def test_camera_shared_by_different_sizes(synth_scene: Path, tmp_path: Path) -> None:
    # 65x49 is within the one-pixel rounding of the factor-1 size, but camera 1 cannot have two sizes.
    scene = _copy(synth_scene, tmp_path / "s")
    Image.new("RGB", (65, 49)).save(scene / "images" / "view_002.png")
    code, out = _run(scene)
    assert code == 1
    assert "camera 1 is shared by images of different sizes (64x48, 65x49)" in out


def test_not_a_folder(tmp_path: Path) -> None:
    code, out = _run(tmp_path / "nope")
    assert code == 1 and "nope: not a folder" in out


def test_name_resolution(tmp_path: Path) -> None:
    d = tmp_path / "images"
    (d / "sub").mkdir(parents=True)
    (d / "a.png").write_bytes(b"")
    (d / "b.png").write_bytes(b"")
    (d / "b.bmp").write_bytes(b"")
    (d / "sub" / "c.png").write_bytes(b"")
    (d / "x[1].png").write_bytes(b"")
    assert resolve_image(d, "a.JPG") == d / "a.png"  # same stem, another extension
    assert resolve_image(d, "a.png") == d / "a.png"
    assert resolve_image(d, "b.JPG") is None  # ambiguous
    assert resolve_image(d, "sub/c.jpg") == d / "sub" / "c.png"
    assert resolve_image(d, "x[1].jpg") == d / "x[1].png"
    assert resolve_image(d, "missing.jpg") is None


@pytest.mark.parametrize(
    ("name", "factor", "sizes"),
    [
        ("llff_fern", "8", "504x378 x20"),
        ("custom_kwrous_cup", "2", "400x300 x77"),
        ("custom_myhan_mouse", "3", "480x640 x17, 640x480 x39"),
    ],
)
def test_real_scenes(name: str, factor: str, sizes: str) -> None:
    scene = shared_scene(name)
    code, out = _run(scene)
    assert code == 0, out
    assert f"downscale    {factor} " in out
    assert f"image size   {sizes}" in out
    if name == "llff_fern":
        assert "SIMPLE_RADIAL" in out and "compress undistorts it" in out


def _fifo(p: Path) -> str:
    p.unlink()
    os.mkfifo(p)  # nobody writes it: a reader that opened it would wait forever
    return "is a FIFO (named pipe), not a regular file"


def _folder(p: Path) -> str:
    p.unlink()
    p.mkdir()
    return "is a folder, not a regular file"


def _dangling(p: Path) -> str:
    p.unlink()
    p.symlink_to(p.parent / "gone.bin")
    return "is a link to a missing file"


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
@pytest.mark.parametrize(
    ("name", "make"),
    [("cameras.bin", _fifo), ("images.bin", _folder), ("points3D.bin", _dangling), ("points3D.bin", _fifo)],
)
def test_a_model_file_that_is_no_regular_file_is_named(
    synth_scene: Path, tmp_path: Path, name: str, make: Callable[[Path], str]
) -> None:
    scene = _copy(synth_scene, tmp_path / "s")
    path = scene / "sparse" / "0" / name
    why = make(path)
    code, out = _run(scene)
    problems = [line for line in out.splitlines() if line.startswith("problem: ")]
    assert code == 1 and problems == [f"problem: {path}: {why}; a COLMAP model needs cameras, images and "
                                      "points3D as regular files"], out  # fmt: skip
    r = CliRunner().invoke(main, ["manifest", str(scene), "--out", str(tmp_path / "m.json")])
    errors = [line for line in r.output.splitlines() if line.startswith("error: ")]
    assert r.exit_code == 1 and len(errors) == 1 and f"{path}: {why}" in errors[0], r.output
    assert "Traceback" not in r.output + out and not (tmp_path / "m.json").exists()
