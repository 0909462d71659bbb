"""SSIM's forward + backward: the fused CUDA kernel (``jsgs/kernels/csrc/ssim.cu``) against the torch twin
(two grouped 1-D convolutions, ``jsgs.kernels``), timed eagerly and as a CUDA-graph replay, with each one's
error against the twin in float64. This is the loss term that both the baseline's ℓ_ph and JSGS's L_obs pay
once per step, so its cost moves the per-iteration time of both methods.

    python3 benchmarks/bench_ssim.py [--sizes 504x378,1297x840] [--repeats 200] [--padding valid]

Prints one table: per image size and implementation, milliseconds per forward + backward (median of
``--repeats``, CUDA events; "graph": the same call recorded once with ``torch.cuda.make_graphed_callables``
and replayed), the speed-up over the twin measured in this run, and the largest absolute difference of the
SSIM value and of the gradient from the float64 twin. CUDA only.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jsgs.kernels import ssim  # noqa: E402


def _time_ms(fn: Callable[[], object], repeats: int) -> float:
    for _ in range(5):
        fn()
    times = []
    for _ in range(repeats):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record()
        fn()
        b.record()
        b.synchronize()
        times.append(a.elapsed_time(b))
    return statistics.median(times)


def _inputs(w: int, h: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 3, h, w, generator=g)
    y = (x + 0.1 * torch.randn(1, 3, h, w, generator=g)).clamp(0, 1)
    return x.cuda(), y.cuda()


def measure(
    w: int, h: int, kernel: str, graph: bool, padding: str, repeats: int
) -> tuple[float, float, float]:
    """(ms per forward + backward, |SSIM - float64 twin|, max |grad - float64 twin's grad|)."""
    x, y = _inputs(w, h)
    xg = x.clone().requires_grad_()

    def loss(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return 1.0 - ssim(a, b, padding=padding, kernel=kernel)

    fn = torch.cuda.make_graphed_callables(loss, (xg, y)) if graph else loss

    def step() -> torch.Tensor:
        xg.grad = None
        out = fn(xg, y)
        out.backward()
        return out

    ms = _time_ms(step, repeats)
    value = step().item()
    x64 = x.double().requires_grad_()
    ref = 1.0 - ssim(x64, y.double(), padding=padding, kernel="torch")
    ref.backward()
    return ms, abs(value - ref.item()), (xg.grad.double() - x64.grad).abs().max().item()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="504x378,1297x840", help="WxH list")
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--padding", default="valid", choices=("valid", "same"))
    a = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("error: bench_ssim needs CUDA", file=sys.stderr)
        return 1
    sizes = [tuple(int(v) for v in s.split("x")) for s in a.sizes.split(",")]
    print(f"device {torch.cuda.get_device_name()}, torch {torch.__version__}, padding {a.padding}, "
          f"median of {a.repeats}")
    print("\n| size | SSIM | launch | ms / fwd+bwd | speed-up vs torch (same launch) | |ΔSSIM| vs float64 | "
          "max |Δgrad| vs float64 |")
    print("|---|---|---|---:|---:|---:|---:|")
    for w, h in sizes:
        for graph in (False, True):
            base = None
            for kernel in ("torch", "cuda"):
                ms, dv, dg = measure(w, h, kernel, graph, a.padding, a.repeats)
                base = ms if base is None else base
                launch = "graph" if graph else "eager"
                row = f"| {w}x{h} | {kernel} | {launch} | {ms:.3f} | {base / ms:.2f}x"
                print(f"{row} | {dv:.2e} | {dg:.2e} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
