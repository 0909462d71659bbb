"""Speed and accuracy of the two ways ``jsgs.ssim`` can blur (the five local moments of SSIM).

Every training step computes SSIM once for ℓ_ph and, with ``--method jsgs``, once more for L_obs, forward and
backward; the separable 11-tap Gaussian blur is most of it. Two implementations (``jsgs.ssim.BLUR``):

* ``conv``: two grouped 1-D convolutions (cuDNN runs one kernel per group: 15 per pass for five RGB moments,
  plus layout transforms);
* ``tiled``: banded matrix products on tiles of 32 output rows / columns (a few batched GEMMs).

    .venv/bin/python benchmarks/bench_ssim.py [--device cuda] [--sizes 504x378,1297x840] [--repeats 50]

Per size and implementation: milliseconds per ``1 - ssim`` forward + backward of one (1, 3, H, W) pair, host
wall time (device-synchronised, median of ``--repeats``) and, on CUDA, the device time of the same work
replayed as a CUDA graph (no launch cost: what it costs inside the JSGS graph, and the GPU work it adds to any
step); aten kernels per call (``jsgs.opcount.KernelCounter``; cuDNN's per-group launches are not aten ops);
the error against float64: the largest absolute difference of SSIM and of its gradient, relative to the
gradient's largest magnitude. cuDNN's TF32 is off, as in training. Prints a markdown table; ``--out`` JSON.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jsgs  # noqa: E402
from jsgs import ssim as ssim_mod  # noqa: E402
from jsgs.opcount import KernelCounter  # noqa: E402
from jsgs.ssim import ssim  # noqa: E402


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _loss_and_grad(x: torch.Tensor, y: torch.Tensor, impl: str) -> tuple[torch.Tensor, torch.Tensor]:
    saved = dict(ssim_mod.BLUR)
    ssim_mod.BLUR[x.device.type] = impl
    try:
        xr = x.detach().clone().requires_grad_()
        loss = 1.0 - ssim(xr, y, padding="valid")
        loss.backward()
        return loss.detach(), xr.grad
    finally:
        ssim_mod.BLUR.clear()
        ssim_mod.BLUR.update(saved)


def _graph_ms(x: torch.Tensor, y: torch.Tensor, impl: str, repeats: int) -> float:
    """Device milliseconds of one forward + backward replayed as a CUDA graph (CUDA events)."""
    saved = dict(ssim_mod.BLUR)
    ssim_mod.BLUR["cuda"] = impl
    try:
        xr = x.detach().clone().requires_grad_()
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(3):
                (1.0 - ssim(xr, y, padding="valid")).backward()
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            (1.0 - ssim(xr, y, padding="valid")).backward()
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        graph.replay()
        start.record()
        for _ in range(repeats):
            graph.replay()
        end.record()
        torch.cuda.synchronize()
        return start.elapsed_time(end) / repeats
    finally:
        ssim_mod.BLUR.clear()
        ssim_mod.BLUR.update(saved)


def measure(size: tuple[int, int], impl: str, device: torch.device, repeats: int) -> dict[str, Any]:
    w, h = size
    g = torch.Generator().manual_seed(0)
    x64 = torch.rand(1, 3, h, w, generator=g, dtype=torch.float64)
    y64 = (x64 + 0.1 * torch.randn(1, 3, h, w, generator=g, dtype=torch.float64)).clamp(0, 1)
    x, y = x64.float().to(device), y64.float().to(device)
    ref_loss, ref_grad = _loss_and_grad(x64, y64, "conv")
    loss, grad = _loss_and_grad(x, y, impl)
    with KernelCounter() as k:
        _loss_and_grad(x, y, impl)
    for _ in range(3):
        _loss_and_grad(x, y, impl)
    times = []
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        _loss_and_grad(x, y, impl)
        _sync(device)
        times.append(time.perf_counter() - t0)
    gmax = ref_grad.abs().max().item()
    return {
        "size": f"{w}x{h}",
        "impl": impl,
        "ms": 1000.0 * statistics.median(times),
        "graph_ms": _graph_ms(x, y, impl, repeats) if device.type == "cuda" else None,
        "kernels": k.total,
        "loss_abs_err": abs(loss.double().item() - ref_loss.item()),
        "grad_rel_err": (grad.double().cpu() - ref_grad).abs().max().item() / gmax,
    }


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--sizes", default="504x378,1297x840", help="image sizes WxH [504x378,1297x840]")
    ap.add_argument("--impls", default="conv,tiled", help="blur implementations [conv,tiled]")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--out", type=Path, help="write the rows as JSON here")
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    torch.backends.cudnn.allow_tf32 = False  # as the trainer runs
    rows = []
    for s in args.sizes.split(","):
        w, h = (int(v) for v in s.lower().split("x"))
        for impl in args.impls.split(","):
            rows.append(measure((w, h), impl, device, args.repeats))
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    print(f"1 - SSIM (valid), forward + backward, {name}, torch {torch.__version__}")
    print()
    print("| size | blur | host ms / call | device ms (graph) | aten kernels | SSIM abs err | grad rel err |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for r in rows:
        g = "–" if r["graph_ms"] is None else f"{r['graph_ms']:.3f}"
        print(
            f"| {r['size']} | {r['impl']} | {r['ms']:.3f} | {g} | {r['kernels']} | {r['loss_abs_err']:.1e} | "
            f"{r['grad_rel_err']:.1e} |"
        )
    if args.out:
        from jsgs.io import write_json_atomic
        from jsgs.schemas import validate

        doc = {
            "format": "jsgs-bench-ssim",
            "format_version": 1,
            "version": jsgs.__version__,
            "settings": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
            "device_name": name,
            "torch": torch.__version__,
            "rows": rows,
        }
        validate(doc, "bench_ssim", str(args.out))
        write_json_atomic(args.out, doc)
    return rows


if __name__ == "__main__":
    main()
