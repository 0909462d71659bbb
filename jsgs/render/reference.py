"""Pure-torch reference rasterizer following gsplat 1.5.3's conventions (pinhole, classic, non-packed).

Runs on any device in float32 or float64 and is differentiable. The stages mirror gsplat's CUDA kernels
(``ProjectionEWA3DGSFused.cu``, ``IntersectTile.cu``, ``RasterizeToPixels3DGS{Fwd,Bwd}.cu``) rule for rule:

* projection: EWA, ``cov2d = J W Σ Wᵀ Jᵀ`` where J is evaluated at the camera-space mean with x/z and y/z
  clamped to the field of view widened by 30 % on each side; ``eps2d`` (0.3 px²) added to the diagonal;
  culling when z is outside [near, far], when det(cov2d) <= 0, when the opacity is below 1/255, when both
  radii are <= ``radius_clip`` and when the bounding box lies off-screen;
* radii: gsplat 1.5.3's opacity-aware axis-aligned box, ``r_x = ceil(e·sqrt(cov2d_xx))`` and
  ``r_y = ceil(e·sqrt(cov2d_yy))`` with ``e = min(3.33, sqrt(2·ln(255·opacity)))``, stored as [C, N, 2] int32;
* tiles: 16x16; a Gaussian is binned to the tiles its box overlaps, sorted front to back by camera depth
  (ties by Gaussian index, as gsplat's stable radix sort);
* compositing per pixel (centre at +0.5): ``σ = ½ dᵀ conic d`` with ``d = mean2d − pixel``;
  ``α = min(0.999, o·exp(−σ))``; a Gaussian is skipped where ``α < 1/255`` (and where σ < 0, which our
  completed-square form of σ never produces); the pixel stops *before* the first Gaussian whose
  ``T·(1 − α) <= 1e-4`` (exclusive); output ``Σ α T c + T_final·bg`` and alpha ``1 − T_final``;
* gradients: as gsplat's backward kernel — none through the 0.999 clamp (where α == 0.999) nor through
  skipped or stopped Gaussians; ``means2d`` is a real node of the graph, so ``retain_grad()`` gives the
  pixel-unit gradient that DefaultStrategy reads.

The compositing of a block of tiles is one autograd Function with an analytic backward (gsplat's
derivatives, vectorised over pixels and depth slots). Blocks are at most ``CHUNK_PAIRS`` pixel×slot pairs;
the forward keeps α and T for the backward up to ``SAVE_PAIRS`` pairs per call and beyond that recomputes
them in backward, so memory stays bounded however large the scene.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

TILE_SIZE = 16
ALPHA_THRESHOLD = 1.0 / 255.0  # gsplat's ALPHA_THRESHOLD: skip and cull below this
ALPHA_MAX = 0.999  # gsplat 1.5.3 clamps α at 0.999 (the Inria rasterizer used 0.99)
T_STOP = 1e-4  # a pixel is done before the Gaussian that would bring T to <= this
EXTEND_MAX = 3.33  # cap of the opacity-aware box extent, in standard deviations
FOV_MARGIN = 0.3  # J is evaluated with x/z, y/z clamped to the FOV widened by this fraction of tan(fov)
# Pixel×Gaussian pairs evaluated at once (per chunk of tiles): bounds the transient memory of the
# forward and backward passes (~10 tensors of this many elements live at a time).
CHUNK_PAIRS = 1 << 20
# Up to this many pixel×slot pairs per call, the forward keeps α, T and a mask (9 bytes a pair) for the
# backward; beyond, the blocks recompute them in backward (bounded memory on large scenes).
SAVE_PAIRS = 1 << 26


@dataclass
class Projected:
    """Screen-space Gaussians for C cameras (all tensors [C, N, ...]).

    ``means2d`` are pixels (x right, y down, pixel (i, j) has its centre at (j + 0.5, i + 0.5));
    ``covars2d`` is J W Σ Wᵀ Jᵀ before the ``eps2d`` dilation, in px²; ``conics`` the upper triangle
    (xx, xy, yy) of the inverse of the dilated covariance; ``jacobians`` the 2x3 J used (with gsplat's FOV
    clamp); ``depths`` camera z. Entries of culled Gaussians (``radii == 0``) are finite but meaningless.
    """

    radii: Tensor  # [C, N, 2] int32
    means2d: Tensor  # [C, N, 2]
    depths: Tensor  # [C, N]
    conics: Tensor  # [C, N, 3]
    covars2d: Tensor  # [C, N, 2, 2]
    jacobians: Tensor  # [C, N, 2, 3]
    means_cam: Tensor  # [C, N, 3]

    @property
    def visible(self) -> Tensor:
        """[C, N] bool: the Gaussian survived culling in this camera (gsplat: ``(radii > 0).all(-1)``)."""
        return (self.radii > 0).all(dim=-1)


def _rotmat_quadratic_np() -> np.ndarray:
    """[16, 9]: R(q) = vec(q qᵀ) @ C for a unit quaternion (w, x, y, z), row-major R; each entry of R is a
    quadratic form in q, with 1 written as w² + x² + y² + z²."""
    c = np.zeros((4, 4, 9))
    w, x, y, z = range(4)

    def put(k: int, terms: list[tuple[float, int, int]]) -> None:
        for coef, a, b in terms:
            c[a, b, k] += coef

    put(0, [(1, w, w), (1, x, x), (-1, y, y), (-1, z, z)])
    put(1, [(2, x, y), (-2, w, z)])
    put(2, [(2, x, z), (2, w, y)])
    put(3, [(2, x, y), (2, w, z)])
    put(4, [(1, w, w), (-1, x, x), (1, y, y), (-1, z, z)])
    put(5, [(2, y, z), (-2, w, x)])
    put(6, [(2, x, z), (-2, w, y)])
    put(7, [(2, y, z), (2, w, x)])
    put(8, [(1, w, w), (-1, x, x), (-1, y, y), (1, z, z)])
    return c.reshape(16, 9)


@cache
def _rotmat_quadratic(dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.as_tensor(_rotmat_quadratic_np(), dtype=dtype, device=device)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] from quaternions [..., 4] in (w, x, y, z) order, normalised first.

    The usual ``1 - 2 (y² + z²)``-style entries, written as quadratic forms of the unit quaternion so that the
    whole map is one outer product and one matrix product (5 kernels instead of ~35: it runs every step on
    every Gaussian, and on a GPU each small kernel costs more than its arithmetic)."""
    q = quats / torch.linalg.vector_norm(quats, dim=-1, keepdim=True)
    qq = (q[..., :, None] * q[..., None, :]).reshape(*q.shape[:-1], 16)
    return (qq @ _rotmat_quadratic(q.dtype, q.device)).reshape(*q.shape[:-1], 3, 3)


def covariance_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """World covariances Σ = R diag(s)² Rᵀ [N, 3, 3] from quaternions [N, 4] and activated scales [N, 3]."""
    m = quat_to_rotmat(quats) * scales[..., None, :]
    return m @ m.transpose(-1, -2)


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
) -> Projected:
    """Project N Gaussians into C pinhole cameras exactly as gsplat's fused EWA projection.

    Args: means [N, 3] world; quats [N, 4] wxyz (any norm); scales [N, 3] activated, world units;
    opacities [N] in [0, 1] (only used for culling and the box extent, as gsplat does); viewmats [C, 4, 4]
    world-to-camera (OpenCV axes); Ks [C, 3, 3]; width/height in pixels.
    """
    C = viewmats.shape[0]
    Rw = viewmats[:, :3, :3]
    tw = viewmats[:, :3, 3]
    means_c = torch.einsum("cij,nj->cni", Rw, means) + tw[:, None, :]
    cov_c = torch.einsum("cij,njk,clk->cnil", Rw, covariance_3d(quats, scales), Rw)

    x, y, z_raw = means_c.unbind(-1)
    in_depth = (z_raw >= near_plane) & (z_raw <= far_plane)
    # Culled entries still flow through autograd (with zero upstream gradient); a safe z keeps them finite
    # so that 0 · inf never turns into NaN in the backward pass.
    z = torch.where(in_depth, z_raw, torch.ones_like(z_raw))
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + FOV_MARGIN * tan_fovx
    lim_x_neg = cx / fx + FOV_MARGIN * tan_fovx
    lim_y_pos = (height - cy) / fy + FOV_MARGIN * tan_fovy
    lim_y_neg = cy / fy + FOV_MARGIN * tan_fovy
    tx = z * torch.clamp(x / z, min=-lim_x_neg, max=lim_x_pos)
    ty = z * torch.clamp(y / z, min=-lim_y_neg, max=lim_y_pos)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * tx / (z * z), zero, fy / z, -fy * ty / (z * z)], dim=-1).reshape(
        C, -1, 2, 3
    )
    cov2d = J @ cov_c @ J.transpose(-1, -2)
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1)

    a = cov2d[..., 0, 0] + eps2d
    b = 0.5 * (cov2d[..., 0, 1] + cov2d[..., 1, 0])
    d = cov2d[..., 1, 1] + eps2d
    det = a * d - b * b
    ok_det = det > 0
    det_safe = torch.where(ok_det, det, torch.ones_like(det))
    conics = torch.stack([d / det_safe, -b / det_safe, a / det_safe], dim=-1)

    with torch.no_grad():
        op = opacities.detach()[None, :].expand_as(a)
        ok_op = op >= ALPHA_THRESHOLD
        extend = torch.sqrt(2.0 * torch.log(op.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD))
        extend = extend.clamp(max=EXTEND_MAX)
        rx = torch.ceil(extend * torch.sqrt(a.detach().clamp_min(0)))
        ry = torch.ceil(extend * torch.sqrt(d.detach().clamp_min(0)))
        too_small = (rx <= radius_clip) & (ry <= radius_clip)
        mx, my = means2d.detach().unbind(-1)
        off = (mx + rx <= 0) | (mx - rx >= width) | (my + ry <= 0) | (my - ry >= height)
        keep = in_depth & ok_det & ok_op & ~too_small & ~off
        radii = torch.where(keep[..., None], torch.stack([rx, ry], -1), torch.zeros_like(means2d))
        radii = radii.to(torch.int32)
    return Projected(radii, means2d, z_raw, conics, cov2d, J, means_c)


# --------------------------------------------------------------------------------------------------------
# Spherical harmonics (gsplat's real SH basis and sign convention, degrees 0..4)


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Real SH basis [..., (degree+1)²] at directions [..., 3] (normalised here), gsplat's order and signs."""
    if not 0 <= degree <= 4:
        raise ValueError(f"sh degree must be in 0..4, got {degree}")
    out = [torch.full_like(dirs[..., 0], 0.28209479177387814)]
    if degree >= 1:
        n = dirs.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(dirs.dtype).tiny)
        x, y, z = (dirs / n).unbind(-1)
        k1 = 0.48860251190291992
        out += [-k1 * y, k1 * z, -k1 * x]
    if degree >= 2:
        xy, z2 = x * y, z * z
        c1 = x * x - y * y
        s1 = 2 * xy
        k2a, k2b, k2c = 1.0925484305920792, 0.31539156525252005, 0.54627421529603959
        b6 = k2b * (3 * z2 - 1)
        out += [k2c * s1, -k2a * y * z, b6, -k2a * x * z, k2c * c1]
    if degree >= 3:
        c2 = x * c1 - y * s1  # cos(3φ)·sin³θ
        s2 = x * s1 + y * c1  # sin(3φ)·sin³θ
        k3a, k3b, k3c, k3d = 0.59004358992664352, 1.4453057213202771, 0.45704579946446572, 0.37317633259011546
        b12 = k3d * z * (5 * z2 - 3)
        p3 = -k3c * (5 * z2 - 1)
        out += [-k3a * s2, k3b * z * s1, p3 * y, b12, p3 * x, k3b * z * c1, -k3a * c2]
    if degree >= 4:
        c3 = x * c2 - y * s2
        s3 = x * s2 + y * c2
        k4a, k4b = 0.62583573544917614, 1.7701307697799304
        p41 = 3.3116114351514601 * z2 - 0.47308734787878002
        p43 = z * (2.0071396306718676 - 4.6833258049010249 * z2)
        b20 = 1.9843134832984430 * z * b12 - 1.0062305898749053 * b6
        out += [k4a * s3, -k4b * z * s2, p41 * s1, p43 * y, b20, p43 * x, p41 * c1, -k4b * z * c2, k4a * c3]
    return torch.stack(out, dim=-1)


def spherical_harmonics(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Colour [..., 3] = Σ_k basis_k(dirs) · coeffs[..., k, :] over the first (degree+1)² coefficients.

    Same as gsplat's ``spherical_harmonics`` (without the +0.5 offset that ``rasterization`` adds).
    """
    nb = (degree + 1) ** 2
    if coeffs.shape[-2] < nb:
        raise ValueError(f"sh degree {degree} needs {nb} coefficients, got {coeffs.shape[-2]}")
    return (sh_basis(degree, dirs)[..., None] * coeffs[..., :nb, :]).sum(dim=-2)


def sh_colors(means: Tensor, coeffs: Tensor, viewmats: Tensor, degree: int) -> Tensor:
    """Per-camera RGB [C, N, 3] from SH coefficients ([N, K, 3] or [C, N, K, 3]) as gsplat's rasterization:
    directions from the camera centre to the means, ``clamp_min(sh + 0.5, 0)``."""
    campos = torch.inverse(viewmats)[:, :3, 3]
    dirs = means[None, :, :] - campos[:, None, :]
    if coeffs.dim() == 3:
        coeffs = coeffs[None].expand(viewmats.shape[0], -1, -1, -1)
    return torch.clamp_min(spherical_harmonics(degree, dirs, coeffs) + 0.5, 0.0)


# --------------------------------------------------------------------------------------------------------
# Tile binning


@dataclass
class TileBins:
    """Gaussian-tile intersections sorted by (camera, tile, depth), as gsplat's isect_tiles/offset_encode.

    Tiles are numbered globally: ``camera·TH·TW + ty·TW + tx``.
    """

    tile_width: int
    tile_height: int
    flatten_ids: Tensor  # [M] int64, index into C·N (camera-major)
    tile_ids: Tensor  # [M] int64
    offsets: Tensor  # [C·TH·TW] int64: first intersection of each tile
    counts: Tensor  # [C·TH·TW] int64
    tiles_per_gauss: Tensor  # [C, N] int32


def bin_tiles(means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int) -> TileBins:
    """Bin projected Gaussians ([C, N, 2] means, [C, N, 2] int radii, [C, N] depths) into 16x16 tiles."""
    C, N = depths.shape
    dev = depths.device
    TW, TH = math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)
    with torch.no_grad():
        m = means2d.detach().reshape(-1, 2)
        r = radii.reshape(-1, 2).to(m.dtype)
        vis = (radii.reshape(-1, 2) > 0).all(-1)
        # gsplat: tile range [floor(m/ts − r/ts), ceil(m/ts + r/ts)) clamped to the grid
        lo = torch.floor(m / TILE_SIZE - r / TILE_SIZE)
        hi = torch.ceil(m / TILE_SIZE + r / TILE_SIZE)
        lim = torch.tensor([TW, TH], device=dev, dtype=m.dtype)
        lo = torch.minimum(lo.clamp_min(0), lim).long()
        hi = torch.minimum(hi.clamp_min(0), lim).long()
        span = (hi - lo).clamp_min(0)
        n_tiles = span[:, 0] * span[:, 1] * vis
        total = int(n_tiles.sum())
        flat = torch.repeat_interleave(torch.arange(C * N, device=dev), n_tiles)
        first = torch.cumsum(n_tiles, 0) - n_tiles
        local = torch.arange(total, device=dev) - first[flat]
        sx = span[flat, 0]
        tx = lo[flat, 0] + local % sx.clamp_min(1)
        ty = lo[flat, 1] + local // sx.clamp_min(1)
        cam = flat // N
        tile = cam * (TH * TW) + ty * TW + tx
        # (camera, tile) major, depth minor, ties by flat index: two stable sorts
        order = torch.argsort(depths.detach().reshape(-1)[flat], stable=True)
        order = order[torch.argsort(tile[order], stable=True)]
        flat, tile = flat[order], tile[order]
        counts = torch.bincount(tile, minlength=C * TH * TW)
        offsets = torch.cumsum(counts, 0) - counts
    return TileBins(TW, TH, flat, tile, offsets, counts, n_tiles.reshape(C, N).to(torch.int32))


# --------------------------------------------------------------------------------------------------------
# Compositing of a block of tiles


def _tile_origins(tiles: Tensor, tw: int, th: int, dtype: torch.dtype) -> Tensor:
    """Centre of the top-left pixel [B, 2] (x, y) of global tile ids [B]."""
    local = tiles % (tw * th)
    ty, tx = local // tw, local % tw
    return torch.stack([tx, ty], dim=-1).to(dtype) * TILE_SIZE + 0.5


@dataclass
class _Weights:
    """Compositing state of one block, [B, 16 (y), 16 (x), K] per (tile, pixel row, pixel column, slot)."""

    alpha: Tensor  # α as composited: 0 where skipped or after the stop (0.999 where clamped)
    T: Tensor  # transmittance in front of the slot (a view)
    T_final: Tensor  # [B, 16, 16]


def _offsets(m: Tensor, origin: Tensor) -> tuple[Tensor, Tensor]:
    """d = mean − pixel centre, separably: dx [B, 1, 16, K] (per column), dy [B, 16, 1, K] (per row)."""
    step = torch.arange(TILE_SIZE, device=m.device, dtype=m.dtype)
    dx = m[:, None, :, 0] - (origin[:, 0, None] + step)[:, :, None]  # [B, 16, K]
    dy = m[:, None, :, 1] - (origin[:, 1, None] + step)[:, :, None]
    return dx[:, None], dy[:, :, None]


def _below(x: float, dtype: torch.dtype) -> float:
    """The largest value of ``dtype`` below x (so that ``v > _below(x)`` ⇔ ``v >= x`` in that dtype)."""
    t = torch.tensor(x, dtype=dtype)
    return torch.nextafter(t, torch.zeros_like(t)).item()


def _weights(m: Tensor, con: Tensor, op: Tensor, origin: Tensor) -> _Weights:
    """gsplat's per-pixel rules for a block: m [B,K,2], con [B,K,3], op [B,K] (0 on padding slots, which
    then never pass the α threshold), origin [B,2].

    Written for speed on CPU: big [B,16,16,K] tensors are only touched by plain arithmetic, masks are
    avoided (``threshold`` and ``ceil`` do their work), and per-row/per-column factors are formed on the
    small [B,16,K] grids first.
    """
    dx, dy = _offsets(m, origin)
    c0, c1, c2 = (c[:, None, None, :] for c in con.unbind(-1))
    # σ = ½dᵀ·conic·d completed to a square, (a·dx + b·dy)² + e·dy² with e = det(conic)/(2·c0) >= 0, is
    # non-negative by construction: gsplat's "skip where σ < 0" (a rounding artefact of the expanded
    # form) cannot occur.
    a = torch.sqrt(0.5 * c0)
    b = c1 / (2.0 * a)
    e = (0.5 * (c2 - c1 * c1 / c0)).clamp_min(0.0)
    v = torch.add(a * dx, b * dy)
    oa = torch.exp(torch.sub(-e * dy * dy, v * v)).mul_(op[:, None, None, :])
    alpha = F.threshold(oa.clamp_(max=ALPHA_MAX), _below(ALPHA_THRESHOLD, oa.dtype), 0.0)
    # The skipped slots have factor 1, so the running product is gsplat's T after each slot; it only
    # decreases, hence the slots before the stop are exactly those whose T_after is still > T_STOP.
    K = alpha.shape[-1]
    buf = torch.empty(alpha.shape[:-1] + (K + 1,), dtype=alpha.dtype, device=alpha.device)
    buf[..., 0] = 1.0
    torch.add(torch.ones((), dtype=alpha.dtype, device=alpha.device), alpha, alpha=-1, out=buf[..., 1:])
    cp = torch.cumprod(buf, dim=-1)  # [1, T_after...]
    alive = torch.ceil(cp[..., 1:] - T_STOP)  # 1 while T_after > T_STOP, else 0 (T_after <= 1)
    alpha.mul_(alive)
    # final transmittance: the last T_after still alive (1 when none is)
    T_final = torch.amin(cp[..., 1:] + (1.0 - alive), dim=-1).clamp_(max=1.0)
    return _Weights(alpha, cp[..., :-1], T_final)


class _CompositeBlock(torch.autograd.Function):
    """Front-to-back compositing of one block of tiles with gsplat's rules; analytic backward."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx,
        m: Tensor,  # [B, K, 2]
        con: Tensor,  # [B, K, 3]
        op: Tensor,  # [B, K]
        col: Tensor,  # [B, K, D]
        bg: Tensor,  # [B, D]
        origin: Tensor,  # [B, 2]
        save: bool,
        absgrad_sink: Callable[[Tensor], None] | None,
    ) -> tuple[Tensor, Tensor]:
        w = _weights(m, con, op, origin)
        B, K = op.shape
        vis = (w.alpha * w.T).reshape(B, -1, K)
        out = torch.baddbmm(w.T_final.reshape(B, -1, 1) * bg[:, None, :], vis, col)
        if save:  # time over memory: B·256·(2K+1)·4 bytes
            ctx.save_for_backward(m, con, op, col, bg, origin, w.alpha, w.T, w.T_final)
        else:  # memory over time: recomputed in backward
            ctx.save_for_backward(m, con, op, col, bg, origin)
        ctx.absgrad_sink = absgrad_sink
        return out, w.T_final.reshape(B, -1)

    @staticmethod
    def backward(ctx, g_out: Tensor, g_T_final: Tensor):  # type: ignore[override]
        m, con, op, col, bg, origin, *saved = ctx.saved_tensors
        w = _Weights(*saved) if saved else _weights(m, con, op, origin)
        B, K = op.shape
        shape = w.alpha.shape
        vis = w.alpha * w.T
        g_col = torch.bmm(vis.reshape(B, -1, K).transpose(1, 2), g_out)
        g_bg = (w.T_final.reshape(B, -1, 1) * g_out).sum(dim=1)
        # With G_k = c_k·g_out: dL/dα_k = T_k·G_k − (Σ_{j>k} α_j T_j G_j + T_final·(bg·g_out + g_T))/(1 − α_k)
        # for the contributing slots (T_final = Π(1 − α) over them). P = α·dL/dα is what the chain needs.
        G = torch.bmm(g_out, col.transpose(1, 2)).reshape(shape)
        wG = vis.mul_(G)
        behind = wG.sum(dim=-1, keepdim=True) - torch.cumsum(wG, dim=-1)
        Tf = w.T_final
        tail = Tf * ((g_out * bg[:, None, :]).sum(-1) + g_T_final).reshape(Tf.shape)
        odds = w.alpha / (1.0 - w.alpha)
        P = wG.sub_(behind.add_(tail[..., None]).mul_(odds))
        # α = o·exp(−σ) passes gradients only where it was not clamped at 0.999 (rare: mask only then)
        clamped = w.alpha >= ALPHA_MAX
        if bool(clamped.any()):
            P = P.masked_fill_(clamped, 0.0)
        dx, dy = _offsets(m, origin)
        dx, dy = dx[:, 0], dy[:, :, 0]  # [B, 16 (x), K], [B, 16 (y), K]
        col_sum = P.sum(dim=1)  # Σ over rows → per column [B, 16, K]
        row_sum = P.sum(dim=2)  # per row [B, 16, K]
        g_op = col_sum.sum(1) / torch.where(op > 0, op, torch.ones_like(op))  # Σ_p g_α·exp(−σ)
        # g_σ = −P; with d = (dx per column, dy per row):
        # ∂L/∂m = Σ_p g_σ·(conic·d), ∂L/∂conic = Σ_p g_σ·(½dx², dx·dy, ½dy²)
        sx = (col_sum * dx).sum(1)
        sy = (row_sum * dy).sum(1)
        sxx = (col_sum * dx * dx).sum(1)
        syy = (row_sum * dy * dy).sum(1)
        sxy = ((P * dx[:, None]).sum(2) * dy).sum(1)
        c0, c1, c2 = con.unbind(-1)
        g_m = -torch.stack([c0 * sx + c1 * sy, c1 * sx + c2 * sy], dim=-1)
        g_con = -torch.stack([0.5 * sxx, sxy, 0.5 * syy], dim=-1)
        if ctx.absgrad_sink is not None:
            cc0, cc1, cc2 = (c[:, None, None, :] for c in (c0, c1, c2))
            ax = (P * (cc0 * dx[:, None] + cc1 * dy[:, :, None])).abs().sum(dim=(1, 2))
            ay = (P * (cc1 * dx[:, None] + cc2 * dy[:, :, None])).abs().sum(dim=(1, 2))
            ctx.absgrad_sink(torch.stack([ax, ay], dim=-1))
        return g_m, g_con, g_op, g_col, g_bg, None, None, None


def _blocks(counts: Tensor, budget: int) -> list[tuple[Tensor, int]]:
    """Non-empty tiles grouped by depth complexity: blocks (tile ids [B], K) with B·256·K <= budget."""
    nz = torch.nonzero(counts > 0).flatten()
    if nz.numel() == 0:
        return []
    c = counts[nz]
    order = torch.argsort(c, descending=True, stable=True)
    nz, c = nz[order], c[order].tolist()
    out, i = [], 0
    while i < len(c):
        k = c[i]
        n = max(1, budget // (TILE_SIZE * TILE_SIZE * k))
        out.append((nz[i : i + n], k))
        i += n
    return out


def _gather_block(bins: TileBins, tiles: Tensor, K: int) -> tuple[Tensor, Tensor]:
    """Depth-ordered flat Gaussian ids [B, K] of the given tiles (padded with 0) and the slot mask."""
    k = torch.arange(K, device=tiles.device)
    slot_ok = k[None, :] < bins.counts[tiles][:, None]
    pos = torch.where(slot_ok, bins.offsets[tiles][:, None] + k[None, :], torch.zeros_like(k[None, :]))
    return bins.flatten_ids[pos], slot_ok


def _tiles_to_image(tiles: Tensor, C: int, th: int, tw: int, height: int, width: int) -> Tensor:
    """[C·TH·TW, 256, D] per-tile pixels → [C, H, W, D] image."""
    D = tiles.shape[-1]
    img = tiles.reshape(C, th, tw, TILE_SIZE, TILE_SIZE, D).permute(0, 1, 3, 2, 4, 5)
    return img.reshape(C, th * TILE_SIZE, tw * TILE_SIZE, D)[:, :height, :width]


def _image_to_tiles(img: Tensor, th: int, tw: int) -> Tensor:
    """[C, H, W] map → [C·TH·TW, 256] per-tile pixels (zero outside the image)."""
    C, H, W = img.shape
    pad = img.new_zeros(C, th * TILE_SIZE, tw * TILE_SIZE)
    pad[:, :H, :W] = img
    return pad.reshape(C, th, TILE_SIZE, tw, TILE_SIZE).permute(0, 1, 3, 2, 4).reshape(-1, TILE_SIZE**2)


def composite(
    proj: Projected,
    bins: TileBins,
    opacities: Tensor,
    colors: Tensor,
    backgrounds: Tensor,
    width: int,
    height: int,
    *,
    absgrad_sink: Tensor | None = None,
    chunk_pairs: int = CHUNK_PAIRS,
    save_pairs: int = SAVE_PAIRS,
) -> tuple[Tensor, Tensor]:
    """Rasterise binned Gaussians. colors [C, N, D] (may be an expanded view), opacities [N],
    backgrounds [C, D]. Returns colours [C, H, W, D] and alphas [C, H, W, 1]. ``absgrad_sink`` ([C·N, 2],
    optional) receives Σ_pixels |∂L/∂means2d| during backward, as gsplat's ``absgrad``. Blocks of at most
    ``chunk_pairs`` pixel×slot pairs; the first ``save_pairs`` pairs keep their forward state for backward."""
    C, N = proj.depths.shape
    D = colors.shape[-1]
    TH, TW = bins.tile_height, bins.tile_width
    n_tiles = C * TH * TW
    P = TILE_SIZE * TILE_SIZE
    m_f = proj.means2d.reshape(C * N, 2)
    con_f = proj.conics.reshape(C * N, 3)
    cam_of_tile = torch.arange(n_tiles, device=m_f.device) // (TH * TW)
    outs, Ts, done = [], [], []
    saved = 0
    for tiles, K in _blocks(bins.counts, chunk_pairs):
        ids, slot_ok = _gather_block(bins, tiles, K)
        cam = ids // N
        sink = None
        if absgrad_sink is not None:
            sink = _make_sink(absgrad_sink, ids, slot_ok)
        op = torch.where(slot_ok, opacities[ids % N], torch.zeros_like(ids, dtype=opacities.dtype))
        origin = _tile_origins(tiles, TW, TH, m_f.dtype)
        save = saved + ids.numel() * P <= save_pairs
        saved += ids.numel() * P if save else 0
        out, T = _CompositeBlock.apply(
            m_f[ids],
            con_f[ids],
            op,
            colors[cam, ids % N],
            backgrounds[cam_of_tile[tiles]],
            origin,
            save,
            sink,
        )
        outs.append(out)
        Ts.append(T)
        done.append(tiles)
    empty = torch.nonzero(bins.counts == 0).flatten()
    if empty.numel():
        outs.append(backgrounds[cam_of_tile[empty]][:, None, :].expand(-1, P, D))
        Ts.append(torch.ones(empty.numel(), P, device=m_f.device, dtype=m_f.dtype))
        done.append(empty)
    order = torch.argsort(torch.cat(done))
    tiles_rgb = torch.cat(outs)[order]
    tiles_T = torch.cat(Ts)[order]
    img = _tiles_to_image(tiles_rgb, C, TH, TW, height, width)
    alpha = 1.0 - _tiles_to_image(tiles_T[..., None], C, TH, TW, height, width)
    return img, alpha


def _make_sink(buf: Tensor, ids: Tensor, slot_ok: Tensor) -> Callable[[Tensor], None]:
    def sink(g: Tensor) -> None:
        buf.index_add_(0, ids[slot_ok], g[slot_ok].to(buf.dtype))

    return sink


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
    r_t = _image_to_tiles(r.detach().to(dt), TH, TW)
    in_t = _image_to_tiles(torch.ones(C, height, width, dtype=dt, device=r.device), TH, TW)
    m_f = proj.means2d.detach().reshape(C * N, 2)
    con_f = proj.conics.detach().reshape(C * N, 3)
    op = opacities.detach()
    s_r = torch.zeros(C * N, dtype=dt, device=m_f.device)
    nu = torch.zeros_like(s_r)
    for tiles, K in _blocks(bins.counts, chunk_pairs):
        ids, slot_ok = _gather_block(bins, tiles, K)
        op_b = torch.where(slot_ok, op[ids % N], torch.zeros_like(ids, dtype=dt))
        w = _weights(m_f[ids], con_f[ids], op_b, _tile_origins(tiles, TW, TH, dt))
        vis = (w.alpha * w.T).reshape(len(tiles), -1, K)  # exactly zero on padding slots
        s_r.index_add_(0, ids.flatten(), torch.bmm(r_t[tiles][:, None, :], vis).flatten())
        nu.index_add_(0, ids.flatten(), torch.bmm(in_t[tiles][:, None, :], vis).flatten())
    o = op[None, :].expand(C, N).reshape(-1)
    o_safe = torch.where(nu > 0, o, torch.ones_like(o))
    return (s_r / o_safe).reshape(C, N), (nu / o_safe).reshape(C, N), nu.reshape(C, N)


# --------------------------------------------------------------------------------------------------------
# The whole pipeline


def prepare_colors(means: Tensor, colors: Tensor, viewmats: Tensor, sh_degree: int | None) -> Tensor:
    """Colour features [C, N, D] (possibly an expanded view) from post-activation colours [N, D] / [C, N, D]
    or, with ``sh_degree``, SH coefficients [N, K, 3] / [C, N, K, 3] (gsplat's +0.5 and clamp at 0)."""
    C = viewmats.shape[0]
    if sh_degree is not None:
        return sh_colors(means, colors, viewmats, sh_degree)
    if colors.dim() == 2:
        return colors[None].expand(C, -1, -1)
    return colors


def rasterize_torch(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    sh_degree: int | None = None,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    backgrounds: Tensor | None = None,
    eps2d: float = 0.3,
    radius_clip: float = 0.0,
    absgrad: bool = False,
    render_mode: str = "RGB",
    extra_channels: Tensor | None = None,
    chunk_pairs: int = CHUNK_PAIRS,
    save_pairs: int = SAVE_PAIRS,
) -> tuple[Tensor, Tensor, dict]:
    """The reference rasterizer; see ``jsgs.render.rasterize`` for the arguments and outputs.

    ``extra_channels`` ([C, N, E], optional) are composited after the colour (and before the depth) channels
    and returned separately as ``info["extra"]`` [C, H, W, E] with a zero background.
    """
    C, N = viewmats.shape[0], means.shape[0]
    proj = project_gaussians(
        means, quats, scales, opacities, viewmats, Ks, width, height,
        eps2d=eps2d, near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip,
    )  # fmt: skip
    feats = [] if render_mode in ("D", "ED") else [prepare_colors(means, colors, viewmats, sh_degree)]
    bgs = []
    if feats:
        D = feats[0].shape[-1]
        bgs.append(backgrounds if backgrounds is not None else feats[0].new_zeros(C, D))
    E = 0
    if extra_channels is not None:
        E = extra_channels.shape[-1]
        feats.append(extra_channels.to(proj.means2d.dtype))
        bgs.append(proj.means2d.new_zeros(C, E))
    if render_mode != "RGB":
        feats.append(proj.depths[..., None])
        bgs.append(proj.means2d.new_zeros(C, 1))
    feats = [f.expand(C, N, -1) for f in feats]
    feat = feats[0] if len(feats) == 1 else torch.cat(feats, dim=-1)
    bg = bgs[0] if len(bgs) == 1 else torch.cat(bgs, dim=-1)

    bins = bin_tiles(proj.means2d, proj.radii, proj.depths, width, height)
    sink = None
    if absgrad:
        sink = torch.zeros(C * N, 2, dtype=proj.means2d.dtype, device=means.device)
    img, alpha = composite(
        proj,
        bins,
        opacities,
        feat,
        bg,
        width,
        height,
        absgrad_sink=sink,
        chunk_pairs=chunk_pairs,
        save_pairs=save_pairs,
    )
    extra = None
    if E:
        n_col = feat.shape[-1] - E - (0 if render_mode == "RGB" else 1)
        extra = img[..., n_col : n_col + E]
        img = torch.cat([img[..., :n_col], img[..., n_col + E :]], dim=-1)
    if render_mode in ("ED", "RGB+ED"):
        img = torch.cat([img[..., :-1], img[..., -1:] / alpha.clamp(min=1e-10)], dim=-1)

    means2d = proj.means2d
    if absgrad and means2d.requires_grad:
        # gsplat writes the attribute during backward; ours is filled in place by the same backward.
        means2d.absgrad = sink.view(C, N, 2)
    info = {
        "batch_ids": None,
        "camera_ids": None,
        "gaussian_ids": None,
        "radii": proj.radii,
        "means2d": means2d,
        "depths": proj.depths,
        "conics": proj.conics,
        "opacities": opacities[None, :].expand(C, N),
        "tile_width": bins.tile_width,
        "tile_height": bins.tile_height,
        "tiles_per_gauss": bins.tiles_per_gauss,
        "flatten_ids": bins.flatten_ids.to(torch.int32),
        "isect_offsets": bins.offsets.reshape(C, bins.tile_height, bins.tile_width).to(torch.int32),
        "width": width,
        "height": height,
        "tile_size": TILE_SIZE,
        "n_batches": 1,
        "n_cameras": C,
        "covars2d": proj.covars2d,
        "jacobians": proj.jacobians,
        "_projected": proj,
        "_bins": bins,
    }
    if extra is not None:
        info["extra"] = extra
    return img, alpha, info
