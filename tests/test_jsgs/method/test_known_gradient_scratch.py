"""Known gradients written over their buffers in the backward (``with_known_gradient(..., scratch=True)``):
the products they replace, bit for bit, with no new tensor of the image's size; the buffers written anew
before their next use (the graph's by its replay, the probe objective's by its next call)."""

from __future__ import annotations

import pytest
import torch
from test_graphed import SETTINGS, _eager_recording, _view_tensors
from test_host_path import _probe_info

from jsgs.base.kept_zeros import kept_zeros
from jsgs.base.known_grad import with_known_gradient
from jsgs.method.graphed import GraphedImageTerms
from jsgs.method.image_terms import terms_with_gradient
from jsgs.method.pooling import ProbeObjective

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.mark.parametrize("upstream", [1.0, 3.0, -0.7])
def test_scratch_gradients_are_the_products_written_over_the_buffers(upstream: float) -> None:
    """The gradients sent on are ``upstream * grad`` bit for bit, in the buffers themselves (scratch) or in
    new tensors (not); a second backward through a scratch scalar is refused."""
    sent: dict[bool, list[torch.Tensor]] = {}
    buffers: dict[bool, list[torch.Tensor]] = {}
    for scratch in (False, True):
        gen = torch.Generator().manual_seed(1)
        a = torch.rand(2, 3, 5, generator=gen).requires_grad_()
        b = torch.rand(4, 2, generator=gen, dtype=torch.float64).requires_grad_()
        xa, xb = a * 3.0, b.exp()
        ga, gb = torch.randn(2, 3, 5, generator=gen), torch.randn(4, 2, generator=gen, dtype=torch.float64)
        seen: list[torch.Tensor] = []
        xa.register_hook(seen.append)
        xb.register_hook(seen.append)
        s = with_known_gradient(xa, torch.tensor(0.5), ga, xb, gb, scratch=scratch)
        (upstream * s).backward(retain_graph=True)
        sent[scratch], buffers[scratch] = seen, [ga, gb]
        if scratch:
            with pytest.raises(RuntimeError, match="second backward"):
                (upstream * s).backward()
    for got, want in zip(sent[True], sent[False], strict=True):
        assert torch.equal(got, want) and got.abs().sum() > 0
    assert [g.data_ptr() for g in sent[True]] == [g.data_ptr() for g in reversed(buffers[True])]
    assert not {g.data_ptr() for g in sent[False]} & {g.data_ptr() for g in buffers[False]}


def test_the_graphs_gradient_buffer_is_scaled_once_per_replay(monkeypatch: pytest.MonkeyPatch) -> None:
    """Through the graph (recorded eagerly), an upstream factor other than 1, view after view: the render
    gets the factor times the eager gradient, bit for bit (the replay writes the buffer anew each time)."""
    monkeypatch.setattr(GraphedImageTerms, "_record", _eager_recording)
    w = (0.2, 0.02, 0.03)
    graphed = GraphedImageTerms(weights=w, **SETTINGS)
    for seed in (1, 2, 1):
        x, y, luma, chroma = _view_tensors(seed, dtype=torch.float32)
        tables = torch.stack([luma, chroma])
        xg = x.clone().requires_grad_()
        (3.0 * graphed(xg, y, tables, "4:2:0").weighted).backward()
        xe = x.clone().requires_grad_()
        _, grad, _, _ = terms_with_gradient(xe, y, tables, weights=w, sampling="4:2:0", **SETTINGS)
        assert grad is not None and torch.equal(xg.grad, grad * torch.tensor(3.0)), seed
    assert len(graphed._graphs) == 1


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_probe_objectives_buffer_is_written_anew_after_each_backward(dtype: torch.dtype) -> None:
    """The probe objective's kept buffer, scaled by one backward's upstream, is whole again at the next
    call: each call's probe gradient is that of a new ``weight·(r, 1)`` map times its upstream, bit for
    bit."""
    w = 0.05 * 4
    obj = ProbeObjective(w)
    for call, upstream in enumerate([2.5, 1.0, -0.3]):
        grads = []
        for kept in (True, False):
            info, g = _probe_info(dtype, (1, 6, 5), seed=call)
            r = torch.rand((1, 6, 5), generator=g, dtype=torch.float32)
            if kept:
                value = obj(info, r)
            else:  # the map made anew, its product in a new tensor
                up = torch.stack([r.to(dtype) * w, torch.full_like(r, w, dtype=dtype)], dim=-1)
                value = with_known_gradient(info["extra"], torch.zeros((), dtype=dtype), up)
            (upstream * value).backward()
            grads.append(info["extra_features"].grad)
        assert torch.equal(grads[0], grads[1]) and grads[0].abs().sum() > 0, call


def test_an_owned_value_is_returned_as_a_view() -> None:
    """``own_value``: the scalar is a view of the caller's value (no copy), with the same gradients as the
    copying form; a value that needs grad is refused."""
    grads = []
    for own in (False, True):
        gen = torch.Generator().manual_seed(3)
        a = torch.rand(2, 3, generator=gen).requires_grad_()
        g = torch.randn(2, 3, generator=gen)
        values = torch.tensor([0.25, 1.5, 2.0])
        s = with_known_gradient(a * 2.0, values[0], g, own_value=own)
        assert s.item() == 0.25
        assert (s.untyped_storage().data_ptr() == values.untyped_storage().data_ptr()) == own
        (3.0 * s).backward()
        grads.append(a.grad)
    assert torch.equal(grads[0], grads[1]) and grads[1].abs().sum() > 0
    with pytest.raises(ValueError, match="own_value"):
        with_known_gradient(a, torch.tensor(1.0, requires_grad=True), g, own_value=True)


def test_the_deferred_objective_is_a_view_of_a_kept_zero() -> None:
    """The render's deferred objective (``info["extra_objective"]``) is a view of one zero kept from render to
    render (no kernel of its own), with the gradients of the copying form, bit for bit; ``own_value``
    refuses a value that needs grad."""
    from jsgs.base.known_grad import with_deferred_gradient
    from jsgs.render.backend import _extras

    grads, storages = [], []
    for own in (False, True, True):
        gen = torch.Generator().manual_seed(5)
        ch = (torch.rand(1, 4, 3, 2, generator=gen) * 2.0).requires_grad_()
        up = torch.randn(1, 4, 3, 2, generator=gen)
        info: dict = {"extra": ch * 1.5}
        make = lambda shape, dtype, device, up=up: up.clone()  # noqa: E731
        if own:
            _extras(info, torch.zeros(3, 2), make)
            obj = info["extra_objective"]
            storages.append(obj.untyped_storage().data_ptr())
        else:
            obj = with_deferred_gradient(info["extra"], torch.zeros(()), make)
        assert obj.item() == 0.0 and obj.requires_grad
        (0.5 * obj + ch.sum()).backward()
        grads.append(ch.grad)
    assert storages[0] == storages[1]  # the same zero, render after render: the kept one
    assert storages[0] == kept_zeros(ch).untyped_storage().data_ptr()
    assert torch.equal(grads[0], grads[1]) and torch.equal(grads[1], grads[2])
    assert not torch.equal(grads[0], torch.ones_like(grads[0]))  # the deferred map reached the channels
    with pytest.raises(ValueError, match="own_value"):
        with_deferred_gradient(ch, torch.tensor(0.0, requires_grad=True), make, own_value=True)


def test_a_unit_upstream_hands_the_scratch_gradients_on_as_they_are() -> None:
    """``unit_upstream`` (a scalar added unweighted to a loss whose backward starts from 1, as the trainer
    adds the folded loss): the gradients sent on are the buffers themselves, untouched, equal bit for bit to
    what the product by the upstream 1 sends (gradients with signed zeros, subnormals and infinities
    included); without ``scratch`` it is refused."""
    sent: dict[bool, list[torch.Tensor]] = {}
    for unit in (False, True):
        gen = torch.Generator().manual_seed(4)
        a = torch.rand(2, 3, 5, generator=gen).requires_grad_()
        ga = torch.randn(2, 3, 5, generator=gen)
        ga[0, 0, :4] = torch.tensor([-0.0, 1e-40, float("inf"), -float("inf")])
        kept = ga.clone()
        xa = a * 3.0
        seen: list[torch.Tensor] = []
        xa.register_hook(seen.append)
        other = (a * 2.0).sum()
        s = with_known_gradient(xa, torch.tensor(0.5), ga, scratch=True, unit_upstream=unit)
        (other + s).backward()
        sent[unit] = [seen[0].clone(), a.grad.clone()]
        if unit:
            assert seen[0].data_ptr() == ga.data_ptr() and torch.equal(ga, kept)
    for got, want in zip(sent[True], sent[False], strict=True):
        assert torch.equal(got, want) and torch.equal(got.signbit(), want.signbit())
    with pytest.raises(ValueError, match="scratch"):
        with_known_gradient(a, torch.tensor(0.5), ga, unit_upstream=True)


def test_a_deferred_map_with_a_unit_upstream_is_handed_on_as_made() -> None:
    """``make.unit_upstream`` (the probe's map when the trainer adds the objective unweighted): the map made
    in the backward reaches the channels as it is, the very tensor, equal bit for bit to the product by the
    upstream 1 (signed zeros, subnormals and infinities included)."""
    from jsgs.base.known_grad import with_deferred_gradient

    class Make:
        def __init__(self, unit: bool) -> None:
            self.unit_upstream, self.made = unit, None

        def __call__(self, shape: tuple[int, ...], dtype: torch.dtype, device: torch.device) -> torch.Tensor:
            g = torch.randn(shape, generator=torch.Generator().manual_seed(6), dtype=dtype)
            g.view(-1)[:4] = torch.tensor([-0.0, 1e-40, float("inf"), -float("inf")])
            self.made = g
            return g

    sent, products = [], []
    for unit in (False, True):
        ch = torch.rand(1, 4, 3, 2, generator=torch.Generator().manual_seed(2)).requires_grad_()
        x = ch * 1.0
        seen: list[torch.Tensor] = []
        x.register_hook(seen.append)
        make = Make(unit)
        obj = with_deferred_gradient(x, torch.zeros(()), make, own_value=True)
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            ((ch * 2.0).sum() + obj).backward()
        products.append(sum(e.name == "aten::mul_" for e in prof.events()))
        sent.append(seen[0].clone())
        assert seen[0].data_ptr() == make.made.data_ptr()
    assert products == [1, 0]  # the product by the upstream, made only without the unit upstream
    assert torch.equal(sent[0], sent[1]) and torch.equal(sent[0].signbit(), sent[1].signbit())
