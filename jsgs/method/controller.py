"""The Gaussian Controller's math (paper eqs. gaussian_risk, controller_scale, fro), for one view.

For view i and Gaussian j (all per-Gaussian tensors are [N], one camera):

* ``r̄_j`` — the block score map r(p) pooled over the pixels j touches in this pass with the footprint weight
  ``κ = t·a`` (opacity excluded), ``r̄ = sg[Σ κ r / (Σ κ + ε_proj)]``; ``V_i = {j : ν_j > 0}`` with
  ``ν = Σ t·α·a``. The pooled sums come from the rasteriser (``jsgs.method.pooling``); here they are inputs.
* ``A_j = sg[J_j W R(q_j)]`` (2 x 3, pixels per world unit): W the rotation of the world-to-camera map,
  R(q) the Gaussian's rotation, J the perspective Jacobian at the camera-space mean ``(x, y, z)``::

      J = [[fx/z, 0, -fx·x'/z], [0, fy/z, -fy·y'/z]],   x' = clamp(x/z, ...), y' = clamp(y/z, ...)

  with gsplat's clamp of x/z and y/z to the field of view widened by 30 % on each side (the same J the
  rasteriser projects with, so that ``A diag(s)² Aᵀ`` is exactly the rasteriser's 2D covariance before its
  0.3 px² dilation; the clamp only changes J for Gaussians whose centre lies far outside the image).
* ``s̄_j = sqrt(½ tr(A diag(s)² Aᵀ)) = sqrt(½ Σ_k ‖A[:, k]‖² s_k²)`` — the projected RMS scale in pixels at
  the training resolution, before the dilation; differentiable in the scales only (A is frozen).
* ``L_fro = (1/|V|) Σ_{j∈V} r̄_j α_j² exp(−s̄_j/τ_s)``; 0 (with zero gradient) when V is empty.

Units: scales are world units (activated, ``exp`` of the stored log-scales), s̄ and τ_s pixels, r̄ and
L_fro unitless. Everything is vectorised over all N Gaussians with a contributor mask — no host
synchronisation, no data-dependent shapes.
"""

from __future__ import annotations

from functools import cache
from typing import NamedTuple

import torch
from torch import Tensor

from jsgs.method.pooling import PooledSums, sums_from_probe_grad
from jsgs.render.reference import quat_to_rotmat

TAU_S = 1.0  # τ_s, pixels at the training resolution
EPS_PROJ = 1e-6  # ε_proj
FOV_MARGIN = 0.3  # gsplat's widening of the FOV used to clamp x/z and y/z in J


@cache
def _image_size(width: int, height: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    # once per image size and device: a host-to-device copy inside the backward would stall the GPU queue
    return torch.tensor([width, height], dtype=dtype, device=device)


@torch.no_grad()
def controller_matrix(
    means: Tensor,
    quats: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
) -> Tensor:
    """``A = J W R(q)`` [N, 2, 3] under stop-gradient (eq. controller_scale).

    Args:
        means: [N, 3] world positions; quats: [N, 4] (w, x, y, z), any norm.
        viewmat: [4, 4] world-to-camera (OpenCV axes); K: [3, 3] intrinsics in pixels.
        width, height: image size in pixels (for gsplat's FOV clamp of J).
        near_plane: Gaussians nearer than this (or behind the camera) are culled by the rasteriser and never
            in V; their J is evaluated at z = 1 only to stay finite.
    """
    means, quats, viewmat, K = means.detach(), quats.detach(), viewmat.detach(), K.detach()
    Rw, tw = viewmat[:3, :3], viewmat[:3, 3]
    xyz = torch.addmm(tw, means, Rw.T)
    z = xyz[:, 2:3]
    z = torch.where(z >= near_plane, z, 1.0)
    f, c = K.diagonal()[:2], K[:2, 2]  # (fx, fy), (cx, cy)
    size = _image_size(width, height, K.dtype, K.device)
    margin = FOV_MARGIN * 0.5 * size / f
    uv = torch.clamp(xyz[:, :2] / z, min=-(c / f) - margin, max=(size - c) / f + margin)  # (x', y')
    # A = J M with M = Rw R(q): row r of A is (f_r / z) (M[r] - uv_r M[2]); written row-wise instead of as
    # J @ M, it is a handful of kernels over all N (this runs inside every backward).
    # M_n = Rw R_n for all n as ONE product, (R_nᵀ stacked) Rwᵀ = (M_nᵀ stacked): a batched product of N
    # 3x3 matrices runs as a tiled GEMM per matrix (measured 1.2 ms per step at N = 590k on an H200)
    R = quat_to_rotmat(quats)
    M = (R.transpose(1, 2).reshape(-1, 3) @ Rw.T).reshape(R.shape).transpose(1, 2)
    return (f / z)[:, :, None] * (M[:, :2, :] - uv[:, :, None] * M[:, 2:3, :])


def projected_rms_scale_sq(A: Tensor, scales: Tensor) -> Tensor:
    """``s̄² = ½ tr(A diag(s)² Aᵀ) = ½ Σ_k ‖A[:, k]‖² s_k²`` [N] in px². A [N, 2, 3] (frozen), scales [N, 3]
    activated (world units), differentiable."""
    col_sq = (A.detach() ** 2).sum(dim=-2)  # [N, 3]: ‖A[:, k]‖²
    return 0.5 * (col_sq * scales * scales).sum(dim=-1)


class ControllerStats(NamedTuple):
    """Per-view GC statistics (0-dim tensors, detached).

    visible: |V_i|. rbar_mean: mean of r̄ over V_i (0 when V_i is empty). damped: the number of Gaussians
    the controller acts on appreciably — j ∈ V_i with r̄_j > 0 and s̄_j ≤ τ_s (their factor exp(−s̄/τ_s) is
    at least 1/e; larger Gaussians are left nearly alone by the exponential)."""

    visible: Tensor
    rbar_mean: Tensor
    damped: Tensor


class FroTerms(NamedTuple):
    """L_fro for one view and what it was made of. ``loss`` 0-dim (differentiable in the opacity logits and
    log-scales when computed by :func:`fro_loss`); ``sbar`` [N] px and ``weight`` [N] = r̄ α² exp(−s̄/τ) m
    (detached); ``stats``."""

    loss: Tensor
    sbar: Tensor
    weight: Tensor
    stats: ControllerStats


def _stats(masked_rbar: Tensor, count: Tensor, sbar: Tensor, tau_s: float) -> ControllerStats:
    """From m r̄ [N] (r̄ on V_i, 0 elsewhere) and |V_i|: m r̄ > 0 ⇔ j ∈ V_i and r̄_j > 0."""
    mr = masked_rbar.detach()
    damped = ((mr > 0) & (sbar.detach() <= tau_s)).sum(dtype=mr.dtype)
    return ControllerStats(count.detach(), mr.sum() / count.clamp_min(1.0), damped)


def fro_loss(
    rbar: Tensor,
    visible: Tensor,
    opacity_logits: Tensor,
    log_scales: Tensor,
    A: Tensor,
    tau_s: float = TAU_S,
) -> FroTerms:
    """``L_fro`` (eq. fro) by autograd: gradients reach ``opacity_logits`` [N] and ``log_scales`` [N, 3] only.

    Args:
        rbar: [N] pooled scores r̄ (detached here); visible: [N] bool, V_i.
        opacity_logits: [N] stored opacity logits (α = sigmoid); log_scales: [N, 3] stored log-scales.
        A: [N, 2, 3] from :func:`controller_matrix` (detached here).
        tau_s: τ_s in pixels.
    """
    rbar = rbar.detach()
    m = visible.to(rbar.dtype)
    alpha = torch.sigmoid(opacity_logits)
    s2 = projected_rms_scale_sq(A, torch.exp(log_scales))
    # sqrt has an infinite slope at 0: evaluate it only where the term is used (non-contributors get s2 = 1,
    # and torch.where gives them zero gradient)
    sbar = torch.sqrt(torch.where(visible, s2, torch.ones_like(s2)))
    per = rbar * alpha * alpha * torch.exp(-sbar / tau_s)
    loss = torch.where(visible, per, torch.zeros_like(per)).sum() / m.sum().clamp_min(1.0)
    stats = _stats(torch.where(visible, rbar, 0.0), m.sum(), sbar, tau_s)
    return FroTerms(loss, sbar.detach(), (per * m).detach(), stats)


@torch.no_grad()
def fro_loss_and_grads(
    rbar: Tensor,
    visible: Tensor,
    opacity_logits: Tensor,
    log_scales: Tensor,
    A: Tensor,
    tau_s: float = TAU_S,
) -> tuple[FroTerms, Tensor, Tensor]:
    """``L_fro`` and its gradient in closed form (same arguments as :func:`fro_loss`), for a caller that
    applies it after the pooled sums are known inside the main backward.

    With m the contributor mask, n = max(|V|, 1), e = exp(−s̄/τ) and c_k = ‖A[:, k]‖²:
    ∂L/∂logit_j = m r̄ e · 2α²(1 − α) / n and ∂L/∂log s_jk = −m r̄ α² e / τ · c_k s_k² / (2 s̄) / n.
    Returns (terms, grad of the logits [N], grad of the log-scales [N, 3]). Shared factors are computed
    once (it runs inside every backward, where each kernel costs more than its arithmetic)."""
    count = visible.sum(dtype=rbar.dtype)
    alpha = torch.sigmoid(opacity_logits.detach())
    s = torch.exp(log_scales.detach())
    cs2 = (A.detach() ** 2).sum(dim=-2) * (s * s)  # c_k s_k², [N, 3]
    s2 = 0.5 * cs2.sum(dim=-1)
    sbar = torch.sqrt(torch.where(visible, s2, 1.0))
    a2e = alpha * alpha * torch.exp(sbar / -tau_s)  # α² e
    mr = torch.where(visible, rbar.detach(), 0.0)  # m r̄
    per = mr * a2e  # r̄ α² e m, the per-Gaussian term
    w = per / count.clamp_min(1.0)
    loss = w.sum()
    g_logit = 2.0 * w * (1.0 - alpha)
    g_log_scale = (w / (-2.0 * tau_s * sbar))[:, None] * cs2
    return FroTerms(loss, sbar, per, _stats(mr, count, sbar, tau_s)), g_logit, g_log_scale


class DeferredFro(NamedTuple):
    """What :func:`fro_from_probe_grad` computes for one view: ``terms`` (L_fro and its statistics),
    ``grad_logit`` [N] and ``grad_log_scale`` [N, 3] (``weight``·∂L_fro/∂θ, ready to add to the parameters'
    gradients), and for inspection the pooled ``sums`` ([1, N] each), ``rbar`` [N], ``visible`` [N] and
    ``A`` [N, 2, 3]."""

    terms: FroTerms
    grad_logit: Tensor
    grad_log_scale: Tensor
    sums: PooledSums
    rbar: Tensor
    visible: Tensor
    A: Tensor


@torch.no_grad()
def fro_from_probe_grad(
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
) -> DeferredFro:
    """The whole deferred Gaussian Controller of one view, from the probe's gradient to the weighted
    gradients of L_fro: the one home of that chain, for the eager hook and for its CUDA graph
    (``jsgs.method.graphed.GraphedController``). A pure function of tensors, without host synchronisation.

    Args:
        probe_grad: [1, N, 2] the probe's gradient after a backward in which ``probe_objective`` entered the
            loss with the factor ``weight`` (= λ_fro): weight·(o·S_r, ν).
        opacity_logits: [N], log_scales: [N, 3], means: [N, 3], quats: [N, 4] the stored parameters (the
            rendered opacities are ``sigmoid(opacity_logits)``, as the trainer activates them).
        viewmat: [4, 4], K: [3, 3], width, height: the view's camera (see :func:`controller_matrix`).
        weight: λ_fro (> 0); near_plane, eps_proj, tau_s: as in the paper's equations.
    """
    alpha = torch.sigmoid(opacity_logits.detach())
    sums = sums_from_probe_grad(probe_grad, alpha, weight)
    rbar = sums.rbar(eps_proj)[0]
    vis = sums.contributors[0]
    A = controller_matrix(means, quats, viewmat, K, width, height, near_plane)
    ft, g_logit, g_ls = fro_loss_and_grads(rbar, vis, opacity_logits, log_scales, A, tau_s)
    return DeferredFro(ft, weight * g_logit, weight * g_ls, sums, rbar, vis, A)


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
    """:func:`fro_from_probe_grad` and :func:`packed_fro_stats` as the three kernels of
    ``jsgs/csrc/controller.cu`` (CUDA, float32 or float64; same arguments, all tensors of one dtype and
    device): ``(grad_logit [N], grad_log_scale [N, 3], stats [4])``, equal to the twin's
    ``(out.grad_logit, out.grad_log_scale, packed_fro_stats(out.terms))`` up to rounding."""
    from jsgs.cuda_ext import build_error, extension

    tensors = (probe_grad, opacity_logits, log_scales, means, quats, viewmat, K)
    # checked in C++ (jsgs/csrc/bindings.cpp), not here: this runs inside every step's backward. A refusal is
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
    K)`` and ``weight`` (the checks of ``jsgs/csrc/bindings.cpp``, in words)."""
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


def packed_fro_stats(terms: FroTerms) -> Tensor:
    """[4]: L_fro, |V_i|, mean r̄ over V_i, #damped (one tensor, so a caller copies them in one kernel)."""
    s = terms.stats
    return torch.stack([terms.loss, s.visible, s.rbar_mean, s.damped])
