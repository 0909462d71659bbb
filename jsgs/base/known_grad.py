"""A scalar whose gradient with respect to a tensor is already known: one autograd node instead of a chain.

Two places in a JSGS step know a gradient before the backward starts:

* the JPEG image terms replayed as one CUDA graph (``jsgs.method.graphed``), which computes the weighted sum
  of L_obs, L_low and L_mid *and* its gradient with respect to the render in the same replay, so the trainer's
  backward only scales that gradient (no second replay, no static-buffer copies of upstream gradients);
* the Gaussian Controller's probe objective (``jsgs.method.pooling.probe_objective``), a sum of products whose
  gradient is the per-pixel upstream map itself and whose value is exactly 0.

On a GPU at training sizes each autograd node and small kernel costs more host time than device time, so
replacing such chains by one node is a measurable part of a step (``tools/diagnostics/bench_graph_host.py``).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor


class _KnownGradient(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, x: Tensor, value: Tensor, grad: Tensor) -> Tensor:
        # kept as an attribute, not saved for backward: the caller may own ``grad``'s memory (a graph's
        # static output, rewritten by its next replay after this step's backward); read in the backward
        ctx.grad = grad
        return value.detach().clone()

    @staticmethod
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor, None, None]:
        return grad_out * ctx.grad, None, None


def with_known_gradient(x: Tensor, value: Tensor, grad: Tensor) -> Tensor:
    """A 0-dim tensor equal to ``value`` whose gradient with respect to ``x`` is ``grad``.

    Args:
        x: the tensor the gradient flows into (any shape; its autograd history continues the backward).
        value: 0-dim, the scalar's value (not differentiated).
        grad: shape of ``x``, ``d value / d x``; read once, during the backward (so it must stay valid until
            then; it is not copied).
    Returns:
        0-dim tensor, a copy of ``value``; ``backward`` sends ``upstream * grad`` to ``x``.
    """
    if value.dim() != 0:
        raise ValueError(f"value must be 0-dim, got shape {tuple(value.shape)}")
    if grad.shape != x.shape:
        raise ValueError(f"grad must have x's shape {tuple(x.shape)}, got {tuple(grad.shape)}")
    return _KnownGradient.apply(x, value, grad)
