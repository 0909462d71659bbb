"""Evaluation at the ``--eval-at`` steps: image metrics against the uncompressed references, render speed,
model size and peak memory.

- PSNR / SSIM / LPIPS-alex via :func:`jsgs.metrics.evaluate_images` on renders clamped to [0, 1] (as
  gsplat's simple_trainer), at the final SH degree, against each test view's lossless reference.
- FPS: ``fps_warmup`` untimed passes over the test views, then ``fps_passes`` timed passes, each pass
  bracketed by device synchronisation and timed with ``time.perf_counter``; FPS = views / median pass time.
  Rendering only (no metrics, no copies to the host).
- Peak memory: on CUDA ``torch.cuda.max_memory_allocated`` since the run (or the resumed part of it) began;
  on CPU the process's peak resident set size (``ru_maxrss``), which includes Python and torch themselves.
"""

from __future__ import annotations

import math
import re
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from jsgs.train.config import TrainConfig
from jsgs.train.data import TrainingScene, TrainingView
from jsgs.train.render_view import render_view


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


#: device -> the largest ``max_memory_allocated`` read just before a :func:`reset_peak_allocated`
_EARLIER_PEAKS: dict[torch.device, int] = {}


def reset_peak_allocated(device: torch.device, forget: bool = False) -> None:
    """``torch.cuda.reset_peak_memory_stats(device)``, remembering the peak it clears so that
    :func:`peak_memory` still reports the run's (a phase profiler resets at every phase); ``forget``: the run
    begins here (nothing earlier counts)."""
    if forget:
        _EARLIER_PEAKS.pop(device, None)
    else:
        peak = int(torch.cuda.max_memory_allocated(device))
        _EARLIER_PEAKS[device] = max(_EARLIER_PEAKS.get(device, 0), peak)
    torch.cuda.reset_peak_memory_stats(device)


def peak_memory(device: torch.device) -> tuple[int, str]:
    """(bytes, kind) of the peak memory so far (see the module docstring)."""
    if device.type == "cuda":
        peak = max(int(torch.cuda.max_memory_allocated(device)), _EARLIER_PEAKS.get(device, 0))
        return peak, "cuda_max_allocated"
    import resource

    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    # Linux reports KiB, macOS bytes
    return int(rss if sys.platform == "darwin" else rss * 1024), "cpu_max_rss"


def safe_name(view: TrainingView) -> str:
    stem = Path(view.name).stem or "view"
    return f"{view.index:04d}_{re.sub(r'[^A-Za-z0-9._-]+', '_', stem)}.png"


def _finite_or_none(x: float | None) -> float | None:
    if x is None or not math.isfinite(x):
        return None
    return float(x)


@torch.no_grad()
def render_test_views(
    splats: torch.nn.ParameterDict,
    views: list[TrainingView],
    cfg: TrainConfig,
    backend: str,
    device: torch.device,
) -> list[Tensor]:
    """[H, W, 3] float renders in [0, 1] (clamped) of ``views`` at the final SH degree."""
    out = []
    for v in views:
        r = render_view(
            splats,
            v.viewmat_tensor(device),
            v.K_tensor(device),
            v.width,
            v.height,
            cfg.render.sh_degree,
            cfg,
            backend,
            distortion=v.distortion_tensor(device),
        )
        out.append(r.rgb[0].clamp(0.0, 1.0))
    return out


@torch.no_grad()
def measure_fps(
    splats: torch.nn.ParameterDict,
    views: list[TrainingView],
    cfg: TrainConfig,
    backend: str,
    device: torch.device,
) -> dict[str, Any]:
    """Median render speed over the test views (see the module docstring)."""
    args = [
        (v.viewmat_tensor(device), v.K_tensor(device), v.width, v.height, v.distortion_tensor(device))
        for v in views
    ]
    for _ in range(cfg.eval.fps_warmup):
        for vm, K, w, h, dist in args:
            render_view(splats, vm, K, w, h, cfg.render.sh_degree, cfg, backend, distortion=dist)
    times = []
    for _ in range(cfg.eval.fps_passes):
        synchronize(device)
        t0 = time.perf_counter()
        for vm, K, w, h, dist in args:
            render_view(splats, vm, K, w, h, cfg.render.sh_degree, cfg, backend, distortion=dist)
        synchronize(device)
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    return {
        "fps": len(views) / med if med > 0 else None,
        "render_ms": 1000.0 * med / len(views),
        "fps_passes": cfg.eval.fps_passes,
    }


def save_png(path: Path, image: Tensor) -> None:
    """[H, W, 3] float in [0, 1] -> 8-bit PNG (rounded), written atomically."""
    from PIL import Image

    from jsgs.base.io import write_with_atomic

    arr = (image.detach().float().cpu().numpy() * 255.0 + 0.5).clip(0, 255).astype(np.uint8)
    write_with_atomic(path, lambda p: Image.fromarray(arr).save(p, format="PNG"))


@torch.no_grad()
def evaluate(
    splats: torch.nn.ParameterDict,
    scene: TrainingScene,
    references: dict[int, Tensor],
    cfg: TrainConfig,
    backend: str,
    device: torch.device,
    step: int,
    render_dir: Path | None,
) -> dict[str, Any]:
    """Metrics of the current model on the test views (one entry of metrics.json ``evals``, without the
    training-time fields the loop adds). ``references``: view index -> [H, W, 3] uint8."""
    from jsgs.metrics import evaluate_images

    t0 = time.perf_counter()
    views = scene.test_views
    renders = render_test_views(splats, views, cfg, backend, device)
    preds = [r.permute(2, 0, 1) for r in renders]
    refs = [references[v.index].permute(2, 0, 1).float() / 255.0 for v in views]
    m = evaluate_images(preds, refs, lpips_weights=cfg.eval.lpips_weights)
    if render_dir is not None and cfg.eval.save_renders:
        for v, r in zip(views, renders, strict=True):
            save_png(render_dir / safe_name(v), r)
    per_view = []
    for v, pv in zip(views, m.per_view, strict=True):
        per_view.append(
            {
                "name": v.name,
                "psnr": _finite_or_none(pv.get("psnr")),
                "ssim": _finite_or_none(pv.get("ssim")),
                "lpips": _finite_or_none(pv.get("lpips")),
            }
        )
    speed = measure_fps(splats, views, cfg, backend, device)
    mem, kind = peak_memory(device)
    return {
        "step": step,
        "psnr": _finite_or_none(m.psnr),
        "ssim": _finite_or_none(m.ssim),
        "lpips": _finite_or_none(m.lpips),
        "lpips_note": m.lpips_note,
        "num_gaussians": int(splats["means"].shape[0]),
        **speed,
        "peak_memory_bytes": mem,
        "peak_memory_kind": kind,
        "eval_time_s": time.perf_counter() - t0,
        "views": per_view,
    }
