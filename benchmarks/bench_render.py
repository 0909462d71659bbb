"""Speed of the rasterizers: the pure-torch reference (CPU at the demo size, and GPU) against gsplat's CUDA
kernels, forward and forward+backward, plus the cost of the Gaussian Controller's pooled sums.

    .venv/bin/python benchmarks/bench_render.py              # CPU rows (and GPU rows when CUDA is there)
    .venv/bin/python benchmarks/bench_render.py --quick      # fewer repetitions and sizes

Scenes are random clouds in front of one camera (f = 1.2·width): SfM-initialisation-like (isotropic
scales from the point spacing, opacity 0.1 as gsplat's init) and trained-like (anisotropic, opacity
U(0.2, 1)). Times are medians over repetitions, synchronised on CUDA. Prints a Markdown table whose
pooling columns are: the extra time of a training step that puts ``probe_objective`` in its loss and
reads the sums after backward; of one that calls ``pool_now`` before backward (one more rasteriser
backward); and ``pool_direct`` on its own (reference tiles, no autograd).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jsgs.method.pooling import (  # noqa: E402
    new_probe,
    pool_direct,
    pool_from_grad,
    pool_now,
    probe_objective,
)
from jsgs.render import rasterize  # noqa: E402


def make_scene(n: int, width: int, height: int, kind: str, device: torch.device, seed: int = 0) -> dict:
    """n Gaussians in a 4 x 3 x 2 box 3-5 units in front of an identity camera; SH degree 3 colours."""
    g = torch.Generator().manual_seed(seed)
    box = torch.tensor([4.0, 3.0, 2.0])
    means = (torch.rand(n, 3, generator=g) - 0.5) * box + torch.tensor([0, 0, 4.0])
    spacing = (box.prod().item() / n) ** (1 / 3)
    if kind == "init":
        scales = torch.full((n, 3), 0.5 * spacing) * torch.exp(0.2 * torch.randn(n, 1, generator=g))
        opacities = torch.full((n,), 0.1)
    else:
        scales = 0.4 * spacing * torch.exp(0.6 * torch.randn(n, 3, generator=g))
        opacities = torch.rand(n, generator=g) * 0.8 + 0.2
    f = 1.2 * width
    s = dict(
        means=means,
        quats=torch.randn(n, 4, generator=g),
        scales=scales,
        opacities=opacities,
        sh=torch.randn(n, 16, 3, generator=g) * 0.2,
        viewmats=torch.eye(4)[None],
        Ks=torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])[None],
    )
    return {k: v.to(device) for k, v in s.items()}


def timed(fn: Callable[[], object], device: torch.device, reps: int, warmup: int = 2) -> float:
    """Median wall time of fn() in milliseconds."""
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(reps):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        out.append((time.perf_counter() - t) * 1e3)
    return statistics.median(out)


def bench_case(s: dict, width: int, height: int, backend: str, reps: int) -> dict:
    dev = s["means"].device
    leaves = {k: s[k].clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "sh")}

    def render(probe: bool = False):
        extra = (
            new_probe(s["means"].shape[0], s["means"], n_cameras=s["viewmats"].shape[0]) if probe else None
        )
        return rasterize(
            leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["sh"],
            s["viewmats"], s["Ks"], width, height, sh_degree=3, backend=backend, extra=extra,
        )  # fmt: skip

    def fwd() -> None:
        with torch.no_grad():
            rasterize(
                s["means"], s["quats"], s["scales"], s["opacities"], s["sh"], s["viewmats"], s["Ks"],
                width, height, sh_degree=3, backend=backend,
            )  # fmt: skip

    def fwd_bwd() -> None:
        img, alpha, info = render()
        info["means2d"].retain_grad()
        (img.square().mean() + alpha.mean()).backward()

    r = torch.rand(1, height, width, device=dev)

    def fwd_bwd_pool() -> None:
        img, alpha, info = render(probe=True)
        info["means2d"].retain_grad()
        pool_now(info, r)
        (img.square().mean() + alpha.mean()).backward()

    def fwd_bwd_probe() -> None:
        img, alpha, info = render(probe=True)
        info["means2d"].retain_grad()
        (img.square().mean() + alpha.mean() + probe_objective(info, r)).backward()
        pool_from_grad(info)

    def direct() -> None:
        pool_direct(
            s["means"], s["quats"], s["scales"], s["opacities"], s["viewmats"], s["Ks"], width, height, r
        )

    with torch.no_grad():
        _, alpha, info = render()
    row = {
        "fwd": timed(fwd, dev, reps),
        "fwd+bwd": timed(fwd_bwd, dev, reps),
        "fwd+bwd+pool_now": timed(fwd_bwd_pool, dev, reps),
        "fwd+bwd+probe": timed(fwd_bwd_probe, dev, reps),
        "pool_direct": timed(direct, dev, max(1, reps // 2)),
        "isects": int(info["tiles_per_gauss"].sum()),
        "coverage": alpha.mean().item(),
    }
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer repetitions and sizes")
    ap.add_argument("--cpu-only", action="store_true")
    ap.add_argument("--gpu-only", action="store_true")
    args = ap.parse_args()
    reps = 3 if args.quick else 7
    cases: list[tuple[str, str, int, int, int, str]] = []  # device, backend, W, H, N, kind
    if not args.gpu_only:
        for n in (1000, 3000) if args.quick else (1000, 3000, 10000):
            for kind in ("init", "trained"):
                cases.append(("cpu", "torch", 160, 120, n, kind))
    if torch.cuda.is_available() and not args.cpu_only:
        for backend in ("gsplat", "torch"):
            cases.append(("cuda", backend, 160, 120, 3000, "init"))
            cases.append(("cuda", backend, 504, 378, 100_000, "init"))
            cases.append(("cuda", backend, 504, 378, 100_000, "trained"))
            if not args.quick:
                cases.append(("cuda", backend, 1008, 756, 300_000, "trained"))
    print(f"torch {torch.__version__}, CPU threads {torch.get_num_threads()}", end="")
    if torch.cuda.is_available():
        print(f", GPU {torch.cuda.get_device_name()}", end="")
    print()
    print(
        "| device | backend | size | N | scene | isects | fwd ms | fwd+bwd ms | it/s | "
        "+probe in loss ms | +pool_now ms | pool_direct ms |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for device, backend, w, h, n, kind in cases:
        s = make_scene(n, w, h, kind, torch.device(device))
        row = bench_case(s, w, h, backend, reps)
        print(
            f"| {device} | {backend} | {w}x{h} | {n} | {kind} | {row['isects']} | {row['fwd']:.1f} | "
            f"{row['fwd+bwd']:.1f} | {1e3 / row['fwd+bwd']:.1f} | "
            f"{row['fwd+bwd+probe'] - row['fwd+bwd']:+.1f} | "
            f"{row['fwd+bwd+pool_now'] - row['fwd+bwd']:+.1f} | {row['pool_direct']:.1f} |",
            flush=True,
        )
        del s
        if device == "cuda":
            torch.cuda.empty_cache()


if __name__ == "__main__":
    main()
