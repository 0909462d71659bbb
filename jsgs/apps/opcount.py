"""Counting the kernels a piece of torch code launches, on any device.

At the image sizes of real scenes (504 x 378) the JSGS terms are launch-bound on a GPU: each eager op costs
10-20 µs of host dispatch and launch, far more than its arithmetic. The number of kernels is then the cost
model, and it is the same on the CPU as on the GPU, so it can be measured and tested without a GPU.

:class:`KernelCounter` counts the aten ops dispatched inside it that produce new data (views, detaches and
aliases are free: they launch nothing). Ops that autograd runs in the backward are counted when the backward
runs inside the counter on the same thread (always on CPU).

It also adds up the bytes each counted op reads and writes (its tensor inputs and outputs; a broadcast input
counts its storage, not its expanded size): at large images the same terms are bound by memory traffic
instead, each unfused elementwise kernel reading and writing whole images, and ``bytes`` / the device's
bandwidth is a lower bound on their device time.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from typing import Any

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

#: aten ops that are not views by schema but launch no kernel either.
FREE_OPS = frozenset({"aten.detach", "aten._unsafe_view", "aten.t", "aten.lift_fresh", "aten.alias"})


class KernelCounter(TorchDispatchMode):
    """``with KernelCounter() as k: ...`` then ``k.total`` (kernels) and ``k.ops`` (Counter by aten op)."""

    def __init__(self) -> None:
        super().__init__()
        self.ops: Counter[str] = Counter()
        #: bytes read and written by the counted ops, by aten op
        self.traffic: Counter[str] = Counter()

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        name = str(func.overloadpacket)
        out = func(*args, **(kwargs or {}))
        if not func.is_view and name not in FREE_OPS:
            self.ops[name] += 1
            self.traffic[name] += sum(_bytes(t) for t in tree_leaves((args, kwargs, out)))
        return out

    @property
    def total(self) -> int:
        return sum(self.ops.values())

    @property
    def bytes(self) -> int:
        """Bytes read and written by all counted ops."""
        return sum(self.traffic.values())


def _bytes(t: Any) -> int:
    """What an op moves for one operand: its elements, or its storage where that is smaller (a broadcast,
    expanded view is read once); 0 for anything but a tensor."""
    if not isinstance(t, torch.Tensor):
        return 0
    n = t.numel() * t.element_size()
    try:
        return min(n, t.untyped_storage().nbytes())
    except (RuntimeError, NotImplementedError):  # tensors without storage (meta, sparse)
        return n


Phases = list[tuple[str, Callable[[], None]]]


def jsgs_step(
    mode: str = "paper",
    sampling: str = "4:2:0",
    size: tuple[int, int] = (96, 64),
    n_gaussians: int = 1000,
    device: torch.device | str = "cpu",
) -> Phases:
    """One view's JSGS work on synthetic inputs, as named phases to run in order: "JO" (``jpeg_observe``),
    "L_obs" (its photometric loss), "DS" (``dct_supervision``), "backward" (through the three, weighted as in
    training) and "GC (in backward)" (``fro_from_probe_grad``: r̄ from the probe's gradient,
    ``controller_matrix``, L_fro and its gradient, for ``n_gaussians``; what the hook runs eagerly or records
    as one CUDA graph). ``size`` is (W, H). What ``tools/diagnostics/bench_kernel_count.py`` and
    ``tests/test_jsgs/apps/test_opcount.py`` count."""
    from jsgs.jpeg.losses import photometric_loss
    from jsgs.jpeg.observe import jpeg_observe
    from jsgs.jpeg.supervision import dct_supervision
    from jsgs.kernels import fro_from_probe_grad

    w, h = size
    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(1, 3, h, w, generator=g).to(device)
    y = torch.rand(1, 3, h, w, generator=g).to(device)
    ly = torch.randint(2, 60, (8, 8), generator=g).float().to(device)
    lc = torch.randint(2, 90, (8, 8), generator=g).float().to(device)
    state: dict[str, Any] = {}

    def jo() -> None:
        state["obs"] = jpeg_observe(x0.clone().requires_grad_(True), ly, lc, sampling, mode)

    def l_obs() -> None:
        state["lo"] = photometric_loss(state["obs"], y, 0.2, padding="valid")

    def ds() -> None:
        state["ds"] = dct_supervision(state["obs"], y, ly)

    def backward() -> None:
        s = state["ds"]
        (0.2 * state["lo"] + 0.02 * s.loss_low.sum() + 0.03 * s.loss_mid.sum()).backward()

    means = (torch.randn(n_gaussians, 3, generator=g) + torch.tensor([0.0, 0.0, 4.0])).to(device)
    quats = torch.randn(n_gaussians, 4, generator=g).to(device)
    logits = torch.randn(n_gaussians, generator=g).to(device)
    log_scales = (torch.randn(n_gaussians, 3, generator=g) - 4.0).to(device)
    probe_grad = torch.rand(1, n_gaussians, 2, generator=g).to(device)
    viewmat = torch.eye(4, device=device)
    K = torch.tensor([[1.2 * w, 0.0, w / 2], [0.0, 1.2 * w, h / 2], [0.0, 0.0, 1.0]], device=device)

    def gc() -> None:
        fro_from_probe_grad(probe_grad, logits, log_scales, means, quats, viewmat, K, w, h, weight=0.05)

    return [("JO", jo), ("L_obs", l_obs), ("DS", ds), ("backward", backward), ("GC (in backward)", gc)]


def count_phases(phases: Phases) -> dict[str, int]:
    """Kernels per phase, after one warm-up pass of all of them (constants built and cached on first use
    are not per-step work)."""
    return {name: k.total for name, k in count_phases_detail(phases).items()}


def count_phases_detail(phases: Phases) -> dict[str, KernelCounter]:
    """Each phase's :class:`KernelCounter` (kernels and bytes moved), after one warm-up pass of them all."""
    for _, fn in phases:
        fn()
    out = {}
    for name, fn in phases:
        with KernelCounter() as k:
            fn()
        out[name] = k
    return out
