"""One test view side by side: the uncompressed reference saved as a JPEG at the dataset's lowest training
quality (what the worst training views look like), the gsplat render, the JSGS render and the reference, each
with its PSNR against the reference, enlarged with nearest-neighbour sampling so the blocks stay visible.

    python scripts/demo_panel.py DATA RUN_GSPLAT RUN_JSGS --out panel.png [--view NAME] [--scale 3]

DATA is the dataset folder (its manifest.json names the views and the JPEG state of each), RUN_* are run
folders of `jsgs train` (their renders/step_<last>/ hold the test renders).
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse)


def last_render(run: Path, view: str) -> Path:
    steps = sorted((run / "renders").glob("step_*"))
    if not steps:
        raise SystemExit(f"error: {run}: no renders/ (train with eval.save_renders on)")
    hits = sorted(steps[-1].glob(f"*_{Path(view).stem}.png"))
    if not hits:
        raise SystemExit(f"error: {steps[-1]}: no render of test view {view}")
    return hits[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("runs", type=Path, nargs=2, metavar="RUN")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--view", default=None, help="test view name [the first test view]")
    ap.add_argument("--scale", type=int, default=3)
    args = ap.parse_args()

    doc = json.loads((args.data / "manifest.json").read_text())
    tests = [v for v in doc["views"] if v["split"] == "test"]
    qualities = [v["jpeg"]["quality"] for v in doc["views"] if v["split"] == "train" and v.get("jpeg")]
    if not tests or not qualities:
        raise SystemExit(f"error: {args.data}/manifest.json: needs test views and JPEG training views")
    view = next((v for v in tests if v["name"] == args.view), None) if args.view else tests[0]
    if view is None:
        raise SystemExit(f"error: --view {args.view}: not a test view of {args.data}")
    ref_path = args.data / (view.get("reference") or view["image"])
    ref = np.asarray(Image.open(ref_path).convert("RGB"))
    q = min(qualities)
    buf = io.BytesIO()
    Image.fromarray(ref).save(buf, "JPEG", quality=q, subsampling=2)
    jpeg = np.asarray(Image.open(buf).convert("RGB"))
    panels = [(f"JPEG q={q}", jpeg)]
    for run, name in zip(args.runs, ("gsplat", "JSGS"), strict=True):
        panels.append((name, np.asarray(Image.open(last_render(run, view["name"])).convert("RGB"))))
    panels.append(("reference", ref))

    h, w = ref.shape[:2]
    s = args.scale
    label_h = 16
    canvas = Image.new("RGB", (len(panels) * (w * s + 4) - 4, h * s + label_h), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for i, (name, img) in enumerate(panels):
        x = i * (w * s + 4)
        canvas.paste(Image.fromarray(img).resize((w * s, h * s), Image.NEAREST), (x, label_h))
        text = name if name == "reference" else f"{name}  {psnr(img, ref):.1f} dB"
        draw.text((x + 2, 2), text, fill=(0, 0, 0))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    canvas.save(args.out)
    print(f"wrote {args.out} (test view {view['name']}: {', '.join(n for n, _ in panels)})", file=sys.stderr)


if __name__ == "__main__":
    main()
