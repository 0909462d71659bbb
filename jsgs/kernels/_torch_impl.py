"""The torch twins of jsgs's kernels: each runs anywhere, on any dtype, and is the reference its CUDA op
(:mod:`jsgs.kernels._wrapper`) is tested against (gsplat's ``_torch_impl`` / ``_wrapper`` pattern).

SSIM as 3D Gaussian Splatting computes it (:func:`ssim_map_torch`, twin of ``csrc/ssim.cu``)
==========================================================================================

11x11 Gaussian window, sigma 1.5, C1 = 0.01^2, C2 = 0.03^2, data range 1, zero padding of 5 ("same" output
size) or none ("valid"). The separable window runs as two 1-D grouped convolutions (same value as the 2-D
one).

The Gaussian Controller (:func:`fro_from_probe_grad`, twin of ``csrc/controller.cu``)
====================================================================================

The paper's eqs. gaussian_risk, controller_scale and fro, for one view.

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

MCMC relocation (:func:`compute_relocation`, :func:`quat_scale_to_covar`, twins of gsplat's CUDA ops)
==================================================================================================

- :func:`compute_relocation` is gsplat's ``relocation`` kernel (``gsplat/cuda/csrc/RelocationCUDA.cu``):
  Equation (9) of Kheradmand et al. 2024, "3D Gaussian Splatting as Markov Chain Monte Carlo". A Gaussian
  of opacity o and scales s that is split into n copies gives each copy

      o' = 1 - (1 - o)^(1/n)
      s' = o / (sum_{i=1..n} sum_{k=0..i-1} C(i-1, k) (-1)^k / sqrt(k+1) (o')^(k+1)) * s

  so that the copies, composited, keep the original's opacity profile.
- :func:`quat_scale_to_covar` is ``gsplat.quat_scale_to_covar_preci(..., compute_covar=True,
  compute_preci=False, triu=False)``: Σ = R diag(s)² Rᵀ (the reference rasterizer's ``covariance_3d``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from jsgs.base.precision import ieee_fp32
from jsgs.render.reference import covariance_3d, quat_to_rotmat

# --- SSIM -------------------------------------------------------------------------------------------------

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


def ssim_map_torch(x: Tensor, y: Tensor, window: Tensor, padding: str) -> Tensor:
    """The SSIM map ``(B, C, H', W')`` of ``x``, ``y`` (``(B, C, H, W)``) with the 1-D window ``window``
    (:func:`gaussian_window`), "same" or "valid" ``padding``: the twin of the fused kernel
    (``csrc/ssim.cu``), one grouped convolution for the five local moments."""
    c = x.shape[1]
    stats = _blur(torch.cat([x, y, x * x, y * y, x * y], dim=1), window, padding)
    mu_x, mu_y, xx, yy, xy = stats.split(c, dim=1)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    s_xx, s_yy, s_xy = xx - mu_xx, yy - mu_yy, xy - mu_xy
    num = (2 * mu_xy + C1) * (2 * s_xy + C2)
    den = (mu_xx + mu_yy + C1) * (s_xx + s_yy + C2)
    return num / den


# --- The Gaussian Controller --------------------------------------------------------------------------------

EPS_PROJ = 1e-6  # the paper's ε_proj
TAU_S = 1.0  # τ_s, pixels at the training resolution
FOV_MARGIN = 0.3  # gsplat's widening of the FOV used to clamp x/z and y/z in J


@dataclass
class PooledSums:
    """Pooled sums per (camera, Gaussian), each [C, N] (``jsgs.method.pooling`` says how the rasteriser gives
    them)."""

    s_r: Tensor  # Σ_p t·a·r
    s_1: Tensor  # Σ_p t·a
    nu: Tensor  # Σ_p t·α (contribution mass)

    def rbar(self, eps: float = EPS_PROJ) -> Tensor:
        """r̄ = S_r / (S_1 + ε_proj), [C, N] (0 where the Gaussian does not contribute)."""
        return self.s_r / (self.s_1 + eps)

    @property
    def contributors(self) -> Tensor:
        """[C, N] bool: V_i = {j : ν_ij > 0}."""
        return self.nu > 0


def sums_from_probe_grad(grad: Tensor, opacities: Tensor, weight: float = 1.0) -> PooledSums:
    """Pooled sums from the probe's gradient ``grad`` [C, N, 2] = weight·(o·S_r, ν) (``probe_objective``
    entered the loss with the factor ``weight``), ``opacities`` [N] or [C, N] the activated o the pass
    rendered with.

    Contributors have o >= 1/255 (others are culled); ν == 0 ⇔ no contribution, and the sums are 0 there."""
    g = grad.detach()
    if weight != 1.0:
        g = g / weight
    nu = g[..., 1]
    o = opacities.detach().to(g.dtype)
    o = (o[None, :] if o.dim() == 1 else o).expand_as(nu)
    o_safe = torch.where(nu > 0, o, 1.0)
    return PooledSums(s_r=g[..., 0] / o_safe, s_1=nu / o_safe, nu=nu)


@functools.cache
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


def packed_fro_stats(terms: FroTerms) -> Tensor:
    """[4]: L_fro, |V_i|, mean r̄ over V_i, #damped (one tensor, so a caller copies them in one kernel)."""
    s = terms.stats
    return torch.stack([terms.loss, s.visible, s.rbar_mean, s.damped])


# --- MCMC relocation ------------------------------------------------------------------------------------


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
    return covariance_3d(quats, scales)
