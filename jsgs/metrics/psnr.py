"""PSNR on images in [0, 1]."""

from __future__ import annotations

import torch
from torch import Tensor


def psnr(pred: Tensor, ref: Tensor) -> Tensor:
    """Peak signal-to-noise ratio in dB, one value per image, peak value 1.

    pred, ref: B x C x H x W or C x H x W, same shape, values in [0, 1]. The MSE is taken over all pixels
    and channels of each image (in float64, so that near-identical images do not lose digits). Returns a
    float64 tensor of B values; +inf where an image matches its reference exactly.
    """
    if pred.shape != ref.shape:
        raise ValueError(f"PSNR: image shapes differ: {tuple(pred.shape)} vs {tuple(ref.shape)}")
    if pred.dim() == 3:
        pred, ref = pred.unsqueeze(0), ref.unsqueeze(0)
    if pred.dim() != 4:
        raise ValueError(f"PSNR: expected B x C x H x W or C x H x W, got shape {tuple(pred.shape)}")
    mse = (pred.double() - ref.double()).pow(2).flatten(1).mean(dim=1)
    return -10.0 * torch.log10(mse)
