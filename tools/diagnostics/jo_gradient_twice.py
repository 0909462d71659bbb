"""How much gradient JO passes back on views saved twice: the norm of ∂L/∂render for an L1 observation loss
with the header tables alone, the effective tables alone, and the effective tables then the header's (what
``method_options.tables: effective`` does), relative to the header alone.

    .venv/bin/python tools/diagnostics/jo_gradient_twice.py DATA/gaussian+r90_s0/manifest.json [--views 8]

The manifest needs the compression analysis (``jsgstools manifest --analyze``, or a bench dataset of a
``<schedule>+r<Q2>`` schedule) and lossless references; the "render" is each view's reference plus Gaussian
noise (σ = 0.02, seed 0), the target its JPEG. CPU, float32, ``--mode`` paper by default.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from jsgs.base.images import read_rgb8
from jsgs.base.manifest import load_manifest
from jsgs.jpeg.observe import jpeg_observe


def _image(path: Path) -> torch.Tensor:
    return torch.from_numpy(read_rgb8(path).astype(np.float32) / 255).permute(2, 0, 1)[None]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("manifest", type=Path)
    ap.add_argument("--views", type=int, default=8, help="double-compressed views to measure [8]")
    ap.add_argument("--mode", default="paper", choices=["paper", "float", "exact"])
    a = ap.parse_args()
    scene = load_manifest(a.manifest)
    print("| view | header q | header alone | effective once | effective then header |")
    print("|---|---:|---:|---:|---:|")
    ratios = []
    for v in scene.views:
        j = v.jpeg
        if j is None or not j.double_compressed or v.reference is None:
            continue
        torch.manual_seed(0)
        x0 = _image(v.reference)
        x0 = (x0 + 0.02 * torch.randn_like(x0)).clamp(0, 1)
        y = _image(v.image)
        header = (np.asarray(j.luma_table), np.asarray(j.chroma_table))
        ec = j.effective_chroma_table if j.effective_chroma_table is not None else j.chroma_table
        eff = (np.asarray(j.effective_luma_table), np.asarray(ec))
        norms = []
        for stages in ([header], [eff], [eff, header]):
            x = x0.clone().requires_grad_(True)
            o = x
            for luma, chroma in stages:
                o = jpeg_observe(o, luma, chroma, j.sampling, a.mode)
            (o - y).abs().mean().backward()
            norms.append(x.grad.norm().item())
        r = [n / norms[0] for n in norms]
        ratios.append(r)
        print(f"| {v.name} | {j.quality} | 1 | {r[1]:.3f} | {r[2]:.3f} |")
        if len(ratios) == a.views:
            break
    if ratios:
        med = np.median(np.asarray(ratios), axis=0)
        print(f"| median of {len(ratios)} | | 1 | {med[1]:.3f} | {med[2]:.3f} |")


if __name__ == "__main__":
    main()
