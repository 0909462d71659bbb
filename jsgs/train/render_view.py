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
    from jsgs.errors import JsgsError

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise JsgsError("--device cuda: CUDA is not available on this machine (use --device cpu)")
    return torch.device(name)


def resolve_backend(cfg: TrainConfig, device: torch.device) -> str:
    """render.backend auto -> gsplat on CUDA, torch (reference rasterizer) elsewhere."""
    from jsgs.errors import JsgsError

    b = cfg.render.backend
    if b == "gsplat" and device.type != "cuda":
        raise JsgsError("render.backend gsplat needs --device cuda (the CPU uses the torch rasterizer)")
    resolved = b if b != "auto" else ("gsplat" if device.type == "cuda" else "torch")
    if resolved == "torch" and cfg.render.packed:
        raise JsgsError("render.packed needs the gsplat backend (the reference rasterizer is non-packed)")
    return resolved


def eval_sh_colors(sh_degree: int, coeffs: Tensor, means: Tensor, viewmat: Tensor) -> Tensor:
    """View-dependent RGB of each Gaussian as gsplat's rasterization computes it before compositing:
    ``clamp_min(SH(dirs) + 0.5, 0)`` with dirs = means - camera centre. coeffs [N, K, 3]; means [N, 3];
    viewmat [1, 4, 4]. Returns [1, N, 3]."""
    from jsgs.render.reference import sh_colors

    return sh_colors(means, coeffs, viewmat, sh_degree)


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
) -> RenderOut:
    """Rasterise one camera. viewmat [1, 4, 4] world-to-camera, K [1, 3, 3] pixels.

    Without ``extra_features`` the SH coefficients go to the rasterizer (``sh_degree`` given). With them
    ([N, E] per-Gaussian features), the SH colours are evaluated here, exactly as gsplat does internally,
    and RGB + E channels are rasterised together in one pass. ``extra_kwargs`` go to ``rasterize`` as they
    are (a method's options such as ``pool_probe``)."""
    from jsgs.render import rasterize

    p = activated(splats)
    kwargs: dict[str, Any] = dict(
        near_plane=cfg.render.near_plane,
        far_plane=cfg.render.far_plane,
        packed=cfg.render.packed,
        absgrad=cfg.strategy.absgrad,
        backend=backend,
    )
    if extra_kwargs:
        kwargs.update(extra_kwargs)
    if extra_features is None:
        colors, sh = p["colors"], sh_degree
    else:
        rgb = eval_sh_colors(sh_degree, p["colors"], p["means"], viewmat)
        colors = torch.cat([rgb, extra_features[None].to(rgb.dtype)], dim=-1)
        sh = None
    renders, alphas, info = rasterize(
        p["means"],
        p["quats"],
        p["scales"],
        p["opacities"],
        colors,
        viewmat,
        K,
        width,
        height,
        sh_degree=sh,
        **kwargs,
    )
    extra = renders[..., 3:] if extra_features is not None else None
    return RenderOut(rgb=renders[..., :3], alpha=alphas, extra=extra, info=info)
