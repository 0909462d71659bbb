"""Which training views dominate the JPEG damage? Per scene and compression schedule, how the
squared error of the training JPEGs is spread over the views and the quality levels. CPU only, no training.

    .venv/bin/python benchmarks/view_damage.py SCENE... [--schedules uniform,gaussian,descending] \
        [--seeds 0] [--work DIR] [--jobs N] [--low-quality 30] [--out view_damage.json]

Every dataset is built exactly as ``jsgs bench`` builds it (``jsgs/bench/harness.py``),
``jsgstools.compress.compress(SCENE, DIR, schedule, quality=None, seed=seed, force=True)`` (test views, every
8th, stay lossless; the training views get qualities 10..90 by schedule), into a temporary folder (or into
``--work DIR/<scene>/<schedule>_s<seed>``, kept).

For every training view (a JPEG): its quality (from ``compress.json``), the MSE of the decoded JPEG (Pillow,
RGB, float in [0, 1], over every pixel and channel) against its lossless reference ``reference/<stem>.png``,
and PSNR = 10 log10(1 / MSE) (null when MSE is 0; such a view then counts in no mean PSNR).

Printed as markdown tables (the progress bar goes to stderr):

1. per scene x schedule x seed: training views, mean PSNR of the training JPEGs, the share of the views of
   quality <= ``--low-quality`` and the share of the total squared error (sum of the per-view MSE) they carry;
2. per schedule, the mean of table 1's rows over the scenes;
3. per quality level and schedule, pooled over scenes and seeds: number of views, mean PSNR.

``--out FILE.json`` also writes everything (with every view) as ``jsgs/schemas/view_damage.schema.json``.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jsgs.base.errors import JsgsError, reports_user_errors  # noqa: E402

MIXED = ("uniform", "gaussian", "descending")
LOW_QUALITY = 30


def load_float(path: str | Path) -> np.ndarray:
    """(H, W, 3) float64 in [0, 1]: the file decoded by Pillow, converted to RGB."""
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"), dtype=np.float64) / 255.0


def view_error(image: str | Path, reference: str | Path) -> tuple[float, float | None]:
    """(MSE, PSNR in dB) of ``image`` against ``reference``; PSNR is None when they are equal."""
    a, b = load_float(image), load_float(reference)
    if a.shape != b.shape:
        raise JsgsError(f"{image}: {a.shape[1]}x{a.shape[0]} differs from its reference {reference}")
    mse = float(np.mean((a - b) ** 2))
    return mse, (10.0 * float(np.log10(1.0 / mse)) if mse > 0 else None)


def measure_dataset(data_dir: str | Path) -> list[dict[str, Any]]:
    """One entry per training JPEG of a compressed dataset (``compress.json``): name, quality, mse, psnr."""
    import json

    data_dir = Path(data_dir)
    record = json.loads((data_dir / "compress.json").read_text())
    out = []
    for v in record["views"]:
        if v["split"] != "train" or v["quality"] is None:
            continue
        mse, psnr = view_error(data_dir / v["image"], data_dir / v["reference"])
        out.append({"name": v["name"], "quality": int(v["quality"]), "mse": mse, "psnr": psnr})
    return out


def _mean(xs: Sequence[float | None]) -> float | None:
    vals = [x for x in xs if x is not None]
    return float(np.mean(vals)) if vals else None


def summarise(views: Sequence[dict[str, Any]], low_quality: int) -> dict[str, Any]:
    """Training views, mean PSNR, and the share of the views and of the squared error (sum of per-view MSE)
    at quality <= ``low_quality`` (shares are None without views or without any error)."""
    n = len(views)
    low = [v for v in views if v["quality"] <= low_quality]
    sse = float(sum(v["mse"] for v in views))
    return {
        "train_views": n,
        "mean_psnr": _mean([v["psnr"] for v in views]),
        "sse": sse,
        "low_views": len(low),
        "low_view_share": len(low) / n if n else None,
        "low_sse_share": float(sum(v["mse"] for v in low)) / sse if sse > 0 else None,
    }


def check_scenes(scenes: Sequence[str | Path]) -> list[tuple[str, Path]]:
    """(name, path) of each scene, validated before anything is built; JsgsError on the first bad one."""
    from jsgstools.validate import require_valid

    out: list[tuple[str, Path]] = []
    for s in scenes:
        path = Path(s)
        if not path.is_dir():
            raise JsgsError(f"{path}: not a folder (expected a COLMAP scene: images/ and sparse/)")
        report = require_valid(path)
        assert report.scene is not None
        name = report.scene.name
        if name in {n for n, _ in out}:
            raise JsgsError(f"{path}: a second scene named {name!r}")
        out.append((name, path))
    return out


def analyse(
    scenes: Sequence[str | Path],
    schedules: Sequence[str] = MIXED,
    seeds: Sequence[int] = (0,),
    work: str | Path | None = None,
    jobs: int | None = None,
    low_quality: int = LOW_QUALITY,
    progress: bool = False,
    command: str | None = None,
) -> dict[str, Any]:
    """Build every (scene, schedule, seed) dataset and measure it: the document of
    ``jsgs/schemas/view_damage.schema.json``."""
    import PIL
    from tqdm import tqdm

    import jsgs
    from jsgstools.compress import compress

    for s in schedules:
        if s not in MIXED:
            raise JsgsError(f"--schedules: {s!r} is not a mixed schedule (choose from {', '.join(MIXED)})")
    if not schedules or not seeds:
        raise JsgsError("--schedules and --seeds need at least one value each")
    if not 10 <= low_quality <= 90:
        raise JsgsError(f"--low-quality {low_quality}: must be within 10..90")
    named = check_scenes(scenes)

    views: list[dict[str, Any]] = []
    datasets: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="view_damage_") as tmp:
        root = Path(work) if work is not None else Path(tmp)
        todo = [(n, p, sch, sd) for n, p in named for sch in schedules for sd in seeds]
        for name, path, schedule, seed in tqdm(todo, desc="compress", unit="dataset", disable=not progress):
            out = root / name / f"{schedule}_s{seed}"
            compress(path, out, schedule, quality=None, seed=seed, force=True, jobs=jobs)
            vs = measure_dataset(out)
            views += [{"scene": name, "schedule": schedule, "seed": seed, **v} for v in vs]
            datasets.append({"scene": name, "schedule": schedule, "seed": seed, **summarise(vs, low_quality)})

    per_schedule = []
    for schedule in schedules:
        rows = [d for d in datasets if d["schedule"] == schedule]
        per_schedule.append(
            {
                "schedule": schedule,
                "datasets": len(rows),
                "mean_train_views": float(np.mean([d["train_views"] for d in rows])),
                "mean_psnr": _mean([d["mean_psnr"] for d in rows]),
                "mean_low_view_share": _mean([d["low_view_share"] for d in rows]),
                "mean_low_sse_share": _mean([d["low_sse_share"] for d in rows]),
            }
        )
    levels = []
    for schedule in schedules:
        for q in range(10, 100, 10):
            vs = [v for v in views if v["schedule"] == schedule and v["quality"] == q]
            levels.append(
                {
                    "schedule": schedule,
                    "quality": q,
                    "count": len(vs),
                    "mean_psnr": _mean([v["psnr"] for v in vs]),
                    "mean_mse": _mean([v["mse"] for v in vs]),
                }
            )
    return {
        "format": "jsgs-view-damage",
        "format_version": 1,
        "version": jsgs.__version__,
        "command": command,
        "settings": {
            "scenes": [str(p) for _, p in named],
            "schedules": list(schedules),
            "seeds": [int(s) for s in seeds],
            "low_quality": low_quality,
            "work": None if work is None else str(work),
            "jobs": jobs,
            "compress": "jsgstools.compress.compress(scene, out, schedule, quality=None, seed=seed, "
            "force=True): defaults test_every 8, subsampling 4:2:0",
            "decoder": f"Pillow {PIL.__version__}, RGB, float64 in [0, 1]",
        },
        "datasets": datasets,
        "schedules": per_schedule,
        "levels": levels,
        "views": views,
    }


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.1f} %"


def _db(x: float | None) -> str:
    return "–" if x is None else f"{x:.2f}"


def markdown(doc: dict[str, Any]) -> str:
    """The three tables of the module docstring."""
    lq = doc["settings"]["low_quality"]
    lines = [
        f"Per scene x schedule (training JPEGs only; q ≤ {lq} = low):",
        "",
        f"| scene | schedule | seed | train views | mean PSNR (dB) | views q ≤ {lq} | "
        f"share of views q ≤ {lq} | share of squared error q ≤ {lq} |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for d in doc["datasets"]:
        lines.append(
            f"| {d['scene']} | {d['schedule']} | {d['seed']} | {d['train_views']} | {_db(d['mean_psnr'])} | "
            f"{d['low_views']} | {_pct(d['low_view_share'])} | {_pct(d['low_sse_share'])} |"
        )
    lines += [
        "",
        "Per schedule, mean over the scene rows above:",
        "",
        f"| schedule | rows | mean train views | mean PSNR (dB) | share of views q ≤ {lq} | "
        f"share of squared error q ≤ {lq} |",
        "|---|---|---|---|---|---|",
    ]
    for s in doc["schedules"]:
        lines.append(
            f"| {s['schedule']} | {s['datasets']} | {s['mean_train_views']:.1f} | {_db(s['mean_psnr'])} | "
            f"{_pct(s['mean_low_view_share'])} | {_pct(s['mean_low_sse_share'])} |"
        )
    schedules = [s["schedule"] for s in doc["schedules"]]
    lines += [
        "",
        "Per quality level, pooled over scenes and seeds (n = training views, PSNR = their mean in dB):",
        "",
        "| q | " + " | ".join(f"{s} n | {s} PSNR" for s in schedules) + " |",
        "|---" * (1 + 2 * len(schedules)) + "|",
    ]
    by = {(lv["schedule"], lv["quality"]): lv for lv in doc["levels"]}
    for q in range(10, 100, 10):
        cells = [f"{by[s, q]['count']} | {_db(by[s, q]['mean_psnr'])}" for s in schedules]
        lines.append(f"| {q} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _ints(text: str, what: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise JsgsError(f"{what} {text!r}: expected comma-separated integers") from None


@reports_user_errors
def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="+", type=Path, help="clean COLMAP scenes (lossless images)")
    ap.add_argument(
        "--schedules", default=",".join(MIXED), help="comma-separated [uniform,gaussian,descending]"
    )
    ap.add_argument("--seeds", default="0", help="comma-separated compress seeds [0]")
    ap.add_argument("--work", type=Path, help="build (and keep) the datasets here [a temporary folder]")
    ap.add_argument("--jobs", type=int, help="compress worker processes [all cores]")
    ap.add_argument(
        "--low-quality", type=int, default=LOW_QUALITY, help="the 'low' qualities are <= this [30]"
    )
    ap.add_argument("--out", type=Path, help="also write the results as JSON here")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = ap.parse_args(argv)
    command = shlex.join(["python", "benchmarks/view_damage.py", *(sys.argv[1:] if argv is None else argv)])
    try:
        from jsgs.base.io import write_json_checked

        doc = analyse(
            args.scenes,
            [s.strip() for s in args.schedules.split(",") if s.strip()],
            _ints(args.seeds, "--seeds"),
            work=args.work,
            jobs=args.jobs,
            low_quality=args.low_quality,
            progress=not args.no_progress,
            command=command,
        )
        print(markdown(doc))
        if args.out:
            write_json_checked(args.out, doc, "view_damage")
    except OSError as e:
        print(f"error: {e.filename or ''}: {e.strerror or e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
