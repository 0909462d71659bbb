"""``method_options.cuda_graph``: JO, L_obs and DS as one pure function of tensors (tested here on the CPU
against the eager hook) and its CUDA-graph replay (GPU only: the same values and gradients as eager)."""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any

import pytest
import torch
from test_jsgs_method import make_view, new_hook, train_step

from jsgs.errors import JsgsError
from jsgs.jpeg.losses import photometric_loss
from jsgs.jpeg.observe import jpeg_observe
from jsgs.jpeg.supervision import dct_supervision
from jsgs.train.graphed import GraphedImageTerms, image_terms
from jsgs.train.jsgs_method import parse_options, use_cuda_graph

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


def test_the_hooks_graphed_branch_gives_the_eager_terms_and_gradients() -> None:
    """The hook's cuda_graph branch, with image_terms run directly (what the graph records) on the CPU."""
    view = make_view(30, "4:2:0")
    eager = train_step(new_hook(view), view)
    hook = new_hook(view)
    hook._graphed = lambda x, y, lu, ch, s: image_terms(x, y, lu, ch, sampling=s, **SETTINGS)
    graphed = train_step(hook, view)
    for k, v in eager["terms"].items():
        assert graphed["terms"][k] == pytest.approx(v, rel=1e-12, abs=1e-15), k
    for k, v in eager["stats"].items():
        assert graphed["stats"][k] == pytest.approx(v, rel=1e-12), k
    for k, g in eager["grads"].items():
        torch.testing.assert_close(graphed["grads"][k], g, rtol=1e-10, atol=1e-14)


def test_a_failed_graph_recording_falls_back_to_eager(monkeypatch: pytest.MonkeyPatch, capsys: Any) -> None:
    """If recording fails (an op that cannot be captured), the step and the rest of the run use the eager
    chain: the same values and gradients, one warning line, and no second attempt."""
    view = make_view(30, "4:2:0")
    eager = train_step(new_hook(view), view)
    tries = []

    def refuse(fn: Any, sample: Any, **kw: Any) -> Any:
        tries.append(1)
        raise RuntimeError("operation not permitted when stream is capturing\nmore detail")

    # only the recording is faked (as if on CUDA): everything else runs on the CPU
    monkeypatch.setattr(torch.cuda, "make_graphed_callables", refuse)
    monkeypatch.setattr(GraphedImageTerms, "_check_device", staticmethod(lambda x: None))
    hook = new_hook(view)
    hook._graphed = GraphedImageTerms(**SETTINGS)
    first, second = train_step(hook, view), train_step(hook, view)
    for k, v in eager["terms"].items():
        assert first["terms"][k] == v == second["terms"][k], k
    for k, g in eager["grads"].items():
        assert torch.equal(first["grads"][k], g), k
    assert tries == [1] and hook._graphed is None
    err = capsys.readouterr().err
    assert err.count("warning: recording JO/L_obs/DS as a CUDA graph failed") == 1
    assert "not permitted" in err and "more detail" not in err


def test_cuda_graph_is_refused_off_cuda_and_with_compile(tmp_path: Path) -> None:
    from jsgs.train.config import TrainConfig
    from jsgs.train.jsgs_method import make_jsgs_hook

    with pytest.raises(JsgsError, match="cannot be combined"):
        parse_options({"cuda_graph": True, "compile": "inductor"})
    cfg = TrainConfig()
    cfg.method, cfg.method_options = "jsgs", {"cuda_graph": True}

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
    assert parse_options({}).cuda_graph == "auto"
    assert use_cuda_graph(parse_options({}), cuda) is True
    assert use_cuda_graph(parse_options({}), cpu) is False
    assert use_cuda_graph(parse_options({"compile": "inductor"}), cuda) is False
    assert use_cuda_graph(parse_options({"cuda_graph": False}), cuda) is False
    assert use_cuda_graph(parse_options({"cuda_graph": True}), cuda) is True
    with pytest.raises(JsgsError, match="needs a CUDA device"):
        use_cuda_graph(parse_options({"cuda_graph": True}), cpu)
    for bad in ("on", 1, None):
        with pytest.raises(JsgsError, match="must be true, false or") as e:
            parse_options({"cuda_graph": bad})
        assert "\n" not in str(e.value)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_gpu_graph_replays_equal_eager_for_every_view() -> None:
    """Three views in turn through one graph (each with its own render, target and tables), twice: values
    and render gradients equal to the eager function's, and earlier results not overwritten by later
    replays."""
    graphed = GraphedImageTerms(**SETTINGS)
    eager = partial(image_terms, sampling="4:2:0", **SETTINGS)
    kept = []
    for rnd in range(2):
        for seed in (1, 2, 3):
            x, y, luma, chroma = _view_tensors(seed, "cuda", torch.float32)
            x = x * (1.0 + 0.01 * rnd)
            xg, xe = x.clone().requires_grad_(), x.clone().requires_grad_()
            out_g, out_e = graphed(xg, y, luma, chroma, "4:2:0"), eager(xe, y, luma, chroma)
            for a, b in zip(out_g, out_e, strict=True):
                torch.testing.assert_close(a, b.detach(), rtol=1e-6, atol=1e-7)
            (0.2 * out_g[0] + 0.02 * out_g[1] + 0.03 * out_g[2]).backward()
            (0.2 * out_e[0] + 0.02 * out_e[1] + 0.03 * out_e[2]).backward()
            torch.testing.assert_close(xg.grad, xe.grad, rtol=1e-5, atol=1e-8)
            kept.append((out_g[0].item(), out_g[0]))
    assert len(graphed._graphs) == 1  # one image size, one sampling: one graph
    for value, tensor in kept:
        assert tensor.item() == value
