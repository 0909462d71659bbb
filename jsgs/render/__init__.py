"""Rasterisers: gsplat 1.5.3's semantics on CUDA (gsplat) and anywhere (pure-torch reference).

``rasterize`` is the entry point (``backend="auto"|"torch"|"gsplat"``), with generic extra channels
(per-Gaussian features composited like the colours); ``jsgs.render.reference`` is the pure-torch twin of
gsplat's CUDA rasterizer; ``jsgs.render.bruteforce`` is the per-pixel ground truth used by the tests.
"""

from .backend import rasterize, resolve_backend
from .reference import (
    ALPHA_MAX,
    ALPHA_THRESHOLD,
    T_STOP,
    TILE_SIZE,
    Projected,
    project_gaussians,
    quat_to_rotmat,
    sh_colors,
    spherical_harmonics,
)

__all__ = [
    "ALPHA_MAX",
    "ALPHA_THRESHOLD",
    "T_STOP",
    "TILE_SIZE",
    "Projected",
    "project_gaussians",
    "quat_to_rotmat",
    "rasterize",
    "resolve_backend",
    "sh_colors",
    "spherical_harmonics",
]
