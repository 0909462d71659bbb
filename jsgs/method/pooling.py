"""Per-Gaussian pooling of a per-pixel map for the Gaussian Controller (paper eq. gaussian_risk).

For camera i, Gaussian j and a per-pixel map r_i(p) (block scores, stop-gradient):

    S_r = Σ_p κ(p)·r(p),   S_1 = Σ_p κ(p),   ν = Σ_p t(p)·α(p),   κ(p) = t(p)·a(p),

over the pixels p where j actually contributes in this rasterisation pass (gsplat's skip and stop rules),
t the transmittance in front of j, α(p) = min(0.999, o_j·exp(−σ)) the composited alpha and a(p) = α(p)/o_j
the footprint without opacity (= exp(−σ) except in the rare core where α hit gsplat's 0.999 clamp; this
definition makes ν = o_j·S_1 the rendered contribution mass exactly). r̄ = S_r / (S_1 + ε_proj).

Three ways to get them, all equal to the pooled sums of ``jsgs.render.bruteforce.render_bruteforce``:

* ``pool_direct`` — the reference rasterizer's tiles evaluated again without autograd (any device; the
  brute-force-checked definition; a second pass).
* The probe — two zero-valued extra feature channels per Gaussian (``new_probe``, [N, 2] or [C, N, 2]),
  rendered through the rasterizer's generic extra channels (``rasterize(..., extra=probe)``, which puts the
  features in ``info["extra_features"]`` and the rendered channels in ``info["extra"]``). Because a rendered
  channel is Σ_j t·α·c_j, its gradient with respect to c_j is Σ_p t·α·g(p) for an upstream gradient g; with
  g = r for channel 0 and g = 1 for channel 1 the probe's gradient is (o·S_r, ν). Works for both backends
  (gsplat: no second rasterisation).
  - ``pool_now(info, r)`` runs that backward at once (``torch.autograd.grad`` through the rasteriser's
    backward only, graph retained) — use it when the loss needs r̄ before the main backward (L_fro does).
  - or add ``probe_objective(info, r)`` (value exactly 0) to the loss and call ``pool_from_grad(info)``
    after ``loss.backward()`` — no extra pass at all, for a caller that can apply its r̄-dependent terms
    after the backward (for instance L_fro's closed-form gradient into opacity and scale).

A cheaper estimate, ``method_options.gc_attribution: footprint`` (no probe, no extra channels):
``footprint_sums`` integrates each Gaussian's screen-space footprint (its 2D mean and conic, a normalised
2D Gaussian, transmittance taken as 1) over the 3 × 3 blocks of 8 × 8 pixels around its mean, so
r̄ ≈ Σ_b w_b r_b / Σ_b w_b with w_b the footprint mass in block b (inside the image), and takes the
contributor set from the ordinary RGB backward: j ∈ V_i ⇔ its conic's gradient is non-zero (a Gaussian that
composites no pixel gets exactly zero; one that does gets a non-zero sum but for an exact cancellation, which
the 2D mean's gradient meets for a symmetric footprint under a uniform upstream gradient, and the conic's
diagonal, an even moment, does not).
Because r is constant on each block, the estimate is exact for a Gaussian whose contributing pixels lie in
one block and unoccluded ones in general; it departs from the probe where occlusion hides part of a footprint
that straddles blocks, and for footprints wider than a block (s̄ ≫ τ_s, which L_fro's exp(−s̄/τ_s) weighs
little). ``probe_grad_from_sums`` turns such sums into the probe gradient they stand for, so the
controller's code downstream (eager, graphed, fused CUDA) is the probe's own.

Gradient contamination. Adding Σ_p r(p)·C(p) for a *rendered* channel C to the loss would also push
gradients into means2d, conics and opacities (∂C/∂α ≠ 0), and DefaultStrategy would densify on r's
gradient as well as the photometric one. The probe avoids this: its colours are zero, so the extra
channels render to exactly 0 and every derivative they send to means2d, conics and opacities carries a
factor c_j or Σ_behind α·T·c (both 0). Measured: gsplat's means2d/parameter gradients with the probe are
equal to those without it within gsplat's own run-to-run atomic-add noise
(tests/test_jsgs/render/test_render_gpu.py); the reference's agree to 1e-14
(tests/test_jsgs/render/test_render_reference.py). Do not use a non-zero probe colour (say r itself).
``probe_objective`` must enter the loss unscaled (no loss weight, no AMP scaler), or the factor
must be divided out of the gradient (``ProbeObjective(weight)`` is the weighted objective in one node).
"""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F
from torch import Tensor

from jsgs.base.kept_zeros import kept_zeros
from jsgs.base.known_grad import with_known_gradient
from jsgs.kernels import PooledSums, sums_from_probe_grad
from jsgs.render.reference import Projected, TileBins, bin_tiles, project_gaussians
from jsgs.render.reference.composite import (
    CHUNK_PAIRS,
    block_weights,
    gather_block,
    image_to_tiles,
    tile_blocks,
    tile_origins,
)


def new_probe(n_gaussians: int, like: Tensor, n_cameras: int | None = None) -> Tensor:
    """The probe: zero features [N, 2] (or [C, N, 2] for per-camera sums over several cameras), a leaf that
    requires grad, in ``like``'s dtype and device; pass it as ``rasterize(..., extra=probe)``."""
    shape = (n_gaussians, 2) if n_cameras is None else (n_cameras, n_gaussians, 2)
    return torch.zeros(shape, dtype=like.dtype, device=like.device, requires_grad=True)


def _opacities(info: dict) -> Tensor:
    """[C, N] the activated opacities the pass rendered with (gsplat's meta; packed: scattered back)."""
    o = info["opacities"].detach()
    if info.get("gaussian_ids") is None:
        return o
    C, N = info["n_cameras"], info["extra_features"].shape[-2]
    full = o.new_zeros(C, N)
    full[info["camera_ids"], info["gaussian_ids"]] = o
    return full


def _sums_from_probe_grad(grad: Tensor, info: dict) -> PooledSums:
    """[N, 2] probes (one camera) are read as [1, N, 2]."""
    return sums_from_probe_grad(grad if grad.dim() == 3 else grad[None], _opacities(info))


def _checked_channels(info: dict, r: Tensor, blocks: bool = False) -> Tensor:
    """The rendered probe channels ``info["extra"]`` [C, H, W, 2], checked against ``r`` [C, H, W] (or,
    with ``blocks``, its block scores [C, H // 8, W // 8] too)."""
    ch = info.get("extra")
    probe = info.get("extra_features")
    if ch is None or probe is None or ch.shape[-1] != 2 or not probe.requires_grad:
        raise ValueError("probe pooling needs rasterize(..., extra=new_probe(...))")
    C, H, W, _ = ch.shape
    if r.shape != (C, H, W) and not (blocks and r.shape == (C, H // 8, W // 8)):
        raise ValueError(f"r must be [C, H, W] = {(C, H, W)}, got {tuple(r.shape)}")
    return ch


def _upstream(info: dict, r: Tensor) -> Tensor:
    ch = _checked_channels(info, r)
    r = r.detach().to(ch.dtype)
    # [C, H, W, 2] = (r, 1): r with a channel of ones padded on, one kernel (stack with ones_like is two)
    return F.pad(r[..., None], (0, 1), value=1.0)


def probe_objective(info: dict, r: Tensor) -> Tensor:
    """Scalar Σ_p r(p)·probe₀(p) + Σ_p probe₁(p) (value exactly 0) to add, unscaled, to the loss.

    After ``backward`` read the sums with ``pool_from_grad(info)``.

    The gradient with respect to the probe channels is the upstream map ``(r, 1)`` itself and the value is
    exactly 0 (the channels render zero colours over a zero background), so the objective is one node with
    that known gradient rather than a product and a sum (``jsgs.base.known_grad``).
    """
    up = _upstream(info, r)
    return with_known_gradient(info["extra"], up.new_zeros(()), up, scratch=True)  # up: made for this call


class ProbeObjective:
    """``weight · probe_objective(info, r)`` step after step, with the upstream map ``weight·(r, 1)`` made
    at each call: two kernels per step (``weight·r`` written into channel 0, ``weight`` into channel 1; the
    zero value is made once and kept, :func:`jsgs.base.kept_zeros.kept_zeros`), where
    :func:`probe_objective` and a loss weight take five (a pad's fill and copy, the zero, and the weight's
    multiplication forward and backward).

    The probe's gradient is ``weight·(o·S_r, ν)`` with the same rounding as ``weight * probe_objective(...)``
    in the loss (``weight·r`` rounded once; the backward multiplies by the loss's upstream 1). The map is
    the returned scalar's known gradient, read in its backward, which writes the upstream times it over it
    (``scratch``: no product of the image's size in the backward) and hands it on, for one backward. The map
    is not kept between calls (8 bytes a pixel in float32): it lives from the call (after the trainer's
    ℓ_ph, past that forward's peak) to the rasteriser's backward, and the steps that render no probe hold
    none; a new buffer is an allocation, no kernel."""

    def __init__(self, weight: float = 1.0) -> None:
        self.weight = float(weight)

    def __call__(self, info: dict, r: Tensor) -> Tensor:
        ch, up = self.upstream(info, r)
        return with_known_gradient(ch, kept_zeros(ch), up, scratch=True)

    def upstream(self, info: dict, r: Tensor) -> tuple[Tensor, Tensor]:
        """The rendered probe channels and their known gradient ``weight·(r, 1)`` (a new buffer, written
        now): the objective's (tensor, gradient) pair, for a caller that puts it on a node of its own
        (:func:`jsgs.base.known_grad.with_known_gradient`) unscaled. The buffer is scratch for that node
        (``scratch``: its backward writes the upstream times it over it). ``r``: r(p) ``[C, H, W]``, or the
        block scores r_b ``[C, H // 8, W // 8]`` it is made of (the same map: r_b on each 8×8 block's
        pixels, 0 on the rest; ``weight·r_b`` written onto each block's pixels, one kernel more where H or W
        is not a multiple of 8, which zeroes the rest first)."""
        ch = _checked_channels(info, r, blocks=True)
        return ch, _probe_map(r, self.weight, ch.shape, ch.dtype, ch.device)


class DeferredProbeMap:
    """The probe channels' gradient ``weight·(r, 1)`` made in the backward: the ``extra_upstream`` of the
    render (:func:`jsgs.render.rasterize`), whose ``info["extra_objective"]`` then stands for ``weight ·
    probe_objective(info, r)`` in the loss with the same gradients, bit for bit (tested). ``r`` (r(p), or
    the block scores r_b it is made of) is set after the render, once the image terms have made it; the
    map exists only from where the backward reaches the objective's node (after the losses on the render,
    which were made after it) to the rasteriser's backward: not at the forward's peak, not at ℓ_ph's
    backward. Unset, it gives no gradient. ``unit_upstream``, set with ``r``: the objective enters a loss
    unweighted whose backward starts from 1, so the map is handed on without the product by the upstream
    (:func:`jsgs.base.known_grad.with_deferred_gradient`)."""

    def __init__(self, weight: float) -> None:
        self.weight = float(weight)
        self.r: Tensor | None = None
        self.unit_upstream = False

    def __call__(self, shape: tuple[int, ...], dtype: torch.dtype, device: torch.device) -> Tensor | None:
        r, self.r = self.r, None
        if r is None:
            return None
        C, H, W, E = shape
        if E != 2 or (r.shape != (C, H, W) and r.shape != (C, H // 8, W // 8)):
            raise ValueError(f"the probe's map: r of shape {tuple(r.shape)} for channels {shape}")
        return _probe_map(r, self.weight, shape, dtype, device)


def _probe_map(
    r: Tensor, weight: float, shape: tuple[int, ...], dtype: torch.dtype, device: torch.device
) -> Tensor:
    """``weight·(r, 1)`` ``[C, H, W, 2]`` (a new tensor) from r(p) ``[C, H, W]`` or the block scores r_b
    ``[C, H // 8, W // 8]`` (r_b on each 8×8 block's pixels, 0 on the rest: written blockwise, one kernel
    more where H or W is not a multiple of 8, which zeroes the rest first)."""
    up = torch.empty(shape, dtype=dtype, device=device)
    r0 = up[..., 0]
    C, H, W = r0.shape
    rd = r.detach().to(dtype)
    if rd.shape[1:] != (H, W):  # r_b: each block's pixels, a strided view of the channel
        nby, nbx = rd.shape[1:]
        if nby * 8 != H or nbx * 8 != W:
            r0.zero_()
        r0 = r0[:, : nby * 8, : nbx * 8].unflatten(2, (nbx, 8)).unflatten(1, (nby, 8))
        rd = rd[:, :, None, :, None].expand(C, nby, 8, nbx, 8)
    torch.mul(rd, weight, out=r0)
    up[..., 1].fill_(weight)
    return up


def pool_from_grad(info: dict) -> PooledSums:
    """Pooled sums from the probe's gradient ``info["extra_features"].grad`` after a backward that included
    ``probe_objective``."""
    g = info["extra_features"].grad
    if g is None:
        raise ValueError("the probe has no gradient: add probe_objective(info, r) to the loss first")
    return _sums_from_probe_grad(g, info)


def pool_now(info: dict, r: Tensor) -> PooledSums:
    """Pooled sums right away: one backward through the rasteriser only (graph retained for the loss).

    Call it before ``loss.backward()``: gsplat *assigns* ``means2d.absgrad`` in every rasteriser backward,
    so a later call would overwrite the loss's absgrad with this backward's (zero) one."""
    (g,) = torch.autograd.grad(
        info["extra"], info["extra_features"], grad_outputs=_upstream(info, r), retain_graph=True
    )
    return _sums_from_probe_grad(g, info)


@torch.no_grad()
def pool_direct(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    r: Tensor,
    *,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    radius_clip: float = 0.0,
) -> PooledSums:
    """Pooled sums by evaluating the reference rasterizer's weights directly (no autograd, any device).

    Same arguments as ``rasterize`` (colours are not needed); r: [C, H, W]."""
    proj = project_gaussians(
        means, quats, scales, opacities, viewmats, Ks, width, height,
        eps2d=eps2d, near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip,
    )  # fmt: skip
    bins = bin_tiles(proj.means2d, proj.radii, proj.depths, width, height)
    s_r, s_1, nu = pooled_sums(proj, bins, opacities, r, width, height)
    return PooledSums(s_r, s_1, nu)


@torch.no_grad()
def pooled_sums(
    proj: Projected,
    bins: TileBins,
    opacities: Tensor,
    r: Tensor,
    width: int,
    height: int,
    *,
    chunk_pairs: int = CHUNK_PAIRS,
) -> tuple[Tensor, Tensor, Tensor]:
    """Per (camera, Gaussian) sums over the pixels it contributes to in this pass (same skip/stop rules):
    ``S_r = Σ_p t·a·r(p)``, ``S_1 = Σ_p t·a``, ``ν = Σ_p t·α(p)``, each [C, N], where t is the transmittance
    before the Gaussian and ``a = α(p)/o`` the footprint without opacity (``exp(−σ)`` except in the rare
    core where α hit the 0.999 clamp). r: [C, H, W] per-pixel map."""
    C, N = proj.depths.shape
    TH, TW = bins.tile_height, bins.tile_width
    dt = proj.means2d.dtype
    r_t = image_to_tiles(r.detach().to(dt), TH, TW)
    in_t = image_to_tiles(torch.ones(C, height, width, dtype=dt, device=r.device), TH, TW)
    m_f = proj.means2d.detach().reshape(C * N, 2)
    con_f = proj.conics.detach().reshape(C * N, 3)
    op = opacities.detach()
    s_r = torch.zeros(C * N, dtype=dt, device=m_f.device)
    nu = torch.zeros_like(s_r)
    for tiles, K in tile_blocks(bins.counts, chunk_pairs):
        ids, slot_ok = gather_block(bins, tiles, K)
        op_b = torch.where(slot_ok, op[ids % N], torch.zeros_like(ids, dtype=dt))
        w = block_weights(m_f[ids], con_f[ids], op_b, tile_origins(tiles, TW, TH, dt))
        vis = (w.alpha * w.T).reshape(len(tiles), -1, K)  # exactly zero on padding slots
        s_r.index_add_(0, ids.flatten(), torch.bmm(r_t[tiles][:, None, :], vis).flatten())
        nu.index_add_(0, ids.flatten(), torch.bmm(in_t[tiles][:, None, :], vis).flatten())
    o = op[None, :].expand(C, N).reshape(-1)
    o_safe = torch.where(nu > 0, o, torch.ones_like(o))
    return (s_r / o_safe).reshape(C, N), (nu / o_safe).reshape(C, N), nu.reshape(C, N)


#: Pixels per side of a JPEG block (the block scores r_b are constant on these).
BLOCK = 8


@functools.cache
def _limits(width: int, height: int, nbx: int, nby: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """[2, 2]: per axis (x, y) the image size in pixels and the last block index. Once per image size and
    device: a host-to-device copy inside the backward would stall the GPU queue."""
    return torch.tensor([[width, nbx - 1], [height, nby - 1]], dtype=dtype, device=device)


@torch.no_grad()
def footprint_sums(
    r: Tensor, means2d: Tensor, conics: Tensor, opacities: Tensor, contributes: Tensor
) -> PooledSums:
    """The footprint estimate of the pooled sums (module docstring), [C, N] each.

    Args:
        r: [C, H, W] the block-score map (constant on 8 × 8 blocks; 0 on the rows and columns without one).
        means2d: [C, N, 2] projected means in pixels (pixel (i, j) has its centre at (j + 0.5, i + 0.5));
        conics: [C, N, 3] the inverse 2D covariances (a, b, c) the rasteriser used (its blur included).
        opacities: [C, N] the activated opacities the pass rendered with.
        contributes: [C, N] bool, the contributor set V_i (from the backward: the conic's gradient is
            non-zero).

    Per axis, the footprint's marginal is a normal (its mean, σ² = Σ_xx or Σ_yy); its mass in each of the
    blocks -1, 0, +1 from the mean's is a difference of its CDF at the blocks' edges clipped to the image
    (a block outside the image gets exactly 0, the partial last block its part), and the 3 × 3 weights are
    the products of the two axes' masses. Returns S_1 = 2π·sqrt(det Σ) (the footprint's unclipped mass, > 0
    on contributors), S_r = r̃·S_1 with r̃ = Σ_b w_b r_b / Σ_b w_b (0 where no block of the 3 × 3 lies in
    the image), and ν = o·S_1; all 0 off V_i. About 40 elementwise kernels, no host synchronisation.
    """
    C, H, W = r.shape
    N = means2d.shape[1]
    dt = means2d.dtype
    rb = r.detach().to(dt)[:, ::BLOCK, ::BLOCK]  # [C, nby, nbx]: one value per (possibly partial) block
    nby, nbx = rb.shape[1:]
    lim = _limits(W, H, nbx, nby, dt, r.device)
    on = contributes.reshape(-1, 1)
    a, b, c = conics.detach().reshape(-1, 3).unbind(-1)
    det = a * c - b * b  # det(Σ⁻¹) > 0 on contributors
    # σ·√2 per axis (Σ_xx = c / det, Σ_yy = a / det); off V_i a finite footprint at the origin (culled
    # Gaussians may carry zero or non-finite conics), masked out at the end
    s2 = torch.where(on, torch.stack([c, a], dim=-1) / det[:, None], 0.5).sqrt_().mul_(math.sqrt(2.0))
    mu = torch.where(on, means2d.detach().reshape(-1, 2), 0.0)  # [M, 2]
    # per axis the blocks -1, 0, +1, +2 from the mean's (their left edges bound the three blocks): [M, 2, 4]
    cells = torch.floor(mu / BLOCK)[..., None] + torch.arange(-1, 3, dtype=dt, device=r.device)
    edges = torch.minimum((cells * BLOCK).clamp_min_(0.0), lim[:, :1])  # clipped to [0, size]
    cdf = torch.erf((edges - mu[..., None]) / s2[..., None])  # 2·CDF − 1
    frac = (cdf[..., 1:] - cdf[..., :-1]).mul_(0.5)  # [M, 2, 3]
    w = frac[:, 1, :, None] * frac[:, 0, None, :]  # [M, 3, 3] (rows, columns)
    # each block's score; indices clamped into the grid (a block outside the image has weight 0)
    idx = torch.minimum(cells[..., :3].clamp_min(0.0), lim[:, 1:])
    flat = idx[:, 1, :, None] * nbx + idx[:, 0, None, :]  # [M, 3, 3]
    if C > 1:
        cam = torch.arange(C, dtype=dt, device=r.device)[:, None].expand(C, N).reshape(-1)
        flat = flat + (cam * (nby * nbx))[:, None, None]
    scores = rb.reshape(-1)[flat.long()]
    mass = w.sum(dim=(1, 2))
    r_tilde = (w * scores).sum(dim=(1, 2)) / mass.clamp_min(torch.finfo(dt).tiny)
    on = on[:, 0]
    s_1 = torch.where(on, (2.0 * math.pi) * det.rsqrt(), 0.0).reshape(C, N)
    return PooledSums(s_r=r_tilde.reshape(C, N) * s_1, s_1=s_1, nu=opacities.detach().to(dt) * s_1)


def probe_grad_from_sums(sums: PooledSums, opacities: Tensor, weight: float = 1.0) -> Tensor:
    """The probe gradient [C, N, 2] = weight·(o·S_r, ν) that ``sums`` stand for (the inverse of
    :func:`jsgs.kernels.sums_from_probe_grad`), ``opacities`` [C, N] the activated o the pass rendered with:
    it feeds the controller (:func:`jsgs.kernels.fro_from_probe_grad` and its fused and graphed twins) as the
    probe's gradient would."""
    o = opacities.detach().to(sums.s_r.dtype)
    return torch.stack([o * sums.s_r, sums.nu], dim=-1) * weight
