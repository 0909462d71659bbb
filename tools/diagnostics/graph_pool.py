"""The image terms' CUDA graph, tensor by tensor, on the CPU: the peak of live storages of the function the
graph records (:func:`jsgs.method.image_terms.terms_with_gradient`: JO, L_obs, DS and the gradient of their
weighted sum) with its tensors laid out as on CUDA, and what is alive at that peak.

    PYTHONPATH=.:/path/to/triton TRITON_INTERPRET=1 .venv/bin/python tools/diagnostics/graph_pool.py \
        --size 960x720 --size 504x378

On CUDA that function's intermediates live in the graph's private pool for the run (``docs/performance.md``,
"Peak memory"); ``step_memory.py``'s ``jsgs-graph-layout`` counts them on the CPU's own path, whose twins
differ (the torch SSIM keeps fifteen-channel planes, the torch JO its blocks). Here instead:

- JO's coding pass, colour maps and DS's Delta run the fused Triton kernels under Triton's interpreter
  (``--jo triton``, the default; needs Triton and ``TRITON_INTERPRET=1``), whose launches are followed by a
  cycle collection (the interpreter keeps a launch's arguments in a reference cycle; a compiled launch keeps
  none); ``--jo torch``: the torch code;
- the fused SSIM is stood in by its outputs: the map and the three maps it saves, each made by the op that
  makes it on CUDA (their values are the torch twin's map and zeros: the accounting needs their sizes, not
  their values), and a gradient of the input's size in the backward;
- the render is a channels-last ``(1, 3, H, W)`` leaf, the target a uint8 image read from a ``[2, H, W, 3]``
  stack by index, r kept as block scores, the gradient written over the render, the observation not returned:
  as ``GraphedImageTerms`` records it (mode "paper", "valid" SSIM padding, DS and GC on).

Storage-level, as ``step_memory.py`` (its :class:`LiveStorages`): the caching allocator's rounding and the
pool's segments come on top. Prints a table per size; writes nothing.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import sys
from collections import Counter
from collections.abc import Iterator, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import torch
from torch.utils._python_dispatch import _disable_current_modes

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from step_memory import LiveStorages  # noqa: E402

from jsgs.base.errors import JsgsError, reports_user_errors  # noqa: E402


class StandInSsim:
    """The fused SSIM kernels' two functions on CPU tensors, for the accounting: what they take and what
    they allocate (``csrc/ssim.cu``: the map and three saved maps forward, the input's gradient backward)."""

    def ssim_forward(self, x: Any, y: Any, window: Any, c1: float, c2: float, same: bool) -> list[Any]:
        from jsgs.kernels._torch_impl import ssim_map_torch

        with _disable_current_modes():
            m = ssim_map_torch(x.detach(), y, window, "same" if same else "valid")
        out = [torch.empty_like(m) for _ in range(4)]
        with _disable_current_modes():
            out[0].copy_(m)
            for t in out[1:]:
                t.zero_()
        return out

    def ssim_backward(self, grad: Any, x: Any, *rest: Any) -> Any:
        g = torch.empty_like(x)
        with _disable_current_modes():
            g.zero_()
        return g


@contextlib.contextmanager
def cuda_layout(jo: str) -> Iterator[None]:
    """Within this block the fused SSIM runs as :class:`StandInSsim` on CPU tensors and, with ``jo``
    "triton", every Triton launch is followed by a cycle collection."""
    import jsgs.kernels._triton_jo as triton_jo
    import jsgs.kernels._wrapper as wrapper

    saved = wrapper.extension, wrapper._use_fused, triton_jo._on
    launch = triton_jo._on

    @contextlib.contextmanager
    def collected(device: torch.device) -> Iterator[None]:
        with launch(device):
            yield
        gc.collect()

    wrapper.extension = lambda warn=True: StandInSsim()
    wrapper._use_fused = lambda x, y, kernel, window_size: not y.requires_grad and window_size == 11
    if jo == "triton":
        triton_jo._on = collected
    try:
        yield
    finally:
        wrapper.extension, wrapper._use_fused, triton_jo._on = saved


def _replay_in_pool(fn: Any) -> Any:  # the frame name LiveStorages charges to the pool
    return fn()


def chain_peak(width: int, height: int, jo: str, sampling: str = "4:2:0") -> dict[str, Any]:
    """The recorded function's live-storage peak at ``width`` x ``height``: ``{"bytes", "per_pixel",
    "rows"}``, rows ``(bytes, phase, op, shape, dtype, origin)`` of the storages alive at the peak, largest
    first."""
    from jsgs.jpeg.supervision import table_weights
    from jsgs.method.image_terms import terms_with_gradient

    g = torch.Generator().manual_seed(0)
    render = torch.rand(1, height, width, 3, generator=g).permute(0, 3, 1, 2)
    x = render.clone(memory_format=torch.preserve_format).requires_grad_(True)
    stack = (torch.rand(2, height, width, 3, generator=g) * 255).to(torch.uint8)
    tables = torch.stack([torch.full((8, 8), 9.0), torch.full((8, 8), 14.0)])
    settings = dict(
        mode="paper", ssim_lambda=0.2, ssim_padding="valid", ssim_kernel="auto", jo_kernel=jo,
        color_kernel=jo, ds=True, gc=True, eps_sm=1e-3, eps_loss=1e-6, eps_block=1e-6,
        ds_weights=table_weights(tables[0], 1, torch.float32, "cpu"),
    )  # fmt: skip
    fn = partial(
        terms_with_gradient, x, stack, tables, weights=(1.0, 0.5, 0.5), sampling=sampling, observation=False,
        grad_into_x=True, r_into=torch.empty(1, height // 8, width // 8), r_blocks=True,
        y_index=torch.tensor([1]), **settings,
    )  # fmt: skip
    mode = LiveStorages(lambda shape: "pixels")
    with cuda_layout(jo):
        fn()  # constants made and cached, kernels traced: not the accounting's
        with torch.no_grad():
            x.copy_(render)  # the render again where the gradient was written
        with mode:
            _replay_in_pool(fn)
    rows: Counter[tuple[str, str, str, str, str]] = Counter()
    for i in mode.at_peak["pool"]:
        m = mode.made[i]
        rows[(m.phase, m.op.removeprefix("aten."), str(m.shape), m.dtype, m.origin)] += m.nbytes
    peak = mode.peak["pool"]
    ordered = sorted(((b, *k) for k, b in rows.items()), key=lambda r: -r[0])
    return {"bytes": peak, "per_pixel": peak / (width * height), "rows": ordered}


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", action="append", help="image size WxH, repeatable [960x720]")
    ap.add_argument(
        "--jo", choices=("triton", "torch"), default="triton",
        help="JO's and DS's kernels: the fused Triton ones (interpreted) or the torch code",
    )  # fmt: skip
    ap.add_argument("--sampling", default="4:2:0", choices=("4:4:4", "4:2:2", "4:2:0"))
    ap.add_argument("--top", type=int, default=20, help="rows listed at each peak [20]")
    return ap.parse_args(argv)


@reports_user_errors
def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    sizes = []
    for s in args.size or ["960x720"]:
        try:
            w, h = (int(v) for v in s.lower().split("x"))
        except ValueError:
            raise JsgsError(f"--size {s!r}: expected WxH, e.g. 960x720") from None
        if w < 16 or h < 16:
            raise JsgsError(f"--size {s!r}: the SSIM's 11-tap window and DS's blocks need at least 16x16")
        sizes.append((w, h))
    if args.jo == "triton":
        from jsgs.kernels._triton_jo import interpreting, triton_available

        if not (triton_available() and interpreting()):
            raise JsgsError("--jo triton needs Triton and TRITON_INTERPRET=1 (its interpreter runs the fused "
                            "kernels on the CPU); or --jo torch")  # fmt: skip
    torch.set_num_threads(1)
    for w, h in sizes:
        out = chain_peak(w, h, args.jo, args.sampling)
        mib = out["bytes"] / 2**20
        print(f"\n{w}x{h}, {args.sampling}, JO {args.jo}: the recorded function's peak {mib:.2f} MiB = "
              f"{out['per_pixel']:.1f} B a pixel; alive at it:")  # fmt: skip
        print("| B a pixel | MiB | phase | op | shape | dtype | origin |\n|---:|---:|---|---|---|---|---|")
        for b, phase, op, shape, dtype, origin in out["rows"][: args.top]:
            print(f"| {b / (w * h):.2f} | {b / 2**20:.2f} | {phase} | {op} | {shape} | {dtype} | {origin} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
