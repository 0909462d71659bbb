"""``RESULTS/results.csv``: one row per run and evaluation step, from each run's ``metrics.json``.
``strategy`` is default or mcmc; ``budget`` the cap (``strategy.cap_max``) of an mcmc run (``auto``: the
scene-sized budget, its count in ``num_gaussians``), empty otherwise.
``train_seconds`` is the training time up to the evaluation (evaluations excluded); ``runs_per_device`` how
many trainings shared the run's device (empty: not stated); ``schedule_steps`` the length of the run's
recipe: a gsplat run trained past it (``jsgs bench --gsplat-steps``) has rows beyond it, which only the
equal-time comparison reads."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

from jsgs.bench.plan import Run

COLUMNS = [
    "scene", "schedule", "method", "seed", "strategy", "budget", "step", "psnr", "ssim", "lpips",
    "train_seconds", "fps", "num_gaussians", "peak_memory_mb",
]  # fmt: skip
#: fixed extra columns right after the leading ones; then loss_<term> and stat_<name> in sorted order
EXTRA = [
    "time_per_iteration_s", "loss", "peak_memory_kind", "backend", "device_name", "runs_per_device",
    "schedule_steps",
]  # fmt: skip
TEXT = {"scene", "schedule", "method", "strategy", "peak_memory_kind", "backend", "device_name"}
MB = 2**20


def rows_for_run(run: Run) -> list[dict[str, Any]]:
    """The run's rows (none when it has no metrics.json, or no folder yet: a budget never resolved)."""
    if not run.out:
        return []
    try:
        doc = json.loads((Path(run.out) / "metrics.json").read_text())
    except (OSError, ValueError):
        return []
    out = []
    for e in doc.get("evals", []):
        row: dict[str, Any] = {
            "scene": run.scene, "schedule": run.schedule, "method": run.method, "seed": run.seed,
            "strategy": run.strategy, "budget": run.budget if run.auto else run.cap, "step": e["step"],
            "psnr": e["psnr"],
            "ssim": e["ssim"], "lpips": e["lpips"],
            "train_seconds": e["train_time_s"], "fps": e["fps"], "num_gaussians": e["num_gaussians"],
            "peak_memory_mb": e["peak_memory_bytes"] / MB,
            "time_per_iteration_s": e["time_per_iteration_s"], "loss": e["train"]["loss"],
            "peak_memory_kind": e["peak_memory_kind"], "backend": doc.get("backend"),
            "device_name": doc.get("device_name"), "runs_per_device": doc.get("runs_per_device"),
            "schedule_steps": run.schedule_steps or run.iterations,
        }  # fmt: skip
        for k, v in e["train"]["terms"].items():
            row[f"loss_{k}"] = v
        for k, v in e["train"]["stats"].items():
            row[f"stat_{k}"] = v
        out.append(row)
    return out


def collect(runs: list[Run]) -> list[dict[str, Any]]:
    """Every run's rows, in the plan's order."""
    rows: list[dict[str, Any]] = []
    for r in runs:
        rows += rows_for_run(r)
    return rows


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if not math.isfinite(v) else repr(v)
    return str(v)


def write_csv(rows: list[dict[str, Any]], path: str | Path) -> list[str]:
    """Write the CSV (atomically); returns its header."""
    dynamic = sorted({k for r in rows for k in r} - set(COLUMNS) - set(EXTRA))
    header = COLUMNS + EXTRA + dynamic
    import io

    from jsgs.base.io import write_bytes_atomic

    buf = io.StringIO(newline="")
    w = csv.writer(buf)
    w.writerow(header)
    for r in rows:
        w.writerow([_fmt(r.get(k)) for k in header])
    write_bytes_atomic(path, buf.getvalue().encode())
    return header


def read_csv(path: str | Path) -> list[dict[str, Any]]:
    """Rows back with numbers as float/int (empty cells: None)."""
    out = []
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            row: dict[str, Any] = {}
            for k, v in r.items():
                if v == "":
                    row[k] = None
                elif k in TEXT:
                    row[k] = v
                elif k == "budget":  # a cap, or auto (the scene-sized budget)
                    row[k] = int(v) if v.isdigit() else v
                elif k in ("seed", "step", "num_gaussians", "runs_per_device", "schedule_steps"):
                    row[k] = int(v)
                else:
                    row[k] = float(v)
            out.append(row)
    return out


def within_recipe(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows at or before their run's recipe length (``schedule_steps``): what the equal-step tables
    compare (a gsplat run trained past its recipe for the equal-time table counts up to there)."""
    return [r for r in rows if r.get("schedule_steps") is None or int(r["step"]) <= int(r["schedule_steps"])]
