"""The cuts to the image terms' chain and its graph that only run as written on CUDA, checked there against
the formulation they replace: the clamp that keeps a mask (against CUDA's hardtanh), the L1 term that keeps
no difference image, the fused SSIM's mean with a broadcast upstream, the luma plane copied out of the
YCbCr image for the fused coding pass, the target laid out as the fused SSIM keeps it, r_b without r(p);
and the graph's calls as the hook makes them (the values the graph's output buffer, not a copy; a unit
upstream handed on without the product; tables shared by views copied only when they change), against the
copying, multiplying call and the eager function. The CPU tests of the same cuts run the same Python with
stand-ins for the CUDA parts (``test_chain_memory.py``, ``test_graphed.py``); these need CUDA (``-m gpu``)."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

import pytest
import torch
import torch.nn.functional as F

from jsgs.jpeg import losses as losses_module
from jsgs.jpeg import observe as observe_module
from jsgs.jpeg import sampling as sampling_module
from jsgs.jpeg.losses import _MeanAbsDifference
from jsgs.jpeg.observe import _Clamp255
from jsgs.jpeg.supervision import table_weights
from jsgs.kernels import _wrapper
from jsgs.kernels._triton_jo import fused_jo_runs
from jsgs.method import image_terms as image_terms_module
from jsgs.method.graphed import GraphedImageTerms
from jsgs.method.image_terms import terms_with_gradient

SETTINGS = dict(
    mode="paper", ssim_lambda=0.2, ssim_padding="valid", ds=True, gc=True, eps_sm=1e-3, eps_loss=1e-6,
    eps_block=1e-6,
)  # fmt: skip
WEIGHTS = (0.2, 0.02, 0.03)


def _bits(t: torch.Tensor) -> torch.Tensor:
    return t.detach().contiguous().view(-1).view(torch.uint8)


def clamp_against_hardtanh(device: str) -> None:
    """:class:`_Clamp255` against ``F.hardtanh(x, 0, 255)`` on ``device``: the values everywhere and the
    gradient wherever the input is not NaN, bit for bit (the bounds, signed zeros, infinities). At NaN the
    clamp writes 0; CUDA's hardtanh passes the upstream there (``(x <= 0 || x >= 255) ? 0 : g``), as the
    CPU's scalar loop does and its vector loop does not: a NaN render fails the step anyway."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 37, 41, generator=g) * 300 - 20
    edges = [0.0, 255.0, -0.0, float("nan"), float("inf"), -float("inf"), 1e-30, 254.99, 255.00002, -1e-30]
    x.view(-1)[: len(edges)] = torch.tensor(edges)
    x.view(-1)[-len(edges) :] = torch.tensor(edges)  # also where a vectorised loop leaves its tail
    x, up = x.to(device), torch.randn(x.shape, generator=g).to(device)
    a, b = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
    ref, out = F.hardtanh(a, 0.0, 255.0), _Clamp255.apply(b)
    assert torch.equal(_bits(ref), _bits(out))
    ((ga,), (gb,)) = torch.autograd.grad(ref, a, up), torch.autograd.grad(out, b, up)
    finite = ~x.isnan()
    assert torch.equal(_bits(ga[finite]), _bits(gb[finite]))
    assert not gb[~finite].any()


def l1_against_autograd(device: str) -> None:
    """``_MeanAbsDifference`` against ``(x - y).abs().mean()`` on ``device`` (a render's layout against a
    contiguous target, as the graph's L1 gets them; ties): the value and both gradients bit for bit. On
    CUDA both divide by the element count as a multiplication by its reciprocal (the mean's backward and
    ``grad / numel``)."""
    g = torch.Generator().manual_seed(5)
    x = torch.rand(1, 97, 131, 3, generator=g).permute(0, 3, 1, 2).to(device)  # 38,121 values: no power of 2
    y = torch.rand(1, 3, 97, 131, generator=g).to(device)
    y[0, 1, 2, :9] = x[0, 1, 2, :9]  # ties: sgn 0
    for grads in ((True, False), (True, True), (False, True)):
        (xa, ya), (xb, yb) = (
            (x.detach().clone().requires_grad_(grads[0]), y.clone().requires_grad_(grads[1])) for _ in "ab"
        )
        ref, out = (xa - ya).abs().mean(), _MeanAbsDifference.apply(xb, yb)
        assert torch.equal(_bits(ref), _bits(out)), grads
        up = torch.tensor(-0.37, device=device)
        want = torch.autograd.grad(ref, [t for t in (xa, ya) if t.requires_grad], up)
        got = torch.autograd.grad(out, [t for t in (xb, yb) if t.requires_grad], up)
        for wt, gt in zip(want, got, strict=True):
            assert torch.equal(_bits(wt), _bits(gt)), grads


class _MapMean:
    """The fused SSIM's mean as the map's mean (what ``_FusedSsimMean`` replaces)."""

    @staticmethod
    def apply(x: torch.Tensor, y: torch.Tensor, window: torch.Tensor, same: bool) -> torch.Tensor:
        return _wrapper._FusedSsimMap.apply(x, y, window, same).mean()


class _PlainL1:
    @staticmethod
    def apply(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return (x - y).abs().mean()


class _Hardtanh:
    apply = staticmethod(observe_module._clamp_255)


def _undo_the_cuts(monkeypatch: pytest.MonkeyPatch, layout: bool) -> None:
    """The chain's formulation before its memory cuts: hardtanh's clamp, autograd's L1, the fused SSIM's
    map and its mean, the luma plane coded in place, torch's replicate pad; ``layout``: also the target as
    the image makes it (not laid out as the fused SSIM keeps it)."""
    monkeypatch.setattr(observe_module, "_Clamp255", _Hardtanh)
    monkeypatch.setattr(observe_module, "_shares_storage", lambda a, b: False)
    monkeypatch.setattr(losses_module, "_MeanAbsDifference", _PlainL1)
    monkeypatch.setattr(_wrapper, "_FusedSsimMean", _MapMean)
    monkeypatch.setattr(sampling_module, "replicate_pad", lambda x, pad: F.pad(x, pad, mode="replicate"))
    if layout:
        monkeypatch.setattr(image_terms_module, "ssim_is_fused", lambda *a, **k: False)
        # the loss hands its pick to ssim: ssim picks for itself here (the layout undone, not the fused SSIM)
        monkeypatch.setattr(losses_module, "ssim_is_fused", lambda *a, **k: False)
        real_ssim = losses_module.ssim
        monkeypatch.setattr(losses_module, "ssim", lambda *a, fused=None, **k: real_ssim(*a, **k))


def chain_against_the_uncut(device: str, monkeypatch: pytest.MonkeyPatch, size: tuple[int, int]) -> bool:
    """The graph's function (:func:`terms_with_gradient` as the graph records it, at 4:2:0 with the fused
    kernels where they run) at ``size`` against itself with the cuts undone: with the same target layout,
    the values, the gradient and r_b bit for bit where the chain is deterministic (a plane padded to whole
    blocks sums its edge's gradients with atomics on CUDA, in either formulation), else within float32's
    rounding; with the target as the image makes it too, within float32's rounding (L1's mean and DS's sums
    may add in another order). Returns whether it was deterministic."""
    h, w = size
    g = torch.Generator().manual_seed(9)
    render = torch.rand(1, h, w, 3, generator=g).to(device) * 1.1 - 0.05
    image = (torch.rand(h, w, 3, generator=g) * 255).to(torch.uint8).to(device)
    tables = torch.stack([torch.full((8, 8), 9.0), torch.full((8, 8), 14.0)]).to(device)
    tables[0, 0, 0], tables[1, 3, 2] = 5.0, 30.0
    x = render.permute(0, 3, 1, 2)
    kern = "triton" if fused_jo_runs(x) else "torch"
    settings = {**SETTINGS, "jo_kernel": kern, "color_kernel": kern, "ssim_kernel": "auto",
                "ds_weights": table_weights(tables[0], 1, torch.float32, x.device)}  # fmt: skip

    def run(r_blocks: bool) -> tuple[torch.Tensor, ...]:
        xa = x.clone(memory_format=torch.preserve_format).requires_grad_(True)
        values, grad, r, _ = terms_with_gradient(
            xa, image, tables, weights=WEIGHTS, sampling="4:2:0", observation=False, r_blocks=r_blocks,
            **settings,
        )  # fmt: skip
        assert grad is not None
        return values, grad, r if r_blocks else r[:, : h // 8 * 8 : 8, : w // 8 * 8 : 8]

    cut, again = run(True), run(True)
    deterministic = all(torch.equal(a, b) for a, b in zip(cut, again, strict=True))
    with monkeypatch.context() as m:
        _undo_the_cuts(m, layout=False)
        uncut = run(False)
    with monkeypatch.context() as m:
        _undo_the_cuts(m, layout=True)
        as_made = run(False)
    print(f"\nchain {w}x{h} on {device}: kernels {kern}, deterministic {deterministic}")
    for a, b, c in zip(cut, uncut, as_made, strict=True):
        if deterministic:
            assert torch.equal(_bits(a), _bits(b))
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-9)
        torch.testing.assert_close(a, c, rtol=1e-5, atol=1e-8)
    return deterministic


def _probe_pair(leaf: torch.Tensor) -> Callable[[torch.Tensor], tuple[torch.Tensor, ...]]:
    """``more`` for a graph call: ``leaf`` with a gradient made from r_b for this call alone (as the probe's
    upstream map is)."""
    return lambda r: (leaf, r.flatten()[: leaf.numel()].reshape(leaf.shape) * 3.0 + 0.5)


def graph_calls_against_copying_ones(device: str, kernel: str = "torch") -> None:
    """Two graph objects fed the same views: one called as the hook calls it (``copy_values=False``,
    ``unit_upstream=True``: the values and weighted sum the output buffer, the gradients handed on as
    they are), one copying the values and multiplying the gradients by the upstream 1. Views share one
    tables tensor (as ``view_tables`` makes them) in runs, other tables come between, in both orientations:
    every call's values, weighted sum, r_b and the render's and a probe-like leaf's gradients equal between
    the two bit for bit, and the eager function's on that view's tables (a stale tables buffer would not).
    ``kernel``: JO's and the colour transform's ("triton": the fused kernels, recorded in the graph, the luma
    plane copied out of the YCbCr image at these sizes)."""
    settings = {**SETTINGS, "jo_kernel": kernel, "color_kernel": kernel}
    plain, direct = (GraphedImageTerms(weights=WEIGHTS, **settings) for _ in range(2))
    g = torch.Generator().manual_seed(21)
    shared = torch.randint(1, 80, (2, 8, 8), generator=g).float().to(device)
    other = torch.randint(1, 80, (2, 8, 8), generator=g).float().to(device)
    calls = [(shared, 48, 64), (shared, 48, 64), (other, 48, 64), (shared, 48, 64), (other, 64, 48),
             (shared, 64, 48), (shared, 48, 64), (other, 64, 48), (other, 64, 48),
             (shared, 48, 64)]  # fmt: skip
    for i, (tables, hh, ww) in enumerate(calls):
        render = torch.rand(1, hh, ww, 3, generator=g).to(device)
        image = torch.randint(0, 256, (hh, ww, 3), generator=g, dtype=torch.uint8).to(device)
        xa, xb, xe, xe2 = (render.clone().permute(0, 3, 1, 2).requires_grad_() for _ in range(4))
        pa, pb = (torch.zeros(2, 3, device=device, requires_grad=True) for _ in range(2))
        a = plain(xa, image, tables, "4:2:0", _probe_pair(pa))
        b = direct(xb, image, tables, "4:2:0", _probe_pair(pb), copy_values=False, unit_upstream=True)
        outputs = [rec.outputs[0].data_ptr() for rec in direct._graphs.values()]
        assert b.weighted.data_ptr() in outputs and b.values.data_ptr() == b.weighted.data_ptr() + 4, i
        assert a.weighted.data_ptr() not in [rec.outputs[0].data_ptr() for rec in plain._graphs.values()], i
        values, grad, r, _ = terms_with_gradient(
            xe, image, tables, weights=WEIGHTS, sampling="4:2:0", r_blocks=True, **settings
        )
        again = terms_with_gradient(xe2, image, tables, weights=WEIGHTS, sampling="4:2:0", r_blocks=True,
                                    **settings)[:3]  # fmt: skip
        # bit for bit where the chain itself is (no atomics in its kernels' backward on this device)
        exact = all(torch.equal(u, v) for u, v in zip((values, grad, r), again, strict=True))
        same = torch.equal if exact else partial(torch.allclose, rtol=1e-6, atol=1e-8)
        assert same(a.values, b.values) and same(a.weighted, b.weighted), i
        assert same(a.r, b.r), i
        torch.testing.assert_close(b.values, values[1:], rtol=1e-6, atol=1e-7)
        torch.testing.assert_close(b.weighted.detach(), values[0], rtol=1e-6, atol=1e-7)
        torch.testing.assert_close(b.r, r, rtol=1e-6, atol=1e-7)
        a.weighted.backward()
        b.weighted.backward()  # from 1: the upstream unit_upstream promises
        assert same(xa.grad, xb.grad) and same(pa.grad, pb.grad), i
        assert grad is not None
        torch.testing.assert_close(xb.grad, grad, rtol=1e-5, atol=1e-8)
    assert len(direct._graphs) == 2  # one recording per orientation


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gpu_the_clamp_is_cudas_hardtanh_bit_for_bit_but_at_nan() -> None:
    clamp_against_hardtanh("cuda")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gpu_the_l1_term_is_autograds_bit_for_bit() -> None:
    l1_against_autograd("cuda")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gpu_the_chains_memory_cuts_leave_its_values_and_gradient(monkeypatch: pytest.MonkeyPatch) -> None:
    assert _wrapper.extension() is not None  # the fused SSIM built: the path the cuts change
    # 80x112: no plane padded (the luma plane a view of the YCbCr image, copied for the fused coding pass);
    # 72x100: luma and chroma padded to whole blocks
    assert chain_against_the_uncut("cuda", monkeypatch, (80, 112))
    chain_against_the_uncut("cuda", monkeypatch, (72, 100))


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("kernel", ["torch", "triton"])
def test_gpu_graph_calls_as_the_hook_makes_them_equal_copying_ones(kernel: str) -> None:
    if kernel == "triton" and not fused_jo_runs(torch.zeros(1, 3, 8, 8, device="cuda")):
        pytest.skip("the fused JO kernels do not run here (Triton)")
    graph_calls_against_copying_ones("cuda", kernel)


def test_the_gpu_checks_run_on_the_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    """The checks above on the CPU, with the eager stand-in for a graph's recording: they run, and a graph
    that keeps stale tables (never copies a view's tables after its recording) fails them."""
    from test_graphed import _eager_recording

    clamp_against_hardtanh("cpu")
    l1_against_autograd("cpu")
    assert chain_against_the_uncut("cpu", monkeypatch, (80, 112))
    chain_against_the_uncut("cpu", monkeypatch, (72, 100))
    with monkeypatch.context() as m:
        m.setattr(GraphedImageTerms, "_record", _eager_recording)
        graph_calls_against_copying_ones("cpu")
        if fused_jo_runs(torch.zeros(1, 3, 8, 8)):  # interpreted Triton
            graph_calls_against_copying_ones("cpu", "triton")
        real_call = GraphedImageTerms.__call__

        def stale(self: GraphedImageTerms, x: torch.Tensor, y: torch.Tensor, tables: torch.Tensor,
                  *args: Any, **kwargs: Any) -> Any:  # fmt: skip
            for rec in self._graphs.values():  # "the buffer holds these tables already"
                self._tables_held[rec.inputs[2].data_ptr()] = tables
            return real_call(self, x, y, tables, *args, **kwargs)

        m.setattr(GraphedImageTerms, "__call__", stale)
        with pytest.raises(AssertionError):
            graph_calls_against_copying_ones("cpu")
