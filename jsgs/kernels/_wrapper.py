"""jsgs's kernels as callers use them: each CUDA op (``csrc/``, built by :mod:`jsgs.kernels._backend`, or
one of gsplat's) beside the choice of its torch twin (:mod:`jsgs.kernels._torch_impl`).

SSIM (:func:`ssim`, :func:`ssim_map`), picked by ``kernel``:

- "torch": the twin :func:`~jsgs.kernels._torch_impl.ssim_map_torch` (two 1-D grouped convolutions). Runs
  anywhere, and is the reference the CUDA kernel is tested against.
- "cuda": ``csrc/ssim.cu``, one fused kernel forward and one backward, built on first use (needs nvcc). On
  a GPU the convolutions cost more than the rasterisation's backward (cuDNN's depthwise kernels plus layout
  transposes); gsplat's simple_trainer uses the fused-ssim package for the same reason.
- "auto" (default): "cuda" for float32/float64 CUDA tensors with the 11-tap window when the kernel builds
  and only ``x`` needs a gradient, else "torch"; a failed build says so once on stderr.

The deferred Gaussian Controller: :func:`fro_from_probe_grad_fused` runs ``csrc/controller.cu``, equal to
its twin :func:`~jsgs.kernels._torch_impl.fro_from_probe_grad` up to rounding (the caller picks with
``method_options.speed.gc_kernel`` through :func:`~jsgs.kernels._backend.use_kernels`).

MCMC relocation: :func:`cpu_twins` sends gsplat's strategy ops on CPU tensors to their twins
(:func:`~jsgs.kernels._torch_impl.compute_relocation`, :func:`~jsgs.kernels._torch_impl.quat_scale_to_covar`)
and CUDA tensors to gsplat's kernels.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import torch
from torch import Tensor

from jsgs.kernels._backend import KERNEL_CHOICES, build_error, extension
from jsgs.kernels._torch_impl import (
    C1,
    C2,
    EPS_PROJ,
    TAU_S,
    compute_relocation,
    gaussian_window,
    quat_scale_to_covar,
    ssim_map_torch,
)

SSIM_KERNELS = KERNEL_CHOICES

# --- SSIM -------------------------------------------------------------------------------------------------


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


class _FusedSsimMean(torch.autograd.Function):
    """The mean of :class:`_FusedSsimMap`'s map in one node: the same value, and a backward that hands the
    kernel the mean's gradient as one value broadcast (all strides 0, which ``ssim_backward`` reads in place)
    instead of the map of it that the mean's own backward makes (4 bytes a map value). The value it reads
    is the mean's backward's, ``grad / numel``, so the gradient is the same bit for bit."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, y: Tensor, window: Tensor, same: bool) -> Tensor:  # type: ignore[override]
        smap, d_mu, d_xx, d_xy = extension().ssim_forward(x, y, window, C1, C2, same)
        ctx.save_for_backward(x, y, window, d_mu, d_xx, d_xy)
        ctx.same = same
        return smap.mean()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, None, None, None]:  # type: ignore[override]
        x, y, window, d_mu, d_xx, d_xy = ctx.saved_tensors
        upstream = (grad / d_mu.numel()).expand(d_mu.shape)
        grad_x = extension().ssim_backward(upstream, x, y, window, d_mu, d_xx, d_xy, ctx.same)
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


def ssim_is_fused(x: Tensor, y: Tensor, kernel: str = "auto", window_size: int = 11) -> bool:
    """Whether :func:`ssim_map` runs the fused kernel on ``x``, ``y`` (which then keeps contiguous copies
    of both for its backward: a caller that keeps ``y`` too saves memory by handing it over contiguous)."""
    return _use_fused(x, y, kernel, window_size)


def ssim_map(
    x: Tensor, y: Tensor, window_size: int = 11, sigma: float = 1.5, padding: str = "same",
    kernel: str = "auto",
) -> Tensor:
    """Per-pixel SSIM ``(B, C, H', W')`` of ``x``, ``y`` (``(B, C, H, W)``, data range 1).

    ``padding="same"``: H' = H, W' = W with zero padding (3DGS / fused-ssim); ``"valid"``: H' = H - 10 etc.
    (no padded samples; needs H, W >= window_size). ``kernel``: "auto", "torch" or "cuda" (module doc).
    """
    _check_pair(x, y, padding)
    w = gaussian_window(window_size, sigma, x.dtype, x.device)
    return _checked_ssim_map(x, y, w, padding, _use_fused(x, y, kernel, window_size))


def _checked_ssim_map(x: Tensor, y: Tensor, window: Tensor, padding: str, fused: bool) -> Tensor:
    """:func:`ssim_map` of a pair :func:`_check_pair` has passed, with its Gaussian ``window`` and
    ``fused``, :func:`_use_fused`'s answer for it: the checks run once per call of :func:`ssim` or
    :func:`ssim_map`, whichever the caller called."""
    if fused:
        return _FusedSsimMap.apply(x.contiguous(), y.contiguous(), window, padding == "same")
    return ssim_map_torch(x, y, window, padding)


def _check_pair(x: Tensor, y: Tensor, padding: str) -> None:
    if padding not in ("same", "valid"):
        raise ValueError(f"padding must be 'same' or 'valid', got {padding!r}")
    if x.shape != y.shape or x.dim() != 4:
        raise ValueError(
            f"ssim needs two (B, C, H, W) tensors of one shape, got {tuple(x.shape)}, {tuple(y.shape)}"
        )


def ssim(x: Tensor, y: Tensor, window_size: int = 11, sigma: float = 1.5, padding: str = "same",
         reduction: str = "mean", kernel: str = "auto", *, fused: bool | None = None) -> Tensor:
    """Structural similarity of two image batches.

    Args:
        x, y: ``(B, C, H, W)`` images in [0, 1] (C = 3 for RGB).
        window_size, sigma: Gaussian window (11, 1.5: the standard).
        padding: "same" (zero padding, 3DGS convention) or "valid".
        reduction: "mean" -> scalar, mean over every pixel, channel and image (3DGS); "none" -> ``(B,)`` per
            image.
        kernel: "auto", "torch" or "cuda" (see the module doc).
        fused: the kernel's pick where the caller has made it: :func:`ssim_is_fused`'s answer for ``x``,
            ``y``, ``kernel`` and ``window_size`` (or for tensors of their dtypes, shapes, device and
            ``requires_grad``); None: picked here.
    Returns:
        SSIM, 1 for identical images.
    """
    _check_pair(x, y, padding)
    if fused is None:
        fused = _use_fused(x, y, kernel, window_size)
    w = gaussian_window(window_size, sigma, x.dtype, x.device)
    if reduction == "mean" and fused:
        # the mean and the map in one node: no map of the mean's gradient in the backward
        return _FusedSsimMean.apply(x.contiguous(), y.contiguous(), w, padding == "same")
    m = _checked_ssim_map(x, y, w, padding, fused)
    if reduction == "mean":
        return m.mean()
    if reduction == "none":
        return m.flatten(1).mean(1)
    raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")


# --- The Gaussian Controller --------------------------------------------------------------------------------


@torch.no_grad()
def fro_from_probe_grad_fused(
    probe_grad: Tensor,
    opacity_logits: Tensor,
    log_scales: Tensor,
    means: Tensor,
    quats: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    *,
    weight: float,
    near_plane: float = 0.01,
    eps_proj: float = EPS_PROJ,
    tau_s: float = TAU_S,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`~jsgs.kernels._torch_impl.fro_from_probe_grad` and
    :func:`~jsgs.kernels._torch_impl.packed_fro_stats` as the three kernels of ``csrc/controller.cu`` (CUDA,
    float32 or float64; same arguments, all tensors of one dtype and device): ``(grad_logit [N],
    grad_log_scale [N, 3], stats [4])``, equal to the twin's ``(out.grad_logit, out.grad_log_scale,
    packed_fro_stats(out.terms))`` up to rounding."""
    tensors = (probe_grad, opacity_logits, log_scales, means, quats, viewmat, K)
    # checked in C++ (csrc/bindings.cpp), not here: this runs inside every step's backward. A refusal is
    # an empty result, worded here (an exception or message built in the extension crashed the process)
    ext = extension(warn=False)
    if ext is None:
        raise RuntimeError(f"the fused Gaussian Controller cannot be built: {build_error()}")
    out = ext.controller_forward(
        *(t.detach().contiguous() for t in tensors), int(width), int(height), float(weight),
        float(near_plane), float(eps_proj), float(tau_s),
    )  # fmt: skip
    if not out:
        raise ValueError(_fused_arguments_error(tensors, weight))
    g_logit, g_ls, stats = out
    return g_logit, g_ls, stats


def _fused_arguments_error(tensors: tuple[Tensor, ...], weight: float) -> str:
    """Why the fused controller refused ``(probe_grad, opacity_logits, log_scales, means, quats, viewmat,
    K)`` and ``weight`` (the checks of ``csrc/bindings.cpp``, in words)."""
    logits = tensors[1]
    if logits.dim() != 1:
        return f"the fused controller: opacity_logits must be [N], got shape {tuple(logits.shape)}"
    if logits.dtype not in (torch.float32, torch.float64):
        return f"the fused controller needs float32 or float64, got {logits.dtype}"
    if not weight > 0:
        return f"the fused controller: weight must be > 0, got {weight}"
    n = logits.shape[0]
    shapes = ((1, n, 2), (n,), (n, 3), (n, 3), (n, 4), (4, 4), (3, 3))
    names = ("probe_grad", "opacity_logits", "log_scales", "means", "quats", "viewmat", "K")
    for t, shape, name in zip(tensors, shapes, names, strict=True):
        if t.dtype != logits.dtype or t.device != logits.device or t.device.type != "cuda":
            return (
                f"the fused controller: {name} is {t.dtype} on {t.device}; every tensor must be "
                f"{logits.dtype} on one CUDA device"
            )
        if tuple(t.shape) != shape:
            return f"the fused controller: {name} has shape {tuple(t.shape)}, expected {shape}"
    return "the fused controller refused its arguments"


# --- MCMC relocation ------------------------------------------------------------------------------------


def _relocation_dispatch(cuda_op: Any) -> Any:
    def op(opacities: Tensor, scales: Tensor, ratios: Tensor, binoms: Tensor) -> tuple[Tensor, Tensor]:
        if opacities.is_cuda:
            return cuda_op(opacities=opacities, scales=scales, ratios=ratios, binoms=binoms)
        return compute_relocation(opacities, scales, ratios, binoms)

    return op


def _covar_dispatch(cuda_op: Any) -> Any:
    def op(quats: Tensor, scales: Tensor, *args: Any, **kwargs: Any) -> tuple[Tensor | None, Tensor | None]:
        if quats.is_cuda:
            return cuda_op(quats, scales, *args, **kwargs)
        return quat_scale_to_covar(quats, scales), None

    return op


@contextlib.contextmanager
def cpu_twins() -> Iterator[None]:
    """Within this block gsplat's strategy ops (``gsplat.strategy.ops``) send CPU tensors to the twins above
    and CUDA tensors to gsplat's kernels. Restored on exit, also after an exception."""
    from gsplat.strategy import ops

    saved = ops.compute_relocation, ops.quat_scale_to_covar_preci
    ops.compute_relocation = _relocation_dispatch(saved[0])
    ops.quat_scale_to_covar_preci = _covar_dispatch(saved[1])
    try:
        yield
    finally:
        ops.compute_relocation, ops.quat_scale_to_covar_preci = saved
