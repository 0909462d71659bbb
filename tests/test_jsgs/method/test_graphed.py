"""``method_options.speed.cuda_graph``: JO, L_obs and DS as one pure function of tensors (tested here on the
CPU against the eager hook) and its CUDA-graph replay (GPU only: the same values and gradients as eager)."""

from __future__ import annotations

from contextlib import nullcontext
from functools import partial
from pathlib import Path
from typing import Any

import pytest
import torch
from test_jsgs_method import jsgs_options, make_splats, make_view, new_hook, target_for, train_step

from jsgs.base.errors import JsgsError
from jsgs.jpeg.losses import photometric_loss
from jsgs.jpeg.observe import jpeg_observe
from jsgs.jpeg.supervision import dct_supervision, pixel_score_of
from jsgs.kernels import fro_from_probe_grad, packed_fro_stats
from jsgs.kernels._triton_jo import triton_available
from jsgs.method import graphed as graphed_module
from jsgs.method.graphed import GraphedController, GraphedImageTerms, _Recording
from jsgs.method.hook import JsgsHook
from jsgs.method.image_terms import image_terms, terms_with_gradient
from jsgs.method.options import parse_options, use_cuda_graph
from jsgs.train.data import image_target, stacked_image

SETTINGS = dict(
    mode="paper", ssim_lambda=0.2, ssim_padding="valid", ds=True, gc=True, eps_sm=1e-3, eps_loss=1e-6,
    eps_block=1e-6,
)  # fmt: skip


def _view_tensors(
    seed: int, device: str = "cpu", dtype: torch.dtype = torch.float64
) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(1, 3, 37, 53, generator=g, dtype=dtype) * 1.1 - 0.05  # a little outside [0, 1] too
    y = torch.rand(1, 3, 37, 53, generator=g, dtype=dtype)
    luma = torch.randint(1, 80, (8, 8), generator=g).to(dtype)
    chroma = torch.randint(1, 120, (8, 8), generator=g).to(dtype)
    return tuple(t.to(device) for t in (x, y, luma, chroma))


@pytest.mark.parametrize(("ds", "gc"), [(True, True), (False, True), (True, False), (False, False)])
def test_image_terms_are_the_three_eager_functions(ds: bool, gc: bool) -> None:
    x, y, luma, chroma = _view_tensors(0)
    x1 = x.clone().requires_grad_()
    l_obs, low, mid, r, obs = image_terms(
        x1, y, luma, chroma, sampling="4:2:0", **{**SETTINGS, "ds": ds, "gc": gc}
    )
    x2 = x.clone().requires_grad_()
    obs2 = jpeg_observe(x2, luma, chroma, "4:2:0", "paper")
    l_obs2 = photometric_loss(obs2, y, 0.2, padding="valid")
    sup = dct_supervision(obs2, y, luma)
    assert torch.equal(obs, obs2.detach()) and l_obs.item() == l_obs2.item()
    if ds:
        assert low.item() == sup.loss_low.sum().item() and mid.item() == sup.loss_mid.sum().item()
    else:
        assert low.item() == 0.0 and mid.item() == 0.0
    assert torch.equal(r, sup.pixel_score) if (ds or gc) else not r.any()
    (0.2 * l_obs + 0.02 * low + 0.03 * mid).backward()
    (0.2 * l_obs2 + (0.02 * sup.loss_low.sum() + 0.03 * sup.loss_mid.sum() if ds else 0.0)).backward()
    torch.testing.assert_close(x1.grad, x2.grad, rtol=1e-12, atol=1e-15)


def _eager_recording(
    self: GraphedImageTerms, x: torch.Tensor, y: torch.Tensor, tables: torch.Tensor, sampling: str,
    observation: bool,
) -> _Recording:
    """GraphedImageTerms._record without CUDA: the same input and output buffers, and a "replay" that runs
    the function the graph would record on the input buffers and writes its results into the outputs."""
    fn, inputs = self._recorded_function(x, y, tables, sampling, observation)
    outputs = fn()

    def replay() -> None:
        for buf, new in zip(outputs, fn(), strict=True):
            if buf is not None:
                buf.copy_(new)

    return _Recording(replay, inputs, outputs)


def test_terms_with_gradient_is_the_gradient_of_the_weighted_sum() -> None:
    x, y, luma, chroma = _view_tensors(4)
    w = (0.2, 0.02, 0.03)
    values, grad, r, obs = terms_with_gradient(
        x.clone().requires_grad_(), y, torch.stack([luma, chroma]), weights=w, sampling="4:2:0", **SETTINGS
    )
    x2 = x.clone().requires_grad_()
    l_obs, low, mid, r2, obs2 = image_terms(x2, y, luma, chroma, sampling="4:2:0", **SETTINGS)
    total = w[0] * l_obs + w[1] * low + w[2] * mid
    total.backward()
    assert values.tolist() == [total.item(), l_obs.item(), low.item(), mid.item()]
    assert grad is not None and torch.equal(grad, x2.grad)
    assert torch.equal(r, r2) and torch.equal(obs, obs2) and not values.requires_grad
    none = terms_with_gradient(x, y, torch.stack([luma, chroma]), weights=w, sampling="4:2:0", **SETTINGS)
    assert none[1] is None and torch.equal(none[0], values)


@pytest.mark.parametrize(
    ("ds", "gc"),
    [(True, {}), (False, {}), (True, {"gc_attribution": "footprint"}), (True, {"lambda_fro": 0.0})],
)
def test_the_hooks_graphed_branch_gives_the_eager_terms_and_gradients(
    monkeypatch: pytest.MonkeyPatch, ds: bool, gc: dict[str, Any]
) -> None:
    """The hook's cuda_graph branch through GraphedImageTerms with its recording replaced by an eager one on
    the CPU (buffers and all): the eager hook's terms, statistics and gradients, the image terms folded into
    one weighted term whose gradient was computed ahead, and nothing the step keeps aliasing the buffers. The
    controller's routes that read r(p) (the footprint attribution; λ_fro 0, pooled at once) make it from the
    graph's block scores; the deferred probe's map is made from them directly."""
    view = make_view(30, "4:2:0")
    eager = train_step(new_hook(view, ds=ds, **gc), view)
    monkeypatch.setattr(GraphedImageTerms, "_record", _eager_recording)
    hook = new_hook(view, ds=ds, **gc)
    w = hook.weights()
    hook._graphed = GraphedImageTerms(
        weights=(w["obs"], w.get("low", 0.0), w.get("mid", 0.0)), **hook._jpeg_settings
    )
    splats = make_splats()
    graphed = train_step(hook, view, splats)
    assert set(graphed["terms"]) == set(eager["terms"])
    for k, v in eager["terms"].items():
        assert graphed["terms"][k] == pytest.approx(v, rel=1e-12, abs=1e-15), k
    for k, v in eager["stats"].items():
        assert graphed["stats"][k] == pytest.approx(v, rel=1e-12), k
    for k, g in eager["grads"].items():
        torch.testing.assert_close(graphed["grads"][k], g, rtol=1e-10, atol=1e-14)
    # a second step through the same buffers (a replay, no new recording) gives the same again
    again = train_step(hook, view)
    assert again["terms"] == graphed["terms"] and len(hook._graphed._graphs) == 1
    for k, g in graphed["grads"].items():
        assert torch.equal(again["grads"][k], g), k
    kept = {k: p.grad.clone() for k, p in splats.items()}
    (rec,) = hook._graphed._graphs.values()
    for b in rec.outputs:
        if b is not None:
            b.fill_(float("nan"))
    for k, p in splats.items():
        assert torch.equal(p.grad, kept[k]), k


def test_the_observation_is_a_graph_output_only_when_asked_for(monkeypatch: pytest.MonkeyPatch) -> None:
    """A graph recorded without the observation keeps no buffer for it and gives the same values, gradient
    and r(p), bit for bit, as one recorded with it; the hook asks for it only with ``keep_last`` (a graph
    of each kind then, the same terms and gradients from both)."""
    x, y, luma, chroma = _view_tensors(5)
    tables, w = torch.stack([luma, chroma]), (0.2, 0.02, 0.03)
    monkeypatch.setattr(GraphedImageTerms, "_record", _eager_recording)
    graphed = GraphedImageTerms(weights=w, **SETTINGS)
    xa, xb = x.clone().requires_grad_(), x.clone().requires_grad_()
    a, b = graphed(xa, y, tables, "4:2:0"), graphed(xb, y, tables, "4:2:0", observation=True)
    assert a.obs is None and b.obs is not None and len(graphed._graphs) == 2
    assert [rec.outputs[3] is None for rec in graphed._graphs.values()] == [True, False]
    xe = x.clone().requires_grad_()
    eager = terms_with_gradient(xe, y, tables, weights=w, sampling="4:2:0", **SETTINGS)
    assert torch.equal(b.obs, eager[3]) and torch.equal(a.values, b.values) and torch.equal(a.r, b.r)
    assert torch.equal(pixel_score_of(a.r, 37, 53), eager[2])
    assert torch.equal(torch.autograd.grad(a.weighted, xa)[0], torch.autograd.grad(b.weighted, xb)[0])
    view = make_view(30, "4:2:0")
    steps = {}
    for keep in (False, True):
        hook = new_hook(view)
        hook.keep_last = keep
        hw = hook.weights()
        hook._graphed = GraphedImageTerms(weights=(hw["obs"], hw["low"], hw["mid"]), **hook._jpeg_settings)
        steps[keep] = train_step(hook, view)
        (key,) = hook._graphed._graphs
        assert key[-1] is keep and ("observation" in hook.last) is keep
    assert steps[False]["terms"] == steps[True]["terms"] and steps[False]["stats"] == steps[True]["stats"]
    for k, g in steps[True]["grads"].items():
        assert torch.equal(steps[False]["grads"][k], g), k


def test_the_graph_makes_the_target_from_the_uint8_image(monkeypatch: pytest.MonkeyPatch) -> None:
    """Given the uint8 training image instead of its target, the graph keeps a 3-byte-a-pixel target buffer
    and gives the values, gradient and r(p) of the trainer's float target, bit for bit; the hook hands it
    the step's image where the context has one, with the same terms and gradients as from the target."""
    monkeypatch.setattr(GraphedImageTerms, "_record", _eager_recording)
    x, _, luma, chroma = _view_tensors(6, dtype=torch.float32)
    image = torch.randint(0, 256, (37, 53, 3), generator=torch.Generator().manual_seed(6), dtype=torch.uint8)
    y = image_target(image).permute(0, 3, 1, 2)
    tables, w = torch.stack([luma, chroma]), (0.2, 0.02, 0.03)
    graphed = GraphedImageTerms(weights=w, **SETTINGS)
    xa, xb = x.clone().requires_grad_(), x.clone().requires_grad_()
    a, b = graphed(xa, y, tables, "4:2:0"), graphed(xb, image, tables, "4:2:0")
    buffers = [rec.inputs[1] for rec in graphed._graphs.values()]
    assert [(t.dtype, t.nbytes) for t in buffers] == [(torch.float32, 12 * 37 * 53),
                                                      (torch.uint8, 3 * 37 * 53)]  # fmt: skip
    assert torch.equal(a.values, b.values) and torch.equal(a.r, b.r) and a.values[0] > 0
    assert torch.equal(torch.autograd.grad(a.weighted, xa)[0], torch.autograd.grad(b.weighted, xb)[0])
    view = make_view(30, "4:2:0")
    image = (torch.as_tensor(target_for(view)[0].numpy()) * 255.0).round().to(torch.uint8)
    steps = []
    for given in (None, image):
        hook = new_hook(view)
        hook.keep_last = False
        hw = hook.weights()
        hook._graphed = GraphedImageTerms(weights=(hw["obs"], hw["low"], hw["mid"]), **hook._jpeg_settings)
        steps.append(train_step(hook, view, image=image, context_image=given is not None))
        (rec,) = hook._graphed._graphs.values()
        assert rec.inputs[1].dtype == (torch.float32 if given is None else torch.uint8)
    assert steps[0]["terms"] == steps[1]["terms"] and steps[0]["stats"] == steps[1]["stats"]
    for k, g in steps[0]["grads"].items():
        assert torch.equal(steps[1]["grads"][k], g), k


def _kept_bytes(graphed: GraphedImageTerms) -> int:
    """Bytes of every storage the object's recordings keep (inputs and outputs), each storage once."""
    storages = {}
    for rec in graphed._graphs.values():
        for t in (*rec.inputs, *rec.outputs):
            if t is not None:
                storages[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
    return sum(storages.values())


def test_two_orientations_share_one_set_of_buffers(monkeypatch: pytest.MonkeyPatch) -> None:
    """Views of W×H and H×W (a scene shot in both orientations) get a recording each, on one set of
    buffers: the render's (channels-last, as the trainer's render is), the uint8 image's, the tables' and
    the block scores', 15 bytes a pixel and 4 bytes a block in all, where a set per recording with r(p)
    kept 38 bytes a pixel. View after view, in either order, each call's values, gradient and r_b are the
    eager function's bit for bit, and r_b makes its r(p)."""
    monkeypatch.setattr(GraphedImageTerms, "_record", _eager_recording)
    w = (0.2, 0.02, 0.03)
    graphed = GraphedImageTerms(weights=w, **SETTINGS)
    h, wd = 24, 40
    g = torch.Generator().manual_seed(11)
    for i, (hh, ww) in enumerate([(h, wd), (wd, h), (wd, h), (h, wd), (wd, h)]):
        render = torch.rand(1, hh, ww, 3, generator=g)  # [1, H, W, 3] as rendered, permuted as the hook does
        image = torch.randint(0, 256, (hh, ww, 3), generator=g, dtype=torch.uint8)
        tables = torch.randint(1, 80, (2, 8, 8), generator=g).float()
        x = render.permute(0, 3, 1, 2).requires_grad_()
        out = graphed(x, image, tables, "4:2:0")
        xe = render.clone().permute(0, 3, 1, 2).requires_grad_()
        values, grad, r, _ = terms_with_gradient(xe, image, tables, weights=w, sampling="4:2:0", **SETTINGS)
        assert torch.equal(out.values, values[1:]) and torch.equal(out.weighted.detach(), values[0]), i
        assert out.r.shape == (1, hh // 8, ww // 8) and torch.equal(pixel_score_of(out.r, hh, ww), r), i
        out.weighted.backward()
        assert torch.equal(x.grad, grad), i
    assert len(graphed._graphs) == 2
    a, b = graphed._graphs.values()
    assert a.inputs[0].stride() == (3 * h * wd, 1, 3 * wd, 3)  # channels-last, as the render
    for buf_a, buf_b in zip((*a.inputs, a.outputs[2]), (*b.inputs, b.outputs[2]), strict=True):
        assert buf_a.data_ptr() == buf_b.data_ptr()
    pixels, blocks = h * wd, (h // 8) * (wd // 8)
    values_bytes = 2 * 4 * 4  # each recording's four values
    assert _kept_bytes(graphed) == 15 * pixels + 4 * blocks + 2 * 64 * 4 + values_bytes  # was 38 a pixel


def test_tables_already_in_the_buffer_are_not_copied_again(monkeypatch: pytest.MonkeyPatch) -> None:
    """Views that share one tables tensor (as ``view_tables`` makes them for equal tables) copy it into the
    graph's buffer once, until other tables (or a recording of another image size, on the same buffer)
    come: view after view, both orientations, each call's values, gradient and r_b are the eager function's
    bit for bit."""
    monkeypatch.setattr(GraphedImageTerms, "_record", _eager_recording)
    w = (0.2, 0.02, 0.03)
    graphed = GraphedImageTerms(weights=w, **SETTINGS)
    g = torch.Generator().manual_seed(17)
    shared, other = (torch.randint(1, 80, (2, 8, 8), generator=g).float() for _ in range(2))
    copied = []
    calls = [(shared, 24, 40), (shared, 24, 40), (other, 24, 40), (shared, 24, 40), (other, 40, 24),
             (shared, 40, 24), (shared, 24, 40), (other, 40, 24), (other, 40, 24)]  # fmt: skip
    for i, (tables, hh, ww) in enumerate(calls):
        render = torch.rand(1, hh, ww, 3, generator=g)
        image = torch.randint(0, 256, (hh, ww, 3), generator=g, dtype=torch.uint8)
        x = render.permute(0, 3, 1, 2).requires_grad_()
        fresh = (tuple(x.shape), x.dtype, torch.uint8, "4:2:0", True, None, False) not in graphed._graphs
        cpu = [torch.profiler.ProfilerActivity.CPU]
        with torch.profiler.profile(activities=cpu, record_shapes=True) as prof:
            out = graphed(x, image, tables, "4:2:0")
        if not fresh:  # copies of the tables into the buffer
            events = prof.events()
            copied.append(sum(e.name == "aten::copy_" and e.input_shapes[:1] == [[2, 8, 8]] for e in events))
        xe = render.clone().permute(0, 3, 1, 2).requires_grad_()
        values, grad, r, _ = terms_with_gradient(xe, image, tables, weights=w, sampling="4:2:0", **SETTINGS)
        assert torch.equal(out.values, values[1:]) and torch.equal(out.weighted.detach(), values[0]), i
        assert torch.equal(pixel_score_of(out.r, hh, ww), r), i
        out.weighted.backward()
        assert torch.equal(x.grad, grad), i
    # calls[1:] but the recordings (calls[0] and calls[4]): the tables copied where they are not the tensor
    # the buffer holds (the recording at calls[4] wrote `other` into the buffer and made it the held tensor)
    assert copied == [0, 1, 1, 1, 0, 1, 0]


def test_values_without_a_copy_are_the_graphs_buffer(monkeypatch: pytest.MonkeyPatch) -> None:
    """``copy_values=False`` (the hook's call: the trainer reads the step's values within the step): the
    values and the weighted sum are the graph's output buffer, with the copying call's values and gradient
    bit for bit; the next replay writes them anew (so a caller reads them before its next call), where the
    copying call's values and weighted sum stay as they were."""
    monkeypatch.setattr(GraphedImageTerms, "_record", _eager_recording)
    w = (0.2, 0.02, 0.03)
    plain, direct = (GraphedImageTerms(weights=w, **SETTINGS) for _ in range(2))
    kept: torch.Tensor | None = None
    copied: tuple[torch.Tensor, ...] = ()
    for seed in (21, 22):
        x, y, luma, chroma = _view_tensors(seed)
        tables = torch.stack([luma, chroma])
        xa, xb = x.clone().requires_grad_(), x.clone().requires_grad_()
        a, b = plain(xa, y, tables, "4:2:0"), direct(xb, y, tables, "4:2:0", copy_values=False)
        (rec,) = direct._graphs.values()
        buffer = rec.outputs[0]
        assert b.weighted.data_ptr() == buffer.data_ptr() and b.values.data_ptr() == buffer[1:].data_ptr()
        assert a.weighted.data_ptr() != plain._graphs[next(iter(plain._graphs))].outputs[0].data_ptr()
        assert torch.equal(a.values, b.values) and torch.equal(a.weighted, b.weighted), seed
        a.weighted.backward()
        b.weighted.backward()
        assert torch.equal(xa.grad, xb.grad), seed
        if kept is not None:  # the previous call's values: rewritten by this call's replay
            assert torch.equal(kept, b.values)
            # the copying call's: left as they were, the weighted sum's value with them
            assert torch.equal(copied[0], copied[1]) and not torch.equal(copied[0], a.values)
            assert copied[2].detach() == copied[3]
        kept = b.values
        copied = (a.values, a.values.clone(), a.weighted, a.weighted.detach().clone())


def test_an_image_of_the_trainers_stack_is_read_in_place(monkeypatch: pytest.MonkeyPatch) -> None:
    """Training images loaded as the trainer loads them (one [V, H, W, 3] tensor per image size, each view's
    image a view of it): the graph reads the step's image from that tensor by index (a one-element index
    buffer, no image buffer and no copy), view after view with the values, gradient and r_b of the copied
    image bit for bit; a standalone image is still copied in."""
    monkeypatch.setattr(GraphedImageTerms, "_record", _eager_recording)
    w = (0.2, 0.02, 0.03)
    g = torch.Generator().manual_seed(13)
    stack = torch.randint(0, 256, (3, 24, 40, 3), generator=g, dtype=torch.uint8)
    assert stacked_image(stack[2]) is not None and stacked_image(stack[2])[1] == 2
    assert stacked_image(stack[1].clone()) is None and stacked_image(stack[1][:, :20]) is None
    in_place, copied = (GraphedImageTerms(weights=w, **SETTINGS) for _ in range(2))
    tables = torch.randint(1, 80, (2, 8, 8), generator=g).float()
    for i in (1, 0, 2, 1):
        render = torch.rand(1, 24, 40, 3, generator=g)
        xa, xb = (render.clone().permute(0, 3, 1, 2).requires_grad_() for _ in range(2))
        a, b = in_place(xa, stack[i], tables, "4:2:0"), copied(xb, stack[i].clone(), tables, "4:2:0")
        assert torch.equal(a.values, b.values) and torch.equal(a.r, b.r), i
        a.weighted.backward()
        b.weighted.backward()
        assert torch.equal(xa.grad, xb.grad), i
    (rec,) = in_place._graphs.values()
    assert rec.inputs[1].dtype == torch.int64 and rec.inputs[1].numel() == 1
    assert _kept_bytes(copied) - _kept_bytes(in_place) == 3 * 24 * 40 - 8


def test_the_gradient_is_written_over_the_render_buffer(monkeypatch: pytest.MonkeyPatch) -> None:
    """``grad_into_x``: the same values and gradient, bit for bit, the gradient in ``x``'s own storage; the
    graph keeps no gradient buffer of its own, and view after view each replay's gradient is that view's."""
    x, y, luma, chroma = _view_tensors(7)
    tables, w = torch.stack([luma, chroma]), (0.2, 0.02, 0.03)
    xa, xb = x.clone().requires_grad_(), x.clone().requires_grad_()
    plain = terms_with_gradient(xa, y, tables, weights=w, sampling="4:2:0", **SETTINGS)
    into = terms_with_gradient(xb, y, tables, weights=w, sampling="4:2:0", grad_into_x=True, **SETTINGS)
    assert into[1] is not None and plain[1] is not None and torch.equal(into[1], plain[1])
    assert into[1].data_ptr() == xb.data_ptr() and torch.equal(xb.detach(), plain[1])
    assert all(torch.equal(a, b) for a, b in zip(into[::2], plain[::2], strict=True))
    monkeypatch.setattr(GraphedImageTerms, "_record", _eager_recording)
    graphed = GraphedImageTerms(weights=w, **SETTINGS)
    for seed in (7, 8, 7):
        x, y, luma, chroma = _view_tensors(seed)
        xg, xe, tables = x.clone().requires_grad_(), x.clone().requires_grad_(), torch.stack([luma, chroma])
        graphed(xg, y, tables, "4:2:0").weighted.backward()
        _, grad, _, _ = terms_with_gradient(xe, y, tables, weights=w, sampling="4:2:0", **SETTINGS)
        assert torch.equal(xg.grad, grad), seed
    (rec,) = graphed._graphs.values()
    assert rec.outputs[1] is not None and rec.outputs[1].data_ptr() == rec.inputs[0].data_ptr()


def test_a_failed_graph_recording_falls_back_to_eager(monkeypatch: pytest.MonkeyPatch, capsys: Any) -> None:
    """If recording fails (an op that cannot be captured), the step and the rest of the run use the eager
    chain: the same values and gradients, one warning line, and no second attempt."""
    view = make_view(30, "4:2:0")
    eager = train_step(new_hook(view), view)
    tries = []

    def refuse() -> Any:
        tries.append(1)
        raise RuntimeError("operation not permitted when stream is capturing\nmore detail")

    # only the recording is faked (as if on CUDA): the warm-up runs on the CPU, the capture fails
    _no_cuda_streams(monkeypatch)
    monkeypatch.setattr(torch.cuda, "CUDAGraph", refuse)
    monkeypatch.setattr(GraphedImageTerms, "_check_device", staticmethod(lambda x: None))
    hook = new_hook(view)
    hook._graphed = GraphedImageTerms(weights=(0.2, 0.02, 0.03), **SETTINGS)
    first, second = train_step(hook, view), train_step(hook, view)
    for k, v in eager["terms"].items():
        assert first["terms"][k] == v == second["terms"][k], k
    for k, g in eager["grads"].items():
        assert torch.equal(first["grads"][k], g), k
    assert tries == [1] and hook._graphed is None
    err = capsys.readouterr().err
    assert err.count("warning: recording JO/L_obs/DS as a CUDA graph failed") == 1
    assert "not permitted" in err and "more detail" not in err


def _no_cuda_streams(monkeypatch: pytest.MonkeyPatch) -> None:
    """The streams of a CUDA device, as far as recording touches them before the graph, on the CPU."""

    class NoStream:
        def __init__(self, device: Any = None) -> None:
            pass

        def wait_stream(self, other: Any) -> None:
            pass

    monkeypatch.setattr(torch.cuda, "current_stream", NoStream)
    monkeypatch.setattr(torch.cuda, "Stream", NoStream)
    monkeypatch.setattr(torch.cuda, "stream", lambda s: nullcontext())
    monkeypatch.setattr(torch.cuda, "graph_pool_handle", lambda: None)
    monkeypatch.setattr(graphed_module, "_SIDE_STREAMS", {})  # no stand-in stream outlives the test


def test_every_recording_runs_on_one_side_stream(monkeypatch: pytest.MonkeyPatch) -> None:
    """Recordings of both graph classes, the controller's again at every change of N or parameter storage,
    all run on one side stream made once for the device (torch keeps a cuBLAS workspace per stream); each
    capture runs inside that stream's context, after its warm-ups there, and the outputs are the chain's."""
    made: list[Any] = []
    entered: list[Any] = []

    class CountedStream:
        def __init__(self, device: Any = None) -> None:
            made.append(self)

        def wait_stream(self, other: Any) -> None:
            pass

    class StreamContext:
        def __init__(self, stream: Any) -> None:
            self.stream = stream

        def __enter__(self) -> None:
            entered.append(self.stream)

        def __exit__(self, *exc: Any) -> None:
            entered.append(None)

    captures: list[int] = []

    class StandInGraph:  # capture_begin/end around the chain's call, as torch's; replay a no-op here
        def capture_begin(self, pool: Any = None, capture_error_mode: str = "global") -> None:
            assert entered and entered[-1] is not None  # inside the side stream's context
            captures.append(len(entered))

        def capture_end(self) -> None:
            pass

        def replay(self) -> None:
            pass

        def pool(self) -> None:
            return None

    _no_cuda_streams(monkeypatch)
    monkeypatch.setattr(torch.cuda, "Stream", CountedStream)
    monkeypatch.setattr(torch.cuda, "stream", StreamContext)
    monkeypatch.setattr(torch.cuda, "CUDAGraph", StandInGraph)
    monkeypatch.setattr(GraphedImageTerms, "_check_device", staticmethod(lambda x: None))
    settings = dict(weight=0.05, near_plane=0.01, eps_proj=1e-6, tau_s=1.0)
    ctl = GraphedController(**settings)
    for i, n in enumerate([50, 80, 30, 80]):
        probe, logits, log_scales, means, quats, viewmat, K = _controller_inputs(n, i, "cpu")
        got = ctl(probe, logits, log_scales, means, quats, viewmat, K, 160, 120)
        ref = fro_from_probe_grad(probe, logits, log_scales, means, quats, viewmat, K, 160, 120, **settings)
        for a, b in zip(got, (ref.grad_logit, ref.grad_log_scale, packed_fro_stats(ref.terms)), strict=True):
            assert torch.equal(a, b)
    terms = GraphedImageTerms(weights=(0.2, 0.02, 0.03), **SETTINGS)
    for seed in (0, 1):
        x, y, luma, chroma = _view_tensors(seed, dtype=torch.float32)
        terms(x[..., : 32 + 8 * seed].requires_grad_(), y[..., : 32 + 8 * seed], torch.stack([luma, chroma]),
              "4:2:0")  # fmt: skip
    assert ctl.recordings == 4 and len(terms._graphs) == 2 and len(captures) == 6
    for rec in terms._graphs.values():  # the gradient is written over the render's buffer, no own output
        assert rec.outputs[1] is not None and rec.outputs[1].data_ptr() == rec.inputs[0].data_ptr()
    assert len(made) == 1 and all(s is made[0] for s in entered if s is not None)
    assert entered.count(made[0]) == 6  # one stream context per recording, warm-ups and capture in it


def test_cuda_graph_is_refused_off_cuda_and_with_compile(tmp_path: Path) -> None:
    from jsgs.method.hook import make_jsgs_hook
    from jsgs.train.config import TrainConfig

    with pytest.raises(JsgsError, match="cannot be combined"):
        parse_options(jsgs_options(cuda_graph=True, compile="inductor"))
    cfg = TrainConfig.from_preset("paper")
    cfg.method, cfg.method_options = "jsgs", jsgs_options(cuda_graph=True)

    class _Scene:  # make_jsgs_hook refuses before it reads the views
        train_views: list = []
        manifest_path = tmp_path / "manifest.json"

    with pytest.raises(JsgsError, match="needs a CUDA device") as e:
        make_jsgs_hook(cfg, _Scene(), torch.device("cpu"))  # type: ignore[arg-type]
    assert "\n" not in str(e.value)


def test_cuda_graph_auto_resolves_by_device_and_compile() -> None:
    """The default ("auto") graphs exactly when the device is CUDA and compile is off; other values are
    refused with one line."""
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert parse_options({}).speed.cuda_graph == "auto"
    assert use_cuda_graph(parse_options({}), cuda) is True
    assert use_cuda_graph(parse_options({}), cpu) is False
    assert use_cuda_graph(parse_options(jsgs_options(compile="inductor")), cuda) is False
    assert use_cuda_graph(parse_options(jsgs_options(cuda_graph=False)), cuda) is False
    assert use_cuda_graph(parse_options(jsgs_options(cuda_graph=True)), cuda) is True
    with pytest.raises(JsgsError, match="needs a CUDA device"):
        use_cuda_graph(parse_options(jsgs_options(cuda_graph=True)), cpu)
    for bad in ("on", 1, None):
        with pytest.raises(JsgsError, match="must be true, false or") as e:
            parse_options(jsgs_options(cuda_graph=bad))
        assert "\n" not in str(e.value)


class _ControllerInBuffers:
    """GraphedController's contract on the CPU: the chain it records (``_run``), its outputs written into
    buffers it owns and overwrites on every call, as a graph's static outputs are."""

    def __init__(self, **settings: Any) -> None:
        self.inner = GraphedController(**settings)
        self.buffers: list[torch.Tensor] = []
        self.calls = 0

    def __call__(self, probe_grad: torch.Tensor, *args: Any) -> list[torch.Tensor]:
        logits, log_scales, means, quats, viewmat, K, w, h = args
        outs = self.inner._run(probe_grad, viewmat, K, (logits, log_scales, means, quats), w, h)
        if [b.shape for b in self.buffers] != [o.shape for o in outs]:
            self.buffers = [torch.empty_like(o) for o in outs]
        for b, o in zip(self.buffers, outs, strict=True):
            b.copy_(o)
        self.calls += 1
        return self.buffers


def test_the_hooks_graphed_controller_branch_gives_the_eager_terms_and_gradients() -> None:
    """The deferred GC through the graph's contract (outputs in buffers that the next replay overwrites):
    bit-for-bit the eager values and gradients, and nothing the step keeps aliases those buffers."""
    view = make_view(30, "4:2:0")
    eager = train_step(new_hook(view), view)
    hook = new_hook(view)
    hook.keep_last = False  # keep_last asks for the pooled sums, which only the eager chain hands back
    fake = hook._gc_graphed = _ControllerInBuffers(**hook._gc_settings)
    splats = make_splats()
    graphed = train_step(hook, view, splats)
    assert fake.calls == 1
    assert graphed["terms"] == eager["terms"] and graphed["stats"] == eager["stats"]
    for k, g in eager["grads"].items():
        assert torch.equal(graphed["grads"][k], g), k
    kept = {k: p.grad.clone() for k, p in splats.items()}
    for b in fake.buffers:
        b.fill_(float("nan"))
    for k, p in splats.items():
        assert torch.equal(p.grad, kept[k]), k
    assert graphed["terms"]["fro"] > 0 and graphed["stats"]["gc_visible"] > 0


def test_a_failed_controller_recording_falls_back_to_eager(
    monkeypatch: pytest.MonkeyPatch, capsys: Any
) -> None:
    """A refused recording of the GC graph: this step and the rest run the eager GC (same values and
    gradients), with one warning line and no second attempt."""
    view = make_view(30, "4:2:0")
    eager = train_step(new_hook(view), view)
    tries = []

    def refuse() -> Any:
        tries.append(1)
        raise RuntimeError("CUDA error: operation not permitted when stream is capturing\nmore detail")

    _no_cuda_streams(monkeypatch)
    monkeypatch.setattr(torch.cuda, "CUDAGraph", refuse)
    monkeypatch.setattr(GraphedImageTerms, "_check_device", staticmethod(lambda x: None))
    hook = new_hook(view)
    hook.keep_last = False
    hook._gc_graphed = GraphedController(**hook._gc_settings)
    first, second = train_step(hook, view), train_step(hook, view)
    for res in (first, second):
        assert res["terms"] == eager["terms"] and res["stats"] == eager["stats"]
        for k, g in eager["grads"].items():
            assert torch.equal(res["grads"][k], g), k
    assert tries == [1] and hook._gc_graphed is None
    err = capsys.readouterr().err
    assert err.count("warning: recording the Gaussian Controller as a CUDA graph failed") == 1
    assert "not permitted" in err and "more detail" not in err


def _controller_inputs(n: int, seed: int, device: str) -> tuple[torch.Tensor, ...]:
    """A probe gradient [1, N, 2] (some Gaussians not contributing), parameters and a camera."""
    g = torch.Generator().manual_seed(seed)
    nu = torch.rand(n, generator=g) * (torch.rand(n, generator=g) > 0.3)
    probe = torch.stack([torch.rand(n, generator=g) * nu, nu], dim=-1)[None] * 0.05
    logits = torch.randn(n, generator=g)
    log_scales = torch.randn(n, 3, generator=g) * 0.5 - 4.0
    means = torch.randn(n, 3, generator=g) + torch.tensor([0.0, 0.0, 4.0])
    quats = torch.randn(n, 4, generator=g)
    viewmat = torch.eye(4)
    viewmat[:3, 3] = torch.randn(3, generator=g) * 0.1
    K = torch.tensor([[300.0, 0.0, 80.0], [0.0, 300.0, 60.0], [0.0, 0.0, 1.0]])
    return tuple(t.to(device) for t in (probe, logits, log_scales, means, quats, viewmat, K))


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_gpu_controller_graph_equals_eager_across_views_and_densification() -> None:
    """Replays for different probe gradients and cameras, a parameter replaced by a new tensor of the same
    size, and N growing and shrinking: each result equal to the eager chain's; one recording per parameter
    storage; memory flat across recordings."""
    settings = dict(weight=0.05, near_plane=0.01, eps_proj=1e-6, tau_s=1.0)
    ctl = GraphedController(**settings)
    params = None
    mem = []
    for i, n in enumerate([5000, 5000, 5000, 7000, 7000, 3000, 5000, 7000, 5000]):
        probe, logits, log_scales, means, quats, viewmat, K = _controller_inputs(n, i, "cuda")
        if params is None or params[0].shape[0] != n or i == 2:
            params = (logits, log_scales, means, quats)  # new storage (i == 2: same N, as after a reset)
        else:  # the same tensors updated in place, as the optimizer does between densifications
            for p, q in zip(params, (logits, log_scales, means, quats), strict=True):
                p.copy_(q)
        got = [t.clone() for t in ctl(probe, *params, viewmat, K, 160, 120)]
        ref = fro_from_probe_grad(probe, *params, viewmat, K, 160, 120, **settings)
        want = (ref.grad_logit, ref.grad_log_scale, packed_fro_stats(ref.terms))
        for a, b in zip(got, want, strict=True):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-9)
        assert want[2][1] > 0  # some Gaussians visible
        torch.cuda.synchronize()
        mem.append(torch.cuda.memory_allocated())
    assert ctl.recordings == 7  # steps 0, 2 (new storage), 3, 5, 6, 7, 8 (N changed)
    assert mem[-1] <= mem[1] + (1 << 20), mem


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
@pytest.mark.parametrize("mode", ["paper", "float", "exact"])
def test_gpu_graph_replays_equal_eager_for_every_view(mode: str) -> None:
    """Three views in turn through one graph (each with its own render, target and tables), twice, in each
    JO mode: values and render gradients equal to the eager function's, and earlier results not
    overwritten by later replays."""
    settings = {**SETTINGS, "mode": mode}
    w = (0.2, 0.02, 0.03)
    graphed = GraphedImageTerms(weights=w, **settings)
    eager = partial(image_terms, sampling="4:2:0", **settings)
    kept = []
    for rnd in range(2):
        for seed in (1, 2, 3):
            x, y, luma, chroma = _view_tensors(seed, "cuda", torch.float32)
            x = x * (1.0 + 0.01 * rnd)
            xg, xe = x.clone().requires_grad_(), x.clone().requires_grad_()
            out_g = graphed(xg, y, torch.stack([luma, chroma]), "4:2:0", observation=True)
            out_e = eager(xe, y, luma, chroma)
            total_e = w[0] * out_e[0] + w[1] * out_e[1] + w[2] * out_e[2]
            torch.testing.assert_close(out_g.values, torch.stack(out_e[:3]).detach(), rtol=1e-6, atol=1e-7)
            torch.testing.assert_close(out_g.weighted, total_e.detach(), rtol=1e-6, atol=1e-7)
            torch.testing.assert_close(pixel_score_of(out_g.r, 37, 53), out_e[3], rtol=1e-6, atol=1e-7)
            torch.testing.assert_close(out_g.obs, out_e[4], rtol=1e-6, atol=1e-7)
            (3.0 * out_g.weighted).backward()  # an upstream factor other than 1 is applied too
            (3.0 * total_e).backward()
            torch.testing.assert_close(xg.grad, xe.grad, rtol=1e-5, atol=1e-8)
            kept.append((out_g.values.tolist(), out_g.values))
    assert len(graphed._graphs) == 1  # one image size, one sampling: one graph
    for value, tensor in kept:
        assert tensor.tolist() == value


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_gpu_two_orientations_replay_on_shared_buffers() -> None:
    """Real graphs for W×H and H×W views in turn, on one set of buffers: each replay's values, r(p) and
    render gradient equal the eager function's, whichever graph ran before it."""
    w = (0.2, 0.02, 0.03)
    graphed = GraphedImageTerms(weights=w, **SETTINGS)
    g = torch.Generator().manual_seed(12)
    for hh, ww in [(40, 64), (64, 40), (64, 40), (40, 64), (64, 40)]:
        render = torch.rand(1, hh, ww, 3, generator=g).cuda()
        image = torch.randint(0, 256, (hh, ww, 3), generator=g, dtype=torch.uint8).cuda()
        tables = torch.randint(1, 80, (2, 8, 8), generator=g).float().cuda()
        x, xe = (render.clone().permute(0, 3, 1, 2).requires_grad_() for _ in range(2))
        out = graphed(x, image, tables, "4:2:0")
        values, grad, r, _ = terms_with_gradient(xe, image, tables, weights=w, sampling="4:2:0", **SETTINGS)
        torch.testing.assert_close(out.values, values[1:], rtol=1e-6, atol=1e-7)
        torch.testing.assert_close(pixel_score_of(out.r, hh, ww), r, rtol=1e-6, atol=1e-7)
        out.weighted.backward()
        torch.testing.assert_close(x.grad, grad, rtol=1e-5, atol=1e-8)
    a, b = graphed._graphs.values()
    assert all(s.data_ptr() == t.data_ptr() for s, t in zip(a.inputs, b.inputs, strict=True))


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_gpu_the_graph_reads_each_steps_image_from_the_stack() -> None:
    """A real graph given images of one [V, H, W, 3] stack on the device (as the trainer loads them): each
    replay reads the image at the index written before it (a device value, not the recording's), so view
    after view, in any order, the values, r_b and render gradient are those of the eager function on a copy
    of that view's image; one recording for every view of the stack."""
    w = (0.2, 0.02, 0.03)
    graphed = GraphedImageTerms(weights=w, **SETTINGS)
    g = torch.Generator().manual_seed(14)
    stack = torch.randint(0, 256, (3, 40, 64, 3), generator=g, dtype=torch.uint8).cuda()
    tables = torch.randint(1, 80, (2, 8, 8), generator=g).float().cuda()
    for i in (2, 0, 1, 1, 2, 0):
        render = torch.rand(1, 40, 64, 3, generator=g).cuda()
        x, xe = (render.clone().permute(0, 3, 1, 2).requires_grad_() for _ in range(2))
        out = graphed(x, stack[i], tables, "4:2:0")
        values, grad, r, _ = terms_with_gradient(
            xe, stack[i].clone(), tables, weights=w, sampling="4:2:0", r_blocks=True, **SETTINGS
        )
        torch.testing.assert_close(out.values, values[1:], rtol=1e-6, atol=1e-7)
        torch.testing.assert_close(out.r, r, rtol=1e-6, atol=1e-7)
        out.weighted.backward()
        torch.testing.assert_close(x.grad, grad, rtol=1e-5, atol=1e-8)
    (rec,) = graphed._graphs.values()
    assert rec.inputs[1].dtype == torch.int64 and rec.inputs[1].numel() == 1


def train_jsgs_variants(tmp_path: Path, variants: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """60-step jsgs runs on CUDA with densification every 10 steps, one per ``method_options`` variant, on
    one JPEG scene: name -> the run's last evaluation."""
    from _train_scene import make_scene

    from jsgs.train.config import TrainConfig
    from jsgs.train.trainer import train

    manifest = make_scene(tmp_path / "scene", jpeg_train=True)
    evals = {}
    for name, options in variants.items():
        c = TrainConfig.from_preset("paper", method="jsgs", iterations=60, eval_at=[60], device="cuda")
        c.method_options = jsgs_options(**options)
        c.strategy.refine_start_iter, c.strategy.refine_every = 5, 10
        c.eval.fps_passes, c.eval.fps_warmup, c.eval.save_renders = 1, 0, False
        evals[name] = train(manifest, tmp_path / name, c, progress=False)["evals"][-1]
    return evals


def assert_same_training(on: dict[str, Any], off: dict[str, Any]) -> None:
    """Two runs' last evaluations agree within gsplat's own run-to-run noise (its backward sums with
    atomics, so two runs are not bit-identical), with the GC at work."""
    assert on["train"]["terms"]["fro"] > 0 and on["train"]["stats"]["gc_visible"] > 0
    for k, v in off["train"]["terms"].items():
        assert on["train"]["terms"][k] == pytest.approx(v, rel=0.05), k
    assert abs(on["psnr"] - off["psnr"]) < 0.5


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_gpu_training_with_graphs_matches_eager(tmp_path: Path, capsys: Any) -> None:
    """A short jsgs run on CUDA with densification every few steps (so the GC graph is recorded again and
    again while N changes: the torch GC, which the graph replays), graphs on and off: no fallback, and the
    same training."""
    evals = train_jsgs_variants(tmp_path, {
        "graphs": {"cuda_graph": True, "gc_kernel": "torch"},
        "eager": {"cuda_graph": False, "gc_kernel": "torch"},
    })  # fmt: skip
    assert "eagerly for the rest of the run" not in capsys.readouterr().err  # no graph fell back
    assert_same_training(evals["graphs"], evals["eager"])


@pytest.mark.gpu
@pytest.mark.skipif(
    not (torch.cuda.is_available() and triton_available()), reason="the fused JO needs CUDA and Triton"
)
def test_gpu_training_with_fused_jo_matches_the_twin(tmp_path: Path, capsys: Any) -> None:
    """The same short run with JO's coding pass as the Triton kernels (method_options.speed.fused_jo, inside
    the CUDA graph) and as its torch twin: no fallback, the same training."""
    evals = train_jsgs_variants(tmp_path, {"fused": {"fused_jo": True}, "twin": {"fused_jo": False}})
    assert "eagerly for the rest of the run" not in capsys.readouterr().err  # the graph recorded the kernels
    print(f"\nfused vs twin: PSNR {evals['fused']['psnr']:.3f} vs {evals['twin']['psnr']:.3f}, terms "
          f"{evals['fused']['train']['terms']} vs {evals['twin']['train']['terms']}")
    assert_same_training(evals["fused"], evals["twin"])


def test_the_controller_graph_follows_cuda_graph_and_its_own_switch() -> None:
    """The GC graph exists exactly with cuda_graph on, the deferred route and cuda_graph_gc (default true);
    config.json's derived.method says so (built for a CUDA device without touching it)."""
    view = make_view(30, "4:2:0")
    cuda = torch.device("cuda")

    def described(**options: Any) -> dict[str, Any]:
        tables = {view.index: new_hook(view).tables[view.index]}
        opts = parse_options(jsgs_options(**{"gc_kernel": "torch", **options}))
        return JsgsHook(opts, tables, device=cuda).describe()

    assert described()["cuda_graph_gc"] is True
    # JO's fused kernels: by default (auto) where Triton imports, in mode paper (checked, not run, for a CUDA
    # device), in modes paper and float; mode exact and fused_jo false run the torch code
    fused = "triton" if triton_available() else "torch"
    assert described(cuda_graph_gc=False) == {
        "color_kernel": fused, "cuda_graph": True, "cuda_graph_gc": False, "gc_attribution": "probe",
        "gc_kernel": "torch", "gc_route": "deferred", "jo_kernel": fused, "jpeg_mode": "paper",
    }  # fmt: skip
    assert described(jpeg_mode="float")["jo_kernel"] == fused
    assert described(jpeg_mode="exact")["jo_kernel"] == described(fused_jo=False)["jo_kernel"] == "torch"
    # the colour kernel: auto (the default) follows the fused coding pass
    assert described(fused_color="auto")["color_kernel"] == fused
    assert described(fused_color=False)["color_kernel"] == "torch"
    assert described(fused_color="auto", fused_jo=False)["color_kernel"] == "torch"
    assert described(gc_pooling="now")["cuda_graph_gc"] is False
    assert described(cuda_graph=False)["cuda_graph_gc"] is False
    if torch.cuda.is_available():  # the default on a GPU: the fused kernels, which need no graph
        assert described(gc_kernel="auto")["gc_kernel"] == "cuda"
        assert described(gc_kernel="auto")["cuda_graph_gc"] is False
    with pytest.raises(JsgsError, match="cuda_graph_gc must be true or false"):
        parse_options(jsgs_options(cuda_graph_gc="yes"))


@pytest.mark.parametrize("free", [True, False])
def test_the_warm_ups_cached_memory_is_handed_back_after_each_image_terms_recording(
    monkeypatch: pytest.MonkeyPatch, free: bool
) -> None:
    """With ``speed.cuda_graph_free_warmup`` (default true) every recording of the image terms ends with one
    ``torch.cuda.empty_cache()``, after the capture (the warm-ups' blocks are free by then), and replays
    release nothing; the controller's recordings (inside the backward) never release; false: no release.
    The hook passes the setting to its graphs (built for a CUDA device without touching it)."""
    events: list[str] = []

    class StandInGraph:
        def capture_begin(self, pool: Any = None, capture_error_mode: str = "global") -> None:
            events.append("capture")

        def capture_end(self) -> None:
            events.append("end")

        def replay(self) -> None:
            events.append("replay")

        def pool(self) -> None:
            return None

    _no_cuda_streams(monkeypatch)
    monkeypatch.setattr(torch.cuda, "CUDAGraph", StandInGraph)
    monkeypatch.setattr(torch.cuda, "empty_cache", lambda: events.append("empty_cache"))
    monkeypatch.setattr(GraphedImageTerms, "_check_device", staticmethod(lambda x: None))
    terms = GraphedImageTerms(weights=(0.2, 0.02, 0.03), free_warmup=free, **SETTINGS)
    for seed in (0, 1, 1):  # two image sizes: two recordings, then a replay
        x, y, luma, chroma = _view_tensors(seed, dtype=torch.float32)
        terms(x[..., : 32 + 8 * seed].requires_grad_(), y[..., : 32 + 8 * seed], torch.stack([luma, chroma]),
              "4:2:0")  # fmt: skip
    per_recording = ["capture", "end", *(["empty_cache"] if free else []), "replay"]
    assert events == per_recording * 2 + ["replay"]
    events.clear()
    ctl = GraphedController(weight=0.05, near_plane=0.01, eps_proj=1e-6, tau_s=1.0)
    probe, logits, log_scales, means, quats, viewmat, K = _controller_inputs(50, 0, "cpu")
    ctl(probe, logits, log_scales, means, quats, viewmat, K, 160, 120)
    assert ctl.recordings == 1 and "empty_cache" not in events
    view = make_view(30, "4:2:0")
    tables = {view.index: new_hook(view).tables[view.index]}
    opts = {"gc_kernel": "torch"} | ({} if free else {"cuda_graph_free_warmup": False})
    hook = JsgsHook(parse_options(jsgs_options(**opts)), tables, device=torch.device("cuda"))
    assert hook._graphed is not None and hook._graphed.free_warmup is free
