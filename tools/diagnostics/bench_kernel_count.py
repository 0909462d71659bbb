"""Kernels launched per training step by the JSGS terms, and their host cost, per phase.

At real scene sizes (llff at 504 x 378) JO, DS and the Gaussian Controller are launch-bound on a GPU: every
eager op costs 10-20 µs of host dispatch and launch (measured on an H200: the deferred GC's 144 kernels took
2.2 ms, about 15 µs each), far more than its arithmetic. The kernel count is then the cost model, and it is
the same on every device, so this benchmark runs anywhere:

    .venv/bin/python tools/diagnostics/bench_kernel_count.py [--size 96x64] [--gaussians 1000] [--modes paper]
        [--sampling 4:2:0] [--device cpu] [--repeats 200]

Per phase, for one view (``B = 1``): JO forward (``jpeg_observe``), L_obs's photometric loss, DS forward
(``dct_supervision``), the backward through all three (λ-weighted as in training), and the deferred GC's
closed-form work inside the backward (r̄ from the pooled sums, ``controller_matrix``,
``fro_loss_and_grads``) for ``--gaussians`` Gaussians. Columns: kernels (aten ops that are not views,
counted by ``jsgs.apps.opcount.KernelCounter``) and the host time per call at the given size (median of
``--repeats``; at the default tiny size this is almost all dispatch, the part that a GPU cannot hide;
``--repeats 0``: not timed).

A second table gives the memory traffic per phase (MB read and written by the counted ops, bytes per pixel)
and what it costs at ``--bandwidth`` GB/s (default: an H100 SXM's 3,350): at large images the terms are
bound by that traffic, not by launches, so this is a lower bound on their device time per view without
kernel fusion:

    .venv/bin/python tools/diagnostics/bench_kernel_count.py --size 1440x1920 --repeats 0
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from jsgs.apps.opcount import KernelCounter, count_phases_detail, jsgs_step  # noqa: E402

PHASES = ("JO", "L_obs", "DS", "backward", "GC (in backward)")


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _host_ms(fn: Callable[[], object], device: torch.device, repeats: int) -> float:
    for _ in range(3):
        fn()
    times = []
    for _ in range(repeats):
        _sync(device)
        t = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times)


def measure(
    mode: str, sampling: str, size: tuple[int, int], n_gauss: int, device: torch.device, repeats: int
) -> dict[str, tuple[int, float]]:
    """phase -> (kernels, host ms per call, bytes moved); host ms is NaN with ``repeats`` 0."""
    steps = jsgs_step(mode, sampling, size, n_gauss, device)
    counted = count_phases_detail(steps)
    out = {name: (k.total, math.nan, k.bytes) for name, k in counted.items()}
    if repeats == 0:
        return out
    # the phases depend on each other: time the chain up to and including a phase, minus the chain before it
    for i, (name, fn) in enumerate(steps):
        before = [f for _, f in steps[:i]]

        def one(fn: Callable[[], None] = fn, before: list[Callable[[], None]] = before) -> None:
            for f in before:
                f()
            fn()

        chain = _host_ms(lambda before=before: [f() for f in before], device, repeats) if before else 0.0
        out[name] = (out[name][0], max(_host_ms(one, device, repeats) - chain, 0.0), out[name][2])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="96x64", help="W x H of the view (default 96x64: dispatch-bound)")
    ap.add_argument("--gaussians", type=int, default=1000)
    ap.add_argument("--modes", default="paper", help="comma list of paper, float, exact")
    ap.add_argument("--sampling", default="4:2:0")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=200, help="timed calls per phase (0: count only)")
    ap.add_argument("--bandwidth", type=float, default=3350.0, help="device memory bandwidth, GB/s [3350]")
    a = ap.parse_args(argv)
    w, h = (int(v) for v in a.size.lower().split("x"))
    device = torch.device(a.device)
    torch.set_num_threads(1)
    print(f"{a.size}, {a.sampling}, {a.gaussians} Gaussians, {device}, torch {torch.__version__}")
    print("")
    print("| mode | " + " | ".join(f"{p} kernels | {p} ms" for p in PHASES) + " | total kernels | total ms |")
    print("|---|" + "---:|" * (2 * len(PHASES) + 2))
    results = {mode: measure(mode, a.sampling, (w, h), a.gaussians, device, a.repeats) for mode in
               a.modes.split(",")}  # fmt: skip
    for mode, r in results.items():
        cells = " | ".join(f"{r[p][0]} | {r[p][1]:.2f}" for p in PHASES)
        tk = sum(v[0] for v in r.values())
        tm = sum(v[1] for v in r.values())
        print(f"| {mode} | {cells} | {tk} | {tm:.2f} |")
    print("")
    print(f"Memory traffic per view (MB read + written by the counted ops; at {a.bandwidth:,.0f} GB/s):")
    print("")
    image = PHASES[:4]
    print("| mode | " + " | ".join(f"{p} MB" for p in PHASES) + " | JO+L_obs+DS+backward: bytes / pixel "
          "| ms at the bandwidth |")  # fmt: skip
    print("|---|" + "---:|" * (len(PHASES) + 2))
    for mode, r in results.items():
        b = sum(r[p][2] for p in image)
        cells = " | ".join(f"{r[p][2] / 1e6:.1f}" for p in PHASES)
        print(f"| {mode} | {cells} | {b / (w * h):,.0f} | {b / (a.bandwidth * 1e9) * 1e3:.2f} |")
    s = ssim_traffic((w, h), device)
    print("")
    print(f"Of L_obs and the backward, SSIM forward + backward on {device.type} ({s[1]}): "
          f"{s[0] / 1e6:.1f} MB, {s[0] / (w * h):,.0f} bytes / pixel (on a GPU the fused kernel of "
          "jsgs/kernels/csrc/ssim.cu runs instead).")  # fmt: skip
    return 0


def ssim_traffic(size: tuple[int, int], device: torch.device) -> tuple[int, str]:
    """Bytes moved by one SSIM forward and backward of a ``size`` (W, H) RGB pair on ``device``, and the
    implementation that ran."""
    from jsgs.kernels import ssim

    w, h = size
    x = torch.rand(1, 3, h, w, device=device, requires_grad=True)
    y = torch.rand(1, 3, h, w, device=device)
    (1.0 - ssim(x, y, padding="valid")).backward()  # warm-up
    with KernelCounter() as k:
        (1.0 - ssim(x, y, padding="valid")).backward()
    return k.bytes, "the separable-convolution twin" if device.type == "cpu" else "as dispatched"


if __name__ == "__main__":
    raise SystemExit(main())
