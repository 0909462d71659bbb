"""Host time of the JSGS image terms (JO, L_obs, DS) per step, without a profiler, forward call and backward
call timed separately, for three ways of running them:

- eager: :func:`jsgs.method.image_terms.image_terms` and autograd;
- two graphs: ``torch.cuda.make_graphed_callables`` on the same function (a forward graph and a backward
  graph, with its copies of inputs and upstream gradients);
- one graph: ``jsgs.method.graphed.GraphedImageTerms`` (forward and the weighted sum's gradient in one replay;
  the backward scales the stored gradient).

    python tools/diagnostics/bench_graph_host.py [--size 504x378] [--steps 300]      # CUDA only

A training step is partly host-bound (``tools/diagnostics/trace_gaps.py``), and a profiler inflates exactly
the
host work it would measure (CUPTI instruments every graph node), so this times the Python calls with
``time.perf_counter`` and no synchronisation inside the timed region: the number is what the host spends
launching, while the device works behind it. The device is synchronised between steps, outside the timing;
``total`` is the forward + backward time with a synchronisation at the end (host and device together).
Medians over ``--steps`` after 20 untimed steps. Prints one table (µs).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from jsgs.method.graphed import GraphedImageTerms  # noqa: E402
from jsgs.method.image_terms import (
    image_term_settings,  # noqa: E402
    image_terms,  # noqa: E402
)
from jsgs.method.options import JsgsOptions  # noqa: E402
from jsgs.train.config import TrainConfig  # noqa: E402

# the training defaults: paper mode, DS and GC on, the trainer's photometric loss
_CFG = TrainConfig.from_preset("paper")
SETTINGS = image_term_settings(
    JsgsOptions(), _CFG.loss.ssim_lambda, _CFG.loss.ssim_padding, _CFG.speed.ssim_kernel
)


def measure(fn: Callable[[Tensor], Tensor], x: Tensor, steps: int) -> dict[str, float]:
    """Median µs of the forward call ``fn(x)`` (the weighted loss), the backward call (host only) and both
    with a final sync."""
    fwd, bwd, both = [], [], []
    for i in range(steps + 20):
        xi = x.detach().clone().requires_grad_(True)
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        loss = fn(xi)
        t1 = time.perf_counter()
        loss.backward()
        t2 = time.perf_counter()
        torch.cuda.synchronize()
        t3 = time.perf_counter()
        if i >= 20:
            fwd.append(t1 - t0)
            bwd.append(t2 - t1)
            both.append(t3 - t0)
    return {k: 1e6 * statistics.median(v) for k, v in (("forward", fwd), ("backward", bwd), ("total", both))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="504x378", help="image size WxH [504x378]")
    ap.add_argument("--steps", type=int, default=300, help="timed steps per variant [300]")
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("error: bench_graph_host needs CUDA (it times host launches of GPU work)", file=sys.stderr)
        return 1
    w_px, h_px = (int(v) for v in args.size.lower().split("x"))
    g = torch.Generator(device="cuda").manual_seed(0)
    x = torch.rand(1, 3, h_px, w_px, device="cuda", generator=g)
    y = torch.rand(1, 3, h_px, w_px, device="cuda", generator=g)
    luma = torch.randint(2, 60, (8, 8), device="cuda", generator=g).float()
    chroma = torch.randint(2, 90, (8, 8), device="cuda", generator=g).float()

    tables = torch.stack([luma, chroma])
    w = (0.2, 0.02, 0.03)

    def eager(xi: Tensor) -> Tensor:
        out = image_terms(xi, y, luma, chroma, sampling="4:2:0", **SETTINGS)
        return w[0] * out[0] + w[1] * out[1] + w[2] * out[2]

    sample = (x.detach().clone().requires_grad_(), y.clone(), luma.clone(), chroma.clone())
    two = torch.cuda.make_graphed_callables(
        partial(image_terms, sampling="4:2:0", **SETTINGS), sample, allow_unused_input=True
    )

    def two_graphs(xi: Tensor) -> Tensor:
        out = two(xi, y, luma, chroma)
        return w[0] * out[0] + w[1] * out[1] + w[2] * out[2]

    one = GraphedImageTerms(weights=w, **SETTINGS)

    def one_graph(xi: Tensor) -> Tensor:
        return one(xi, y, tables, "4:2:0").weighted

    mode = SETTINGS["mode"]
    print(f"{torch.cuda.get_device_name()}, torch {torch.__version__}, {w_px}x{h_px}, 4:2:0, {mode} mode")
    print("\n| variant | host µs forward | host µs backward | µs forward + backward + sync |")
    print("|---|---:|---:|---:|")
    variants = (("eager", eager), ("two graphs (make_graphed_callables)", two_graphs),
                ("one graph + known gradient", one_graph))  # fmt: skip
    for name, fn in variants:
        m = measure(fn, x, args.steps)
        print(f"| {name} | {m['forward']:.1f} | {m['backward']:.1f} | {m['total']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
