"""Torch twins of the two CUDA-only ops that gsplat's MCMC strategy calls, so that it also runs on the CPU
with the reference rasterizer.

- :func:`compute_relocation` is gsplat's ``relocation`` kernel (``gsplat/cuda/csrc/RelocationCUDA.cu``):
  Equation (9) of Kheradmand et al. 2024, "3D Gaussian Splatting as Markov Chain Monte Carlo". A Gaussian
  of opacity o and scales s that is split into n copies gives each copy

      o' = 1 - (1 - o)^(1/n)
      s' = o / (sum_{i=1..n} sum_{k=0..i-1} C(i-1, k) (-1)^k / sqrt(k+1) (o')^(k+1)) * s

  so that the copies, composited, keep the original's opacity profile.
- :func:`quat_scale_to_covar` is ``gsplat.quat_scale_to_covar_preci(..., compute_covar=True,
  compute_preci=False, triu=False)``: Σ = R diag(s)² Rᵀ (the reference rasterizer's ``covariance_3d``).

:func:`cpu_twins` routes CPU tensors to these for the duration of a strategy call; CUDA tensors keep gsplat's
kernels.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import torch
from torch import Tensor


def compute_relocation(
    opacities: Tensor, scales: Tensor, ratios: Tensor, binoms: Tensor
) -> tuple[Tensor, Tensor]:
    """New opacities [N] and scales [N, 3] of Gaussians split ``ratios`` [N] ways (int, clamped to
    [1, n_max] in place as gsplat does), from opacities [N] in (0, 1), activated scales [N, 3] and the
    binomial table ``binoms`` [n_max, n_max] (``binoms[n, k] = C(n, k)``). Sums are accumulated in float64
    and the results returned in the inputs' dtype."""
    n_max = binoms.shape[0]
    if scales.shape != (opacities.shape[0], 3) or ratios.shape != opacities.shape:
        raise ValueError(
            f"compute_relocation: opacities {tuple(opacities.shape)}, scales {tuple(scales.shape)}, "
            f"ratios {tuple(ratios.shape)} (expected [N], [N, 3], [N])"
        )
    ratios.clamp_(min=1, max=n_max)
    n = ratios.to(torch.int64)
    o = opacities.to(torch.float64)
    new_o = 1.0 - torch.pow(1.0 - o, 1.0 / n.to(torch.float64))
    # sum over i <= n of C(i-1, k) = C(n, k+1) (the hockey-stick identity), computed from the table as the
    # kernel does: column sums of binoms over rows 0..n-1
    cum = torch.cumsum(binoms.to(torch.float64), dim=0)  # cum[r, k] = sum_{i<=r} C(i, k)
    weight = cum[n - 1]  # [N, n_max]: sum_{i=1..n} C(i-1, k)
    k = torch.arange(n_max, dtype=torch.float64, device=o.device)
    sign = torch.where(k.remainder(2) == 0, 1.0, -1.0) / torch.sqrt(k + 1.0)
    powers = new_o[:, None] ** (k[None, :] + 1.0)
    denom = (weight * sign[None, :] * powers).sum(dim=1)
    coeff = o / denom
    new_scales = coeff[:, None] * scales.to(torch.float64)
    return new_o.to(opacities.dtype), new_scales.to(scales.dtype)


def quat_scale_to_covar(quats: Tensor, scales: Tensor) -> Tensor:
    """World covariances [N, 3, 3] from (unnormalised) quaternions [N, 4] (w, x, y, z) and activated scales
    [N, 3]."""
    from jsgs.render.reference import covariance_3d

    return covariance_3d(quats, scales)


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
