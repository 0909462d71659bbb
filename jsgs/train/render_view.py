"""One view of the Gaussians through ``jsgs.render.rasterize`` with the run's settings."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from jsgs.train.config import TrainConfig
from jsgs.train.model import activated


@dataclass
class RenderOut:
    """``rgb`` [1, H, W, 3], ``alpha`` [1, H, W, 1], ``extra`` [1, H, W, E] or None, ``info`` (gsplat's)."""

    rgb: Tensor
    alpha: Tensor
    extra: Tensor | None
    info: dict[str, Any]


def resolve_device(name: str) -> torch.device:
    """auto -> cuda when available, else cpu. Raises JsgsError for cuda without CUDA."""
    from jsgs.base.errors import JsgsError

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise JsgsError("--device cuda: CUDA is not available on this machine (use --device cpu)")
    return torch.device(name)


def resolve_backend(cfg: TrainConfig, device: torch.device) -> str:
    """render.backend auto -> gsplat on CUDA, torch (reference rasterizer) elsewhere."""
    from jsgs.base.errors import JsgsError

    b = cfg.render.backend
    if b == "gsplat" and device.type != "cuda":
        raise JsgsError("render.backend gsplat needs --device cuda (the CPU uses the torch rasterizer)")
    resolved = b if b != "auto" else ("gsplat" if device.type == "cuda" else "torch")
    if resolved == "torch" and cfg.render.packed:
        raise JsgsError("render.packed needs the gsplat backend (the reference rasterizer is non-packed)")
    return resolved


def render_view(
    splats: torch.nn.ParameterDict,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    sh_degree: int,
    cfg: TrainConfig,
    backend: str,
    extra_features: Tensor | None = None,
    extra_kwargs: dict[str, Any] | None = None,
    distortion: Tensor | None = None,
    distributed: bool = False,
) -> RenderOut:
    """Rasterise one camera. viewmat [1, 4, 4] world-to-camera, K [1, 3, 3] pixels.

    ``extra_features`` ([N, E] per-Gaussian features, optional) are the rasterizer's extra channels,
    composited in the same pass as RGB (``rasterize(..., extra=...)``). ``extra_kwargs`` go to ``rasterize``
    as they are. ``distortion`` [1, 4]: the camera's lens distortion (reference backend only).
    ``distributed``: ``splats`` are this process's shard and the render is gsplat's distributed one,
    non-packed whatever ``render.packed`` says (every process calls it together; :func:`jsgs.render.rasterize`
    says why not packed)."""
    from jsgs.render import rasterize

    p = activated(splats)
    kwargs: dict[str, Any] = dict(
        near_plane=cfg.render.near_plane,
        far_plane=cfg.render.far_plane,
        packed=cfg.render.packed,
        absgrad=cfg.strategy.absgrad,
        backend=backend,
    )
    if distributed:
        kwargs.update(distributed=True, packed=False)
    if extra_kwargs:
        kwargs.update(extra_kwargs)
    if distortion is not None:
        kwargs["distortion"] = distortion
    renders, alphas, info = rasterize(
        p["means"],
        p["quats"],
        p["scales"],
        p["opacities"],
        p["colors"],
        viewmat,
        K,
        width,
        height,
        sh_degree=sh_degree,
        extra=extra_features,
        **kwargs,
    )
    return RenderOut(rgb=renders, alpha=alphas, extra=info.get("extra"), info=info)
