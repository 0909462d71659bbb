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
    def forward(
        ctx: Any, value: Tensor, scratch: bool, own_value: bool, unit_upstream: bool, *pairs: Tensor
    ) -> Tensor:
        # (x, grad) pairs; the gradients kept as an attribute, not saved for backward: the caller may own
        # their memory (a graph's static output, rewritten by its next replay after this step's backward);
        # read in the backward
        ctx.grads = pairs[1::2]
        ctx.scratch = scratch
        ctx.unit_upstream = unit_upstream
        # an input returned as it is becomes a view of it (autograd's rule): no copy
        return value if own_value else value.detach().clone()

    @staticmethod
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor | None, ...]:
        out: list[Tensor | None] = [None, None, None, None]
        if not ctx.scratch:
            for g in ctx.grads:
                out += [grad_out * g, None]
            return tuple(out)
        if ctx.grads is None:
            raise RuntimeError(
                "with_known_gradient(scratch=True): a second backward through the same scalar (the first "
                "wrote its gradients over the known ones)"
            )
        grads, ctx.grads = ctx.grads, None
        for g in grads:  # upstream·g written over g: the same values as the product, no new tensor
            # (an upstream of exactly 1 leaves g as it is, bit for bit: no kernel)
            out += [g if ctx.unit_upstream else g.mul_(grad_out), None]
        return tuple(out)


def with_known_gradient(
    x: Tensor, value: Tensor, grad: Tensor, *more: Tensor, scratch: bool = False, own_value: bool = False,
    unit_upstream: bool = False,
) -> Tensor:  # fmt: skip
    """A 0-dim tensor equal to ``value`` whose gradient with respect to ``x`` is ``grad`` (and with respect
    to each further ``x_k`` in ``more = (x_2, grad_2, x_3, grad_3, ...)`` its ``grad_k``): one autograd node
    for them all, where a sum of such scalars takes one per scalar and an addition.

    Args:
        x: the tensor the gradient flows into (any shape; its autograd history continues the backward).
        value: 0-dim, the scalar's value (not differentiated).
        grad: shape of ``x``, ``d value / d x``; read once, during the backward (so it must stay valid until
            then; it is not copied).
        more: further (tensor, its gradient) pairs, alike.
        scratch: the gradients are the caller's scratch, not read again before the caller writes them anew
            (a graph's output buffer, rewritten by its next replay): the backward writes ``upstream * grad``
            over each and hands that on, so no product of the image's size is allocated in the backward
            (the same values: a product of two numbers in either order). One backward only.
        own_value: ``value`` is the caller's own tensor, not written again while the scalar is in use (a
            copy the caller made): the result is a view of it instead of a copy (one kernel fewer).
        unit_upstream: with ``scratch``, the caller guarantees that the scalar's upstream gradient is
            exactly 1 (it enters a loss unweighted, whose backward starts from 1: the trainer's folded
            loss, :attr:`jsgs.train.hook.StepContext.folded_upstream_one`): the gradients are handed on as
            they are, which is ``1·grad`` bit for bit, without the product's kernel.
    Returns:
        0-dim tensor, a copy of ``value`` (with ``own_value``, a view of it); ``backward`` sends
        ``upstream * grad`` to ``x`` (and ``upstream * grad_k`` to each ``x_k``).
    """
    if value.dim() != 0:
        raise ValueError(f"value must be 0-dim, got shape {tuple(value.shape)}")
    if len(more) % 2:
        raise ValueError("more must be (tensor, gradient) pairs")
    pairs = (x, grad, *more)
    for xk, gk in zip(pairs[::2], pairs[1::2], strict=True):
        if gk.shape != xk.shape:
            raise ValueError(f"grad must have x's shape {tuple(xk.shape)}, got {tuple(gk.shape)}")
    if own_value and value.requires_grad:
        raise ValueError("own_value: value must not require grad (it is not differentiated)")
    if unit_upstream and not scratch:
        raise ValueError("unit_upstream hands the gradients on as they are: they must be scratch")
    return _KnownGradient.apply(value, scratch, own_value, unit_upstream, *pairs)


class _DeferredGradient(torch.autograd.Function):
    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, value: Tensor, make: Any, own_value: bool, x: Tensor
    ) -> Tensor:
        ctx.make = make
        ctx.like = (tuple(x.shape), x.dtype, x.device)
        # an input returned as it is becomes a view of it (autograd's rule): no copy
        return value if own_value else value.detach().clone()

    @staticmethod
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor | None, ...]:
        make, ctx.make = ctx.make, None
        if make is None:
            raise RuntimeError("with_deferred_gradient: a second backward through the same scalar")
        g = make(*ctx.like)
        if g is None or getattr(make, "unit_upstream", False):  # an upstream of exactly 1: g as it is
            return None, None, None, g
        return None, None, None, g.mul_(grad_out)


def with_deferred_gradient(x: Tensor, value: Tensor, make: Any, own_value: bool = False) -> Tensor:
    """A 0-dim tensor equal to ``value`` whose gradient with respect to ``x`` is ``make(shape, dtype,
    device)`` (``x``'s), made when the backward reaches this scalar's node (None: no gradient), then
    multiplied in place by the upstream: :func:`with_known_gradient` for a gradient that need not exist
    before. Made early in the forward (e.g. with the render), the node has an early place in autograd's
    order, so the backward reaches it after the nodes made later (the losses on the render), and the
    gradient lives only from then to where it is consumed. One backward only. ``own_value``: as
    :func:`with_known_gradient`'s (the result a view of ``value``, which the caller never writes while the
    scalar is in use; e.g. a zero it keeps from step to step), no copy. A true ``make.unit_upstream`` when
    the backward reaches the node: the caller guarantees the upstream is exactly 1 (as
    :func:`with_known_gradient`'s ``unit_upstream``), and the gradient is handed on as made, without the
    product by 1 (the same bits).
    """
    if value.dim() != 0:
        raise ValueError(f"value must be 0-dim, got shape {tuple(value.shape)}")
    if own_value and value.requires_grad:
        raise ValueError("own_value: value must not require grad (it is not differentiated)")
    return _DeferredGradient.apply(value, make, own_value, x)

