"""Densification strategies: how many Gaussians a run has and where they go.

Two of gsplat 1.5.3's strategies, chosen by ``strategy.type`` in the run's settings:

- ``default``: ``gsplat.strategy.DefaultStrategy`` (the original 3DGS heuristics: duplicate / split by the
  screen-space gradient, prune by opacity and size, opacity resets). The number of Gaussians is whatever the
  heuristics grow, and a loss that is larger grows more.
- ``mcmc``: ``gsplat.strategy.MCMCStrategy`` (Kheradmand et al. 2024): a budget ``strategy.cap_max``, fixed
  for the run (by default chosen from the scene when it starts: ``strategy.cap_max_auto``);
  every ``refine_every`` steps low-opacity Gaussians are relocated onto high-opacity ones and 5 % more are
  added until the cap is reached; positions get noise scaled by the means' learning rate times ``noise_lr``.
  Runs with equal caps have equal model sizes, which is what a fair comparison of losses needs.

:class:`Densifier` is the one interface the trainer calls for either. gsplat's MCMC ops call two CUDA
kernels; on the CPU their torch twins in :mod:`jsgs.kernels` run instead.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from jsgs.base.errors import JsgsError

if TYPE_CHECKING:
    from jsgs.train.config import StrategyConfig

STRATEGY_TYPES = ("default", "mcmc")


class Densifier:
    """gsplat's strategy for ``cfg.type``, with one call signature for both (gsplat's differ in
    ``step_post_backward``'s keyword: ``packed`` for DefaultStrategy, ``lr`` for MCMCStrategy)."""

    def __init__(self, cfg: StrategyConfig) -> None:
        from gsplat.strategy import DefaultStrategy, MCMCStrategy

        self.type = cfg.type
        self.cap_max: int | None = None
        if cfg.type == "default":
            self.gsplat: Any = DefaultStrategy(
                prune_opa=cfg.prune_opa,
                grow_grad2d=cfg.grow_grad2d,
                grow_scale3d=cfg.grow_scale3d,
                grow_scale2d=cfg.grow_scale2d,
                prune_scale3d=cfg.prune_scale3d,
                prune_scale2d=cfg.prune_scale2d,
                refine_scale2d_stop_iter=cfg.refine_scale2d_stop_iter,
                refine_start_iter=cfg.refine_start_iter,
                refine_stop_iter=cfg.refine_stop_iter,
                reset_every=cfg.reset_every,
                refine_every=cfg.refine_every,
                pause_refine_after_reset=cfg.pause_refine_after_reset,
                absgrad=cfg.absgrad,
                revised_opacity=cfg.revised_opacity,
                verbose=False,
            )
        elif cfg.type == "mcmc":
            self.cap_max = cfg.cap_max
            self.gsplat = MCMCStrategy(
                cap_max=cfg.cap_max,
                noise_lr=cfg.noise_lr,
                refine_start_iter=cfg.refine_start_iter,
                refine_stop_iter=cfg.refine_stop_iter,
                refine_every=cfg.refine_every,
                min_opacity=cfg.min_opacity,
                verbose=False,
            )
        else:  # the config check refuses other values first
            raise JsgsError(f"strategy.type: {cfg.type!r} is not one of {', '.join(STRATEGY_TYPES)}")

    def check_sanity(self, params: torch.nn.ParameterDict, optimizers: dict[str, Any]) -> None:
        self.gsplat.check_sanity(params, optimizers)

    def initialize_state(self, scene_scale: float) -> dict[str, Any]:
        """The strategy's running state (saved in checkpoints)."""
        if self.type == "default":
            return self.gsplat.initialize_state(scene_scale=scene_scale)
        return self.gsplat.initialize_state()

    def step_pre_backward(
        self,
        params: torch.nn.ParameterDict,
        optimizers: dict[str, Any],
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
    ) -> None:
        self.gsplat.step_pre_backward(params, optimizers, state, step, info)

    def may_change_count(self, step: int) -> bool:
        """Whether :meth:`step_post_backward` at ``step`` may change the number of Gaussians: a refinement
        step of gsplat's schedule (DefaultStrategy grows and prunes, MCMCStrategy relocates, which keeps the
        count, and adds). A superset of the steps that do (DefaultStrategy's pause after an opacity reset
        and a view without gradient are not excluded); every process answers alike."""
        gs = self.gsplat
        return gs.refine_start_iter < step < gs.refine_stop_iter and step % gs.refine_every == 0

    def step_post_backward(
        self,
        params: torch.nn.ParameterDict,
        optimizers: dict[str, Any],
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
        *,
        lr: float,
        packed: bool,
    ) -> None:
        """After the optimizers' step: densify / prune (default) or relocate / add / perturb (mcmc, with
        ``lr`` the means' current learning rate, as gsplat's simple_trainer passes it)."""
        if self.type == "default":
            self.gsplat.step_post_backward(params, optimizers, state, step, info, packed=packed)
            return
        from jsgs.kernels import cpu_twins

        with cpu_twins():
            self.gsplat.step_post_backward(params, optimizers, state, step, info, lr=lr)


def initial_subset(count: int, cap_max: int | None, seed: int) -> Tensor | None:
    """Indices of the initial points to keep when a budget is below their count (a seeded random subset,
    sorted), else None (keep all)."""
    if cap_max is None or count <= cap_max:
        return None
    g = torch.Generator().manual_seed(seed)
    return torch.randperm(count, generator=g)[:cap_max].sort().values
