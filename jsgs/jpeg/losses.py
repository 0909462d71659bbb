"""Image-domain losses: the photometric loss (paper eq. photometric) and the JPEG observation loss L_obs
(eq. obs_loss)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from torch import Tensor

from ..ssim import ssim
from .observe import jpeg_observe

LAMBDA_SSIM = 0.2


def photometric_loss(
    x: Tensor, y: Tensor, lambda_ssim: float = LAMBDA_SSIM, reduction: str = "mean", padding: str = "same",
    ssim_kernel: str = "auto",
) -> Tensor:
    """``l_ph(X, Y) = (1 - lambda) ||X - Y||_1 / (3HW) + lambda (1 - SSIM(X, Y))`` (eq. photometric).

    Args:
        x, y: ``(B, 3, H, W)`` RGB in [0, 1].
        lambda_ssim: D-SSIM weight (0.2 in the paper).
        reduction: "mean" -> scalar (mean over views of the per-view loss, equal to the mean over everything
            since views share H, W); "none" -> ``(B,)``.
        padding: SSIM borders, "same" (zero-padded, the original 3DGS) or "valid" (gsplat's training loss).
        ssim_kernel: the SSIM implementation, "auto", "torch" or "cuda" (:mod:`jsgs.ssim`; same value).
    Returns:
        The loss (unitless).
    """
    if reduction == "mean":
        l1 = (x - y).abs().mean()
    elif reduction == "none":
        l1 = (x - y).abs().flatten(1).mean(1)
    else:
        raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")
    s = ssim(x, y, padding=padding, reduction=reduction, kernel=ssim_kernel)
    return (1.0 - lambda_ssim) * l1 + lambda_ssim * (1.0 - s)


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
) -> ObservationLoss:
    """``L_obs = l_ph(C_JPEG(rendered; T^Y, T^C), target)`` (eq. obs_loss).

    Args:
        rendered: ``(B, 3, H, W)`` rendered RGB in [0, 1].
        target: ``(B, 3, H, W)`` the decoded training JPEGs, in [0, 1].
        luma_table, chroma_table, sampling, mode: as :func:`jsgs.jpeg.observe.jpeg_observe`.
    """
    observation = jpeg_observe(rendered, luma_table, chroma_table, sampling, mode)
    return ObservationLoss(photometric_loss(observation, target, lambda_ssim, reduction), observation)
