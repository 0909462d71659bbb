"""tools/results/build_report.py: the results folders rebuild byte for byte; --baseline: a folder of
one recipe's JSGS runs gets the other folder's gsplat runs of the same cells and the clean runs of the same
scenes and budgets, with their settings, and nothing else."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from conftest import load_benchmark

from jsgs.bench.results import read_csv, write_csv

br = load_benchmark("build_report", "tools/results")


def _row(scene: str, schedule: str, method: str, seed: int, lpips: float, budget: int = 100000) -> dict:
    return {
        "scene": scene, "schedule": schedule, "method": method, "seed": seed, "strategy": "mcmc",
        "budget": budget, "step": 10000, "psnr": 25.0, "ssim": 0.9, "lpips": lpips, "num_gaussians": budget,
        "train_seconds": 100.0, "time_per_iteration_s": 0.01,
    }  # fmt: skip


def test_baseline_brings_the_cells_gsplat_and_clean_runs(tmp_path: Path) -> None:
    base, bench, target = tmp_path / "default", tmp_path / "bench", tmp_path / "variant"
    base.mkdir(), bench.mkdir()
    rows = [_row(sc, sch, m, s, 0.2) for sc in ("a", "b") for sch in ("uniform", "descending")
            for m in ("gsplat", "jsgs") for s in (0, 1)]  # fmt: skip
    rows += [_row(sc, "clean", "gsplat", s, 0.1) for sc in ("a", "b") for s in (0, 1)]
    rows += [_row("a", "uniform", "gsplat", 0, 0.3, budget=300000)]  # another budget: not brought
    write_csv(rows, base / "results.csv")
    (base / "configs.json").write_text(json.dumps({br.run_key(r): {"settings": {"k": br.run_key(r)}}
                                                   for r in rows}))  # fmt: skip
    # the bench trained one recipe on scene a, uniform, seeds 0-1
    write_csv([_row("a", "uniform", "jsgs", s, 0.15) for s in (0, 1)], bench / "results.csv")
    br.main(target, [bench], "auto", base)
    got = read_csv(target / "results.csv")
    cells = sorted({(r["scene"], r["schedule"], r["method"], int(r["budget"])) for r in got})
    assert cells == [("a", "clean", "gsplat", 100000), ("a", "uniform", "gsplat", 100000),
                     ("a", "uniform", "jsgs", 100000)]  # fmt: skip
    assert sorted(float(r["lpips"]) for r in got if r["method"] == "jsgs") == [0.15, 0.15]  # the bench's
    assert len(got) == 6
    configs = json.loads((target / "configs.json").read_text())
    want = {f"a/{sch}/gsplat/mcmc-100000/s{s}" for sch in ("uniform", "clean") for s in (0, 1)}
    assert set(configs) == want
    assert (target / "report.md").is_file()


def test_refuses_results_without_budget_columns(tmp_path: Path) -> None:
    old = tmp_path / "old"
    old.mkdir()
    # a results.csv from before the strategy and budget columns (write_csv would add them, empty)
    row = _row("a", "gaussian", "gsplat", 0, 0.2)
    row = {k: v for k, v in row.items() if k not in ("strategy", "budget")}
    with (old / "results.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(row))
        w.writeheader()
        w.writerow(row)
    with pytest.raises(SystemExit, match=r"old/results.csv: no strategy and budget columns; it rebuilds"):
        br.main(old, [])
    # nothing written into the folder it refused
    assert sorted(p.name for p in old.iterdir()) == ["results.csv"]


# Every equal-budget results folder rebuilds (the 17 take about 15 s on 2 cores); a representative few are
# tested, one per way the tables pick their step: the last step (operating_point, double), a fixed step
# (captures, --step 7000) and each scene's last common evaluation (levers/nogc, --step auto).
REBUILT = [
    ("operating_point", None),
    ("double", None),
    ("budget/captures", 7000),
    ("budget/levers/nogc", "auto"),
]


@pytest.mark.parametrize(("folder", "step"), REBUILT, ids=[f for f, _ in REBUILT])
def test_a_results_folder_rebuilds_byte_for_byte(tmp_path: Path, folder: str, step: int | str | None) -> None:
    """A results folder is what the bench's report code makes of its own results.csv and configs.json (with
    the step its tables name): report.md, results.csv and configs.json byte for byte, the same plots (their
    pixels depend on the matplotlib version, so only their names are compared)."""
    import shutil

    committed = Path(__file__).resolve().parents[2] / "docs" / "results" / folder
    target = tmp_path / committed.name
    shutil.copytree(committed, target)
    shutil.rmtree(target / "plots")
    (target / "report.md").unlink()  # made again from results.csv and configs.json, which it rewrites
    br.main(target, [], step)
    for name in ("report.md", "results.csv", "configs.json"):
        assert (target / name).read_bytes() == (committed / name).read_bytes(), name
    assert sorted(p.name for p in (target / "plots").iterdir()) == sorted(
        p.name for p in (committed / "plots").iterdir())  # fmt: skip
