"""The method protocol of the generic trainer: a loss hook and extra render channels.

Each training step the trainer renders the sampled view, computes the baseline photometric loss
l_ph = (1 - ssim_lambda) L1 + ssim_lambda (1 - SSIM) and then calls the method's :class:`LossHook` with a
:class:`StepContext` (the render, the observed image, the view's JPEG state, the rasterizer's ``info``, the
parameters). The hook returns a :class:`HookOutput`: named *unweighted* scalar terms with their weights, and
statistics to log. The total loss is::

    loss = loss.base_weight * l_ph + sum_k weights[k] * terms[k] (+ gsplat's optional regularisers)

(a hook may hand some terms' weighted sum over ready-made, ``HookOutput.folded_loss``).

Every term (base ones included) is checked for NaN/Inf each step; a bad one stops the run naming the term and
the step. Term values and stats are shown on the progress bar and averaged into ``RUN/metrics.json`` between
evaluations (``train`` of each entry of ``evals``). A value the method did not compute at a step (a part of it
that runs on some steps only; ``HookOutput.skipped``) is left out of both: the progress bar shows the latest
computed value with its step, the means are over the steps that computed it.

A hook may also ask for extra rasterised channels (:meth:`LossHook.extra_channels`): per-Gaussian features
[N, E] that are composited with the same weights t * alpha as the colours, in the *same* rasterisation
pass (the rasterizer's generic extra channels, ``jsgs.render.rasterize(..., extra=...)``); the trainer hands
the E rendered channels to the hook as ``StepContext.extra`` [1, H, W, E]. Gradients of a loss on ``extra``
with respect to the features are the per-Gaussian pooled sums sum_p t alpha dL/dextra(p) (how a Gaussian
Controller can pool block scores without a second pass, ``jsgs.method.pooling``).

Hooks with state (running statistics, schedules) implement ``state_dict``/``load_state_dict`` so that
``--resume`` stays bit-exact.

A method's hook comes from its factory in the method registry, :mod:`jsgs.train.method`
(:func:`make_hook`); ``--method gsplat`` has none (:func:`gsplat_baseline`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from jsgs.base.errors import JsgsError
from jsgs.train.method import method_factory

if TYPE_CHECKING:
    from jsgs.train.config import TrainConfig
    from jsgs.train.data import TrainingScene, TrainingView


@dataclass
class StepContext:
    """What a loss hook sees at one training step (batch of one view, C = 1 camera).

    - ``step``: 0-based step index (the step being taken).
    - ``view``: the sampled training view (name, camera, ``jpeg`` state dict from the manifest or None for a
      lossless image; see :class:`jsgs.train.data.TrainingView`).
    - ``render``: [1, H, W, 3] rendered RGB in linear [0, 1]-ish range (not clamped), differentiable; the
      same tensor l_ph was computed on (after random-background compositing, when enabled).
    - ``alpha``: [1, H, W, 1] accumulated opacity.
    - ``target``: [1, H, W, 3] the observed (decoded) training image in [0, 1], float32.
    - ``info``: the rasterizer's info dict (gsplat semantics: means2d, radii, conics, opacities, ...).
    - ``splats``: the parameters (``jsgs.train.model``'s ParameterDict: means, scales (log), quats,
      opacities (logit), sh0, shN).
    - ``extra``: [1, H, W, E] extra channels asked for by :meth:`LossHook.extra_channels`, else None.
    - ``base_terms``: the baseline's unweighted terms {"l1", "ssim" (= 1 - SSIM), "photometric" (= l_ph)}.
    - ``sh_degree``: the SH degree used at this step.
    - ``image``: [H, W, 3] uint8, the training image ``target`` was made from
      (:func:`jsgs.train.data.image_target`), or None where ``target`` was not made so.
    - ``folded_upstream_one``: the caller adds :attr:`HookOutput.folded_loss` to the loss unweighted and
      runs the loss's backward from 1 (as the trainer does), so the folded loss's upstream gradient is
      exactly 1: a known gradient inside it need not be multiplied by it
      (:func:`jsgs.base.known_grad.with_known_gradient`'s ``unit_upstream``). False: any upstream.
    """

    step: int
    view: TrainingView
    render: Tensor
    alpha: Tensor
    target: Tensor
    info: dict[str, Any]
    splats: torch.nn.ParameterDict
    extra: Tensor | None
    base_terms: dict[str, Tensor]
    sh_degree: int
    image: Tensor | None = None
    folded_upstream_one: bool = False


@dataclass
class HookOutput:
    """A hook's contribution: ``terms`` (name -> scalar tensor, unweighted, differentiable), ``weights``
    (name -> float; every term needs one, 0 logs a term without optimising it) and ``stats`` (name -> float or
    0-dim tensor; logged only, never differentiated).

    A hook that computes some terms' weighted sum with its gradient in one go (JSGS's graphed image terms)
    returns that sum as ``folded_loss`` (0-dim, differentiable, = Σ weights[k]·terms[k] over ``folded``) and
    names those terms in ``folded``: their ``terms`` entries are then values to log (and to check), and the
    trainer adds ``folded_loss`` to the loss instead of weighting them again."""

    terms: dict[str, Tensor] = field(default_factory=dict)
    weights: dict[str, float] = field(default_factory=dict)
    stats: dict[str, float | Tensor] = field(default_factory=dict)
    folded: frozenset[str] = frozenset()
    folded_loss: Tensor | None = None
    #: this step's multiplier on the weight of the baseline's l_ph (``loss.base_weight``): a method may
    #: trust some views' pixels less than others
    base_scale: float = 1.0
    #: terms and stats this step did not compute (a part of the method that runs on some steps only): their
    #: values are placeholders (a term's enters the loss as it is), which the logs leave out
    skipped: frozenset[str] = frozenset()

    def check(self, hook_name: str) -> None:
        missing = sorted(set(self.terms) - set(self.weights))
        if missing:
            raise JsgsError(f"method {hook_name}: loss term {missing[0]!r} has no weight")
        unknown = sorted(self.folded - set(self.terms))
        if unknown or (self.folded and self.folded_loss is None):
            what = f"folds {unknown[0]!r}, which it does not return" if unknown else "returns no folded_loss"
            raise JsgsError(f"method {hook_name}: {what}")
        stray = sorted(self.skipped - set(self.terms) - set(self.stats))
        if stray:
            raise JsgsError(f"method {hook_name}: skips {stray[0]!r}, which it does not return")
        clash = sorted(set(self.terms) & RESERVED_TERMS)
        if clash:
            raise JsgsError(f"method {hook_name}: loss term name {clash[0]!r} is reserved")


RESERVED_TERMS = frozenset({"l1", "ssim", "photometric", "loss", "opacity_reg", "scale_reg"})


class LossHook:
    """Base class of a method's per-step extension. Subclasses override :meth:`losses` (required) and, when
    needed, :meth:`extra_channels`, :meth:`render_kwargs`, :meth:`describe`, :meth:`notes`,
    :meth:`state_dict`, :meth:`load_state_dict`."""

    name: str = "hook"

    def extra_channels(self, step: int, view: TrainingView, splats: torch.nn.ParameterDict) -> Tensor | None:
        """Per-Gaussian features [N, E] to rasterise alongside RGB in this step's pass, or None."""
        return None

    def renders_extra(self) -> bool:
        """Whether :meth:`extra_channels` may return features in this run. On several GPUs such a run renders
        each view from all the Gaussians gathered on its process (:mod:`jsgs.train.distributed`), since a
        method's per-Gaussian sums are per view."""
        return type(self).extra_channels is not LossHook.extra_channels

    def render_kwargs(self, step: int, view: TrainingView) -> dict[str, Any]:
        """Extra keyword arguments for this step's ``jsgs.render.rasterize`` call (e.g. ``render_mode``;
        what it adds to ``info`` reaches :meth:`losses` through ``StepContext.info``)."""
        return {}

    def losses(self, ctx: StepContext) -> HookOutput:
        """Extra loss terms and statistics for this step."""
        raise NotImplementedError

    def describe(self) -> dict[str, Any]:
        """What the method resolved from its options for this run (config.json ``derived.method``)."""
        return {}

    def notes(self) -> list[str]:
        """One-line notes for the user when training starts (printed as ``note: ...``; config.json
        ``derived.notes``)."""
        return []

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state:
            raise JsgsError(f"method {self.name}: the checkpoint holds hook state this hook does not take")


def make_hook(cfg: TrainConfig, scene: TrainingScene, device: torch.device) -> LossHook | None:
    """The hook of ``cfg.method`` (JsgsError naming the available methods when unknown)."""
    hook: LossHook | None = method_factory(cfg.method)(cfg, scene, device)
    return hook


def gsplat_baseline(cfg: TrainConfig, scene: TrainingScene, device: torch.device) -> LossHook | None:
    """``--method gsplat``: no hook (the trainer's own loss only); it takes no method_options."""
    if cfg.method_options:
        key = sorted(cfg.method_options)[0]
        raise JsgsError(f"config: method gsplat takes no method_options (got {key!r})")
    return None
