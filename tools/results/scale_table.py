"""The table of `tools/campaigns/scale.sh`: one row per run found under ROOT.

    python3 tools/results/scale_table.py .res/scale

ROOT holds ROOT/SCENE/METHOD/gN/ (a `jsgs train --gpus N` run folder: metrics.json, config.json); METHOD is
the trained method, with `_torch` or `_gsplat` appended where the run named its exchange
(`speed.exchange`). Per run: its GPUs, steps, views seen, views per second over the whole run (N views per
step / the training seconds per step: setup and evaluations left out, the first steps in) and the speed-up
over the same method's 1-GPU run (METHOD's own g1, else the g1 of the method without the exchange's suffix:
on one GPU there is no exchange); where the run was evaluated more than once (scale.sh evaluates after the
first fifth and at the end), the same after the first evaluation (the steps between the first and the last
evaluation: the run's rate once kernels are loaded, collectives connected and memory pools grown) and the
seconds the steps up to the first evaluation took beyond that rate (the run's fixed cost); the last
evaluation's test metrics, the Gaussians, the exchange and the GPU.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

HEADER = (
    "| scene | method | GPUs | steps | views seen | views/s | speed-up | views/s after first eval | "
    "speed-up | first steps' extra s | PSNR | SSIM | LPIPS | Gaussians | exchange | device |"
)


def rates(m: dict[str, Any]) -> tuple[float, float | None, float | None]:
    """A complete run's views per second over the whole run, between its first and last evaluation (None
    with one evaluation) and the seconds its steps up to the first evaluation took beyond that rate."""
    n = int(m.get("world_size", 1))
    whole = n / m["time_per_iteration_s"]
    evals = m["evals"]
    if len(evals) < 2 or evals[-1]["step"] <= evals[0]["step"]:
        return whole, None, None
    a, b = evals[0], evals[-1]
    per_step = (b["train_time_s"] - a["train_time_s"]) / (b["step"] - a["step"])
    return whole, n / per_step, a["train_time_s"] - a["step"] * per_step


def _num(x: float | None, digits: int) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}"


def table(root: Path) -> str:
    """The markdown table of every run under ``root``."""
    runs: dict[tuple[str, str, int], dict[str, Any]] = {}
    for path in sorted(root.glob("*/*/g*/metrics.json")):
        runs[(path.parts[-4], path.parts[-3], int(path.parts[-2][1:]))] = {
            "metrics": json.loads(path.read_text()),
            "config": json.loads((path.parent / "config.json").read_text()),
        }
    lines = [HEADER, "|" + "---|" * HEADER.count(" | ") + "---|"]
    for (scene, method, n), run in sorted(runs.items()):
        m = run["metrics"]
        if m["status"] != "complete" or not m["evals"]:
            lines.append(f"| {scene} | {method} | {n} | {m['step']} | | {m['status']} |")
            continue
        whole, steady, fixed = rates(m)
        plain = method.removesuffix("_torch").removesuffix("_gsplat")
        base = runs.get((scene, method, 1)) or runs.get((scene, plain, 1))
        base_whole = base_steady = None
        if base is not None and base["metrics"]["status"] == "complete":
            base_whole, base_steady, _ = rates(base["metrics"])
        up = _num(whole / base_whole, 2) if base_whole else "n/a"
        up_steady = _num(steady / base_steady, 2) if steady and base_steady else "n/a"
        e = m["evals"][-1]
        lines.append(
            f"| {scene} | {method} | {n} | {m['step']} | {n * m['step']} | {whole:.1f} | {up} | "
            f"{_num(steady, 1)} | {up_steady} | {_num(fixed, 2)} | {_num(e['psnr'], 3)} | "
            f"{_num(e['ssim'], 4)} | {_num(e['lpips'], 4)} | {m['num_gaussians']} | "
            f"{run['config']['derived'].get('exchange', '-')} | {m.get('device_name', '-')} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    if len(sys.argv) != 2 or not Path(sys.argv[1]).is_dir():
        sys.exit("usage: scale_table.py ROOT (the folder scale.sh trains into, e.g. .res/scale)")
    print(table(Path(sys.argv[1])))
