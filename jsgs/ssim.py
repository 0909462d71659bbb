"""SSIM as 3D Gaussian Splatting computes it (and fused-ssim reproduces): 11x11 Gaussian window, sigma 1.5,
C1 = 0.01^2, C2 = 0.03^2, data range 1, zero padding of 5 ("same" output size), mean over every pixel and
channel.

Two implementations of one definition, picked by ``kernel``:

- "torch": the separable window as two 1-D grouped convolutions (same value as the 2-D one). Runs
  anywhere, and is the reference the CUDA kernel is tested against.
- "cuda": ``jsgs/csrc/ssim.cu``, one fused kernel forward and one backward, built on first use
  (:mod:`jsgs.cuda_ext`, needs nvcc). On a GPU the convolutions cost more than the rasterisation's
  backward (cuDNN's depthwise kernels plus layout transposes); gsplat's simple_trainer uses the fused-ssim
  package for the same reason.
- "auto" (default): "cuda" for float32/float64 CUDA tensors with the 11-tap window when the kernel builds
  and only ``x`` needs a gradient, else "torch"; a failed build says so once on stderr.
"""

from __future__ import annotations

import functools
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from jsgs.base.precision import ieee_fp32
from jsgs.cuda_ext import KERNEL_CHOICES, build_error, extension

C1 = 0.01**2
C2 = 0.03**2
SSIM_KERNELS = KERNEL_CHOICES


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


class _FusedSsimMap(torch.autograd.Function):
    """SSIM map through the fused kernels; differentiable in ``x`` only (y is a target)."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, y: Tensor, window: Tensor, same: bool) -> Tensor:  # type: ignore[override]
        ext = extension()
        smap, d_mu, d_xx, d_xy = ext.ssim_forward(x, y, window, C1, C2, same)
        ctx.save_for_backward(x, y, window, d_mu, d_xx, d_xy)
        ctx.same = same
        return smap

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, None, None, None]:  # type: ignore[override]
        x, y, window, d_mu, d_xx, d_xy = ctx.saved_tensors
        grad_x = extension().ssim_backward(grad, x, y, window, d_mu, d_xx, d_xy, ctx.same)
        return grad_x, None, None, None


def _use_fused(x: Tensor, y: Tensor, kernel: str, window_size: int) -> bool:
    if kernel not in SSIM_KERNELS:
        raise ValueError(f"kernel must be one of {', '.join(SSIM_KERNELS)}, got {kernel!r}")
    if kernel == "torch":
        return False
    # the kernel's grid has one z-slice per image x channel (CUDA allows 65535)
    fits = (
        x.dtype == y.dtype and x.dtype in (torch.float32, torch.float64) and window_size == 11
        and x.shape[0] * x.shape[1] <= 65535
    )  # fmt: skip
    if kernel == "cuda":
        if not x.is_cuda:
            raise ValueError(f"the fused SSIM kernel needs CUDA tensors, got {x.device.type}")
        if not fits:
            raise ValueError(
                f"the fused SSIM kernel needs float32 or float64, an 11-tap window and at most 65535 "
                f"images x channels, got {x.dtype}, {y.dtype}, {window_size}, {x.shape[0] * x.shape[1]}"
            )
        if y.requires_grad:
            raise ValueError("the fused SSIM kernel differentiates x only; y must not need a gradient")
        if extension(warn=False) is None:
            raise RuntimeError(f"the fused SSIM kernel cannot be built: {build_error()}")
        return True
    return x.is_cuda and fits and not y.requires_grad and extension() is not None


def ssim_map(
    x: Tensor, y: Tensor, window_size: int = 11, sigma: float = 1.5, padding: str = "same",
    kernel: str = "auto",
) -> Tensor:
    """Per-pixel SSIM ``(B, C, H', W')`` of ``x``, ``y`` (``(B, C, H, W)``, data range 1).

    ``padding="same"``: H' = H, W' = W with zero padding (3DGS / fused-ssim); ``"valid"``: H' = H - 10 etc.
    (no padded samples; needs H, W >= window_size). ``kernel``: "auto", "torch" or "cuda" (module doc).
    """
    if padding not in ("same", "valid"):
        raise ValueError(f"padding must be 'same' or 'valid', got {padding!r}")
    if x.shape != y.shape or x.dim() != 4:
        raise ValueError(
            f"ssim needs two (B, C, H, W) tensors of one shape, got {tuple(x.shape)}, {tuple(y.shape)}"
        )
    c = x.shape[1]
    w = gaussian_window(window_size, sigma, x.dtype, x.device)
    if _use_fused(x, y, kernel, window_size):
        return _FusedSsimMap.apply(x.contiguous(), y.contiguous(), w, padding == "same")
    # One grouped convolution for the five local moments.
    stats = _blur(torch.cat([x, y, x * x, y * y, x * y], dim=1), w, padding)
    mu_x, mu_y, xx, yy, xy = stats.split(c, dim=1)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    s_xx, s_yy, s_xy = xx - mu_xx, yy - mu_yy, xy - mu_xy
    num = (2 * mu_xy + C1) * (2 * s_xy + C2)
    den = (mu_xx + mu_yy + C1) * (s_xx + s_yy + C2)
    return num / den


def ssim(x: Tensor, y: Tensor, window_size: int = 11, sigma: float = 1.5, padding: str = "same",
         reduction: str = "mean", kernel: str = "auto") -> Tensor:
    """Structural similarity of two image batches.

    Args:
        x, y: ``(B, C, H, W)`` images in [0, 1] (C = 3 for RGB).
        window_size, sigma: Gaussian window (11, 1.5: the standard).
        padding: "same" (zero padding, 3DGS convention) or "valid".
        reduction: "mean" -> scalar, mean over every pixel, channel and image (3DGS); "none" -> ``(B,)`` per
            image.
        kernel: "auto", "torch" or "cuda" (see the module doc).
    Returns:
        SSIM, 1 for identical images.
    """
    m = ssim_map(x, y, window_size, sigma, padding, kernel)
    if reduction == "mean":
        return m.mean()
    if reduction == "none":
        return m.flatten(1).mean(1)
    raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")


__all__ = ["C1", "C2", "SSIM_KERNELS", "gaussian_window", "ssim", "ssim_map"]
