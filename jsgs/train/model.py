"""Gaussian parameters, their initialisation and their optimizers, as gsplat 1.5.3's simple_trainer.

Parameters live in a ``torch.nn.ParameterDict`` with gsplat's names and activations, so that gsplat's
``DefaultStrategy`` (which duplicates, splits and removes rows of every parameter *and* of the Adam state)
works on them unchanged:

- ``means``     N x 3   world positions (normalised world units)
- ``scales``    N x 3   log of the per-axis standard deviations
- ``quats``     N x 4   rotation quaternion (w, x, y, z), unnormalised (the rasterizer normalises)
- ``opacities`` N       logit of the opacity
- ``sh0``       N x 1 x 3   SH band 0 (``(rgb - 0.5) / C0`` at initialisation)
- ``shN``       N x K-1 x 3 higher SH bands (zero at initialisation), K = (sh_degree + 1)^2
"""

from __future__ import annotations

import torch
from torch import Tensor

from jsgs.base.errors import JsgsError
from jsgs.train.config import TrainConfig

SH_C0 = 0.28209479177387814
PARAM_NAMES = ("means", "scales", "quats", "opacities", "sh0", "shN")


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """Colour in [0, 1] -> SH band-0 coefficient (gsplat ``utils.rgb_to_sh``)."""
    return (rgb - 0.5) / SH_C0


def knn_sq_dists(points: Tensor, k: int, chunk: int | None = None) -> Tensor:
    """Squared Euclidean distances from each point to its ``k`` nearest *other* points, exactly (brute force
    in float64, in chunks of ``chunk`` rows so memory stays O(chunk x N), about 1 GB at most by default).

    points: N x 3. Returns N x k (ascending). As gsplat's sklearn-based ``knn(points, k + 1)[:, 1:]``: the
    nearest hit of each query is dropped as "itself" (with exact duplicates that hit may be the twin, and the
    distance to the other is then 0, as in gsplat)."""
    n = points.shape[0]
    if n < k + 1:
        raise JsgsError(f"kNN initialisation needs at least {k + 1} points (got {n})")
    if chunk is None:
        chunk = max(1, min(1024, (1 << 27) // n))
    p = points.double()
    sq = (p * p).sum(-1)
    out = torch.empty(n, k, dtype=torch.float64, device=points.device)
    for start in range(0, n, chunk):
        q = p[start : start + chunk]
        # |q - p|^2 = |q|^2 + |p|^2 - 2 q.p; clamp the tiny negatives of cancellation
        d2 = (sq[start : start + chunk, None] + sq[None, :] - 2.0 * q @ p.T).clamp_min_(0.0)
        vals = torch.topk(d2, k + 1, dim=1, largest=False, sorted=True).values
        out[start : start + chunk] = vals[:, 1:]
    return out


def init_splats(
    points: Tensor,
    rgb: Tensor,
    cfg: TrainConfig,
    scene_scale: float,
    device: torch.device,
    max_points: int | None = None,
) -> torch.nn.ParameterDict:
    """Initial Gaussians (gsplat ``create_splats_with_optimizers``).

    points: P x 3 float (normalised world) and rgb: P x 3 in [0, 1] (sfm); ignored for ``init.type=random``,
    which draws ``init.num_points`` points (at most ``max_points``: the strategy's budget).
    Draws the quaternions (and random points) from torch's global generator, which the caller seeds.
    """
    ic = cfg.init
    if ic.type == "sfm":
        pts = points.float()
        rgbs = rgb.float()
        if pts.shape[0] == 0:
            raise JsgsError(
                "the manifest has no points: SfM initialisation is impossible (use init.type=random)"
            )
    else:
        n = ic.num_points if max_points is None else min(ic.num_points, max_points)
        pts = ic.extent * scene_scale * (torch.rand((n, 3)) * 2 - 1)
        rgbs = torch.rand((n, 3))
    # Mean of the squared distances to the k nearest neighbours, then sqrt: gsplat's
    # dist2_avg = (knn(points, 4)[:, 1:] ** 2).mean(-1); dist_avg = sqrt(dist2_avg)
    dist2 = knn_sq_dists(pts.to(device), ic.knn_neighbors).mean(dim=-1)
    dist = torch.sqrt(dist2).float().clamp_min(ic.min_distance).cpu()
    scales = torch.log(dist * ic.scale).unsqueeze(-1).repeat(1, 3)
    n = pts.shape[0]
    quats = torch.rand((n, 4))
    opacities = torch.logit(torch.full((n,), ic.opacity))
    k = (cfg.render.sh_degree + 1) ** 2
    colors = torch.zeros((n, k, 3))
    colors[:, 0, :] = rgb_to_sh(rgbs)
    params = {
        "means": pts,
        "scales": scales,
        "quats": quats,
        "opacities": opacities,
        "sh0": colors[:, :1, :],
        "shN": colors[:, 1:, :],
    }
    return torch.nn.ParameterDict(
        {name: torch.nn.Parameter(v.contiguous()) for name, v in params.items()}
    ).to(device)


def learning_rates(cfg: TrainConfig, scene_scale: float) -> dict[str, float]:
    """Initial learning rate of each parameter group (means scaled by the scene scale)."""
    o = cfg.optim
    return {
        "means": o.means_lr * scene_scale,
        "scales": o.scales_lr,
        "quats": o.quats_lr,
        "opacities": o.opacities_lr,
        "sh0": o.sh0_lr,
        "shN": o.shN_lr,
    }


def make_optimizers(
    splats: torch.nn.ParameterDict, cfg: TrainConfig, scene_scale: float
) -> dict[str, torch.optim.Adam]:
    """One Adam per parameter, one param group each named after it (DefaultStrategy's convention)."""
    lrs = learning_rates(cfg, scene_scale)
    o = cfg.optim
    return {
        name: torch.optim.Adam(
            [{"params": splats[name], "lr": lrs[name], "name": name}],
            eps=o.eps,
            betas=(o.beta1, o.beta2),
        )
        for name in PARAM_NAMES
    }


def make_means_scheduler(
    optimizer: torch.optim.Optimizer, cfg: TrainConfig
) -> torch.optim.lr_scheduler.ExponentialLR:
    """The means' exponential decay to ``means_lr_final_factor`` x over ``optim.means_lr_decay_steps`` steps
    (0: ``iterations``), at the same rate past them."""
    steps = cfg.optim.means_lr_decay_steps or cfg.iterations
    gamma = cfg.optim.means_lr_final_factor ** (1.0 / steps)
    return torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=gamma)


def splats_from_state(state: dict[str, Tensor], device: torch.device) -> torch.nn.ParameterDict:
    """Rebuild the ParameterDict from a checkpoint's tensors (exact copies)."""
    missing = [n for n in PARAM_NAMES if n not in state]
    if missing:
        raise JsgsError(f"checkpoint lacks parameter {missing[0]}")
    return torch.nn.ParameterDict({n: torch.nn.Parameter(state[n].to(device).clone()) for n in PARAM_NAMES})


def sh_degree_at(step: int, cfg: TrainConfig) -> int:
    """SH degree used at (0-based) ``step``: +1 every ``sh_degree_interval`` steps up to ``sh_degree``."""
    return min(step // cfg.render.sh_degree_interval, cfg.render.sh_degree)


def activated(splats: torch.nn.ParameterDict) -> dict[str, Tensor]:
    """The rasterizer's inputs: quats as stored, exp(scales), sigmoid(opacities), SH [N, K, 3]."""
    return {
        "means": splats["means"],
        "quats": splats["quats"],
        "scales": torch.exp(splats["scales"]),
        "opacities": torch.sigmoid(splats["opacities"]),
        "colors": torch.cat([splats["sh0"], splats["shN"]], 1),
    }


__all__ = [
    "PARAM_NAMES",
    "activated",
    "init_splats",
    "knn_sq_dists",
    "learning_rates",
    "make_means_scheduler",
    "make_optimizers",
    "rgb_to_sh",
    "sh_degree_at",
    "splats_from_state",
]
