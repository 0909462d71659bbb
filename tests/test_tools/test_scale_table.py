"""tools/results/scale_table.py: views per second over the whole run and between the first and the last
evaluation, the first steps' extra seconds, and each speed-up over the method's 1-GPU run (a run that named
its exchange against the method's plain 1-GPU run)."""

from __future__ import annotations

import json
from pathlib import Path

from conftest import load_benchmark

st = load_benchmark("scale_table", "tools/results")


def _run(
    root: Path, method: str, n: int, evals: list[tuple[int, float]], exchange: str | None = None
) -> None:
    run = root / "scene" / method / f"g{n}"
    run.mkdir(parents=True)
    steps, seconds = evals[-1]
    rows = [{"step": s, "train_time_s": t, "psnr": 20.0, "ssim": 0.9, "lpips": 0.1} for s, t in evals]
    (run / "metrics.json").write_text(json.dumps({
        "status": "complete", "world_size": n, "step": steps, "time_per_iteration_s": seconds / steps,
        "num_gaussians": 1000, "device_name": "GPU", "evals": rows,
    }))  # fmt: skip
    derived = {} if exchange is None else {"exchange": exchange}
    (run / "config.json").write_text(json.dumps({"derived": derived}))


def _cells(text: str, method: str, n: int) -> list[str]:
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if cells[1:3] == [method, str(n)]:
            return cells
    raise AssertionError(f"no row {method} {n}:\n{text}")


def test_rates_and_speed_ups(tmp_path: Path) -> None:
    # one GPU: 1,000 steps in 10.5 s, 2.5 s at step 200: 10 ms a step after it, 0.5 s extra before it
    _run(tmp_path, "gsplat", 1, [(200, 2.5), (1000, 10.5)])
    # two GPUs: 500 steps in 6.1 s, 1.7 s at step 100: 11 ms a step after it, 0.6 s extra before it
    _run(tmp_path, "gsplat", 2, [(100, 1.7), (500, 6.1)], "gsplat")
    _run(tmp_path, "gsplat_torch", 2, [(100, 1.9), (500, 6.3)], "torch")
    _run(tmp_path, "gsplat_gsplat", 2, [(100, 1.9), (500, 6.3)], "gsplat")
    _run(tmp_path, "jsgs", 2, [(500, 6.0)], "torch")  # no 1-GPU run, one evaluation
    text = st.table(tmp_path)
    assert _cells(text, "gsplat", 1)[5:10] == ["95.2", "1.00", "100.0", "1.00", "0.50"]
    # whole run 2 / (6.1 / 500) = 163.9 views/s, 1.72x; after the first evaluation 2 / 0.011 = 181.8, 1.82x
    assert _cells(text, "gsplat", 2)[5:10] == ["163.9", "1.72", "181.8", "1.82", "0.60"]
    assert _cells(text, "gsplat", 2)[14] == "gsplat"
    # against gsplat's 1-GPU run: 2 / (6.3 / 500) = 158.7, 1.67x; 2 / 0.011 again
    assert _cells(text, "gsplat_torch", 2)[5:10] == ["158.7", "1.67", "181.8", "1.82", "0.80"]
    assert _cells(text, "gsplat_torch", 2)[14] == "torch"
    assert _cells(text, "gsplat_gsplat", 2)[5:10] == _cells(text, "gsplat_torch", 2)[5:10]
    assert _cells(text, "gsplat_gsplat", 2)[14] == "gsplat"
    assert _cells(text, "jsgs", 2)[5:10] == ["166.7", "n/a", "n/a", "n/a", "n/a"]
