"""How closely ``method_options.gc_attribution: footprint`` follows the exact probe on synthetic scenes.

    .venv/bin/python tools/diagnostics/gc_attribution_agreement.py

Scenes of 600, 1,500 and 3,000 Gaussians (float64, the CPU reference rasteriser, 96x64 px, projected RMS
sizes log-uniform in ~0.3-7.5 px, more overlap with more Gaussians) and a skewed block-constant score map.
The probe's pooled sums come from ``pool_now``; the footprint's from ``footprint_sums`` with V_i read from an
RGB loss's conic gradients, as the trainer's hook reads it. Per scene: |V_i| of each and whether the sets
are equal; Pearson and Spearman correlation of r̄ over V_i (and, for comparison, of r at the pixel under the
Gaussian's mean alone); the Pearson correlation over the Gaussians L_fro acts on (s̄ <= τ_s); the overlap of
the 10 % largest per-Gaussian L_fro terms; the Jaccard index of the controller's damped sets (j in V_i,
r̄ > 0, s̄ <= τ_s); the ratio of the two L_fro values. The scenes are those of
``tests/test_jsgs/method/test_gc_attribution.py`` (which asserts bounds on the 1,500-Gaussian one).
"""

from __future__ import annotations

import argparse
import math
import sys

import torch

from jsgs import __version__
from jsgs.kernels import PooledSums, controller_matrix, fro_loss
from jsgs.method.pooling import footprint_sums, new_probe, pool_now
from jsgs.train.config import TrainConfig
from jsgs.train.render_view import render_view

D = torch.float64
W, H, F = 96, 64, 80.0
SCENES = ((600, 1), (1500, 0), (3000, 2))  # (Gaussians, seed)


def scene(n: int, seed: int) -> torch.nn.ParameterDict:
    g = torch.Generator().manual_seed(seed)
    z = 3.0 + 3.0 * torch.rand(n, generator=g, dtype=D)
    half = torch.tensor([W, H], dtype=D) * 1.1 / F
    xy = (torch.rand(n, 2, generator=g, dtype=D) - 0.5) * half * z[:, None]
    px = torch.exp(torch.rand(n, 3, generator=g, dtype=D) * math.log(25.0)) * 0.3
    p = {
        "means": torch.cat([xy, z[:, None]], 1),
        "scales": torch.log(z[:, None] / F * px),
        "quats": torch.randn(n, 4, generator=g, dtype=D),
        "opacities": torch.randn(n, generator=g, dtype=D) + 0.5,
        "sh0": torch.randn(n, 1, 3, generator=g, dtype=D),
        "shN": torch.zeros(n, 0, 3, dtype=D),
    }
    return torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, v in p.items()})


def block_map(seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(100 + seed)
    b = torch.rand(1, H // 8, W // 8, generator=g, dtype=D) ** 3
    return b[:, :, None, :, None].expand(1, H // 8, 8, W // 8, 8).reshape(1, H, W)


def _corr(a: torch.Tensor, b: torch.Tensor) -> float:
    return torch.corrcoef(torch.stack([a, b]))[0, 1].item()


def _ranks(x: torch.Tensor) -> torch.Tensor:
    return x.argsort().argsort().to(D)


def compare(n: int, seed: int) -> dict[str, float | int | bool]:
    splats, r = scene(n, seed), block_map(seed)
    viewmat, K = torch.eye(4, dtype=D), torch.tensor([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]], dtype=D)
    probe = new_probe(n, splats["means"])
    cfg = TrainConfig.from_preset("paper")
    out = render_view(splats, viewmat[None], K[None], W, H, 0, cfg, "torch", probe)
    info = out.info
    exact = pool_now(info, r)
    info["conics"].retain_grad()
    (out.rgb - 0.3).abs().sum().backward()
    on = (info["conics"].grad != 0).any(-1)
    est: PooledSums = footprint_sums(r, info["means2d"].detach(), info["conics"], info["opacities"], on)
    vis = exact.contributors[0]
    rx, re = exact.rbar()[0], est.rbar()[0]
    m2 = info["means2d"].detach()[0]
    centre = r[0, m2[:, 1].floor().long().clamp(0, H - 1), m2[:, 0].floor().long().clamp(0, W - 1)]
    A = controller_matrix(splats["means"], splats["quats"], viewmat, K, W, H)
    ft = {
        k: fro_loss(s.rbar()[0], vis, splats["opacities"], splats["scales"], A)
        for k, s in (("x", exact), ("e", est))
    }
    small = vis & (ft["x"].sbar <= 1.0)
    k = int(vis.sum()) // 10
    top = [set(f.weight.topk(k).indices.tolist()) for f in ft.values()]
    damped = [(f.weight > 0) & (f.sbar <= 1.0) for f in ft.values()]
    return {
        "gaussians": n,
        "seed": seed,
        "visible_probe": int(vis.sum()),
        "visible_footprint": int(est.contributors.sum()),
        "same_visible_set": bool(torch.equal(est.contributors[0], vis)),
        "rbar_pearson": _corr(re[vis], rx[vis]),
        "rbar_spearman": _corr(_ranks(re[vis]), _ranks(rx[vis])),
        "centre_pixel_pearson": _corr(centre[vis], rx[vis]),
        "centre_pixel_spearman": _corr(_ranks(centre[vis]), _ranks(rx[vis])),
        "small_gaussians": int(small.sum()),
        "rbar_pearson_small": _corr(re[small], rx[small]),
        "top10pct_overlap": len(top[0] & top[1]) / k,
        "damped_jaccard": int((damped[0] & damped[1]).sum()) / max(int((damped[0] | damped[1]).sum()), 1),
        "fro_ratio": ft["e"].loss.item() / ft["x"].loss.item(),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.parse_args(argv)
    torch.set_num_threads(1)
    rows = [compare(n, seed) for n, seed in SCENES]
    print(f"jsgs {__version__}, torch {torch.__version__}, {W}x{H} px, float64, the CPU reference rasteriser")
    cols = list(rows[0])
    print("| " + " | ".join(cols) + " |")
    print("|---" * len(cols) + "|")
    for row in rows:
        print("| " + " | ".join(f"{v:.4f}" if isinstance(v, float) else str(v) for v in row.values()) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
