"""SSIM as 3D Gaussian Splatting computes it (and fused-ssim reproduces): 11x11 Gaussian window, sigma 1.5,
C1 = 0.01^2, C2 = 0.03^2, data range 1, zero padding of 5 ("same" output size), mean over every pixel and
channel. The window is separable, so it is applied as two 1-D convolutions (same value as the 2-D one).
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import Tensor

from jsgs.precision import ieee_fp32

C1 = 0.01**2
C2 = 0.03**2


@functools.cache
def _window_cached(size: int, sigma: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    x = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return (g / g.sum()).to(dtype=dtype, device=device)


def gaussian_window(size: int = 11, sigma: float = 1.5, dtype: torch.dtype = torch.float32,
                    device: torch.device | str | None = None) -> Tensor:
    """Normalised 1-D Gaussian ``(size,)``, centred (3DGS's ``gaussian(window_size, sigma)``)."""
    return _window_cached(size, sigma, dtype, torch.device(device if device is not None else "cpu"))


def _blur(x: Tensor, window: Tensor, padding: str) -> Tensor:
    """Separable Gaussian blur of ``(B, C, H, W)`` per channel; zero padding for "same", none for "valid"."""
    c = x.shape[1]
    k = window.numel()
    pad = k // 2 if padding == "same" else 0
    wv = window.view(1, 1, k, 1).expand(c, 1, k, 1)
    wh = window.view(1, 1, 1, k).expand(c, 1, 1, k)
    # without TF32: SSIM subtracts nearly equal blurred moments (E[x²] − μ²), which TF32 would swamp
    with ieee_fp32(x.device):
        x = F.conv2d(x, wv, padding=(pad, 0), groups=c)
        return F.conv2d(x, wh, padding=(0, pad), groups=c)


def ssim_map(
    x: Tensor, y: Tensor, window_size: int = 11, sigma: float = 1.5, padding: str = "same"
) -> Tensor:
    """Per-pixel SSIM ``(B, C, H', W')`` of ``x``, ``y`` (``(B, C, H, W)``, data range 1).

    ``padding="same"``: H' = H, W' = W with zero padding (3DGS / fused-ssim); ``"valid"``: H' = H - 10 etc.
    (no padded samples; needs H, W >= window_size).
    """
    if padding not in ("same", "valid"):
        raise ValueError(f"padding must be 'same' or 'valid', got {padding!r}")
    if x.shape != y.shape or x.dim() != 4:
        raise ValueError(
            f"ssim needs two (B, C, H, W) tensors of one shape, got {tuple(x.shape)}, {tuple(y.shape)}"
        )
    c = x.shape[1]
    w = gaussian_window(window_size, sigma, x.dtype, x.device)
    # One grouped convolution for the five local moments.
    stats = _blur(torch.cat([x, y, x * x, y * y, x * y], dim=1), w, padding)
    mu_x, mu_y, xx, yy, xy = stats.split(c, dim=1)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    s_xx, s_yy, s_xy = xx - mu_xx, yy - mu_yy, xy - mu_xy
    num = (2 * mu_xy + C1) * (2 * s_xy + C2)
    den = (mu_xx + mu_yy + C1) * (s_xx + s_yy + C2)
    return num / den


def ssim(x: Tensor, y: Tensor, window_size: int = 11, sigma: float = 1.5, padding: str = "same",
         reduction: str = "mean") -> Tensor:
    """Structural similarity of two image batches.

    Args:
        x, y: ``(B, C, H, W)`` images in [0, 1] (C = 3 for RGB).
        window_size, sigma: Gaussian window (11, 1.5: the standard).
        padding: "same" (zero padding, 3DGS convention) or "valid".
        reduction: "mean" -> scalar, mean over every pixel, channel and image (3DGS); "none" -> ``(B,)`` per
            image.
    Returns:
        SSIM, 1 for identical images.
    """
    m = ssim_map(x, y, window_size, sigma, padding)
    if reduction == "mean":
        return m.mean()
    if reduction == "none":
        return m.flatten(1).mean(1)
    raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")


__all__ = ["C1", "C2", "gaussian_window", "ssim", "ssim_map"]
