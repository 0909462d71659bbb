"""Two JSGS recipes against the same gsplat runs, pair by pair: which one lowers LPIPS more, per scene,
schedule and budget, and what each does to PSNR.

    cd docs/results/budget
    ../../../.venv/bin/python ../../../tools/results/compare.py pixels/ref2 default
    ../../../.venv/bin/python ../../../tools/results/compare.py default ramp

BASE is a results folder (``results.csv``) with gsplat's runs and one recipe's ``jsgs`` runs; each VARIANT
folder (a bench folder brought back from a GPU call, or several: their rows are pooled) holds the other
recipe's ``jsgs`` runs, on the same datasets and seeds. Gsplat's runs come from BASE, or from the variant
folders where BASE has none for that scene, schedule, budget and seed. Each scene is compared, at each
budget, at the last evaluation every run in the comparison reached (:func:`jsgs.bench.budget.common_steps`).
Prints a markdown table: per cell, the seed means of gsplat, BASE and VARIANT, ΔLPIPS % and ΔPSNR dB of each
recipe against gsplat (paired by seed, then averaged), and on how many seeds VARIANT's LPIPS is below BASE's;
then the means over all pairs, and VARIANT's shift from BASE seed by seed (its ΔLPIPS points and ΔPSNR dB
minus BASE's) with a 95 % t-interval, per scene (with more than one) and over all pairs. Only the cells
and seeds both recipes (and gsplat) hold are compared.
"""

from __future__ import annotations

import statistics
import sys
from collections.abc import Iterable
from pathlib import Path

from jsgs.bench.budget import BudgetReport, common_steps, mean_ci
from jsgs.bench.results import read_csv


def cell(r: dict) -> tuple[str, str, int]:
    return r["scene"], r["schedule"], int(r["budget"])


def main(base: Path, variants: list[Path]) -> None:
    base_rows = [r for r in read_csv(base / "results.csv") if r["strategy"] == "mcmc"]
    var_rows = [r for v in variants for r in read_csv(v / "results.csv") if r["strategy"] == "mcmc"]
    # the variant's recipe is method "variant" (both are "jsgs"); the comparison covers the cells both hold
    cells = {cell(r) for r in var_rows if r["method"] == "jsgs"} & {
        cell(r) for r in base_rows if r["method"] == "jsgs"}  # fmt: skip
    have = {(*cell(r), int(r["seed"])) for r in base_rows if r["method"] == "gsplat"}
    rows = [r for r in base_rows if r["method"] in ("gsplat", "jsgs") and cell(r) in cells] + [
        {**r, "method": "variant"} if r["method"] == "jsgs" else r
        for r in var_rows
        if cell(r) in cells and (r["method"] == "jsgs" or
                                 (r["method"] == "gsplat" and (*cell(r), int(r["seed"])) not in have))
    ]  # fmt: skip
    rep = BudgetReport(rows, common_steps(rows))
    print(f"BASE {base}; VARIANT {', '.join(map(str, variants))}\n")
    print("| scene | schedule | budget | step | LPIPS gsplat / BASE / VARIANT | ΔLPIPS % BASE / VARIANT "
          "| PSNR gsplat / BASE / VARIANT | ΔPSNR dB BASE / VARIANT | VARIANT lower than BASE |")
    print("|---|---|---:|---:|---|---|---|---|---:|")
    pairs: dict[str, list[tuple[float, float]]] = {"jsgs": [], "variant": []}
    by_scene: dict[str, list[tuple[float, float]]] = {}  # scene -> VARIANT − BASE per seed (LPIPS, PSNR)
    for key in sorted(cells):
        scene, schedule, budget = key
        step = rep.step_at(scene, budget)
        vals = {(m, metric): rep.values(scene, schedule, m, budget, metric)
                for m in ("gsplat", "jsgs", "variant") for metric in ("lpips", "psnr")}  # fmt: skip
        seeds = sorted(set.intersection(*(set(v) for v in vals.values())))
        if not seeds:
            print(f"| {scene} | {schedule} | {budget:,} | {step} | no seed with gsplat and both |||||")
            continue
        d = {m: list(zip(rep.paired(key, "lpips", True, m, within=seeds),
                         rep.paired(key, "psnr", method=m, within=seeds), strict=True))
             for m in pairs}  # fmt: skip
        for m in pairs:
            pairs[m] += d[m]
        by_scene.setdefault(scene, []).extend(shifts(d["jsgs"], d["variant"]))
        cols = {
            metric: " / ".join(avg([vals[m, metric][s] for s in seeds], digits)
                               for m in ("gsplat", "jsgs", "variant"))
            for metric, digits in (("lpips", 4), ("psnr", 2))
        }  # fmt: skip
        wins = sum(vals["variant", "lpips"][s] < vals["jsgs", "lpips"][s] for s in seeds)
        print(f"| {scene} | {schedule} | {budget:,} | {step} | {cols['lpips']} | "
              f"{mean(d['jsgs'], 0, 1)} / {mean(d['variant'], 0, 1)} | {cols['psnr']} | "
              f"{mean(d['jsgs'], 1, 2)} / {mean(d['variant'], 1, 2)} | {wins}/{len(seeds)} |")  # fmt: skip
    a, b = pairs["jsgs"], pairs["variant"]
    print(f"\nover the {len(a)} seeds with gsplat and both recipes: BASE ΔLPIPS {mean(a, 0, 1)} %, "
          f"ΔPSNR {mean(a, 1, 2)} dB; VARIANT ΔLPIPS {mean(b, 0, 1)} %, ΔPSNR {mean(b, 1, 2)} dB")
    if len(by_scene) > 1:
        print("\n| scene | pairs | VARIANT − BASE: ΔLPIPS points | ΔPSNR dB | VARIANT's ΔLPIPS lower |")
        print("|---|---:|---|---|---:|")
        for scene, sh in sorted(by_scene.items()):
            print(f"| {scene} | {len(sh)} | {ci([x[0] for x in sh], 1)} | {ci([x[1] for x in sh], 2)} | "
                  f"{sum(x[0] < 0 for x in sh)} of {len(sh)} |")
        print()
    if a:
        shift = shifts(a, b)
        print(f"VARIANT − BASE, seed by seed: ΔLPIPS {ci([s[0] for s in shift], 1)} points, "
              f"ΔPSNR {ci([s[1] for s in shift], 2)} dB (mean ± 95 % t-interval); VARIANT's ΔLPIPS lower "
              f"on {sum(s[0] < 0 for s in shift)} of {len(shift)}")


def shifts(base: list[tuple[float, float]], variant: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """VARIANT's paired (ΔLPIPS %, ΔPSNR dB) minus BASE's, seed by seed."""
    return [(q[0] - p[0], q[1] - p[1]) for p, q in zip(base, variant, strict=True)]


def mean(v: list[tuple[float, float]], i: int, d: int) -> str:
    """The mean of the i-th member of paired differences, signed, d decimals."""
    return f"{statistics.mean(p[i] for p in v):+.{d}f}" if v else "—"


def ci(v: list[float], d: int) -> str:
    """``mean ± half-width`` of the 95 % t-interval (:func:`jsgs.bench.budget.mean_ci`), d decimals."""
    m, h = mean_ci(v)
    if m is None:
        return "—"
    m = round(m, d) or 0.0  # no "-0.0"
    return f"{m:+.{d}f}" + (f" ± {h:.{d}f}" if h is not None else "")


def avg(v: Iterable[float], d: int) -> str:
    v = list(v)
    return f"{statistics.mean(v):.{d}f}" if v else "—"


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit("usage: compare.py BASE VARIANT [VARIANT ...]  (results folders; see the docstring)")
    main(Path(sys.argv[1]), [Path(p) for p in sys.argv[2:]])
