"""gsplat's DefaultStrategy (pure torch) runs on CPU with the reference rasterizer's info and grows, splits
and prunes exactly as its rules say."""

from __future__ import annotations

import torch
from gsplat.strategy import DefaultStrategy

from jsgs.render import rasterize

W, H = 48, 32


def _setup(seed: int = 0) -> tuple[torch.nn.ParameterDict, dict, torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    N = 60
    means = (torch.rand(N, 3, generator=g) - 0.5) * torch.tensor([2.0, 1.4, 0.5]) + torch.tensor([0, 0, 3.0])
    # log-scales around the duplicate/split threshold (grow_scale3d · scene_scale = 0.05 below)
    log_scales = torch.log(torch.rand(N, 3, generator=g) * 0.08 + 0.02)
    params = torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter(means),
            "scales": torch.nn.Parameter(log_scales),
            "quats": torch.nn.Parameter(torch.randn(N, 4, generator=g)),
            "opacities": torch.nn.Parameter(torch.logit(torch.rand(N, generator=g) * 0.9 + 0.05)),
            "colors": torch.nn.Parameter(torch.rand(N, 3, generator=g)),
        }
    )
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    vm = torch.eye(4).repeat(2, 1, 1)
    vm[1, 0, 3] = 0.2
    K = torch.tensor([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]]).repeat(2, 1, 1)
    target = torch.rand(2, H, W, 3, generator=g)
    return params, optimizers, vm, K, target


def _render(params: torch.nn.ParameterDict, vm: torch.Tensor, K: torch.Tensor):
    return rasterize(
        params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
        params["colors"], vm, K, W, H, backend="torch",
    )  # fmt: skip


def test_default_strategy_runs_on_cpu_and_follows_its_rules() -> None:
    params, optimizers, vm, K, target = _setup()
    scene_scale = 5.0
    strategy = DefaultStrategy(refine_start_iter=0, refine_every=2, grow_grad2d=2e-4, prune_opa=0.1)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=scene_scale)
    grown = False
    for step in range(1, 7):
        n_before = len(params["means"])
        img, _, info = _render(params, vm, K)
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss = (img - target).abs().mean()
        loss.backward()

        # what the state will hold after this step's update (gsplat's rules written out)
        g2 = info["means2d"].grad.clone()
        assert g2.shape == (2, n_before, 2) and torch.isfinite(g2).all()
        g2[..., 0] *= W / 2 * 2
        g2[..., 1] *= H / 2 * 2
        sel = (info["radii"] > 0).all(-1)
        grad2d = torch.zeros(n_before) if state["grad2d"] is None else state["grad2d"].clone()
        count = torch.zeros(n_before) if state["count"] is None else state["count"].clone()
        grad2d.index_add_(0, torch.where(sel)[1], g2[sel].norm(dim=-1))
        count.index_add_(0, torch.where(sel)[1], torch.ones(int(sel.sum())))

        refine = step % strategy.refine_every == 0
        expected = n_before
        if refine:
            high = grad2d / count.clamp_min(1) > strategy.grow_grad2d
            small = torch.exp(params["scales"]).max(-1).values <= strategy.grow_scale3d * scene_scale
            dupli, split = high & small, high & ~small
            low = torch.sigmoid(params["opacities"]) < strategy.prune_opa
            n_prune = int(low.sum() + (low & dupli).sum() + (low & split).sum())
            expected = n_before + int(dupli.sum()) + int(split.sum()) - n_prune
            grown |= bool(dupli.any() and split.any())

        strategy.step_post_backward(params, optimizers, state, step, info)
        if not refine:
            assert torch.allclose(state["grad2d"], grad2d, rtol=1e-5, atol=1e-9)
            assert torch.equal(state["count"], count)
        assert len(params["means"]) == expected, (step, len(params["means"]), expected)
        for p in params.values():
            assert len(p) == expected
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
    assert grown, "the scene should both duplicate and split"


def test_absgrad_strategy_reads_absgrad() -> None:
    params, optimizers, vm, K, target = _setup(1)
    strategy = DefaultStrategy(refine_start_iter=0, refine_every=2, absgrad=True, grow_grad2d=8e-4)
    state = strategy.initialize_state(scene_scale=5.0)
    for step in range(1, 3):
        img, _, info = rasterize(
            params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
            params["colors"], vm, K, W, H, backend="torch", absgrad=True,
        )  # fmt: skip
        strategy.step_pre_backward(params, optimizers, state, step, info)
        (img - target).abs().mean().backward()
        assert (info["means2d"].absgrad >= info["means2d"].grad.abs() - 1e-7).all()
        strategy.step_post_backward(params, optimizers, state, step, info)
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
    assert len(params["means"]) >= 60
