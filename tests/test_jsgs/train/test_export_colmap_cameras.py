"""``jsgs export --frame colmap`` checked against the scene's own cameras, independently of the exporter's
arithmetic: the COLMAP world of the tiny scene is moved by a known similarity (scale 7, a rotation, a shift)
so that the trainer's normalisation is far from the identity; the exported centres, projected with the
manifest's cameras as :func:`jsgs.base.manifest.load_manifest` reads them, must land on the pixels where the
training-frame centres land through the training cameras, and sit among the scene's SfM points. Also: the
file ``jsgs train`` writes at the end of a run is that export, and ``jsgs render`` / ``jsgs export`` refuse a
folder that is not a run in one line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _train_scene import make_scene, train_tiny_run
from click.testing import CliRunner

from jsgs.cli import main

SCALE = 7.0
SHIFT = np.array([3.0, -20.0, 11.0])


def _rotation(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _move_world(manifest: Path, s: float, Q: np.ndarray, c: np.ndarray) -> None:
    """Rewrite the manifest in the world x' = s Q x + c (cameras and points): the same scene and images."""
    doc = json.loads(manifest.read_text())
    for v in doc["views"]:
        R, t = np.array(v["R"]), np.array(v["t"])
        # R x + t = R Qᵀ (x' - c) / s + t: scaled by s, the camera is (R Qᵀ, s t - R Qᵀ c)
        Rn = R @ Q.T
        v["R"], v["t"] = Rn.tolist(), (s * t - Rn @ c).tolist()
    xyz = np.asarray(doc["points"]["xyz"], dtype=np.float64)
    doc["points"]["xyz"] = (s * xyz @ Q.T + c).tolist()
    manifest.write_text(json.dumps(doc))


@pytest.fixture(scope="module")
def moved_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("export_colmap")
    manifest = make_scene(root / "scene", width=32, height=24)
    _move_world(manifest, SCALE, _rotation(1), SHIFT)
    run = root / "run"
    r = train_tiny_run(root, eval_at="", manifest=manifest)
    assert "point_cloud.ply, point_cloud_colmap.ply" in r.stdout.splitlines()[-1]  # the outputs line names it
    return manifest, run


def _project(x: np.ndarray, world_to_camera: np.ndarray, K: np.ndarray) -> np.ndarray:
    """x [N, 3] -> pixels [N, 2] through a 4x4 world-to-camera and 3x3 pinhole K (float64)."""
    pc = x @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    return pc[:, :2] / pc[:, 2:] @ np.diag([K[0, 0], K[1, 1]]) + K[:2, 2]


def test_exported_centres_project_with_the_colmap_cameras(
    moved_run: tuple[Path, Path], tmp_path: Path
) -> None:
    from jsgs.base.manifest import load_manifest
    from jsgs.base.ply import load_ply
    from jsgs.train.config import load_config_file
    from jsgs.train.data import load_training_scene

    manifest, run = moved_run
    out = tmp_path / "scene.ply"
    r = CliRunner().invoke(main, ["export", str(run), "--out", str(out)])
    assert r.exit_code == 0, r.output
    exported, trained = load_ply(out), load_ply(run / "point_cloud.ply")
    assert exported["means"].shape == trained["means"].shape
    colmap_views = load_manifest(manifest).views  # the scene's cameras, in its own frame
    training = load_training_scene(manifest, load_config_file(run / "config.json"))  # the trainer's cameras
    assert abs(np.linalg.det(training.transform[:3, :3]) ** (1 / 3) - 1.0) > 0.5  # not a trivial frame
    for colmap, v in zip(colmap_views, training.views, strict=True):
        assert colmap.name == v.name
        a = _project(trained["means"].astype(np.float64), v.viewmat, v.K)
        w2c = np.asarray(colmap.world_to_camera)
        b = _project(exported["means"].astype(np.float64), w2c, colmap.camera.K)
        assert np.abs(a - b).max() < 1e-3, (v.name, float(np.abs(a - b).max()))
    # the centres sit among the SfM points they started from (COLMAP units, not the normalised ones)
    pts = np.asarray(load_manifest(manifest).points_xyz, dtype=np.float64).reshape(-1, 3)
    nearest = np.linalg.norm(exported["means"][:, None, :] - pts[None], axis=2).min(axis=1)
    assert np.median(nearest) < 0.05 * np.ptp(pts, axis=0).max()
    # sizes scale with the world: the normalised world's unit is 1 / (the normalisation's scale) here
    s = float(np.linalg.det(training.transform[:3, :3]) ** (1 / 3))
    ratio = np.exp(exported["scales_log"] - trained["scales_log"])
    assert np.allclose(ratio, 1.0 / s, rtol=1e-4)


def test_the_run_holds_the_colmap_frame_export(moved_run: tuple[Path, Path], tmp_path: Path) -> None:
    from jsgs.base.ply import load_ply

    _, run = moved_run
    out = tmp_path / "again.ply"
    assert CliRunner().invoke(main, ["export", str(run), "--out", str(out)]).exit_code == 0
    written, again = load_ply(run / "point_cloud_colmap.ply"), load_ply(out)
    for key in ("means", "quats", "scales_log", "opacities_logit", "sh0", "shN"):
        assert np.array_equal(written[key], again[key]), key


@pytest.mark.parametrize(
    ("command", "options"),
    [("render", ["--out", "out.mp4", "--device", "cpu"]), ("export", ["--out", "o.ply"])],
)
def test_not_a_run_is_one_line(command: str, options: list[str], tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("not a run")
    options = [str(tmp_path / o) if o in ("out.mp4", "o.ply") else o for o in options]
    r = CliRunner().invoke(main, [command, str(tmp_path), *options])
    assert r.exit_code == 1, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and str(tmp_path) in lines[0], r.output
    assert "Traceback" not in r.output
