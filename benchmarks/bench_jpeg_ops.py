"""Speed and fidelity of the JPEG observation operator (JO) and DCT supervision (DS).

Speed (default): times one training-step's worth of JPEG work for one view, forward + backward:
    JO (each mode) -> L_obs (L1 + D-SSIM) + DS (L_low, L_mid, block scores)
at 1297 x 840 (the paper's Mip-NeRF 360 training size), beside, on CUDA with gsplat installed, one gsplat
``rasterization`` forward + backward at the same size with ~500k random Gaussians, and prints the ratios.

    .venv/bin/python benchmarks/bench_jpeg_ops.py                      # CPU
    .venv/bin/python benchmarks/bench_jpeg_ops.py --device cuda --compile
    .venv/bin/python benchmarks/bench_jpeg_ops.py --fidelity           # PSNR vs Pillow, per mode and q
    .venv/bin/python benchmarks/bench_jpeg_ops.py --fused-jo --device cuda   # Triton JO vs its twin

Fused JO (``--fused-jo``): mode "paper"'s coding pass as the Triton kernels of ``jsgs/kernels/_triton_jo.py``
against the torch twin, at ``--sizes`` (default 1440x1920 and 504x378, width x height): the largest
difference of JO's output and gradient, and the time of the coding pass alone, of JO, and (CUDA) of the
whole JO + L_obs + DS chain with its gradient replayed as one CUDA graph (what a training step runs), each
twin vs fused; then JO's two colour conversions (``addmm``) vs their elementwise kernel
(``method_options.speed.fused_color``): alone, inside the fused JO, and in the graph; last, mode paper's
coding-pass kernels alone per launch setting, against the twin block by block (``tie_flip_agreement``:
blocks off by one quantizer tie flip are counted apart from real disagreements); and those kernels on the
step's own launches (:func:`coding_launches`: the luma and the chroma launch JO makes, beside the three-plane
one above, each alone, with its Triton specialisation and, on CUDA, its binary's registers and spills).
``--coding-launches`` (with ``--fused-jo``) prints only that table per size:

    .venv/bin/python benchmarks/bench_jpeg_ops.py --fused-jo --coding-launches --device cuda --sizes 504x378

Fidelity: PSNR of each mode's output against Pillow's (libjpeg-turbo's) decode of Pillow's encode, on
photographs from ../shared/scenes, per quality and sampling; for mode "exact" also the share of bit-exact
images. Prints a markdown table (the README's).
"""

from __future__ import annotations

import argparse
import io
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jsgs.jpeg.color import rgb_to_ycbcr, ycbcr_to_rgb  # noqa: E402
from jsgs.jpeg.losses import photometric_loss  # noqa: E402
from jsgs.jpeg.observe import MODES, jpeg_observe  # noqa: E402
from jsgs.jpeg.supervision import dct_supervision  # noqa: E402
from jsgs.jpeg.tables import ijg_tables  # noqa: E402

SCENES = ROOT.parent / "shared" / "scenes"


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_it(fn: Callable[[], None], device: torch.device, repeats: int, warmup: int) -> float:
    """Median wall time of ``fn`` in milliseconds."""
    for _ in range(warmup):
        fn()
    _sync(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append(1000 * (time.perf_counter() - t0))
    return statistics.median(times)


def jpeg_step(mode: str, sampling: str, with_obs_loss: bool = True) -> Callable[..., torch.Tensor]:
    """JO + DS losses (+ L_obs, whose D-SSIM is most of its cost) for a batch of views, with the paper's
    weights: the scalar to backprop."""

    def step(rendered: torch.Tensor, target: torch.Tensor, luma: torch.Tensor,
             chroma: torch.Tensor) -> torch.Tensor:
        obs = jpeg_observe(rendered, luma, chroma, sampling, mode)
        ds = dct_supervision(obs, target, luma)
        loss = 0.02 * ds.loss_low.mean() + 0.03 * ds.loss_mid.mean()
        return loss + 0.2 * photometric_loss(obs, target) if with_obs_loss else loss

    return step


def gsplat_step(n: int, width: int, height: int, device: torch.device) -> Callable[[], None] | None:
    """One gsplat rasterization forward + backward with ``n`` random Gaussians in front of the camera."""
    if device.type != "cuda":
        return None
    try:
        from gsplat import rasterization
    except Exception as exc:  # noqa: BLE001 - any import problem means "no gsplat"
        print(f"gsplat not usable: {exc}")
        return None
    g = torch.Generator(device=device).manual_seed(0)
    means = torch.randn(n, 3, device=device, generator=g) * torch.tensor([2.0, 1.5, 1.0], device=device)
    means[:, 2] += 5.0
    quats = torch.randn(n, 4, device=device, generator=g)
    scales = torch.log(0.02 + 0.03 * torch.rand(n, 3, device=device, generator=g))
    opac = torch.logit(0.1 + 0.8 * torch.rand(n, device=device, generator=g))
    colors = torch.rand(n, 3, device=device, generator=g)
    params = [p.requires_grad_() for p in (means, quats, scales, opac, colors)]
    f = 0.9 * width
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], device=device)[None]
    view = torch.eye(4, device=device)[None]

    def step() -> None:
        m, q, s, o, c = params
        img, _, _ = rasterization(m, q, torch.exp(s), torch.sigmoid(o), c, view, K, width, height)
        img.sum().backward()

    return step


def run_speed(args: argparse.Namespace) -> None:
    device = torch.device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    h, w = args.height, args.width
    gen = torch.Generator().manual_seed(0)
    rendered = torch.rand(1, 3, h, w, generator=gen).to(device)
    target = torch.rand(1, 3, h, w, generator=gen).to(device)
    luma, chroma = (torch.tensor(t, dtype=torch.float32, device=device)[None]
                    for t in ijg_tables(args.quality))
    print(f"device {device} ({torch.cuda.get_device_name(device) if device.type == 'cuda' else 'cpu'}), "
          f"{torch.get_num_threads()} threads, torch {torch.__version__}, view {w}x{h}, q={args.quality}, "
          f"{args.sampling}, compile={args.compile} ({args.compile_mode})")
    gs = gsplat_step(args.gaussians, w, h, device) if args.gaussians > 0 else None
    t_gs = time_it(gs, device, args.repeats, args.warmup) if gs else None
    if t_gs:
        print(f"gsplat rasterization fwd + bwd, {args.gaussians} Gaussians: {t_gs:.2f} ms")
    print()
    head = "| mode | JO fwd (ms) | JO + DS, fwd + bwd (ms) | JO + DS + L_obs, fwd + bwd (ms) |"
    print(head + (" ratios to gsplat |" if t_gs else ""))
    print("|---|---|---|---|" + ("---|" if t_gs else ""), flush=True)
    for mode in MODES:
        steps = [jpeg_step(mode, args.sampling, False), jpeg_step(mode, args.sampling, True)]
        observe = lambda x, m=mode: jpeg_observe(x, luma, chroma, args.sampling, m)  # noqa: E731
        if args.compile:
            steps = [torch.compile(s, dynamic=False, mode=args.compile_mode) for s in steps]
            observe = torch.compile(observe, dynamic=False, mode=args.compile_mode)

        def fwd_only(observe=observe) -> None:
            with torch.no_grad():
                observe(rendered)

        def fwd_bwd(step) -> None:
            x = rendered.detach().requires_grad_()
            step(x, target, luma, chroma).backward()

        t_fwd = time_it(fwd_only, device, args.repeats, args.warmup)
        t_ds, t_all = (time_it(lambda s=s: fwd_bwd(s), device, args.repeats, args.warmup) for s in steps)
        ratio = f" {100 * t_ds / t_gs:.0f} % / {100 * t_all / t_gs:.0f} % |" if t_gs else ""
        print(f"| {mode} | {t_fwd:.2f} | {t_ds:.2f} | {t_all:.2f} |{ratio}", flush=True)


def _loop_ms(fn: Callable[[], object], device: torch.device, n: int, warmup: int) -> float:
    """Milliseconds per call of ``fn`` over ``n`` back-to-back calls (CUDA events on a GPU)."""
    for _ in range(warmup):
        fn()
    _sync(device)
    if device.type != "cuda":
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        return 1000 * (time.perf_counter() - t0) / n
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    start.record()
    for _ in range(n):
        fn()
    end.record()
    end.synchronize()
    return start.elapsed_time(end) / n


KERNEL_PAIR = ("torch", "triton")


def _fused_jo_size(width: int, height: int, args: argparse.Namespace, device: torch.device) -> None:
    from jsgs.jpeg.color import kernel_coefficients
    from jsgs.kernels._triton_jo import color_convert as color_affine
    from jsgs.kernels._triton_jo import paper_code

    def color_convert(x: torch.Tensor, name: str) -> torch.Tensor:
        return color_affine(x, *kernel_coefficients(name, x.dtype, x.device))
    from jsgs.method.graphed import GraphedImageTerms

    gen = torch.Generator().manual_seed(0)
    rgb = torch.rand(1, 3, height, width, generator=gen).to(device)
    target = torch.rand(1, 3, height, width, generator=gen).to(device)
    weight = torch.randn(1, 3, height, width, generator=gen).to(device)
    luma, chroma = (torch.tensor(t, dtype=torch.float32, device=device) for t in ijg_tables(args.quality))
    print(f"\n{width}x{height}, q={args.quality}, {args.sampling}")
    for mode in ("paper", "float"):
        out = {}
        for kernel in ("torch", "triton"):
            x = rgb.clone().requires_grad_()
            obs = jpeg_observe(x, luma, chroma, args.sampling, mode, kernel=kernel)
            (grad,) = torch.autograd.grad((obs * weight).sum(), x)
            out[kernel] = (obs.detach(), grad)
        d_obs = 255 * (out["triton"][0] - out["torch"][0]).abs()
        d_grad = (out["triton"][1] - out["torch"][1]).abs()
        share = 100 * float((d_obs > 0.01).float().mean())
        largest = float(out["torch"][1].abs().max())
        print(f"mode {mode}: max |fused - twin| of JO {float(d_obs.max()):.2e} (8-bit units; pixels > 0.01: "
              f"{share:.4f} %), of its gradient {float(d_grad.max()):.2e} (largest gradient {largest:.2e})")
    deltas = [dct_supervision(rgb, target, luma, kernel=k).delta for k in ("torch", "triton")]
    print(f"max |fused - twin| of DS's Delta {float((deltas[1] - deltas[0]).abs().max()):.2e} (largest "
          f"{float(deltas[0].abs().max()):.2e})")
    x255 = 255 * rgb
    for name, twin_map in (("rgb2ycc", rgb_to_ycbcr), ("ycc2rgb", ycbcr_to_rgb)):
        err = float((color_convert(x255, name) - twin_map(x255)).abs().max())
        print(f"max |kernel - addmm| of colour map {name}: {err:.2e} (8-bit units)")
    planes = (255 * torch.rand(1, 3, 8 * (height // 8), 8 * (width // 8), generator=gen)).to(device)
    tab = luma.expand(1, 8, 8)
    p_grad = torch.randn_like(planes)

    def coding(kernel: str) -> Callable[[], object]:
        def run() -> None:
            x = planes.clone().requires_grad_()
            y = paper_code(x, tab) if kernel == "triton" else _twin_code(x, tab)
            torch.autograd.grad(y, x, p_grad)

        return run

    def jo(kernel: str, mode: str = "paper") -> Callable[[], object]:
        def run() -> None:
            x = rgb.clone().requires_grad_()
            y = jpeg_observe(x, luma, chroma, args.sampling, mode, kernel=kernel)
            torch.autograd.grad(y, x, weight)

        return run

    def ds(kernel: str) -> Callable[[], object]:
        def run() -> None:
            x = rgb.clone().requires_grad_()
            sup = dct_supervision(x, target, luma, kernel=kernel)
            torch.autograd.grad(sup.loss_low.sum() + sup.loss_mid.sum(), x)

        return run

    rows = [
        ("coding pass (3 planes, mode paper), fwd + bwd", coding),
        ("JO (mode paper), fwd + bwd", jo),
        ("JO (mode float), fwd + bwd", lambda k: jo(k, "float")),
        ("DS, fwd + bwd", ds),
    ]
    if device.type == "cuda":
        settings = dict(mode="paper", ssim_lambda=0.2, ssim_padding="valid", ds=True, gc=True, eps_sm=1e-3,
                        eps_loss=1e-6, eps_block=1e-6)
        tables = torch.stack([luma, chroma])

        def graphed(kernel: str) -> Callable[[], object]:
            terms = GraphedImageTerms(weights=(0.2, 0.02, 0.03), jo_kernel=kernel, **settings)
            x = rgb.clone().requires_grad_()
            return lambda: terms(x, target, tables, args.sampling)

        rows.append(("JO + L_obs + DS + gradient, one CUDA graph replay", graphed))
    def colour(kernel: str) -> Callable[[], object]:
        def run() -> None:
            x = x255.clone().requires_grad_()
            if kernel == "triton":
                y = color_convert(color_convert(x, "rgb2ycc"), "ycc2rgb")
            else:
                y = ycbcr_to_rgb(rgb_to_ycbcr(x))
            torch.autograd.grad(y, x, weight)

        return run

    def jo_colour(kernel: str) -> Callable[[], object]:
        def run() -> None:
            x = rgb.clone().requires_grad_()
            y = jpeg_observe(x, luma, chroma, args.sampling, "paper", kernel="triton", color_kernel=kernel)
            torch.autograd.grad(y, x, weight)

        return run

    colour_rows = [
        ("colour maps alone (RGB->YCbCr->RGB), addmm vs kernel, fwd + bwd", colour),
        ("fused JO (mode paper), colour by addmm vs kernel, fwd + bwd", jo_colour),
    ]
    if device.type == "cuda":

        def graphed_colour(kernel: str) -> Callable[[], object]:
            terms = GraphedImageTerms(
                weights=(0.2, 0.02, 0.03), jo_kernel="triton", color_kernel=kernel, **settings
            )
            x = rgb.clone().requires_grad_()
            return lambda: terms(x, target, tables, args.sampling)

        colour_rows.append(("fused chain as one CUDA graph, colour by addmm vs kernel", graphed_colour))
    _time_rows(rows, device, args)
    _time_rows(colour_rows, device, args)
    _blocks_per_program(planes, tab, p_grad, args, device)
    coding_launches(width, height, args, device)


def _time_rows(
    rows: list[tuple[str, Callable[[str], Callable[[], object]]]], device: torch.device,
    args: argparse.Namespace,
) -> None:
    """One markdown table: each row's function made with the torch and the Triton kernel, timed."""
    print("| what | twin (ms) | fused (ms) | saved (ms) |")
    print("|---|---|---|---|")
    for name, make in rows:
        try:
            t_twin, t_fused = (_loop_ms(make(k), device, args.repeats, args.warmup) for k in KERNEL_PAIR)
        except Exception as exc:  # noqa: BLE001 - one failed row (e.g. a graph that did not record) says why
            print(f"| {name} | failed: {' '.join(str(exc).split())[:200]} | | |", flush=True)
            continue
        print(f"| {name} | {t_twin:.3f} | {t_fused:.3f} | {t_twin - t_fused:.3f} |", flush=True)


def _blocks_per_program(
    planes: torch.Tensor, tab: torch.Tensor, grad: torch.Tensor, args: argparse.Namespace,
    device: torch.device,
) -> None:
    """Mode paper's two coding-pass kernels alone, per (8x8 blocks per Triton program, warps)."""
    from jsgs.kernels._triton_jo import BLOCKS_PER_PROGRAM, WARPS, paper_code_backward, paper_code_forward

    q = tab.reshape(1, 64).contiguous()
    reference = _twin_code(planes, tab).detach()
    cells = []
    for bn, warps in ((16, 4), (16, 8), (32, 4), (32, 8), (64, 8)):
        out = paper_code_forward(planes, q, bn, warps)
        a = tie_flip_agreement(out, reference, planes, tab)

        def run(bn: int = bn, warps: int = warps, out: torch.Tensor = out) -> None:
            paper_code_forward(planes, q, bn, warps)
            paper_code_backward(planes, q, out, grad, bn, warps)

        ms = _loop_ms(run, device, args.repeats, args.warmup)
        cells.append(f"{bn}/{warps}: {ms:.3f} ms (max |fused - twin| {a.largest:.1e}; {a.describe()})")
    print(f"mode paper's coding-pass kernels alone (fwd + bwd), by blocks per program / warps (used: "
          f"{BLOCKS_PER_PROGRAM}/{WARPS}), against the twin block by block: " + ", ".join(cells))


def _device_ms(fn: Callable[[], object], device: torch.device, n: int, warmup: int) -> float:
    """Milliseconds per call of ``fn`` on the device: on CUDA ``n`` calls recorded as one CUDA graph and
    replayed (a training step replays its kernels so; no host launch time between them), else
    :func:`_loop_ms`."""
    if device.type != "cuda":
        return _loop_ms(fn, device, n, warmup)
    for _ in range(max(warmup, 1)):
        fn()
    torch.cuda.synchronize(device)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        for _ in range(n):
            fn()
    return _loop_ms(graph.replay, device, 1, 1) / n  # one warm replay, then one timed


class _KernelRecorder:
    """Stands in for one of ``jsgs.kernels._triton_jo``'s Triton kernels and keeps what its launches return
    (the compiled kernel on CUDA: its registers and spills; None under the interpreter)."""

    def __init__(self, kernel: Any) -> None:
        self.kernel, self.compiled = kernel, []

    def __getitem__(self, grid: Any) -> Callable[..., Any]:
        def launch(*args: Any, **kwargs: Any) -> Any:
            compiled = self.kernel[grid](*args, **kwargs)
            self.compiled.append(compiled)
            return compiled

        return launch


def _registers(tj: Any, name: str, fn: Callable[[], object]) -> str:
    """``fn()`` run once with kernel ``name`` recorded: "registers / spills" of the binary it launched."""
    recorder = _KernelRecorder(getattr(tj, name))
    setattr(tj, name, recorder)
    try:
        fn()
    finally:
        setattr(tj, name, recorder.kernel)
    last = recorder.compiled[-1] if recorder.compiled else None
    regs, spills = getattr(last, "n_regs", None), getattr(last, "n_spills", None)
    return "n/a" if regs is None else f"{regs} / {spills}"


def _specialisation(names: list[str], values: tuple[int, ...]) -> str:
    """How Triton's launcher specialises these integer arguments (equal to 1: compiled in as a constant;
    divisible by 16: that hint), those that are neither named: one binary per specialisation, and ptxas
    allocates registers per binary."""
    ones = [n for n, v in zip(names, values, strict=True) if v == 1 and not n.endswith("_w")]
    odd = [n for n, v in zip(names, values, strict=True) if v != 1 and v % 16]
    return f"=1: {', '.join(ones) or '-'}; not /16: {', '.join(odd) or '-'}"


def coding_launches(width: int, height: int, args: argparse.Namespace, device: torch.device) -> None:
    """Mode paper's coding-pass kernels timed on exactly the tensors a training step hands them: JO with the
    fused kernels (and the colour kernel) on a ``width`` x ``height`` view, its backward's launches recorded
    (the padded luma plane, then the two chroma planes; their layout, the saved output and the incoming
    gradient as the chain passes them), then each launch alone, forward and backward, at 16 and 32 blocks
    per program and 4 warps, beside the three-plane launch of the rows above (``8 (H // 8) x 8 (W // 8)``,
    one table). On CUDA each time is a CUDA graph of ``--repeats`` launches replayed (device time, as the
    step's graph runs them); the registers / spills per thread are the binary's (CUDA only). ns/block is
    the backward's time per 8x8 block."""
    from jsgs.kernels import _triton_jo as tj

    gen = torch.Generator().manual_seed(1)
    rgb = torch.rand(1, 3, height, width, generator=gen).to(device)
    weight = torch.randn(1, 3, height, width, generator=gen).to(device)
    luma, chroma = (torch.tensor(t, dtype=torch.float32, device=device) for t in ijg_tables(args.quality))
    launches: list[tuple[str, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]] = []
    backward = tj.paper_code_backward

    def record(planes: torch.Tensor, tables: torch.Tensor, out: torch.Tensor, grad: torch.Tensor,
               *rest: Any) -> torch.Tensor:  # fmt: skip
        launches.append(("", planes.detach(), tables, out.detach(), grad.detach()))
        return backward(planes, tables, out, grad, *rest)

    tj.paper_code_backward = record
    try:
        x = rgb.clone().requires_grad_()
        y = jpeg_observe(x, luma, chroma, args.sampling, "paper", kernel="triton", color_kernel="triton")
        torch.autograd.grad(y, x, weight)
    finally:
        tj.paper_code_backward = backward
    launches = [("step, luma" if p.shape[1] == 1 else "step, chroma", p, q, o, g)  # the luma plane first
                for _, p, q, o, g in sorted(launches, key=lambda item: item[1].shape[1])]
    planes = (255 * torch.rand(1, 3, 8 * (height // 8), 8 * (width // 8), generator=gen)).to(device)
    q = luma.reshape(1, 64).contiguous()
    out = tj.paper_code_forward(planes, q)
    launches.append(("bench, 3 planes", planes, q, out, torch.randn_like(planes)))
    names = [a for a in tj._paper_backward.arg_names if not a.endswith("_ptr") and a != "BN"]
    print(f"mode paper's coding-pass kernels on the step's own launches at {width}x{height} "
          f"({args.sampling}), each alone (used: {tj.BLOCKS_PER_PROGRAM}/{tj.WARPS})")
    print("| blocks/warps | launch | planes | strides (planes; out, grad) | specialisation | blocks | fwd ms "
          "| bwd ms | bwd ns/block | bwd registers / spills |")
    print("|---|---|---|---|---|---:|---:|---:|---:|---|")
    for bn, warps in ((16, 4), (32, 4)):
        for label, p, tab, out, grad in launches:
            _, launch = tj._grid_args(p, bn)
            values = (*launch, *p.stride(), *out.stride(), *grad.stride())

            def fwd(p: torch.Tensor = p, tab: torch.Tensor = tab, bn: int = bn, warps: int = warps) -> None:
                tj.paper_code_forward(p, tab, bn, warps)

            def bwd(p: torch.Tensor = p, tab: torch.Tensor = tab, out: torch.Tensor = out,
                    grad: torch.Tensor = grad, bn: int = bn, warps: int = warps) -> None:  # fmt: skip
                tj.paper_code_backward(p, tab, out, grad, bn, warps)

            regs = _registers(tj, "_paper_backward", bwd)
            t_fwd, t_bwd = (_device_ms(f, device, args.repeats, args.warmup) for f in (fwd, bwd))
            same = out.stride() == grad.stride() == p.stride()
            strides = f"{p.stride()}; " + ("alike" if same else f"{out.stride()}, {grad.stride()}")
            spec = _specialisation(names, values)
            print(f"| {bn}/{warps} | {label} | {tuple(p.shape)} | {strides} | {spec} | {launch[0]} | "
                  f"{t_fwd:.4f} | {t_bwd:.4f} | {1e6 * t_bwd / launch[0]:.2f} | {regs} |", flush=True)


@dataclass
class TieFlips:
    """Mode paper's coding pass against its twin, block by block (:func:`tie_flip_agreement`)."""

    blocks: int  # 8x8 blocks compared
    flipped: int  # blocks beyond the tolerance that one coefficient rounded the other way explains
    other: int  # blocks beyond the tolerance that no single tie flip explains: a real disagreement
    within: float  # largest difference over the blocks within the tolerance (8-bit units)
    largest: float  # largest difference over all blocks

    def describe(self) -> str:
        return (f"{self.flipped} of {self.blocks} blocks off by one quantizer tie flip, {self.other} "
                f"otherwise, the rest within {self.within:.1e}")  # fmt: skip


def tie_flip_agreement(
    out: torch.Tensor, reference: torch.Tensor, planes: torch.Tensor, tables: torch.Tensor,
    tol: float = 2e-3, ulps: float = 8.0,
) -> TieFlips:
    """Mode paper's coding pass ``out`` (the kernel) against ``reference`` (the twin), both of ``planes``
    ``(B, C, H, W)`` with ``tables`` ``(B, 8, 8)``, in 8-bit units. The soft rounding ``round(z) + (z -
    round z)^3`` jumps by 3/4 of a step where ``z`` crosses a half-integer, so two float32 computations that
    differ by an ulp of ``z`` there differ by up to ~0.2 of the step in a block's samples: the largest
    difference over all pixels says nothing about the kernel. A block beyond ``tol`` counts as a tie flip
    when one of its coefficients has ``z`` (float64, from ``planes``) within ``ulps`` float32 ulps of a
    half-integer and, of the block decoded in float64 with that coefficient rounded down and rounded up,
    ``out`` matches one and ``reference`` the other within ``tol``; any other block beyond ``tol`` is a real
    disagreement."""
    from jsgs.jpeg.dct import blockify
    from jsgs.jpeg.rounding import round_half_away
    from jsgs.kernels._triton_jo import dct_kron

    b = planes.shape[0]
    err = blockify((out.detach() - reference).abs().double()).reshape(-1, 64).amax(-1)
    bad = err > tol
    within = float(err[~bad].max()) if bool((~bad).any()) else 0.0
    rows = bad.nonzero()[:, 0]
    flipped = 0
    if rows.numel():
        per_view = err.numel() // b
        x = blockify(planes.detach().double()).reshape(-1, 64)[rows] - 128.0
        got = blockify(out.detach().double()).reshape(-1, 64)[rows]
        want = blockify(reference.detach().double()).reshape(-1, 64)[rows]
        q = tables.detach().double().reshape(b, 64)[rows // per_view]
        k = dct_kron(torch.float64, planes.device)
        z = (x @ k.T) / q
        r = round_half_away(z)
        frac = z.abs() - z.abs().floor()
        at_tie = (frac - 0.5).abs() <= ulps * torch.finfo(torch.float32).eps * z.abs().clamp(min=1.0)
        block, coef = at_tie.nonzero(as_tuple=True)  # each candidate: one coefficient of one bad block
        if block.numel():
            pick = torch.arange(block.numel(), device=r.device)
            zb, down = z[block], z[block, coef].floor()
            decoded = []
            for level in (down, down + 1.0):  # the half-integer's two neighbours
                rb = r[block].clone()
                rb[pick, coef] = level
                decoded.append(((q[block] * (rb + (zb - rb) ** 3)) @ k + 128.0).clamp(0.0, 255.0))

            def close(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
                return (a - b).abs().amax(-1) <= tol

            lo, hi = decoded
            g, w = got[block], want[block]
            ok = (close(g, lo) & close(w, hi)) | (close(g, hi) & close(w, lo))
            explained = torch.zeros(rows.numel(), dtype=torch.bool, device=r.device)
            explained[block[ok]] = True
            flipped = int(explained.sum())
    return TieFlips(int(err.numel()), flipped, int(rows.numel()) - flipped, within, float(err.max()))


def _twin_code(planes: torch.Tensor, tables: torch.Tensor) -> torch.Tensor:
    """Mode "paper"'s coding pass of ``(1, C, H, W)`` planes as JO's torch code runs it."""
    from jsgs.jpeg.dct import blockify, unblockify
    from jsgs.jpeg.observe import _code_blocks

    blocks = blockify(planes)
    n = blocks.shape[1] * blocks.shape[2] * blocks.shape[3]
    coded = _code_blocks(blocks.reshape(1, n, 8, 8), tables[:, None].expand(1, n, 8, 8), "paper")
    return unblockify(coded.reshape(blocks.shape))


def run_fused_jo(args: argparse.Namespace) -> None:
    from jsgs.kernels._triton_jo import fused_jo_runs, triton_available

    device = torch.device(args.device)
    probe = torch.zeros(1, device=device)
    if not fused_jo_runs(probe):
        raise SystemExit(
            f"--fused-jo needs Triton ({'present' if triton_available() else 'not installed'}) and a CUDA "
            "device (or TRITON_INTERPRET=1 on cpu)"
        )
    import triton

    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu, Triton's interpreter"
    print(f"device {device} ({name}), torch {torch.__version__}, triton {triton.__version__}, "
          f"{args.repeats} timed calls after {args.warmup} warm-up calls")  # fmt: skip
    for size in args.sizes.split(","):
        width, height = (int(v) for v in size.lower().split("x"))
        if args.coding_launches:
            coding_launches(width, height, args, device)
        else:
            _fused_jo_size(width, height, args, device)


def _photos(n: int) -> list[np.ndarray]:
    from PIL import Image

    files = sorted(SCENES.glob("*/images/*.png")) if SCENES.is_dir() else []
    if not files:
        raise SystemExit(f"no photographs under {SCENES}")
    step = max(1, len(files) // n)
    return [np.asarray(Image.open(f).convert("RGB")) for f in files[::step][:n]]


def run_fidelity(args: argparse.Namespace) -> None:
    from PIL import Image

    torch.set_num_threads(args.threads or 1)
    photos = _photos(args.photos)
    sub = {"4:4:4": 0, "4:2:2": 1, "4:2:0": 2}
    qualities = [int(q) for q in args.qualities.split(",")]
    sizes = ", ".join(f"{p.shape[1]}x{p.shape[0]}" for p in photos)
    print(f"{len(photos)} photographs from {SCENES} ({sizes}); "
          "PSNR in dB against Pillow's decode, min / mean over the photographs")
    for sampling in args.samplings.split(","):
        print(f"\n{sampling}\n")
        print("| q | exact: bit-exact | float: min / mean | paper: min / mean |")
        print("|---|---|---|---|")
        for q in qualities:
            exact_ok = 0
            psnrs: dict[str, list[float]] = {"float": [], "paper": []}
            for arr in photos:
                buf = io.BytesIO()
                Image.fromarray(arr).save(buf, "JPEG", quality=q, subsampling=sub[sampling])
                buf.seek(0)
                im = Image.open(buf)
                ref = np.asarray(im.convert("RGB")).astype(np.float64)
                luma = np.array(im.quantization[0]).reshape(8, 8)
                chroma = np.array(im.quantization[1]).reshape(8, 8)
                x = torch.from_numpy(arr.copy()).permute(2, 0, 1)[None].float() / 255
                for mode in MODES:
                    with torch.no_grad():
                        out = jpeg_observe(x, luma, chroma, sampling, mode)[0]
                    out = out.permute(1, 2, 0).double().numpy() * 255
                    if mode == "exact":
                        exact_ok += int(np.array_equal(np.round(out), ref))
                    else:
                        mse = float(((out - ref) ** 2).mean())
                        psnrs[mode].append(99.0 if mse == 0 else 10 * np.log10(255**2 / mse))
            cells = [f"{min(v):.1f} / {np.mean(v):.1f}" for v in psnrs.values()]
            print(f"| {q} | {exact_ok}/{len(photos)} | {cells[0]} | {cells[1]} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--compile", action="store_true", help="torch.compile the JO + DS step")
    p.add_argument("--compile-mode", default="default", help="torch.compile mode, e.g. reduce-overhead")
    p.add_argument("--height", type=int, default=840)
    p.add_argument("--width", type=int, default=1297)
    p.add_argument("--quality", type=int, default=50)
    p.add_argument("--sampling", default="4:2:0")
    p.add_argument("--gaussians", type=int, default=500_000, help="0: skip gsplat")
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    p.add_argument("--fidelity", action="store_true", help="PSNR vs Pillow instead of speed")
    p.add_argument("--photos", type=int, default=8)
    p.add_argument("--qualities", default="1,5,10,20,30,40,50,60,70,80,90,95,100")
    p.add_argument("--samplings", default="4:2:0,4:2:2,4:4:4")
    p.add_argument("--fused-jo", action="store_true", help="the fused Triton JO against its twin")
    p.add_argument("--sizes", default="1440x1920,504x378", help="--fused-jo: image sizes, width x height")
    p.add_argument("--coding-launches", action="store_true",
                   help="with --fused-jo: only the coding-pass kernels on the step's own launches")
    args = p.parse_args()
    if args.coding_launches and not args.fused_jo:
        p.error("--coding-launches goes with --fused-jo")
    if args.fused_jo:
        run_fused_jo(args)
    else:
        run_fidelity(args) if args.fidelity else run_speed(args)


if __name__ == "__main__":
    main()
