"""``rasterize``: one entry point for the reference rasterizer (any device) and gsplat's CUDA rasterizer.

Both backends take gsplat 1.5.3 ``rasterization``'s arguments (a subset: pinhole, classic mode, no batch
dimensions) and return the same three things, so that the trainer and gsplat's ``DefaultStrategy`` see no
difference. ``extra`` ([N, E] or [C, N, E] per-Gaussian features) are composited with the same weights as the
colours and returned as E extra image channels ``info["extra"]``; the gradient of a loss on those channels
with respect to the features is the per-Gaussian sum Σ_p t·α·∂L/∂extra(p), which is how a method pools
per-pixel maps per Gaussian (for instance ``jsgs.method.pooling``).
"""

from __future__ import annotations

from typing import Any, Literal

import torch
from torch import Tensor

from jsgs.base.kept_zeros import kept_zeros
from jsgs.base.known_grad import with_deferred_gradient

from . import reference

Backend = Literal["auto", "torch", "gsplat"]
RenderMode = Literal["RGB", "D", "ED", "RGB+D", "RGB+ED"]
_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")


def resolve_backend(backend: str, device: torch.device) -> str:
    """ "auto" → "gsplat" on CUDA tensors, "torch" elsewhere; anything else is returned checked."""
    if backend == "auto":
        return "gsplat" if device.type == "cuda" else "torch"
    if backend not in ("torch", "gsplat"):
        raise ValueError(f"backend must be 'auto', 'torch' or 'gsplat', got {backend!r}")
    if backend == "gsplat" and device.type != "cuda":
        raise ValueError("backend 'gsplat' needs CUDA tensors (its kernels do not run on CPU)")
    return backend


def _check(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    sh_degree: int | None,
    backgrounds: Tensor | None,
    render_mode: str,
) -> None:
    N, C = means.shape[0], viewmats.shape[0]
    if means.shape != (N, 3) or quats.shape != (N, 4) or scales.shape != (N, 3) or opacities.shape != (N,):
        raise ValueError(
            f"expected means [N,3], quats [N,4], scales [N,3], opacities [N]; got {tuple(means.shape)}, "
            f"{tuple(quats.shape)}, {tuple(scales.shape)}, {tuple(opacities.shape)}"
        )
    if viewmats.shape != (C, 4, 4) or Ks.shape != (C, 3, 3):
        raise ValueError(
            f"expected viewmats [C,4,4] and Ks [C,3,3]; got {tuple(viewmats.shape)}, {tuple(Ks.shape)}"
        )
    if sh_degree is None:
        ok = (colors.dim() == 2 and colors.shape[0] == N) or (
            colors.dim() == 3 and colors.shape[:2] == (C, N)
        )
        if not ok:
            raise ValueError(f"colors must be [N,D] or [C,N,D] without sh_degree; got {tuple(colors.shape)}")
    else:
        ok = (colors.dim() == 3 and colors.shape[0] == N) or (
            colors.dim() == 4 and colors.shape[:2] == (C, N)
        )
        if not ok or colors.shape[-1] != 3 or (sh_degree + 1) ** 2 > colors.shape[-2]:
            raise ValueError(
                "SH colors must be [N,K,3] or [C,N,K,3] with K >= (sh_degree+1)^2; "
                f"got {tuple(colors.shape)} for sh_degree={sh_degree}"
            )
    if render_mode not in _MODES:
        raise ValueError(f"render_mode must be one of {_MODES}, got {render_mode!r}")
    if backgrounds is not None and (backgrounds.dim() != 2 or backgrounds.shape[0] != C):
        raise ValueError(f"backgrounds must be [C, D]; got {tuple(backgrounds.shape)}")


def rasterize(
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
    backend: Backend = "auto",
    packed: bool = False,
    absgrad: bool = False,
    render_mode: RenderMode = "RGB",
    extra: Tensor | None = None,
    distortion: Tensor | None = None,
    distributed: bool = False,
    extra_upstream: Any = None,
) -> tuple[Tensor, Tensor, dict]:
    """Rasterise N 3D Gaussians into C pinhole cameras (gsplat 1.5.3 ``rasterization`` semantics).

    Args:
        means: [N, 3] world positions. quats: [N, 4] rotations (w, x, y, z), any norm.
        scales: [N, 3] activated (exp) standard deviations, world units. opacities: [N] activated, [0, 1].
        colors: [N, D] or [C, N, D] features when ``sh_degree`` is None, else SH coefficients [N, K, 3] or
            [C, N, K, 3] evaluated up to ``sh_degree`` along camera-centre→mean, then ``max(sh + 0.5, 0)``.
        viewmats: [C, 4, 4] world-to-camera (OpenCV axes: x right, y down, z forward).
        Ks: [C, 3, 3] intrinsics in pixels (principal point in the convention where pixel (i, j) has its
            centre at (j + 0.5, i + 0.5)). width, height: image size in pixels.
        near_plane, far_plane: camera-z culling range. eps2d: px² added to the projected covariance's
            diagonal. radius_clip: cull Gaussians whose radii are both <= this (px).
        backgrounds: [C, D] colour behind everything (added as T_final·bg); None = black.
        backend: "torch" (reference, any device/dtype), "gsplat" (CUDA kernels), "auto" (gsplat on CUDA).
        packed: gsplat's packed layout (gsplat backend only). absgrad: also accumulate
            ``info["means2d"].absgrad`` = Σ_pixels |∂L/∂means2d| during backward (AbsGS).
        render_mode: "RGB", "D" (accumulated depth), "ED" (expected depth), "RGB+D", "RGB+ED".
        extra: [N, E] or [C, N, E] per-Gaussian features composited like the colours over a zero
            background and returned as ``info["extra"]`` [C, H, W, E] (not in render_colors); the features
            themselves are ``info["extra_features"]``. Needs a colour render_mode. Rendered colours are
            unchanged by it; zero-valued features leave every other gradient unchanged too.
        distortion: [C, 4] lens distortion (k1, k2, p1, p2: COLMAP's SIMPLE_RADIAL, RADIAL, OPENCV) of each
            camera; the image is rendered on the distorted pixel grid
            (:func:`jsgs.render.reference.projection.distort`: means distorted, covariances carried through
            the distortion's Jacobian). The gsplat backend projects with the reference's torch projection
            (differentiable; gsplat's own ``with_ut`` projection is not) and composites with gsplat's tile
            intersection and rasterisation kernels: the same image as the reference backend.
        distributed: gsplat's ``rasterization(..., distributed=True)`` (gsplat backend, non-packed, no
            extra channels, no distortion, no absgrad): ``means`` ... are this process's shard of the
            Gaussians and ``viewmats``/``Ks`` its own cameras; every process of the torch.distributed group
            calls it together, each Gaussian is projected on its owner for every process's cameras and sent
            to the process that renders the camera, and the backward sends the gradients back to the
            owners. ``info``'s projection keys ("means2d", "radii": [C_all, N_shard, ...], cameras by
            rank) are the owner's; "n_cameras" is this process's C. The packed layout is refused: gsplat
            1.5.3's packed distributed path tiles with the image ids of the projection (numbered over every
            process's cameras, one per Gaussian *sent*) instead of those received, which reads past their
            end and renders with the wrong Gaussians.
        extra_upstream: with ``extra``, :func:`_extras`'s ``make`` (the channels' values then not kept).

    Returns:
        render_colors [C, H, W, D(+1 with depth)], render_alphas [C, H, W, 1], info: gsplat's meta keys
        ("means2d" [C, N, 2] in pixels — a non-leaf whose ``.grad`` DefaultStrategy reads after
        ``retain_grad()`` —, "radii" [C, N, 2] int32, "depths" [C, N], "conics" [C, N, 3], "opacities" [C, N],
        "width", "height", "n_cameras", "gaussian_ids" (None unless packed), tile data...) plus "backend".
    """
    _check(means, quats, scales, opacities, colors, viewmats, Ks, sh_degree, backgrounds, render_mode)
    which = resolve_backend(backend, means.device)
    feats = _extra_features(extra, render_mode, viewmats.shape[0], means.shape[0])
    _check_layout(which, viewmats.shape[0], packed, absgrad, extra, distortion, distributed)
    if which == "torch":
        if packed:
            raise ValueError("the reference rasterizer implements the non-packed layout only (packed=False)")
        img, alpha, info = reference.rasterize_torch(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height,
            sh_degree=sh_degree, near_plane=near_plane, far_plane=far_plane, backgrounds=backgrounds,
            eps2d=eps2d, radius_clip=radius_clip, absgrad=absgrad, render_mode=render_mode,
            extra_channels=feats, distortion=distortion,
        )  # fmt: skip
    elif distortion is not None:
        img, alpha, info = _rasterize_gsplat_distorted(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height, distortion,
            sh_degree=sh_degree, near_plane=near_plane, far_plane=far_plane, backgrounds=backgrounds,
            eps2d=eps2d, radius_clip=radius_clip, absgrad=absgrad, render_mode=render_mode, extra=feats,
        )  # fmt: skip
    else:
        img, alpha, info = _rasterize_gsplat(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height,
            sh_degree=sh_degree, near_plane=near_plane, far_plane=far_plane, backgrounds=backgrounds,
            eps2d=eps2d, radius_clip=radius_clip, packed=packed, absgrad=absgrad, render_mode=render_mode,
            extra=feats, distributed=distributed, extra_values=extra_upstream is None,
        )  # fmt: skip
    info["backend"] = which
    _extras(info, extra, extra_upstream)
    return img, alpha, info


def _extras(info: dict, extra: Tensor | None, make: Any) -> None:
    """``info["extra_features"]`` (``extra``), and with ``make``: ``info["extra_objective"]``, a 0-dim zero
    (a view of a zero kept from call to call, :func:`jsgs.base.kept_zeros.kept_zeros`: no kernel) whose
    gradient with respect to the extra channels is ``make(shape, dtype, device)`` (or None), made when the
    backward reaches it (:func:`jsgs.base.known_grad.with_deferred_gradient`). Made here with the render, its
    node is reached after the losses computed on the render later, right before the rasteriser's backward.
    ``info["extra_upstream"]`` is ``make``; the channels themselves are not kept (no ``info["extra"]``: the
    node's edge to them is all the backward needs, and with gsplat the colours are copied out of the image
    with them, which is then freed after the render)."""
    if extra is None:
        return
    info["extra_features"] = extra
    if make is not None:  # the channels' values are not kept: only the node's edge to them
        ch = info.pop("extra")
        info["extra_objective"] = with_deferred_gradient(ch, kept_zeros(ch), make, own_value=True)
        info["extra_upstream"] = make


def _extra_features(extra: Tensor | None, render_mode: str, C: int, N: int) -> Tensor | None:
    """The extra channels as [C, N, E] (an [N, E] one expanded over the cameras), checked."""
    if extra is None:
        return None
    if render_mode in ("D", "ED"):
        raise ValueError("extra channels need a colour render_mode ('RGB', 'RGB+D' or 'RGB+ED')")
    if extra.dim() not in (2, 3) or extra.shape[-2] != N or (extra.dim() == 3 and extra.shape[0] != C):
        raise ValueError(f"extra must be [N, E] or [C, N, E] with N={N}, C={C}; got {tuple(extra.shape)}")
    return extra if extra.dim() == 3 else extra[None].expand(C, -1, -1)


def _check_layout(
    which: str, C: int, packed: bool, absgrad: bool, extra: Tensor | None, distortion: Tensor | None,
    distributed: bool,
) -> None:  # fmt: skip
    """ValueError for lens distortion of the wrong shape or in the packed layout, and for a distributed
    rasterisation that is not gsplat's packed one without extras."""
    if distortion is not None:
        if distortion.shape != (C, 4):
            raise ValueError(f"distortion must be [C, 4] with C={C}; got {tuple(distortion.shape)}")
        if packed:
            raise ValueError("lens distortion renders in the non-packed layout only (packed=False)")
    if distributed and (which != "gsplat" or packed or extra is not None or distortion is not None
                        or absgrad):
        raise ValueError(
            "distributed rasterisation is gsplat's: backend gsplat, non-packed, without extra channels, lens "
            "distortion or absgrad"
        )


def _rasterize_gsplat(
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
    sh_degree: int | None,
    near_plane: float,
    far_plane: float,
    backgrounds: Tensor | None,
    eps2d: float,
    radius_clip: float,
    packed: bool,
    absgrad: bool,
    render_mode: str,
    extra: Tensor | None,
    distributed: bool = False,
    extra_values: bool = True,
) -> tuple[Tensor, Tensor, dict]:
    """gsplat.rasterization in classic mode; with extra features [C, N, E], SH are evaluated here (gsplat's
    own CUDA op) so that the extra channels can be appended to the colour features. Without
    ``extra_values`` the colours are copied out of the image with the extra channels (a contiguous
    [C, H, W, D], as without extra channels), so that the caller, keeping no view of the extra channels,
    holds none of that image after the render (8 bytes a pixel less for two channels)."""
    import gsplat  # imported lazily: the package imports on CPU, but only this path needs it

    kw = dict(
        near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip, eps2d=eps2d, packed=packed,
        tile_size=reference.TILE_SIZE, absgrad=absgrad, rasterize_mode="classic",
    )  # fmt: skip
    if distributed:
        kw["distributed"] = True
    if extra is None:
        return gsplat.rasterization(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height,
            sh_degree=sh_degree, backgrounds=backgrounds, render_mode=render_mode, **kw,
        )  # fmt: skip

    C = viewmats.shape[0]
    if sh_degree is not None:
        from gsplat.cuda._wrapper import spherical_harmonics

        # camera centres C = -Rᵀt of the rigid world-to-camera maps; torch.inverse (what gsplat uses) would
        # synchronise with the host on CUDA (its singularity check), once per step
        R, t = viewmats[:, :3, :3], viewmats[:, :3, 3:]
        campos = -(R.transpose(1, 2) @ t)[..., 0]
        dirs = means[None, :, :] - campos[:, None, :]
        coeffs = colors if colors.dim() == 4 else colors[None].expand(C, -1, -1, -1)
        rgb = torch.clamp_min(spherical_harmonics(sh_degree, dirs, coeffs) + 0.5, 0.0)
    else:
        rgb = colors if colors.dim() == 3 else colors[None].expand(C, -1, -1)
    n_col = rgb.shape[-1]
    E = extra.shape[-1]
    feats = [rgb, extra.to(rgb.dtype)]
    # the extra channels' background is 0: one zero tensor for all the channels without a background
    if backgrounds is None:
        bg_all = rgb.new_zeros(C, n_col + E)
    else:
        bg_all = torch.cat([backgrounds, rgb.new_zeros(C, E)], dim=-1)
    # gsplat appends the depth channel after our features in "RGB+D"/"RGB+ED"
    img, alpha, info = gsplat.rasterization(
        means, quats, scales, opacities, torch.cat(feats, dim=-1), viewmats, Ks, width, height,
        sh_degree=None, backgrounds=bg_all, render_mode=render_mode, **kw,
    )  # fmt: skip
    # one split (its backward is one cat of the parts' gradients); a depth channel, if any, is re-attached
    parts = img.split([n_col, E, img.shape[-1] - n_col - E], dim=-1)
    info["extra"] = parts[1]
    if parts[2].shape[-1]:
        img = torch.cat([parts[0], parts[2]], dim=-1)
    else:
        img = parts[0] if extra_values else parts[0].contiguous()
    return img, alpha, info


def _rasterize_gsplat_distorted(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    distortion: Tensor,
    *,
    sh_degree: int | None,
    near_plane: float,
    far_plane: float,
    backgrounds: Tensor | None,
    eps2d: float,
    radius_clip: float,
    absgrad: bool,
    render_mode: str,
    extra: Tensor | None,
) -> tuple[Tensor, Tensor, dict]:
    """A distorted camera on CUDA: the reference's projection (torch, differentiable; [C, N] tensors, cheap
    next to compositing) and colours, then gsplat's tile intersection and rasterisation kernels, laid out as
    :func:`reference.rasterize_torch` lays out its channels (colours, extra, depth)."""
    from gsplat.cuda._wrapper import isect_offset_encode, isect_tiles, rasterize_to_pixels

    C, N = viewmats.shape[0], means.shape[0]
    proj = reference.project_gaussians(
        means, quats, scales, opacities, viewmats, Ks, width, height,
        eps2d=eps2d, near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip,
        distortion=distortion,
    )  # fmt: skip
    feat, bg = reference.stack_features(
        proj, means, colors, viewmats, sh_degree, backgrounds, extra, render_mode
    )
    T = reference.TILE_SIZE
    tw, th = (width + T - 1) // T, (height + T - 1) // T
    tiles_per_gauss, isect_ids, flatten_ids = isect_tiles(
        proj.means2d, proj.radii, proj.depths, T, tw, th, packed=False, n_images=C
    )
    offsets = isect_offset_encode(isect_ids, C, tw, th).reshape(C, th, tw)
    img, alpha = rasterize_to_pixels(
        proj.means2d, proj.conics, feat.contiguous(), opacities[None, :].expand(C, N).contiguous(), width,
        height, T, offsets, flatten_ids, backgrounds=bg, absgrad=absgrad,
    )  # fmt: skip
    info: dict = {
        "batch_ids": None, "camera_ids": None, "gaussian_ids": None, "radii": proj.radii,
        "means2d": proj.means2d, "depths": proj.depths, "conics": proj.conics,
        "opacities": opacities[None, :].expand(C, N), "tile_width": tw, "tile_height": th,
        "tiles_per_gauss": tiles_per_gauss, "isect_ids": isect_ids, "flatten_ids": flatten_ids,
        "isect_offsets": offsets, "width": width, "height": height, "tile_size": T, "n_batches": 1,
        "n_cameras": C,
    }  # fmt: skip
    img, extra_img = reference.split_features(img, alpha, extra, render_mode)
    if extra_img is not None:
        info["extra"] = extra_img
    return img, alpha, info
