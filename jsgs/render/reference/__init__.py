"""Pure-torch reference rasterizer following gsplat 1.5.3's conventions (pinhole, classic, non-packed).

Runs on any device in float32 or float64 and is differentiable; the CUDA path is tested against it. The
modules mirror gsplat's CUDA kernels rule for rule (``ProjectionEWA3DGSFused.cu``, ``IntersectTile.cu``,
``RasterizeToPixels3DGS{Fwd,Bwd}.cu``):

* ``projection``: EWA, ``cov2d = J W Σ Wᵀ Jᵀ`` where J is evaluated at the camera-space mean with x/z and y/z
  clamped to the field of view widened by 30 % on each side; ``eps2d`` (0.3 px²) added to the diagonal;
  culling when z is outside [near, far], when det(cov2d) <= 0, when the opacity is below 1/255, when both
  radii are <= ``radius_clip`` and when the bounding box lies off-screen; radii are gsplat 1.5.3's
  opacity-aware axis-aligned box, ``r_x = ceil(e·sqrt(cov2d_xx))``, ``r_y = ceil(e·sqrt(cov2d_yy))`` with
  ``e = min(3.33, sqrt(2·ln(255·opacity)))``, stored as [C, N, 2] int32;
* ``sh``: gsplat's real SH basis (degrees 0..4) and colours ``max(SH + 0.5, 0)``;
* ``tiles``: 16x16; a Gaussian is binned to the tiles its box overlaps, sorted front to back by camera depth
  (ties by Gaussian index, as gsplat's stable radix sort);
* ``composite``: per pixel (centre at +0.5) ``σ = ½ dᵀ conic d`` with ``d = mean2d − pixel``;
  ``α = min(0.999, o·exp(−σ))``; a Gaussian is skipped where ``α < 1/255`` (and where σ < 0, which the
  completed-square form of σ never produces); the pixel stops *before* the first Gaussian whose
  ``T·(1 − α) <= 1e-4`` (exclusive); output ``Σ α T c + T_final·bg`` and alpha ``1 − T_final``; gradients
  as gsplat's backward kernel — none through the 0.999 clamp (where α == 0.999) nor through skipped or
  stopped Gaussians; ``means2d`` is a real node of the graph, so ``retain_grad()`` gives the pixel-unit
  gradient that DefaultStrategy reads;
* ``rasterize``: the pipeline, ``rasterize_torch``, returning gsplat's meta keys.
"""

from .composite import ALPHA_MAX, CHUNK_PAIRS, SAVE_PAIRS, T_STOP, block_weights, composite
from .projection import (
    ALPHA_THRESHOLD,
    EXTEND_MAX,
    FOV_MARGIN,
    Projected,
    covariance_3d,
    project_gaussians,
    quat_to_rotmat,
)
from .rasterize import rasterize_torch, split_features, stack_features
from .sh import prepare_colors, sh_basis, sh_colors, spherical_harmonics
from .tiles import TILE_SIZE, TileBins, bin_tiles

__all__ = [
    "ALPHA_MAX",
    "ALPHA_THRESHOLD",
    "CHUNK_PAIRS",
    "EXTEND_MAX",
    "FOV_MARGIN",
    "SAVE_PAIRS",
    "TILE_SIZE",
    "T_STOP",
    "Projected",
    "TileBins",
    "bin_tiles",
    "block_weights",
    "composite",
    "covariance_3d",
    "prepare_colors",
    "project_gaussians",
    "quat_to_rotmat",
    "rasterize_torch",
    "sh_basis",
    "sh_colors",
    "spherical_harmonics",
    "split_features",
    "stack_features",
]
