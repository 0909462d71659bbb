"""Where a dataset's JPEG damage lies: luma or chroma, and how much of the chroma damage is the 4:2:0
subsampling that every view of the scene shares.

    .venv/bin/python tools/diagnostics/damage_channels.py DATA/cup_gaussian/manifest.json [MANIFEST ...] \
        [--weights ../shared/lpips/alexnet_features.pth]

For every JPEG training view with a lossless reference R and its decoded JPEG J (Y, Cb, Cr by libjpeg's JFIF
conversion, ``jsgs.jpeg.color``), four images are compared with R:

- ``jpeg``: J itself;
- ``luma``: J's Y with R's Cb and Cr (the damage to the luma plane alone);
- ``chroma``: R's Y with J's Cb and Cr (the damage to the chroma planes alone, subsampling included);
- ``sub``: R saved by Pillow at quality 100 with the dataset's chroma subsampling and decoded (what the
  subsampling costs with almost no quantisation: a floor that no JPEG view of the scene is below).

Per manifest: the median over views of PSNR (dB, RGB) and LPIPS-alex of each image against R, and the
median ratio LPIPS(luma) / LPIPS(jpeg), LPIPS(chroma) / LPIPS(jpeg) and LPIPS(sub) / LPIPS(jpeg). CPU,
float64 colour conversion, LPIPS in float32. Without LPIPS weights the LPIPS columns read n/a.

The last column says what kind of luma damage it is: R's luma DCT coefficients quantised with the view's
luma table (rounding half away from zero), and the share of the squared error that sits in coefficients
quantised to zero (detail the file drops, about which it tells only that it was smaller than half a step)
rather than in the rounding of the coefficients it keeps (median over views).

A second table asks which measure read from the file alone tells the views' visible damage apart: the
Spearman rank correlation, over the views of each manifest and over all of them together, of LPIPS(jpeg)
with the file's estimated quantisation-noise variance (``jsgs.jpeg.noise.jpeg_noise_variance``, what
``method_options.base_noise: pixels`` weights by), with the blockiness of its decoded luma
(:func:`jsgs.jpeg.noise.blockiness`: steps across the 8×8 block edges over steps inside the blocks, what
``method_options.base_block_ref`` weights by) and with its block contrast (:func:`block_contrast`: the
excess of the edge steps over the inside steps, against the square root of the inside steps).
"""

from __future__ import annotations

import argparse
import io
import statistics
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from jsgs.base.images import read_rgb8, read_ycbcr8
from jsgs.base.manifest import load_manifest
from jsgs.jpeg.color import rgb_to_ycbcr, ycbcr_to_rgb
from jsgs.jpeg.noise import block_steps, blockiness, jpeg_noise_variance, plane_dct
from jsgs.jpeg.rounding import round_half_away
from jsgs.jpeg.tables import CHROMA_SAMPLINGS
from jsgs.metrics.lpips import lpips
from jsgs.metrics.psnr import psnr

PILLOW_SUBSAMPLING = {name: s.pillow for name, s in CHROMA_SAMPLINGS.items() if s.pillow is not None}
IMAGES = ("jpeg", "luma", "chroma", "sub")


def _planes(rgb8: np.ndarray) -> torch.Tensor:
    """[H, W, 3] uint8 RGB -> float64 [3, H, W] Y, Cb, Cr in 0..255."""
    return rgb_to_ycbcr(torch.from_numpy(np.array(rgb8)).permute(2, 0, 1).double())


def _rgb01(ycc: torch.Tensor) -> torch.Tensor:
    """float64 [3, H, W] Y, Cb, Cr -> float32 [3, H, W] RGB in [0, 1] (clamped, as a display would)."""
    return (ycbcr_to_rgb(ycc) / 255.0).clamp(0.0, 1.0).float()


def _resaved(rgb8: np.ndarray, sampling: str) -> np.ndarray:
    buf = io.BytesIO()
    Image.fromarray(rgb8).save(buf, "JPEG", quality=100, subsampling=PILLOW_SUBSAMPLING[sampling])
    buf.seek(0)
    return np.asarray(Image.open(buf).convert("RGB"))


def zeroed_share(y: np.ndarray, luma_table: np.ndarray) -> float:
    """Of the squared error of quantising plane ``y`` [H, W] (0..255) with ``luma_table`` (8, 8), natural
    order, the share in coefficients quantised to zero (0..1; 0 when nothing is lost)."""
    c = plane_dct(y).astype(np.float64)
    steps = luma_table.reshape(1, 64).astype(np.float64)
    q = round_half_away(torch.from_numpy(c / steps)).numpy()
    err = (c - q * steps) ** 2
    total = float(err.sum())
    return float(err[q == 0].sum()) / total if total > 0 else 0.0


def block_contrast(y: np.ndarray) -> float:
    """(E − I) / √I of :func:`jsgs.jpeg.noise.block_steps` (8-bit units^½): how far the steps across the
    8×8 block edges exceed those inside the blocks, against the square root of the inside steps (texture
    masks a grid, less than in proportion). 0 where no grid shows; NaN-free (I + 1e-6)."""
    e, i = block_steps(y)
    return (e - i) / float(np.sqrt(i + 1e-6))


def spearman(a: list[float], b: list[float]) -> float:
    """Spearman's rank correlation of two equally long samples (ties broken by order; NaN under 3)."""
    if len(a) < 3:
        return float("nan")
    ra = np.argsort(np.argsort(np.asarray(a)))
    rb = np.argsort(np.argsort(np.asarray(b)))
    return float(np.corrcoef(ra, rb)[0, 1])


def view_rows(manifest: Path, weights: str | None) -> list[dict[str, float]]:
    """One dict per JPEG view with a reference: ``psnr_<image>``, ``lpips_<image>`` (NaN without weights)."""
    rows = []
    for v in load_manifest(manifest).views:
        if v.jpeg is None or v.reference is None:
            continue
        ref8 = read_rgb8(v.reference, "reference")
        j, r = _planes(read_rgb8(v.image, "JPEG view")), _planes(ref8)
        images = {
            "jpeg": _rgb01(j),
            "luma": _rgb01(torch.cat([j[:1], r[1:]])),
            "chroma": _rgb01(torch.cat([r[:1], j[1:]])),
            "sub": _rgb01(_planes(_resaved(ref8, v.jpeg.sampling))),
        }
        ref = _rgb01(r)
        ycc8 = read_ycbcr8(v.image, "JPEG view")
        chroma_table = v.jpeg.chroma_table if v.jpeg.chroma_table is not None else v.jpeg.luma_table
        row: dict[str, float] = {
            "zeroed": zeroed_share(r[0].numpy(), v.jpeg.luma_table),
            "noise": jpeg_noise_variance(ycc8, v.jpeg.luma_table, chroma_table, v.jpeg.sampling),
            "blockiness": blockiness(ycc8[..., 0]),
            "contrast": block_contrast(ycc8[..., 0]),
        }
        with torch.no_grad():
            batch = torch.stack([images[k] for k in IMAGES])
            lp = lpips(batch, ref.expand_as(batch), weights)
            ps = psnr(batch, ref.expand_as(batch))
        for i, k in enumerate(IMAGES):
            row[f"psnr_{k}"] = float(ps[i])
            row[f"lpips_{k}"] = float(lp[i]) if lp is not None else float("nan")
        rows.append(row)
    return rows


def summary(rows: list[dict[str, float]]) -> dict[str, float]:
    """Medians over views of every column and of each image's LPIPS relative to the JPEG's."""
    out = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
    for k in ("luma", "chroma", "sub"):
        out[f"share_{k}"] = statistics.median(r[f"lpips_{k}"] / r["lpips_jpeg"] for r in rows)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("manifests", nargs="+", type=Path)
    ap.add_argument("--weights", default=None, help="LPIPS backbone weights (default: as jsgs finds them)")
    a = ap.parse_args(argv)
    print("| dataset | views | PSNR jpeg / luma / chroma / sub (dB) | LPIPS jpeg / luma / chroma / sub | "
          "LPIPS luma / chroma / sub relative to jpeg | luma error in zeroed coefficients |")  # fmt: skip
    print("|---|---:|---|---|---|---:|")
    every: dict[str, list[dict[str, float]]] = {}
    for m in a.manifests:
        rows = view_rows(m, a.weights)
        if not rows:
            print(f"error: {m}: no JPEG view with a lossless reference", file=sys.stderr)
            return 1
        every[m.parent.name] = rows
        s = summary(rows)
        ps = " / ".join(f"{s[f'psnr_{k}']:.2f}" for k in IMAGES)
        lp = " / ".join(f"{s[f'lpips_{k}']:.4f}" for k in IMAGES)
        sh = " / ".join(f"{s[f'share_{k}']:.2f}" for k in ("luma", "chroma", "sub"))
        print(f"| {m.parent.name} | {len(rows)} | {ps} | {lp} | {sh} | {s['zeroed']:.2f} |")
    print()
    print("| views of | views | median noise variance (8-bit²) | median blockiness | median block contrast | "
          "rank correlation of LPIPS(jpeg) with noise variance / blockiness / block contrast |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---|")
    pooled = [r for rs in every.values() for r in rs]
    groups = list(every.items()) + ([("all", pooled)] if len(every) > 1 else [])
    for name, rows in groups:
        lp = [r["lpips_jpeg"] for r in rows]
        noise, blocks = [r["noise"] for r in rows], [r["blockiness"] for r in rows]
        contrast = [r["contrast"] for r in rows]
        print(f"| {name} | {len(rows)} | {statistics.median(noise):.1f} | {statistics.median(blocks):.2f} | "
              f"{statistics.median(contrast):.2f} | {spearman(lp, noise):.2f} / {spearman(lp, blocks):.2f} / "
              f"{spearman(lp, contrast):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
