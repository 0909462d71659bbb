"""The JSGS step's host-side shortcuts compute what the longer forms they replace computed, bit for bit: the
weighted probe objective with its kept upstream buffer (one node and one kernel, where λ_fro times the
objective took a pad, a zero, and a multiplication each way), the controller's term folded into the loss
unweighted, and the extra channels' background as one zero tensor."""

from __future__ import annotations

import weakref
from typing import Any

import pytest
import torch
from test_graphed import _eager_recording
from test_jsgs_method import make_splats, make_view, new_hook, render, target_for, train_step

from jsgs.base.kept_zeros import kept_zeros
from jsgs.base.known_grad import with_known_gradient
from jsgs.jpeg.losses import photometric_loss
from jsgs.jpeg.supervision import pixel_score_of
from jsgs.method.graphed import GraphedImageTerms
from jsgs.method.pooling import ProbeObjective, probe_objective
from jsgs.train.hook import StepContext
from jsgs.train.trainer import weighted_loss

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _probe_info(dtype: torch.dtype, shape: tuple[int, int, int], seed: int) -> tuple[dict[str, Any], Any]:
    """A probe [N, 2] and channels [C, H, W, 2] linear in it (a stand-in rasteriser), as ``info`` holds
    them."""
    g = torch.Generator().manual_seed(seed)
    n = 7
    probe = torch.zeros(n, 2, dtype=dtype, requires_grad=True)
    weights = torch.rand(*shape, n, generator=g, dtype=dtype)
    channels = torch.einsum("chwn,nk->chwk", weights, probe)
    return {"extra": channels, "extra_features": probe}, g


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_weighted_probe_objective_is_the_weight_times_the_objective(dtype: torch.dtype) -> None:
    """``ProbeObjective(w)`` gives the probe the gradient of ``w * probe_objective`` in a loss, bit for bit,
    call after call and when the image size changes; its value is 0, a new tensor each call (a copy of the
    kept zero, :func:`jsgs.base.kept_zeros.kept_zeros`). Between calls it holds no tensor: the map lives
    from the call to the backward that consumes it."""
    w = 0.05 * 4  # λ_fro · gc_every, as the hook weights it
    obj = ProbeObjective(w)
    for call, shape in enumerate([(1, 6, 5), (1, 6, 5), (1, 4, 3)]):
        grads = []
        for new in (False, True):
            info, g = _probe_info(dtype, shape, seed=call)
            r = torch.rand(shape, generator=g, dtype=torch.float32)  # r(p) is float32, as DS makes it
            other = info["extra"].sum() * 0.0 + 1.0
            value = obj(info, r) if new else w * probe_objective(info, r)
            (other + value).backward()
            assert value.item() == 0.0
            grads.append(info["extra_features"].grad)
        assert torch.equal(grads[0], grads[1]) and grads[1].abs().sum() > 0, call
    assert obj(info, r) is not obj(info, r)
    zero = kept_zeros(info["extra"])
    assert obj(info, r).untyped_storage().data_ptr() != zero.untyped_storage().data_ptr() and zero.item() == 0
    assert not [v for v in vars(obj).values() if isinstance(v, torch.Tensor)]
    _, up = obj.upstream(info, r)
    gone = weakref.ref(up)
    del up
    assert gone() is None


@pytest.mark.parametrize("shape", [(1, 16, 24), (1, 19, 27), (1, 5, 7)])
def test_the_probe_map_from_block_scores_is_the_map_from_r(shape: tuple[int, int, int]) -> None:
    """The upstream map made from the block scores r_b (what the image terms' graph keeps) equals the one
    made from r(p) bit for bit, with and without rows and columns outside the full blocks (and with no
    block at all)."""
    w = 0.2
    obj = ProbeObjective(w)
    info, g = _probe_info(torch.float32, shape, seed=3)
    c, h, wd = shape
    blocks = torch.rand(c, h // 8, wd // 8, generator=g)
    r = pixel_score_of(blocks, h, wd)
    _, from_r = obj.upstream(info, r)
    _, from_blocks = obj.upstream(info, blocks)
    assert torch.equal(from_blocks, from_r) and from_r.shape == (*shape, 2)
    with pytest.raises(ValueError, match="r must be"):
        obj.upstream(info, blocks[:, :, :-1] if wd >= 16 else torch.zeros(c, h, wd + 1))


def _step(hook: Any, view: Any, old_form: bool) -> dict[str, Any]:
    """One training step on the tiny scene; ``old_form``: the loss takes λ_fro · probe_objective(info, r) as
    a weighted term instead of the hook's folded objective (the form the hook used before)."""
    splats = make_splats()
    target = target_for(view)
    out = render(splats, hook.extra_channels(0, view, splats))
    ctx = StepContext(0, view, out.rgb, out.alpha, target, out.info, splats, out.extra, {}, 0)
    h = hook.losses(ctx)
    h.check("jsgs")
    x, y = out.rgb.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2)
    terms = {"photometric": photometric_loss(x, y, 0.2, padding="valid"), **h.terms}
    weights = {"photometric": 0.7, **h.weights}
    if old_form:
        assert h.folded == {"fro"} and h.folded_loss is not None
        r = hook.last["ds"].pixel_score
        terms["fro"] = probe_objective(out.info, r)  # its value (0) is the logged one's until the backward
        loss = weighted_loss(terms, weights)
    else:
        loss = weighted_loss(terms, weights, h.folded, h.folded_loss)
    loss.backward()
    return {
        "loss": loss.item(),
        "terms": {k: v.item() for k, v in h.terms.items()},
        "stats": {k: float(v) for k, v in h.stats.items()},
        "grads": {k: p.grad.clone() for k, p in splats.items() if p.grad is not None},
    }


def test_the_folded_controller_term_gives_the_weighted_terms_step() -> None:
    """A step with the deferred controller's objective folded into the loss unweighted equals the step with
    λ_fro · probe_objective as a weighted term: loss, terms, statistics and every gradient, bit for bit."""
    view = make_view(50, "4:2:0")
    new, old = (_step(new_hook(view), view, old_form=f) for f in (False, True))
    assert new["loss"] == old["loss"] and new["terms"] == old["terms"] and new["stats"] == old["stats"]
    assert new["terms"]["fro"] > 0 and set(new["grads"]) == set(old["grads"])
    for k, g in old["grads"].items():
        assert torch.equal(new["grads"][k], g), k


def test_a_lossless_views_step_is_the_photometric_step() -> None:
    """On a lossless view the hook's terms and statistics are zeros logged with weight 0 (views of the kept
    zeros, :func:`jsgs.base.kept_zeros.kept_zeros`): the step's loss and gradients are those of ℓ_ph alone,
    bit for bit."""
    view = make_view(None)
    hook = new_hook(view)
    runs = []
    for with_hook in (True, False):
        splats = make_splats()
        target = target_for(view)
        out = render(splats, hook.extra_channels(0, view, splats))
        x, y = out.rgb.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2)
        terms = {"photometric": photometric_loss(x, y, 0.2, padding="valid")}
        weights = {"photometric": 0.7}
        if with_hook:
            ctx = StepContext(0, view, out.rgb, out.alpha, target, out.info, splats, out.extra, {}, 0)
            h = hook.losses(ctx)
            h.check("jsgs")
            assert set(h.terms) == {"obs", "low", "mid", "fro"} and set(h.stats) == {
                "gc_visible",
                "gc_rbar",
                "gc_damped",
            }
            logged = (*h.terms.values(), *h.stats.values())
            assert all(v.item() == 0.0 for v in logged)
            # views of one kept zero vector, not zeros filled anew at each step
            kept = kept_zeros(out.rgb, (len(logged),)).untyped_storage().data_ptr()
            assert {v.untyped_storage().data_ptr() for v in logged} == {kept}
            terms.update(h.terms)
            weights.update(h.weights)
        loss = weighted_loss(terms, weights)
        loss.backward()
        runs.append((loss.item(), {k: p.grad.clone() for k, p in splats.items() if p.grad is not None}))
    (loss_a, grads_a), (loss_b, grads_b) = runs
    assert loss_a == loss_b and set(grads_a) == set(grads_b)
    for k, g in grads_b.items():
        assert torch.equal(grads_a[k], g), k


def test_one_node_carries_several_known_gradients() -> None:
    """``with_known_gradient(x, v, g, x2, g2)``: the value v, and the gradients the sum of two such scalars
    (v and 0) sends, bit for bit, through one node; mismatched pairs are refused."""
    grads = []
    for together in (False, True):
        gen = torch.Generator().manual_seed(0)
        a = torch.rand(2, 3, generator=gen, dtype=torch.float64).requires_grad_()
        b = torch.rand(4, generator=gen, dtype=torch.float64).requires_grad_()
        xa, xb = a * 3.0, b.exp()
        ga, gb = (
            torch.rand(2, 3, generator=gen, dtype=torch.float64),
            torch.rand(4, generator=gen, dtype=torch.float64),
        )
        v = torch.tensor(1.25, dtype=torch.float64)
        if together:
            s = with_known_gradient(xa, v, ga, xb, gb)
        else:
            s = with_known_gradient(xa, v, ga) + with_known_gradient(xb, torch.zeros((), dtype=v.dtype), gb)
        (0.5 * s).backward()
        assert s.item() == 1.25
        grads.append((a.grad, b.grad))
    assert all(torch.equal(u, w) for u, w in zip(*grads, strict=True))
    with pytest.raises(ValueError, match="pairs"):
        with_known_gradient(xa, v, ga, xb)
    with pytest.raises(ValueError, match="shape"):
        with_known_gradient(xa, v, ga, xb, ga)


class _SeparateObjective(GraphedImageTerms):
    """The graph's terms without the probe objective on its node (the hook then adds it on its own)."""

    def __call__(self, x: Any, y: Any, tables: Any, sampling: str, more: Any = None, **kw: Any) -> Any:
        return super().__call__(x, y, tables, sampling, **kw)


def test_the_probe_objective_on_the_graphs_node_gives_the_separate_objectives_step(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The hook's CUDA-graph branch (recorded eagerly on the CPU): the controller's objective riding on the
    image terms' node gives the step of the objective as a term of its own, bit for bit."""
    monkeypatch.setattr(GraphedImageTerms, "_record", _eager_recording)
    view = make_view(50, "4:2:0")
    steps = []
    for graph_class in (GraphedImageTerms, _SeparateObjective):
        hook = new_hook(view)
        w = hook.weights()
        hook._graphed = graph_class(
            weights=(w["obs"], w.get("low", 0.0), w.get("mid", 0.0)), **hook._jpeg_settings
        )
        steps.append(_step(hook, view, old_form=False))
    one, separate = steps
    assert one["loss"] == separate["loss"] and one["terms"] == separate["terms"]
    assert one["stats"] == separate["stats"] and one["terms"]["fro"] > 0
    for k, g in separate["grads"].items():
        assert torch.equal(one["grads"][k], g), k


@pytest.mark.parametrize("graph", [False, True])
def test_the_probe_map_made_in_the_backward_gives_the_same_step(
    monkeypatch: pytest.MonkeyPatch, graph: bool
) -> None:
    """The render given the hook's render_kwargs (as the trainer's is) carries the probe objective's node,
    made with the render, and the probe's map is made in the backward, after ℓ_ph's backward has reached
    the render (where the map made at the hook's call was alive since the hook's call): the same terms,
    statistics and gradients, bit for bit, eager and with the image terms' graph."""
    from jsgs.method.pooling import DeferredProbeMap

    monkeypatch.setattr(GraphedImageTerms, "_record", _eager_recording)
    events: list[str] = []
    make = DeferredProbeMap.__call__

    def recorded(self: Any, *args: Any) -> Any:
        events.append("map")
        return make(self, *args)

    monkeypatch.setattr(DeferredProbeMap, "__call__", recorded)
    monkeypatch.setattr(torch.Tensor, "permute", _noting_permute(events))
    view = make_view(50, "4:2:0")
    steps = []
    for in_render in (False, True):
        hook = new_hook(view)
        hook.keep_last = False
        if graph:
            w = hook.weights()
            hook._graphed = GraphedImageTerms(weights=(w["obs"], w["low"], w["mid"]), **hook._jpeg_settings)
        events.clear()
        steps.append(train_step(hook, view, render_kwargs=in_render))
        assert ("map" in events) is in_render
        if in_render:  # every loss on the render (ℓ_ph's and the image terms' permutes) came back first
            permutes = [i for i, e in enumerate(events) if e == "permute backward"]
            assert len(permutes) >= 2 and max(permutes) < events.index("map"), events
    old, new = steps
    assert new["terms"] == old["terms"] and new["stats"] == old["stats"] and new["terms"]["fro"] > 0
    for k, g in old["grads"].items():
        assert torch.equal(new["grads"][k], g), k
    assert torch.equal(new["means2d"], old["means2d"])


def _noting_permute(events: list[str]) -> Any:
    """``Tensor.permute`` whose result, where it is a render's [1, H, W, 3] to [1, 3, H, W] (ℓ_ph's, the
    image terms'), notes in ``events`` when the backward passes through it."""
    permute = torch.Tensor.permute

    def noting(self: torch.Tensor, *dims: Any) -> torch.Tensor:
        out = permute(self, *dims)
        if out.requires_grad and dims == (0, 3, 1, 2) and self.dim() == 4 and self.shape[-1] == 3:
            out.register_hook(lambda g: events.append("permute backward"))
        return out

    return noting


def test_the_extra_channels_background_is_one_zero_tensor(monkeypatch: pytest.MonkeyPatch) -> None:
    """With extra channels, gsplat's rasteriser gets the colours and extras side by side and a background
    of zeros for all of them (or the caller's background and zeros for the extras), in the colours' dtype."""
    import gsplat

    from jsgs.render import backend

    seen: list[dict[str, Any]] = []

    def rasterization(means: Any, quats: Any, scales: Any, opacities: Any, colors: Any, viewmats: Any,
                      Ks: Any, width: int, height: int, **kw: Any) -> Any:  # fmt: skip
        seen.append({"colors": colors, **kw})
        c = viewmats.shape[0]
        return torch.zeros(c, height, width, colors.shape[-1]), torch.zeros(c, height, width, 1), {}

    monkeypatch.setattr(gsplat, "rasterization", rasterization)
    n, c = 5, 2
    g = torch.Generator().manual_seed(0)
    colors, extra = torch.rand(n, 3, generator=g), torch.rand(c, n, 2, generator=g)
    bg = torch.rand(c, 3, generator=g)
    kw: dict[str, Any] = dict(
        sh_degree=None, near_plane=0.01, far_plane=1e10, eps2d=0.3, radius_clip=0.0, packed=False,
        absgrad=False, render_mode="RGB", extra=extra,
    )  # fmt: skip
    cams = (torch.eye(4).expand(c, 4, 4), torch.eye(3).expand(c, 3, 3))
    for given in (None, bg):
        img, _, info = backend._rasterize_gsplat(
            torch.rand(n, 3), torch.rand(n, 4), torch.rand(n, 3), torch.rand(n), colors, *cams, 8, 6,
            backgrounds=given, **kw,
        )  # fmt: skip
        call = seen[-1]
        assert torch.equal(call["colors"], torch.cat([colors[None].expand(c, -1, -1), extra], dim=-1))
        want = torch.zeros(c, 5) if given is None else torch.cat([bg, torch.zeros(c, 2)], dim=-1)
        assert call["backgrounds"].dtype == colors.dtype and torch.equal(call["backgrounds"], want)
        assert img.shape == (c, 6, 8, 3) and info["extra"].shape == (c, 6, 8, 2)


def test_the_image_with_the_probe_channels_is_freed_after_the_render(monkeypatch: pytest.MonkeyPatch) -> None:
    """With the probe's map made in the backward (``extra_upstream``) the extra channels' values are not
    kept: gsplat's five-channel image is freed after the render (the colours copied out, contiguous, the
    same values), ``info`` has the objective and no channels; without it the colours are a view of that
    image and ``info["extra"]`` its other channels. The reference backend alike (its colours are a copy)."""
    import weakref

    import gsplat

    from jsgs.render import backend

    made: list[Any] = []

    def rasterization(means: Any, quats: Any, scales: Any, opacities: Any, colors: Any, viewmats: Any,
                      Ks: Any, width: int, height: int, **kw: Any) -> Any:  # fmt: skip
        c = viewmats.shape[0]
        img = torch.rand(c, height, width, colors.shape[-1]) + colors.sum() * 0.0  # on the autograd graph
        made.append(weakref.ref(img))
        return img, torch.zeros(c, height, width, 1), {}

    monkeypatch.setattr(gsplat, "rasterization", rasterization)
    n = 5
    probe = torch.zeros(n, 2, requires_grad=True)
    kw: dict[str, Any] = dict(
        sh_degree=None, near_plane=0.01, far_plane=1e10, backgrounds=None, eps2d=0.3, radius_clip=0.0,
        packed=False, absgrad=False, render_mode="RGB", extra=probe[None],
    )  # fmt: skip
    cams = (torch.eye(4)[None], torch.eye(3)[None])
    colors = torch.rand(n, 3, requires_grad=True)
    for keep in (True, False):
        img, _, info = backend._rasterize_gsplat(
            torch.rand(n, 3), torch.rand(n, 4), torch.rand(n, 3), torch.rand(n), colors, *cams, 8, 6,
            extra_values=keep, **kw,
        )  # fmt: skip
        full = made[-1]()
        assert full is not None and torch.equal(img, full[..., :3])
        channels = info["extra"]
        del full
        backend._extras(info, probe, None if keep else (lambda *like: None))
        assert ("extra" in info) is keep and ("extra_objective" in info) is not keep
        del channels
        assert (made[-1]() is None) is not keep and img.is_contiguous() is not keep
    view = make_view(50, "4:2:0")
    hook = new_hook(view)
    splats = make_splats()
    out = render(splats, hook.extra_channels(0, view, splats), hook.render_kwargs(0, view))
    assert out.extra is None and "extra" not in out.info and out.info["extra_objective"].item() == 0.0


def test_host_path_cpu_passes_on_profile_steps_options() -> None:
    """tools/diagnostics/host_path_cpu.py names the options it passes on to profile_step.py: exactly that
    script's, less ``--device`` (it sets cpu); one profile_step.py does not take is refused in one line."""
    import inspect
    import re
    import sys
    from pathlib import Path

    tools = Path(__file__).resolve().parents[3] / "tools" / "diagnostics"
    saved = list(sys.path)
    sys.path.insert(0, str(tools))
    try:
        import host_path_cpu
        import profile_step
    finally:
        sys.path[:] = saved
    declared = set(re.findall(r'"(--[a-z][a-z-]*)"', inspect.getsource(profile_step.parse_args)))
    assert set(host_path_cpu.PASSED_ON) == declared - {"--device"}
    assert host_path_cpu.main(["--steps", "3", "--not-an-option"]) == 2


def test_host_path_cpu_runs_the_step_with_the_stand_ins(tmp_path: Any) -> None:
    """tools/diagnostics/host_path_cpu.py runs (in its own process: it patches the hook class): a profile of
    both methods on a tiny synthetic scene, the JSGS step through the stood-in graph and controller, its
    clock and stand-ins recorded, and JSGS counting more ops per step than gsplat."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    config = tmp_path / "small.json"
    config.write_text(json.dumps({"init": {"type": "random", "num_points": 60}}))
    out = tmp_path / "out.json"
    args = ["--size", "16x12", "--views", "4", "--preset", "mcmc", "--config", str(config), "--warmup", "3",
            "--settle", "1", "--steps", "2", "--threads", "1", "--no-fresh", "--top", "3", "--cpu-time",
            "--workdir", str(tmp_path / "work"), "--out", str(out)]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(root)}
    run = subprocess.run(
        [sys.executable, str(root / "tools" / "diagnostics" / "host_path_cpu.py"), *args],
        capture_output=True, text=True, env=env, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]
    doc = json.loads(out.read_text())
    assert doc["device"] == "cpu" and doc["settings"]["host_path_cpu"]["clock"] == "thread_time"
    r = doc["results"]
    assert r["jsgs"]["kernel_launches_per_step"] > r["gsplat"]["kernel_launches_per_step"] > 0
