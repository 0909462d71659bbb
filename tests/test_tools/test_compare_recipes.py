"""tools/results/compare.py: two JSGS recipes against the same gsplat runs, on hand-made results whose
answer is known: only the cells and seeds both recipes hold are compared."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from conftest import load_benchmark

from jsgs.bench.results import write_csv

cmp = load_benchmark("compare", "tools/results")


def _row(scene: str, method: str, seed: int, lpips: float, psnr: float, schedule: str = "gaussian") -> dict:
    return {
        "scene": scene, "schedule": schedule, "method": method, "seed": seed, "strategy": "mcmc",
        "budget": 100000, "step": 10000, "psnr": psnr, "ssim": 0.9, "lpips": lpips,
    }  # fmt: skip


def test_compares_only_the_cells_and_seeds_both_recipes_hold(tmp_path: Path, capsys: Any) -> None:
    base, var = tmp_path / "base", tmp_path / "var"
    base.mkdir(), var.mkdir()
    write_csv(
        [
            # cell a: gsplat and BASE on seeds 0-2; the variant has seeds 0-1 only
            *(_row("a", "gsplat", s, 0.2, 25.0) for s in range(3)),
            _row("a", "jsgs", 0, 0.1, 26.0), _row("a", "jsgs", 1, 0.1, 26.0),
            _row("a", "jsgs", 2, 0.3, 20.0),  # seed 2: not in the variant, must not count
            # cell b: BASE only (no variant run): not compared
            _row("b", "gsplat", 0, 0.2, 25.0), _row("b", "jsgs", 0, 0.4, 20.0),
        ],
        base / "results.csv",
    )  # fmt: skip
    write_csv(
        [
            _row("a", "jsgs", 0, 0.15, 25.5), _row("a", "jsgs", 1, 0.05, 25.5),
            # cell c: the variant only: not compared
            _row("c", "gsplat", 0, 0.2, 25.0), _row("c", "jsgs", 0, 0.1, 27.0),
        ],
        var / "results.csv",
    )  # fmt: skip
    cmp.main(base, [var])
    out = capsys.readouterr().out
    table = [line for line in out.splitlines() if line.startswith(("| a ", "| b ", "| c "))]
    assert len(table) == 1 and table[0].startswith("| a | gaussian | 100,000 | 10000 |")
    # seeds 0-1: gsplat 0.2, BASE 0.1 / 0.1 (-50 %), VARIANT 0.15 / 0.05 (-25 %, -75 %: mean -50 %)
    assert "| 0.2000 / 0.1000 / 0.1000 | -50.0 / -50.0 |" in table[0]
    assert "| 25.00 / 26.00 / 25.50 | +1.00 / +0.50 | 1/2 |" in table[0]
    assert "over the 2 seeds with gsplat and both recipes: BASE ΔLPIPS -50.0 %, ΔPSNR +1.00 dB; " \
           "VARIANT ΔLPIPS -50.0 %, ΔPSNR +0.50 dB" in out  # fmt: skip
    # seed by seed the variant's ΔLPIPS is +25 and -25 points off BASE's (mean 0, t(1) 12.706 x 25 = 317.65),
    # its ΔPSNR -0.5 dB on both
    assert "VARIANT − BASE, seed by seed: ΔLPIPS +0.0 ± 317.6 points, ΔPSNR -0.50 ± 0.00 dB" in out
    assert "VARIANT's ΔLPIPS lower on 1 of 2" in out


def test_the_shift_per_scene(tmp_path: Path, capsys: Any) -> None:
    base, var = tmp_path / "base", tmp_path / "var"
    base.mkdir(), var.mkdir()
    # scene a: the variant 10 points lower on both seeds, PSNR level; scene b: 20 points higher on its one
    # seed, 1 dB lower
    write_csv(
        [
            *(_row(sc, "gsplat", s, 0.2, 25.0) for sc in "ab" for s in range(2)),
            *(_row("a", "jsgs", s, 0.1, 26.0) for s in range(2)), _row("b", "jsgs", 0, 0.1, 26.0),
        ],
        base / "results.csv",
    )  # fmt: skip
    write_csv([*(_row("a", "jsgs", s, 0.08, 26.0) for s in range(2)), _row("b", "jsgs", 0, 0.14, 25.0)],
              var / "results.csv")  # fmt: skip
    cmp.main(base, [var])
    out = capsys.readouterr().out
    assert "| a | 2 | -10.0 ± 0.0 | +0.00 ± 0.00 | 2 of 2 |" in out
    assert "| b | 1 | +20.0 | -1.00 | 0 of 1 |" in out
    # over the three seeds: (-10 - 10 + 20) / 3 = 0
    assert "VARIANT − BASE, seed by seed: ΔLPIPS +0.0 ± " in out
    assert "VARIANT's ΔLPIPS lower on 2 of 3" in out
