"""Where a training step's aten ops come from, by part of the code, on the CPU (an exact count, the same under
any load): JO, DS, the SSIMs, L_obs, the Gaussian Controller, the rasteriser, the trainer, the strategy.

    .venv/bin/python tools/diagnostics/op_sources.py                    # synthetic 160x120, 16 views, jsgs
    .venv/bin/python tools/diagnostics/op_sources.py --method gsplat --steps 8 --detail

Trains ``--warmup`` steps of the ``--preset`` (``paper``; ``mcmc`` at the fixed 300,000 Gaussians unless
``--cap-max N|auto`` says otherwise, as in ``profile_step.py``) on a synthetic scene (``profile_step.py``'s),
then records ``--steps`` resumed steps under ``torch.profiler`` with Python stacks. Ops are counted by
``profile_step.py``'s rule (views and allocations free, a composite op counted as the ops it runs). A
forward op is charged to the first part of :data:`PARTS` that a Python frame above it names; a backward op
to the part whose forward op made its autograd node (matched by the node's sequence number); an op with
neither (the probe's gradient hook, which runs the Gaussian Controller inside AccumulateGrad) is "other".
``--detail`` also lists the op names per part; ``--products`` the matrix products and convolutions (cuBLAS
and cuDNN calls on a GPU) with their input shapes, per part. Host reads: ``aten::_local_scalar_dense`` per
step, the op under ``.item()``, ``float(t)``, ``bool(t)`` (``.tolist()`` and ``.cpu()`` do not show on the
CPU).
"""

from __future__ import annotations

import argparse
import collections
import shutil
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import profile_step as ps  # noqa: E402
from bench_train_overhead import CAP_MAX_HELP, build_scene, start_config, variant_config  # noqa: E402

from jsgs.base.errors import reports_user_errors  # noqa: E402
from jsgs.train.config import PRESETS  # noqa: E402
from jsgs.train.trainer import train  # noqa: E402

#: (substring of a Python frame's name, part): an op belongs to the first part any of its frames names
PARTS = (
    ("jsgs/method/pooling", "GC probe"),
    ("): ssim", "SSIM"),
    ("jsgs/jpeg/supervision", "DS"),
    ("jsgs/jpeg/losses", "photometric (L1, mixing)"),
    ("jsgs/jpeg/", "JO"),
    ("jsgs/method/", "hook"),
    ("jsgs/kernels", "GC"),
    ("jsgs/render/", "rasteriser"),
    ("strategy.py", "strategy"),
    ("trainer.py", "trainer"),
)

#: the counted ops that are matrix products or convolutions (``--products``)
PRODUCTS = frozenset({
    "aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm", "aten::addbmm", "aten::mv", "aten::addmv",
    "aten::dot", "aten::vdot", "aten::convolution", "aten::_convolution", "aten::mkldnn_convolution",
    "aten::convolution_backward",
})  # fmt: skip


def part_of(event: Any) -> str:
    """The first part of :data:`PARTS` that any Python frame enclosing a forward op names, else "other"."""
    frames = []
    q = event.cpu_parent
    while q is not None:
        frames.append(q.name)
        q = q.cpu_parent
    for key, part in PARTS:
        if any(key in f for f in frames):
            return part
    return "other"


def counted(e: Any) -> bool:
    """Whether ``profile_step.py`` counts this event as one op (a kernel not inside another counted op)."""
    if not e.name.startswith("aten::") or ps.aten_kind(e.name) != "kernel":
        return False
    p = e.cpu_parent
    while p is not None and not (p.name.startswith("aten::") and ps.aten_kind(p.name) != "composite"):
        p = p.cpu_parent
    return p is None


def _charged(events: Sequence[Any]) -> list[tuple[str, Any]]:
    """``(part, event)`` for every counted op of the window (a backward op charged as the module says)."""
    forward: dict[int, str] = {}
    for e in events:
        if e.sequence_nr >= 0 and not e.name.startswith("autograd::"):
            forward.setdefault(e.sequence_nr, part_of(e))
    out = []
    for e in events:
        if not counted(e):
            continue
        part, p = None, e.cpu_parent
        while p is not None and part is None:
            if p.name.startswith("autograd::engine::evaluate_function"):
                part = forward.get(p.sequence_nr, "other") + " (backward)"
            p = p.cpu_parent
        out.append((part or part_of(e), e))
    return out


def attribute(events: Sequence[Any]) -> tuple[collections.Counter[tuple[str, str]], int]:
    """``(part, op name) -> count`` over the recorded window, and the number of host reads."""
    out = collections.Counter((part, e.name) for part, e in _charged(events))
    return out, sum(e.name == "aten::_local_scalar_dense" for e in events)


def products(events: Sequence[Any]) -> collections.Counter[tuple[str, str, str]]:
    """``(part, op name, input shapes) -> count`` of the :data:`PRODUCTS` ops of a window recorded with
    shapes (``record_events(..., shapes=True)``)."""
    return collections.Counter(
        (part, e.name, str([list(s) for s in e.input_shapes if s]))
        for part, e in _charged(events) if e.name in PRODUCTS
    )  # fmt: skip


def run(method: str, size: tuple[int, int], views: int, warmup: int, steps: int) -> tuple[Any, int]:
    """:func:`attribute` of :func:`record_events`'s window (the ``paper`` preset)."""
    return attribute(record_events(method, size, views, warmup, steps))


def record_events(
    method: str, size: tuple[int, int], views: int, warmup: int, steps: int, preset: str = "paper",
    shapes: bool = False, cap_max: str | None = None,
) -> list[Any]:  # fmt: skip
    """The host events of ``steps`` steps resumed after ``warmup`` steps of ``preset`` (its budget
    ``cap_max``: :func:`bench_train_overhead.start_config`) on a synthetic scene (``shapes``: with the ops'
    input shapes)."""
    settle = 2
    work = Path(tempfile.mkdtemp(prefix="op_sources."))
    try:
        manifest = build_scene(work / "synthetic", size, views)
        base = start_config(preset, None, cap_max)
        cfg = variant_config(base, method, dict(base.method_options), warmup + settle + steps + 1, "cpu")
        cfg.checkpoint_every = 0
        train(manifest, work / "run", cfg, force=True, stop_at=warmup, progress=False, log=ps._quiet)
        captured: dict[str, Any] = {}
        with torch.profiler.profile(
            activities=[torch.profiler.ProfilerActivity.CPU], schedule=ps.StepWindow.schedule(settle, steps),
            on_trace_ready=lambda p: captured.update(events=p.events()), with_stack=True,
            record_shapes=shapes,
        ) as prof:  # fmt: skip
            clock = ps.StepWindow(torch.device("cpu"), settle, steps, prof)
            train(manifest, work / "run", resume=True, progress=False, log=ps._quiet,
                  callbacks=[ps.StepCallback(clock)])  # fmt: skip
        return ps._recorded(captured["events"])
    finally:
        shutil.rmtree(work, ignore_errors=True)


@reports_user_errors
def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--method", default="jsgs", choices=["jsgs", "gsplat"])
    ap.add_argument("--size", default="160x120", help="synthetic scene image size WxH [160x120]")
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--warmup", type=int, default=60)
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--preset", default="paper", choices=sorted(PRESETS))
    ap.add_argument("--cap-max", metavar="N|auto", help=CAP_MAX_HELP)
    ap.add_argument("--detail", action="store_true", help="also the op names per part")
    ap.add_argument("--products", action="store_true", help="also the matrix products and their shapes")
    args = ap.parse_args(argv)
    if args.warmup < 1 or args.steps < 1 or args.views < 2:
        ap.error("--warmup and --steps must be >= 1, --views >= 2")
    torch.set_num_threads(args.threads)
    w, h = (int(v) for v in args.size.lower().split("x"))
    events = record_events(args.method, (w, h), args.views, args.warmup, args.steps, args.preset,
                           shapes=args.products, cap_max=args.cap_max)  # fmt: skip
    ops, reads = attribute(events)
    n = args.steps
    parts: collections.Counter[str] = collections.Counter()
    for (part, _), c in ops.items():
        parts[part.removesuffix(" (backward)")] += c
    total = sum(ops.values()) / n
    print(f"{args.method}: {total:.1f} aten ops per step, {reads / n:.2f} host reads per step")
    print()
    print("| part (forward and backward) | aten ops per step |")
    print("|---|---:|")
    for part, c in parts.most_common():
        print(f"| {part} | {c / n:.1f} |")
    if args.detail:
        print()
        print("| part | op | per step |")
        print("|---|---|---:|")
        for (part, name), c in sorted(ops.items(), key=lambda kv: (kv[0][0], -kv[1])):
            print(f"| {part} | {name} | {c / n:.1f} |")
    if args.products:
        print()
        print("| part | op | input shapes | per step |")
        print("|---|---|---|---:|")
        for (part, name, shape), c in sorted(products(events).items()):
            print(f"| {part} | {name} | {shape} | {c / n:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
