"""One test view side by side: the uncompressed reference saved as a JPEG at the dataset's lowest training
quality (what the worst training views look like), the gsplat render, the JSGS render and the reference,
each with its PSNR against the reference, enlarged with nearest-neighbour sampling so the blocks stay
visible; below them the same four cropped to where that JPEG damages the view most (the window, a third of
the view a side, with the largest squared error of the JPEG against the reference; outlined above), zoomed
further; below those, each crop's absolute error against the reference (×3, grey: black is exact).

    python scripts/demo_panel.py DATA RUN_GSPLAT RUN_JSGS --out panel.png [--view NAME] [--scale 3]

DATA is the dataset folder (its manifest.json names the views and the JPEG state of each), RUN_* are run
folders of `jsgs train` (their renders/step_<last>/ hold the test renders).
"""

from __future__ import annotations

import argparse
import io
import json
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

#: the error row's gain (mean absolute error over the channels, 8-bit units, times this)
ERROR_GAIN = 3


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse)


def damage_window(a: np.ndarray, b: np.ndarray) -> tuple[int, int, int, int]:
    """(x, y, w, h) of the window a third of the view a side where ``a`` differs most from ``b`` (sum of
    squared differences over the window; the first such window in row-major order)."""
    err = ((a.astype(np.float64) - b.astype(np.float64)) ** 2).sum(axis=2)
    h, w = err.shape
    ch, cw = max(1, h // 3), max(1, w // 3)
    c = np.zeros((h + 1, w + 1))
    c[1:, 1:] = err.cumsum(0).cumsum(1)
    sums = c[ch:, cw:] - c[:-ch, cw:] - c[ch:, :-cw] + c[:-ch, :-cw]
    y, x = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return int(x), int(y), cw, ch


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
    cx, cy, cw, ch = damage_window(jpeg, ref)
    z = max(1, (w * s) // cw)  # the crop as wide as a panel
    rows_h = h * s + 3 * label_h + 2 * ch * z
    canvas = Image.new("RGB", (len(panels) * (w * s + 4) - 4, rows_h), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for i, (name, img) in enumerate(panels):
        x = i * (w * s + 4)
        canvas.paste(Image.fromarray(img).resize((w * s, h * s), Image.NEAREST), (x, label_h))
        text = name if name == "reference" else f"{name}  {psnr(img, ref):.1f} dB"
        draw.text((x + 2, 2), text, fill=(0, 0, 0))
        box = (x + cx * s, label_h + cy * s, x + (cx + cw) * s - 1, label_h + (cy + ch) * s - 1)
        draw.rectangle(box, outline=(255, 0, 0))
        crop = img[cy : cy + ch, cx : cx + cw]
        canvas.paste(Image.fromarray(crop).resize((cw * z, ch * z), Image.NEAREST), (x, h * s + 2 * label_h))
        part = ref[cy : cy + ch, cx : cx + cw]
        text = f"{name}, crop" if name == "reference" else f"{name}, crop  {psnr(crop, part):.1f} dB"
        draw.text((x + 2, h * s + label_h + 2), text, fill=(0, 0, 0))
        if name != "reference":
            err = np.abs(crop.astype(np.int16) - part.astype(np.int16)).mean(axis=2) * ERROR_GAIN
            grey = Image.fromarray(np.clip(err, 0, 255).astype(np.uint8)).convert("RGB")
            top = h * s + 2 * label_h + ch * z
            canvas.paste(grey.resize((cw * z, ch * z), Image.NEAREST), (x, top + label_h))
            draw.text((x + 2, top + 2), f"{name}, crop: |error| x{ERROR_GAIN}", fill=(0, 0, 0))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    canvas.save(args.out)
    names = ", ".join(n for n, _ in panels)
    print(
        f"wrote {args.out} (test view {view['name']}: {names}; below, where the JPEG damages it most, "
        f"{cw}x{ch} px at ({cx}, {cy}) x{z}, and its errors)"
    )


if __name__ == "__main__":
    main()
