"""Tile binning (gsplat's ``isect_tiles`` / ``isect_offset_encode``): 16x16 tiles, Gaussians sorted front to
back per (camera, tile)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

TILE_SIZE = 16


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
