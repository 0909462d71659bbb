"""The whole reference pipeline: projection, colours, tile binning, compositing, gsplat's meta keys."""

from __future__ import annotations

import torch
from torch import Tensor

from .composite import CHUNK_PAIRS, SAVE_PAIRS, composite
from .projection import Projected, project_gaussians
from .sh import prepare_colors
from .tiles import TILE_SIZE, bin_tiles


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
    distortion: Tensor | None = None,
) -> tuple[Tensor, Tensor, dict]:
    """The reference rasterizer; see ``jsgs.render.rasterize`` for the arguments and outputs.

    ``extra_channels`` ([C, N, E], optional) are composited after the colour (and before the depth) channels
    and returned separately as ``info["extra"]`` [C, H, W, E] with a zero background.
    """
    C, N = viewmats.shape[0], means.shape[0]
    proj = project_gaussians(
        means, quats, scales, opacities, viewmats, Ks, width, height,
        eps2d=eps2d, near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip,
        distortion=distortion,
    )  # fmt: skip
    feat, bg = stack_features(
        proj, means, colors, viewmats, sh_degree, backgrounds, extra_channels, render_mode
    )

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
    img, extra = split_features(img, alpha, extra_channels, render_mode)

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


def stack_features(
    proj: Projected,
    means: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    sh_degree: int | None,
    backgrounds: Tensor | None,
    extra: Tensor | None,
    render_mode: str,
) -> tuple[Tensor, Tensor]:
    """The channels composited in one pass and their backgrounds: colours (unless ``render_mode`` is depth
    only; background ``backgrounds`` or black), then ``extra`` [C, N, E] (zero background), then the camera
    depth (modes with D / ED; zero background). Returns features [C, N, F] and backgrounds [C, F]."""
    C, N = viewmats.shape[0], means.shape[0]
    feats: list[Tensor] = []
    bgs: list[Tensor] = []
    if render_mode not in ("D", "ED"):
        rgb = prepare_colors(means, colors, viewmats, sh_degree)
        feats.append(rgb)
        bgs.append(backgrounds if backgrounds is not None else rgb.new_zeros(C, rgb.shape[-1]))
    if extra is not None:
        feats.append(extra.to(proj.means2d.dtype))
        bgs.append(proj.means2d.new_zeros(C, extra.shape[-1]))
    if render_mode != "RGB":
        feats.append(proj.depths[..., None])
        bgs.append(proj.means2d.new_zeros(C, 1))
    feats = [f.expand(C, N, -1) for f in feats]
    feat = feats[0] if len(feats) == 1 else torch.cat(feats, dim=-1)
    return feat, bgs[0] if len(bgs) == 1 else torch.cat(bgs, dim=-1)


def split_features(
    img: Tensor, alpha: Tensor, extra: Tensor | None, render_mode: str
) -> tuple[Tensor, Tensor | None]:
    """Undo :func:`stack_features` on a composited image [C, H, W, F]: the image without the extra channels
    (expected depth divided by the alpha for ED modes) and the extra channels [C, H, W, E] (None without)."""
    out = None
    if extra is not None:
        E = extra.shape[-1]
        n_col = img.shape[-1] - E - (0 if render_mode == "RGB" else 1)
        out = img[..., n_col : n_col + E]
        img = torch.cat([img[..., :n_col], img[..., n_col + E :]], dim=-1)
    if render_mode in ("ED", "RGB+ED"):
        img = torch.cat([img[..., :-1], img[..., -1:] / alpha.clamp(min=1e-10)], dim=-1)
    return img, out
