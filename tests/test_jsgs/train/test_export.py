"""``jsgs export``: the SH band rotations against direct evaluation, the COLMAP-frame export rendered with
the COLMAP cameras equal to the trained model rendered with the training cameras (centres, rotations, scales
and view-dependent colour all undone correctly), the standard PLY layout, the other formats, the record."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from _train_scene import train_tiny_run
from click.testing import CliRunner

from jsgs.train.export import quat_multiply, sh_band_rotations, split_similarity, to_colmap_frame


def _random_rotation(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_sh_rotation_matches_direct_evaluation() -> None:
    from jsgs.render.reference.sh import spherical_harmonics

    R = _random_rotation(1)
    coeffs = np.random.default_rng(2).normal(size=(16, 3))
    rotated = coeffs.copy()
    for band, M in enumerate(sh_band_rotations(R, 3), start=1):
        sl = slice(band * band, (band + 1) ** 2)
        rotated[sl] = M @ coeffs[sl]
        assert np.allclose(M @ M.T, np.eye(2 * band + 1), atol=1e-9)  # a rotation of the band
    d = np.random.default_rng(3).normal(size=(50, 3))
    new = spherical_harmonics(3, torch.from_numpy(d), torch.from_numpy(rotated)[None].expand(50, -1, -1))
    old = spherical_harmonics(3, torch.from_numpy(d @ R.T), torch.from_numpy(coeffs)[None].expand(50, -1, -1))
    assert torch.allclose(new, old, atol=1e-9)


def test_similarity_and_quaternions() -> None:
    R = _random_rotation(4)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = 2.5 * R, [1.0, -2.0, 0.5]
    s, R2, t = split_similarity(T)
    assert s == pytest.approx(2.5) and np.allclose(R2, R) and np.allclose(t, [1.0, -2.0, 0.5])
    bad = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(Exception, match="not a rotation and scale"):
        split_similarity(bad)
    q = np.array([[0.5, 0.5, 0.5, 0.5]])
    assert np.allclose(quat_multiply(np.array([1.0, 0, 0, 0]), q), q)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:

    root = tmp_path_factory.mktemp("export")
    out = root / "run"
    cfg = root / "cfg.json"
    cfg.write_text(json.dumps({"render": {"sh_degree_interval": 5}}))  # SH bands in use within 20 steps
    train_tiny_run(root, "--config", str(cfg))
    return out


def _render(p: dict[str, np.ndarray], viewmat: np.ndarray, K: np.ndarray, w: int, h: int) -> torch.Tensor:
    from jsgs.render import rasterize

    t = {k: torch.from_numpy(np.ascontiguousarray(v)).double() for k, v in p.items()}
    colors = torch.cat([t["sh0"], t["shN"]], dim=1)
    rgb, _, _ = rasterize(
        t["means"], t["quats"] / t["quats"].norm(dim=1, keepdim=True), torch.exp(t["scales_log"]),
        torch.sigmoid(t["opacities_logit"]), colors, torch.from_numpy(viewmat)[None].double(),
        torch.from_numpy(K)[None].double(), w, h, sh_degree=3, backend="torch", near_plane=1e-4,
    )  # fmt: skip
    return rgb[0]


def test_colmap_frame_renders_what_was_trained(run: Path) -> None:
    from jsgs.apps.viewer import load_run_model
    from jsgs.base.ply import load_ply

    model = load_run_model(run, "cpu")
    T = np.asarray(json.loads((run / "config.json").read_text())["derived"]["normalization"])
    s, R, t = split_similarity(T)
    assert not np.allclose(T, np.eye(4))  # the tiny scene is normalised: the test is not trivial
    trained = load_ply(run / "point_cloud.ply")
    assert np.abs(trained["shN"]).max() > 1e-4  # view-dependent colour was learned
    colmap = to_colmap_frame(trained, T)
    for v in model.scene.views[:3]:
        c2w = v.camtoworld
        c2w_colmap = np.eye(4)
        c2w_colmap[:3, :3] = R.T @ c2w[:3, :3]
        c2w_colmap[:3, 3] = R.T @ (c2w[:3, 3] - t) / s
        a = _render(trained, np.linalg.inv(c2w), v.K, v.width, v.height)
        b = _render(colmap, np.linalg.inv(c2w_colmap), v.K, v.width, v.height)
        assert (a - b).abs().max() < 1e-6, float((a - b).abs().max())
        # the centres project to the same pixels
        def proj(x: np.ndarray, vm: np.ndarray, K: np.ndarray = v.K) -> np.ndarray:
            pc = x @ vm[:3, :3].T + vm[:3, 3]
            return (pc[:, :2] / pc[:, 2:]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]

        pa = proj(trained["means"].astype(np.float64), np.linalg.inv(c2w))
        pb = proj(colmap["means"].astype(np.float64), np.linalg.inv(c2w_colmap))
        assert np.abs(pa - pb).max() < 1e-3


def test_cli_export_formats_and_record(run: Path, tmp_path: Path) -> None:
    from jsgs.base.ply import load_ply, property_names, read_ply_vertices
    from jsgs.base.schema import validate
    from jsgs.cli import main

    out = tmp_path / "scene.ply"
    r = CliRunner().invoke(main, ["export", str(run), "--out", str(out)])
    assert r.exit_code == 0, r.output
    rec = json.loads((tmp_path / "scene.ply.json").read_text())
    validate(rec, "export", "record")
    assert rec["settings"] == {"format": "ply", "frame": "colmap"}
    names = list(read_ply_vertices(out).dtype.names or ())
    standard = [n for n in property_names(15) if n not in ("nx", "ny", "nz")]
    assert [n for n in names if n not in ("nx", "ny", "nz")] == standard  # the 3DGS layout viewers read
    back = load_ply(out)
    assert back["means"].shape[0] == rec["gaussians"] and back["shN"].shape[1] == 15
    for fmt in ("splat", "ply-compressed"):
        f = tmp_path / f"scene.{fmt}"
        args = ["export", str(run), "--out", str(f), "--format", fmt, "--frame", "training"]
        r = CliRunner().invoke(main, args)
        assert r.exit_code == 0 and f.stat().st_size > 0, r.output
    assert (tmp_path / "scene.splat").stat().st_size == 32 * rec["gaussians"]  # antimatter15: 32 B/splat
    r = CliRunner().invoke(main, ["export", str(run), "--out", str(out)])
    assert r.exit_code == 1 and "exists (use --force" in r.output
    r = CliRunner().invoke(main, ["export", str(tmp_path), "--out", str(tmp_path / "x.ply")])
    assert r.exit_code == 1 and "not a run folder" in r.output and r.output.count("\n") == 1
    assert math.isfinite(rec["bytes"])
