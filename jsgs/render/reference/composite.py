"""Front-to-back compositing of binned Gaussians with gsplat's per-pixel rules (``RasterizeToPixels3DGS
{Fwd,Bwd}.cu``): one autograd Function per block of tiles with an analytic backward.

Blocks are at most ``CHUNK_PAIRS`` pixel×slot pairs; the forward keeps α and T for the backward up to
``SAVE_PAIRS`` pairs per call and beyond that recomputes them in backward. ``tile_blocks``,
``gather_block``, ``block_weights``, ``tile_origins`` and ``image_to_tiles`` are the block machinery, public
for callers that evaluate the compositing weights directly.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from .projection import ALPHA_THRESHOLD, Projected
from .tiles import TILE_SIZE, TileBins

ALPHA_MAX = 0.999  # gsplat 1.5.3 clamps α at 0.999 (the Inria rasterizer used 0.99)
T_STOP = 1e-4  # a pixel is done before the Gaussian that would bring T to <= this
# Pixel×Gaussian pairs evaluated at once (per chunk of tiles): bounds the transient memory of the
# forward and backward passes (~10 tensors of this many elements live at a time).
CHUNK_PAIRS = 1 << 20
# Up to this many pixel×slot pairs per call, the forward keeps α, T and a mask (9 bytes a pair) for the
# backward; beyond, the blocks recompute them in backward (bounded memory on large scenes).
SAVE_PAIRS = 1 << 26


def tile_origins(tiles: Tensor, tw: int, th: int, dtype: torch.dtype) -> Tensor:
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


def block_weights(m: Tensor, con: Tensor, op: Tensor, origin: Tensor) -> _Weights:
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
        w = block_weights(m, con, op, origin)
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
        w = _Weights(*saved) if saved else block_weights(m, con, op, origin)
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


def tile_blocks(counts: Tensor, budget: int) -> list[tuple[Tensor, int]]:
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


def gather_block(bins: TileBins, tiles: Tensor, K: int) -> tuple[Tensor, Tensor]:
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


def image_to_tiles(img: Tensor, th: int, tw: int) -> Tensor:
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
    for tiles, K in tile_blocks(bins.counts, chunk_pairs):
        ids, slot_ok = gather_block(bins, tiles, K)
        cam = ids // N
        sink = None
        if absgrad_sink is not None:
            sink = _make_sink(absgrad_sink, ids, slot_ok)
        op = torch.where(slot_ok, opacities[ids % N], torch.zeros_like(ids, dtype=opacities.dtype))
        origin = tile_origins(tiles, TW, TH, m_f.dtype)
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
