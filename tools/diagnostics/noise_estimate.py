"""How much quantisation noise the JPEG training views carry: the tables' bound (every coefficient loses
Q²/12; what ``method_options.base_noise: tables`` uses), the estimate from each file's own coefficients
(``jsgs.jpeg.noise``; ``base_noise: pixels``) and the truth (the mean squared difference between the decoded
Y, Cb, Cr and the lossless reference's, libjpeg's JFIF conversion), in 8-bit units².

    .venv/bin/python tools/diagnostics/noise_estimate.py DATA/flower_gaussian/manifest.json [MANIFEST ...]

Needs datasets with lossless references (``jsgstools compress``). Prints a table per manifest (every view by
quality) and one line per manifest: the median and range of estimate / truth and of bound / truth.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from jsgs.base.images import read_rgb8, read_ycbcr8
from jsgs.base.manifest import load_manifest
from jsgs.jpeg.color import rgb_to_ycbcr
from jsgs.jpeg.noise import jpeg_noise_variance
from jsgs.method.image_terms import quantization_noise_variance


def ycbcr_of(rgb: np.ndarray) -> np.ndarray:
    """[H, W, 3] RGB -> float64 [H, W, 3] Y, Cb, Cr (JFIF, as libjpeg converts: jsgs.jpeg.color)."""
    t = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).double()
    return rgb_to_ycbcr(t).permute(1, 2, 0).numpy()


def rows_of(manifest: Path) -> list[tuple[str, int | None, float, float, float]]:
    """(view, quality, truth, estimate, bound) for every JPEG view with a lossless reference."""
    out = []
    for v in load_manifest(manifest).views:
        j = v.jpeg
        if j is None or v.reference is None:
            continue
        dec = read_ycbcr8(v.image)
        truth = float(((dec - ycbcr_of(read_rgb8(v.reference))) ** 2).mean())
        luma, chroma = np.asarray(j.luma_table), np.asarray(j.chroma_table)
        est = jpeg_noise_variance(dec, luma, chroma, j.sampling)
        out.append((v.name, j.quality, truth, est, quantization_noise_variance(luma, chroma)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("manifests", type=Path, nargs="+")
    a = ap.parse_args()
    summary = ["| dataset | views | estimate / truth: median (range) | bound / truth: median (range) |",
               "|---|---:|---|---|"]  # fmt: skip
    for m in a.manifests:
        rows = sorted(rows_of(m), key=lambda r: (r[1] or 0, r[0]))
        print(f"\n{m}\n\n| view | quality | truth | estimate | tables' bound |\n|---|---:|---:|---:|---:|")
        for name, q, t, e, b in rows:
            print(f"| {name} | {q} | {t:.1f} | {e:.1f} | {b:.0f} |")
        if rows:
            re = np.array([r[3] / r[2] for r in rows])
            rb = np.array([r[4] / r[2] for r in rows])
            summary.append(
                f"| {m.parent.name} | {len(rows)} | {np.median(re):.2f} ({re.min():.2f}–{re.max():.2f}) | "
                f"{np.median(rb):.1f} ({rb.min():.1f}–{rb.max():.1f}) |"
            )
    print("\n" + "\n".join(summary))


if __name__ == "__main__":
    main()
