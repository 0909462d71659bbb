"""``jsgs view`` (jsgs.apps.viewer): the camera conversions against OpenCV and the trainer's own cameras, a
finished CPU run rendered by the viewer equal to the trainer's saved evaluation render, the server answering
HTTP on a free port, saved cameras (schema), and one-line errors."""

from __future__ import annotations

import json
import math
import shutil
import socket
import subprocess
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest
from _train_scene import make_scene, train_tiny_run
from click.testing import CliRunner
from PIL import Image

from jsgs.apps.viewer import (
    add_frustums,
    camera_matrices,
    frustum_scale,
    image_size,
    load_run_model,
    render_rgb,
    save_camera,
    start_camera,
)
from jsgs.base.rotations import matrix_to_quat, quat_to_matrix


def test_quaternions_against_opencv_rodrigues() -> None:
    rng = np.random.default_rng(0)
    vecs = [rng.normal(size=3) * s for s in (0.1, 1.0, 3.0)] + [np.array([math.pi, 0, 0]), np.zeros(3)]
    vecs += [np.array([0.0, math.pi - 1e-9, 0.0]), np.array([0.0, 0.0, -3.1])]
    for rv in vecs:
        R, _ = cv2.Rodrigues(rv)
        q = matrix_to_quat(R)
        assert q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
        np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-12)
        # the rotation angle of q is the length of OpenCV's rotation vector (modulo the sign of q)
        angle = 2 * math.atan2(np.linalg.norm(q[1:]), q[0])
        assert angle == pytest.approx(np.linalg.norm(rv) % (2 * math.pi), abs=1e-9) or angle == pytest.approx(
            2 * math.pi - np.linalg.norm(rv), abs=1e-9
        )


def test_image_size() -> None:
    assert image_size(4 / 3, 320) == (320, 240) and image_size(0.75, 320) == (240, 320)
    assert image_size(1.0, 17) == (17, 17) and image_size(1000.0, 16) == (16, 1)


def test_frustums_are_small_beside_the_camera_spacing() -> None:
    angles = np.linspace(0, 2 * math.pi, 24, endpoint=False)
    ring = np.stack([np.cos(angles), np.sin(angles), np.zeros(24)], axis=1)
    gap = float(np.linalg.norm(ring[1] - ring[0]))
    s = frustum_scale(ring, extent=1.1)
    assert s == pytest.approx(min(0.25 * gap, 0.022))  # a quarter of the spacing, at most 2 % of the extent
    assert frustum_scale(ring * 100, extent=110.0) == pytest.approx(2.2)  # the cap scales with the scene
    assert frustum_scale(ring[:1], extent=2.0) == frustum_scale(np.zeros((3, 3)), extent=2.0) == 0.02


def test_the_browser_starts_at_a_training_camera_looking_at_the_model() -> None:
    from _train_scene import look_at

    centre = np.array([4.0, 0.0, 1.0])
    R, t = look_at(centre, np.array([0.0, 0.5, 0.0]), np.array([0.0, 0.0, 1.0]))  # aimed beside the model
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = R.T, -R.T @ t
    means = np.random.default_rng(0).normal(size=(500, 3)) * 0.2 + np.array([0.0, 0.0, 0.3])
    position, target, up = start_camera(c2w, means)
    np.testing.assert_allclose(position, centre, atol=1e-12)
    axis = (target - position) / np.linalg.norm(target - position)
    np.testing.assert_allclose(axis, c2w[:3, 2], atol=1e-12)  # the training camera's own orientation
    np.testing.assert_allclose(up, -c2w[:3, 1], atol=1e-12)
    depth = float(np.dot(np.median(means, axis=0) - centre, c2w[:3, 2]))
    assert np.linalg.norm(target - position) == pytest.approx(depth)  # orbits about the model's depth
    behind = np.array([[8.0, 0.0, 1.0]])  # a model behind the camera: the distance instead
    assert np.linalg.norm(start_camera(c2w, behind)[1] - centre) == pytest.approx(4.0)


def test_frustums_are_thin_and_skip_the_start_camera() -> None:
    class Scene:
        def __init__(self) -> None:
            self.calls: list[dict] = []

        def add_camera_frustum(self, name: str, **kw):  # noqa: ANN003, ANN202
            self.calls.append({"name": name, **kw})
            return name

    class V:
        def __init__(self, i: int) -> None:
            self.index, self.width, self.height = i, 40, 30
            self.K = np.array([[30.0, 0, 20], [0, 30.0, 15], [0, 0, 1]])
            self.camtoworld = np.eye(4)

    scene = Scene()
    handles = add_frustums(scene, [V(0), V(3), V(5)], scale=0.01, skip=3)
    assert handles == ["/cameras/0000", "/cameras/0005"]
    assert all(c["scale"] == 0.01 and c["thickness_units"] == "screen" for c in scene.calls)
    assert all(c["thickness"] <= 2 for c in scene.calls)  # pixels: thin at any distance


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory: pytest.TempPathFactory) -> Path:

    root = tmp_path_factory.mktemp("viewer")
    train_tiny_run(root)
    return root / "run"


def test_viewer_renders_what_the_trainer_rendered(finished_run: Path) -> None:
    model = load_run_model(finished_run, "cpu")
    v = model.scene.test_views[0]
    # the viewer's camera from a pose and a vertical field of view is the trainer's camera (centred K)
    fov = 2 * math.atan(0.5 * v.height / v.K[1, 1])
    pose = (v.camtoworld[:3, 3], matrix_to_quat(v.camtoworld[:3, :3]))
    viewmat, K = camera_matrices(*pose, fov, v.width, v.height)
    np.testing.assert_allclose(viewmat, v.viewmat, atol=1e-9)
    np.testing.assert_allclose(K, v.K, rtol=1e-9)
    img = render_rgb(model, viewmat, K, v.width, v.height)
    saved = sorted(finished_run.glob(f"renders/**/{v.index:04d}_*.png"))
    assert saved, "the trainer saved no evaluation render"
    ref = np.asarray(Image.open(saved[-1]).convert("RGB"))
    assert img.shape == ref.shape and img.dtype == np.uint8
    assert np.abs(img.astype(int) - ref.astype(int)).max() <= 1  # same model, rasterizer and camera
    assert img.std() > 5  # something is drawn, not a flat background


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_server_answers_and_cameras_are_saved(finished_run: Path) -> None:
    from jsgs.apps.viewer import Viewer
    from jsgs.base.schema import validate

    model = load_run_model(finished_run, "cpu")
    viewer = Viewer(model, port=_free_port(), max_size=64)
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{viewer.port}/", timeout=20) as resp:
            assert resp.status == 200 and b"<html" in resp.read(4096).lower()
    finally:
        viewer.stop()
    v = model.scene.train_views[0]
    for _ in range(2):
        path = save_camera(model, v.camtoworld[:3, 3], matrix_to_quat(v.camtoworld[:3, :3]), 0.8, 4 / 3)
    doc = json.loads(path.read_text())
    validate(doc, "viewer_cameras", str(path))
    assert len(doc["cameras"]) == 2 and doc["frame"] == "training"
    np.testing.assert_allclose(np.array(doc["cameras"][0]["camtoworld"]), v.camtoworld, atol=1e-12)


def test_a_run_of_an_earlier_version_opens(
    finished_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``jsgs view``'s loading of a run whose config.json was written before ``speed`` existed: read with the
    values that version used (one note naming them, as render and export say it) and drawn as the run
    written today is."""
    from jsgs.train import config

    run = tmp_path / "old"
    shutil.copytree(finished_run, run)
    doc = json.loads((run / "config.json").read_text())
    del doc["settings"]["speed"]
    (run / "config.json").write_text(json.dumps(doc))
    config._said.clear()  # the note is said once per file and process
    old = load_run_model(run, "cpu")
    (note,) = capsys.readouterr().err.splitlines()
    assert note.startswith(f"note: {run / 'config.json'} was written before some settings existed"), note
    assert note.endswith('speed.ssim_kernel "torch", speed.exchange "gsplat"'), note
    assert (old.cfg.speed.ssim_kernel, old.cfg.speed.exchange) == ("torch", "gsplat")
    today = load_run_model(finished_run, "cpu")
    v = today.scene.test_views[0]
    drawn = [render_rgb(m, v.viewmat, v.K, v.width, v.height) for m in (old, today)]
    assert np.array_equal(*drawn) and drawn[0].std() > 5


def test_view_errors_are_one_line(tmp_path: Path, finished_run: Path) -> None:
    from jsgs.cli import main

    r = CliRunner().invoke(main, ["view", str(tmp_path / "nope")])
    assert r.exit_code == 1 and r.output.count("\n") == 1 and "no such run folder" in r.output
    half = tmp_path / "half"
    half.mkdir()
    (half / "config.json").write_text((finished_run / "config.json").read_text())
    r = CliRunner().invoke(main, ["view", str(half)])
    assert r.exit_code == 1 and "no point_cloud.ply" in r.output and r.output.count("\n") == 1


def test_live_viewer_serves_the_model_while_it_trains(tmp_path: Path) -> None:
    from jsgs.apps.viewer import LiveViewer
    from jsgs.train.callbacks import Callback
    from jsgs.train.config import TrainConfig
    from jsgs.train.trainer import train

    manifest = make_scene(tmp_path / "scene", width=32, height=24)
    live = LiveViewer(port=_free_port(), max_size=32, announce=lambda s: None)
    seen: list[tuple[int, int, float]] = []

    class Probe(Callback):
        def on_step_end(self, trainer, result) -> None:  # noqa: ANN001
            if result.step in (0, 9):
                assert live.viewer is not None and live.viewer.model.splats is trainer.splats
                with urllib.request.urlopen(f"http://127.0.0.1:{live.viewer.port}/", timeout=20) as resp:
                    status = resp.status
                v = trainer.scene.train_views[0]
                img = render_rgb(live.viewer.model, v.viewmat, v.K, v.width, v.height)
                seen.append((result.step, status, float(img.std())))

    cfg = TrainConfig.from_preset("paper")
    cfg.iterations, cfg.eval_at, cfg.device = 10, [], "cpu"
    train(manifest, tmp_path / "run", cfg, progress=False, callbacks=[live, Probe()])
    assert [(s, st) for s, st, _ in seen] == [(0, 200), (9, 200)] and all(sd > 1 for *_, sd in seen)
    assert live.viewer is None  # stopped with the run


@pytest.mark.skipif(shutil.which("chromium") is None, reason="needs Debian's chromium (setup_env.sh)")
def test_the_browser_shows_the_splat(finished_run: Path, tmp_path: Path) -> None:
    """Headless Chromium opens the viewer; the screenshot shows the model, and the same page of a model with
    zero opacity is a blank canvas (so the check can fail)."""
    import torch

    from jsgs.apps.viewer import Viewer

    model = load_run_model(finished_run, "cpu")

    def contrast(name: str, looks: int) -> float:
        """Peak-to-peak grey level at the centre of the canvas, left of the GUI panel (the tiny model is
        drawn there; a blank canvas is flat), over up to ``looks`` page loads: the frame arrives over the
        page's websocket, which headless Chromium's virtual time does not wait for, so on a busy machine a
        screenshot can come before it (seen once in a full test run); a later look waits longer."""
        viewer = Viewer(model, port=_free_port(), max_size=96)
        shot = tmp_path / name
        value = 0.0
        try:
            for look in range(looks):
                subprocess.run(
                    ["chromium", "--headless=new", "--no-sandbox", "--disable-gpu", "--use-gl=swiftshader",
                     "--enable-unsafe-swiftshader", "--window-size=640,480",
                     f"--virtual-time-budget={15000 * 2**look}", f"--screenshot={shot}",
                     f"http://127.0.0.1:{viewer.port}/"],
                    capture_output=True, timeout=120, check=False,
                )  # fmt: skip
                assert shot.is_file(), "chromium wrote no screenshot"
                img = np.asarray(Image.open(shot).convert("L"), dtype=np.float64)
                crop = img[180:300, 200:300]
                value = float(crop.max() - crop.min())
                if value > 20.0:
                    break
        finally:
            viewer.stop()
        return value

    drawn = contrast("model.png", looks=4)
    assert drawn > 20.0, f"a blank canvas after 4 looks (contrast {drawn:.0f})"
    with torch.no_grad():
        model.splats["opacities"].fill_(-30.0)
    assert contrast("blank.png", looks=1) < 10.0


@pytest.mark.parametrize(
    ("position", "wxyz", "fov", "aspect", "needle"),
    [([math.nan, 0, 0], [1, 0, 0, 0], 0.8, 1.3, "position"),
     ([1e308, 0, 0], [1, 0, 0, 0], 0.8, 1.3, "position"),
     ([0, 0, 0], [0, 0, 0, 0], 0.8, 1.3, "quaternion"),
     ([0, 0, 0], [math.nan, 0, 0, 1], 0.8, 1.3, "quaternion"),
     ([0, 0, 0], [1, 0, 0, 0], 0.0, 1.3, "field of view"),
     ([0, 0, 0], [1, 0, 0, 0], math.pi, 1.3, "field of view"),
     ([0, 0, 0], [1, 0, 0, 0], 0.8, math.inf, "aspect"),
     ([0, 0], [1, 0, 0, 0], 0.8, 1.3, "malformed")],
)  # fmt: skip
def test_broken_browser_cameras_are_never_saved(tmp_path: Path, position: list[float], wxyz: list[float],
                                                fov: float, aspect: float, needle: str) -> None:  # fmt: skip
    """What a browser reports is checked before anything is computed or written: one line, no file."""
    from types import SimpleNamespace

    from jsgs.apps.viewer import check_camera
    from jsgs.base.errors import JsgsError

    with pytest.raises(JsgsError, match=needle):
        check_camera(position, wxyz, fov, aspect)
    with pytest.raises(JsgsError, match=needle):
        save_camera(SimpleNamespace(run=tmp_path), np.array(position), np.array(wxyz), fov, aspect)  # type: ignore[arg-type]
    assert not (tmp_path / "viewer_cameras.json").exists()
    p, q, f, a = check_camera([1, 2, 3], [2, 0, 0, 0], 0.8, 1.5)
    assert q.tolist() == [1, 0, 0, 0] and p.tolist() == [1, 2, 3] and (f, a) == (0.8, 1.5)


def test_saved_cameras_with_broken_values_are_refused_by_render(tmp_path: Path) -> None:
    """A viewer_cameras.json edited to hold a NaN position or a scaled rotation: one line from read_path."""
    from jsgs.apps.camera_path import read_path
    from jsgs.base.errors import JsgsError

    good = np.eye(4).tolist()
    for (i, j, bad), needle in (((0, 3, math.nan), "not a finite number"), ((0, 3, 1e300), "beyond"),
                                ((0, 0, 2.0), "not a camera pose")):  # fmt: skip
        cams = np.eye(4)
        cams[i, j] = bad
        doc = {"format": "jsgs-viewer-cameras", "format_version": 1, "jsgs_version": "0", "frame": "training",
               "cameras": [{"camtoworld": c, "fov_y_deg": 50.0, "aspect": 1.0, "saved": "now"}
                           for c in (good, cams.tolist())]}  # fmt: skip
        path = tmp_path / "viewer_cameras.json"
        path.write_text(json.dumps(doc))
        with pytest.raises(JsgsError, match=needle) as e:
            read_path(path, 10, np.eye(3), 32, 24)
        assert "\n" not in str(e.value) and str(path) in str(e.value)
