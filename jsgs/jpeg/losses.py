"""Image-domain losses: the photometric loss (paper eq. photometric) and the JPEG observation loss L_obs
(eq. obs_loss)."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..kernels import ssim, ssim_is_fused
from .observe import jpeg_observe

LAMBDA_SSIM = 0.2
#: SSIM window padding of l_ph when none is given: zero-padded "same", as the paper's eq. photometric (the
#: original 3DGS). The trainer always passes its ``loss.ssim_padding`` (default "valid", gsplat's training
#: loss).
SSIM_PADDING = "same"


class PhotometricTerms(NamedTuple):
    """``loss``: l_ph; ``l1``: the mean absolute difference; ``d_ssim``: 1 - SSIM (each a scalar, or ``(B,)``
    with reduction "none")."""

    loss: Tensor
    l1: Tensor
    d_ssim: Tensor


class _MeanAbsDifference(torch.autograd.Function):
    """``(x - y).abs().mean()`` with autograd's gradient, bit for bit, keeping nothing of its own for the
    backward: the difference (4 bytes a value, which ``abs`` would keep) is made again there from ``x`` and
    ``y``, which the loss's SSIM keeps anyway, and becomes the gradient in place."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, y: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(x, y)
        return (x - y).abs_().mean()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, Tensor | None]:  # type: ignore[override]
        x, y = ctx.saved_tensors
        # autograd's chain: the mean's grad / numel, times sgn(x - y) (abs), then +/- (the subtraction)
        g = (x - y).sgn_().mul_(grad / x.numel())
        gx = g if ctx.needs_input_grad[0] else None
        gy = (-g if ctx.needs_input_grad[0] else g.neg_()) if ctx.needs_input_grad[1] else None
        return gx, gy


def photometric_terms(
    x: Tensor, y: Tensor, lambda_ssim: float = LAMBDA_SSIM, reduction: str = "mean",
    padding: str = SSIM_PADDING, ssim_kernel: str = "auto", channels_last: bool = False, *,
    ssim_fused: bool | None = None,
) -> PhotometricTerms:
    """``l_ph(X, Y) = (1 - lambda) ||X - Y||_1 / (3HW) + lambda (1 - SSIM(X, Y))`` (eq. photometric) with its
    two parts: the one l_ph of the project (the trainer's baseline term and JSGS's L_obs).

    Args:
        x, y: ``(B, 3, H, W)`` RGB in [0, 1], or ``(B, H, W, 3)`` with ``channels_last`` (a render as the
            rasterizer returns it; the L1 part is taken on it as it is, SSIM on its ``(B, 3, H, W)`` view).
        lambda_ssim: D-SSIM weight (0.2 in the paper).
        reduction: "mean" -> scalars (mean over views of the per-view loss, equal to the mean over everything
            since views share H, W); "none" -> ``(B,)``.
        padding: SSIM borders, "same" (zero-padded, the original 3DGS; :data:`SSIM_PADDING`) or "valid"
            (gsplat's training loss, the trainer's default ``loss.ssim_padding``).
        ssim_kernel: the SSIM implementation, "auto", "torch" or "cuda" (:mod:`jsgs.kernels`; same value).
        channels_last: x and y are ``(B, H, W, 3)``.
        ssim_fused: the SSIM kernel's pick where the caller has made it: :func:`jsgs.kernels.ssim_is_fused`'s
            answer for ``x``, ``y`` (``(B, 3, H, W)``) and ``ssim_kernel``, or for tensors of their dtypes,
            shapes, device and ``requires_grad``; None: picked here (or by ``ssim``).
    Returns:
        The loss and its parts (unitless).
    """
    # the SSIM kernel's pick, the caller's or made here: passed to ssim, not made there again
    fused = ssim_fused
    if reduction == "mean" and x.shape == y.shape:
        if fused is None and not channels_last and x.is_contiguous():
            fused = ssim_is_fused(x, y, ssim_kernel)
        if fused:
            # the fused SSIM keeps a contiguous copy of y for its backward, L1 keeps y: one copy for both
            y = y.contiguous()
        l1 = _MeanAbsDifference.apply(x, y)
    elif reduction == "mean":
        l1 = (x - y).abs().mean()
    elif reduction == "none":
        l1 = (x - y).abs().flatten(1).mean(1)
    else:
        raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")
    if channels_last:
        x, y = x.permute(0, 3, 1, 2), y.permute(0, 3, 1, 2)
    d_ssim = 1.0 - ssim(x, y, padding=padding, reduction=reduction, kernel=ssim_kernel, fused=fused)
    return PhotometricTerms((1.0 - lambda_ssim) * l1 + lambda_ssim * d_ssim, l1, d_ssim)


def photometric_loss(
    x: Tensor, y: Tensor, lambda_ssim: float = LAMBDA_SSIM, reduction: str = "mean",
    padding: str = SSIM_PADDING, ssim_kernel: str = "auto", *, ssim_fused: bool | None = None,
) -> Tensor:
    """l_ph alone: ``photometric_terms(...).loss`` (same arguments)."""
    return photometric_terms(x, y, lambda_ssim, reduction, padding, ssim_kernel, ssim_fused=ssim_fused).loss


class ObservationLoss(NamedTuple):
    """``loss``: L_obs (scalar, or ``(B,)`` with reduction "none"); ``observation``: the JO output
    ``(B, 3, H, W)`` in [0, 1], needed again by the DCT supervision."""

    loss: Tensor
    observation: Tensor


def obs_loss(
    rendered: Tensor,
    target: Tensor,
    luma_table: Tensor | np.ndarray,
    chroma_table: Tensor | np.ndarray,
    sampling: str = "4:2:0",
    mode: str = "paper",
    lambda_ssim: float = LAMBDA_SSIM,
    reduction: str = "mean",
    padding: str = SSIM_PADDING,
) -> ObservationLoss:
    """``L_obs = l_ph(C_JPEG(rendered; T^Y, T^C), target)`` (eq. obs_loss).

    Args:
        rendered: ``(B, 3, H, W)`` rendered RGB in [0, 1].
        target: ``(B, 3, H, W)`` the decoded training JPEGs, in [0, 1].
        luma_table, chroma_table, sampling, mode: as :func:`jsgs.jpeg.observe.jpeg_observe`.
        lambda_ssim, reduction, padding: as :func:`photometric_terms`.
    """
    observation = jpeg_observe(rendered, luma_table, chroma_table, sampling, mode)
    loss = photometric_loss(observation, target, lambda_ssim, reduction, padding)
    return ObservationLoss(loss, observation)
