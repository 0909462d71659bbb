"""Small copies of a bench's test renders, to bring back from a GPU call beside its metrics: each run's
renders at its first and last evaluation, 1/SCALE of their size, JPEG at quality 85 (a 1440x1920 view at
1/4 is about 30 kB).

    python3 tools/results/thumbs.py BENCH OUT [--scale 4]

BENCH is a `jsgs bench` output folder (its runs at
``runs/<scene>/<schedule>/<method>/<strategy-budget>/s<seed>``, each with
``renders/step_NNNNNN/<view>.png``); OUT gets ``<scene>/<schedule>/<method>/<strategy-budget>/s<seed>/
step_NNNNNN/<view>.jpg``. What a run has not rendered yet is left out; files already in OUT are written
again. Prints how many it wrote. A per-view metric that falls at one view (report.md's "Per test view") is
then seen, not guessed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from PIL import Image

QUALITY = 85


def evaluation_dirs(run: Path) -> list[Path]:
    """The first and the last ``renders/step_NNNNNN`` folder of ``run`` (one if it has one, none if none)."""
    steps = sorted(d for d in (run / "renders").glob("step_*") if d.is_dir())
    return steps[:1] + steps[1:][-1:]


def thumbnail(src: Path, dst: Path, scale: int) -> None:
    """``src`` (an image) at 1/``scale`` of its width and height (at least 1 px), as a JPEG at ``dst``."""
    with Image.open(src) as im:
        rgb = im.convert("RGB")
    size = (max(1, rgb.width // scale), max(1, rgb.height // scale))
    dst.parent.mkdir(parents=True, exist_ok=True)
    rgb.resize(size, Image.Resampling.BOX).save(dst, quality=QUALITY)


def write_thumbs(bench: Path, out: Path, scale: int = 4) -> int:
    """Every run's renders at its first and last evaluation, under ``out`` (module docstring); returns how
    many."""
    runs = bench / "runs"
    n = 0
    for run in sorted(p.parent for p in runs.glob("*/*/*/*/*/renders")):
        for step in evaluation_dirs(run):
            for png in sorted(step.glob("*.png")):
                thumbnail(png, out / run.relative_to(runs) / step.name / f"{png.stem}.jpg", scale)
                n += 1
    return n


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bench", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--scale", type=int, default=4, help="1/SCALE of each side (default 4)")
    a = ap.parse_args(argv)
    if a.scale < 1:
        print(f"thumbs: --scale {a.scale}: must be at least 1", file=sys.stderr)
        return 2
    if not (a.bench / "runs").is_dir():
        print(f"thumbs: {a.bench}: no runs/ folder (not a bench output)", file=sys.stderr)
        return 2
    print(f"thumbs: {write_thumbs(a.bench, a.out, a.scale)} render(s) of {a.bench} -> {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
