"""A tiny synthetic scene for the trainer's tests: a manifest (schemas/manifest.schema.json) with PNG views
rendered by the reference rasterizer from a known set of Gaussians, and the initial point cloud taken from
those Gaussians' centres (jittered), so that a few dozen steps visibly reduce the loss on CPU."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image


def look_at(centre: np.ndarray, target: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t), OpenCV axes (x right, y down, z forward)."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ centre


def gt_gaussians(n: int, rng: np.random.Generator) -> dict[str, torch.Tensor]:
    means = rng.uniform(-1.0, 1.0, (n, 3)) * np.array([1.0, 1.0, 0.5])
    colors = rng.uniform(0.1, 0.9, (n, 3))
    return {
        "means": torch.tensor(means, dtype=torch.float32),
        "quats": torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32),
        "scales": torch.tensor(rng.uniform(0.08, 0.25, (n, 3)), dtype=torch.float32),
        "opacities": torch.tensor(rng.uniform(0.6, 0.95, n), dtype=torch.float32),
        "colors": torch.tensor(colors, dtype=torch.float32),
    }


def make_scene(
    root: Path,
    *,
    n_views: int = 6,
    width: int = 32,
    height: int = 24,
    n_gaussians: int = 40,
    test_every: int = 3,
    seed: int = 0,
    jpeg_train: bool = False,
) -> Path:
    """Write ``root/manifest.json`` and ``root/images/*.png``; returns the manifest path.

    Views on a ring of radius 4 around the origin, looking at it; every ``test_every``-th view is a test
    view. With ``jpeg_train`` the training views are saved as JPEG (quality 75) with a ``jpeg`` state and a
    lossless reference; test views are always lossless PNGs."""
    from jsgs.render import rasterize

    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    (root / "images").mkdir(exist_ok=True)
    gt = gt_gaussians(n_gaussians, rng)
    f = 0.9 * width
    views: list[dict[str, Any]] = []
    for i in range(n_views):
        a = 2 * math.pi * i / n_views
        centre = np.array([4.0 * math.cos(a), 4.0 * math.sin(a), 1.0])
        R, t = look_at(centre, np.zeros(3), np.array([0.0, 0.0, 1.0]))
        viewmat = torch.eye(4)
        viewmat[:3, :3] = torch.tensor(R, dtype=torch.float32)
        viewmat[:3, 3] = torch.tensor(t, dtype=torch.float32)
        K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float32)
        with torch.no_grad():
            img, alpha, _ = rasterize(
                gt["means"], gt["quats"], gt["scales"], gt["opacities"], gt["colors"], viewmat[None], K[None],
                width, height, backend="torch",
            )  # fmt: skip
        # a grey background so that empty pixels carry a colour too
        rgb = img[0] + 0.35 * (1 - alpha[0])
        arr = (rgb.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
        split = "test" if i % test_every == 0 else "train"
        name = f"view_{i:03d}.png"
        ref = f"images/{name}"
        Image.fromarray(arr).save(root / ref)
        image, jpeg, reference = ref, None, None
        if jpeg_train and split == "train":
            image = f"images/view_{i:03d}.jpg"
            Image.fromarray(arr).save(root / image, quality=75)
            jpeg = jpeg_state(75)
            reference = ref
        views.append(
            {
                "name": name,
                "image": image,
                "split": split,
                "camera": {
                    "model": "PINHOLE",
                    "width": width,
                    "height": height,
                    "fx": f,
                    "fy": f,
                    "cx": width / 2,
                    "cy": height / 2,
                    "distortion": None,
                },  # fmt: skip
                "R": R.tolist(),
                "t": t.tolist(),
                "jpeg": jpeg,
                "reference": reference,
            }
        )
    pts = gt["means"].numpy().astype(np.float64)
    pts = np.concatenate([pts, pts + rng.normal(scale=0.1, size=pts.shape)])
    rgb = np.concatenate([gt["colors"].numpy()] * 2)
    manifest = {
        "format": "jsgs-manifest",
        "format_version": 1,
        "producer": {"tool": "tests", "version": "0", "command": "make_scene", "settings": {}},
        "scene": {
            "name": "tiny",
            "source": str(root),
            "schedule": "clean",
            "quality": None,
            "seed": seed,
            "test_every": test_every,
            "subsampling": None,
            "downscale": None,
            "undistorted": False,
        },  # fmt: skip
        "views": views,
        "points": {
            "count": len(pts),
            "xyz": pts.tolist(),
            "rgb": (rgb * 255).round().astype(int).tolist(),
        },
    }
    path = root / "manifest.json"
    path.write_text(json.dumps(manifest))
    return path


def jpeg_state(quality: int) -> dict[str, Any]:
    from jsgs.jpeg.tables import ijg_tables

    luma, chroma = ijg_tables(quality)
    return {
        "luma_table": np.asarray(luma).tolist(),
        "chroma_table": np.asarray(chroma).tolist(),
        "sampling": "4:2:0",
        "quality": quality,
        "quality_exact": True,
        "precision": 8,
    }


def edit_manifest(path: Path, fn: Any) -> None:
    """Apply ``fn(doc)`` (in place) to the manifest JSON at ``path``."""
    doc = json.loads(path.read_text())
    fn(doc)
    path.write_text(json.dumps(doc))


def short_jsgs_runs(
    tmp_path: Path, variants: dict[str, dict[str, Any]], iterations: int = 30
) -> dict[str, tuple[dict[str, Any], dict[str, torch.Tensor]]]:
    """Train the ``jsgs`` method for ``iterations`` steps on the synthetic JPEG scene once per variant
    (``λ_fro = 1`` plus the variant's method options, no densification, so the Gaussians stay matched one
    to one across runs), each into ``tmp_path/<name>``; returns name -> (the final eval, the final
    checkpoint's splats)."""
    from jsgs.train import checkpoint as ckpt
    from jsgs.train.config import TrainConfig
    from jsgs.train.trainer import train

    manifest = make_scene(tmp_path / "scene", jpeg_train=True, n_views=9, n_gaussians=60)
    runs = {}
    for name, opts in variants.items():
        c = TrainConfig.from_preset(
            "paper", method="jsgs", iterations=iterations, eval_at=[iterations], device="cpu"
        )
        c.method_options = {"lambda_fro": 1.0, **opts}
        c.strategy.refine_start_iter = 10**6
        c.eval.fps_passes, c.eval.fps_warmup, c.eval.save_renders = 1, 0, False
        ev = train(manifest, tmp_path / name, c, progress=False)["evals"][-1]
        checkpoint = tmp_path / name / "checkpoints" / f"step_{iterations:06d}.pt"
        runs[name] = (ev, ckpt.load_checkpoint(checkpoint)["splats"])
    return runs


def train_tiny_run(root: Path, *options: str, iterations: int = 20, eval_at: str = "20",
                   manifest: Path | None = None) -> Any:  # fmt: skip
    """``jsgs train`` on the CPU for ``iterations`` steps (evaluations at ``eval_at``) into ``root/run``, on
    ``manifest`` or a new 32×24 :func:`make_scene` in ``root/scene``, with more ``options``; asserts it
    succeeded and returns click's result (the run folder is ``root / "run"``)."""
    from click.testing import CliRunner

    from jsgs.cli import main

    manifest = manifest or make_scene(root / "scene", width=32, height=24)
    args = ["train", str(manifest), "--out", str(root / "run"), "--iterations", str(iterations), "--eval-at",
            eval_at, "--device", "cpu", "--quiet", *options]  # fmt: skip
    r = CliRunner().invoke(main, args, catch_exceptions=False)
    assert r.exit_code == 0, r.output + r.stderr
    return r


def invoke_afresh(args: list[str]) -> Any:
    """``jsgs ARGS`` as a command of its own: the notes said once per process (``jsgs.train.config``'s)
    start afresh, as in a new process; click's result."""
    from click.testing import CliRunner

    from jsgs.cli import main
    from jsgs.train import config

    config._said.clear()
    return CliRunner().invoke(main, args)
