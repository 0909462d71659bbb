"""Two JSGS recipes against the same gsplat runs, pair by pair: which one lowers LPIPS more, per scene,
schedule and budget, and what each does to PSNR.

    cd docs/results/budget
    ../../../.venv/bin/python compare.py pixels/ref2 default
    ../../../.venv/bin/python compare.py default ../../../.res/ramp/r3000 ../../../.res/ramp/r5000

BASE is a results folder (``results.csv``) with gsplat's runs and one recipe's ``jsgs`` runs; each VARIANT
folder (a bench folder brought back from a GPU call, or several: their rows are pooled) holds the other
recipe's ``jsgs`` runs, on the same datasets and seeds. Gsplat's runs come from BASE, or from the variant
folders where BASE has none for that scene, schedule, budget and seed. Each scene is compared, at each
budget, at the last evaluation every run in the comparison reached (:func:`jsgs.bench.budget.common_steps`).
Prints a markdown table: per cell, the seed means of gsplat, BASE and VARIANT, ΔLPIPS % and ΔPSNR dB of each
recipe against gsplat (paired by seed, then averaged), and on how many seeds VARIANT's LPIPS is below BASE's;
then the means over all pairs.
"""

from __future__ import annotations

import statistics
import sys
from pathlib import Path

from jsgs.bench.budget import common_steps
from jsgs.bench.results import read_csv

Key = tuple[str, str, int, int]  # scene, schedule, budget, seed


def runs(rows: list[dict], method: str) -> dict[tuple[Key, int], tuple[float, float]]:
    """{((scene, schedule, budget, seed), step): (lpips, psnr)} of one method's mcmc rows."""
    out = {}
    for r in rows:
        if r["method"] == method and r["strategy"] == "mcmc" and r["lpips"] not in ("", None):
            key = (r["scene"], r["schedule"], int(r["budget"]), int(r["seed"]))
            out[(key, int(r["step"]))] = (float(r["lpips"]), float(r["psnr"]))
    return out


def main(base: Path, variants: list[Path]) -> None:
    base_rows = read_csv(base / "results.csv")
    var_rows = [r for v in variants for r in read_csv(v / "results.csv")]
    gsplat = {**runs(var_rows, "gsplat"), **runs(base_rows, "gsplat")}
    a, b = runs(base_rows, "jsgs"), runs(var_rows, "jsgs")
    seeds_b = {k for k, _ in b}
    # the step: over every run this comparison uses (gsplat's, both recipes') of the variant's cells
    cells = {k[:3] for k in seeds_b}
    # (the variant's rows relabelled: common_steps keys runs by method, and both recipes are "jsgs")
    tagged = base_rows + [{**r, "method": "variant"} if r["method"] == "jsgs" else r for r in var_rows]
    used = [r for r in tagged if (r["scene"], r["schedule"], int(r["budget"])) in cells
            and r["method"] in ("gsplat", "jsgs", "variant") and r["strategy"] == "mcmc"]  # fmt: skip
    at = common_steps(used)
    print(f"BASE {base}; VARIANT {', '.join(map(str, variants))}\n")
    print("| scene | schedule | budget | step | LPIPS gsplat / BASE / VARIANT | ΔLPIPS % BASE / VARIANT "
          "| PSNR gsplat / BASE / VARIANT | ΔPSNR dB BASE / VARIANT | VARIANT lower than BASE |")
    print("|---|---|---:|---:|---|---|---|---|---:|")
    all_a: list[tuple[float, float]] = []
    all_b: list[tuple[float, float]] = []
    for scene, schedule, budget in sorted(cells):
        step = at[(scene, budget)]
        g_l, a_l, b_l, g_p, a_p, b_p, da, db, wins, n = [], [], [], [], [], [], [], [], 0, 0
        for seed in sorted(s for (sc, sh, bu, s) in seeds_b if (sc, sh, bu) == (scene, schedule, budget)):
            key = (scene, schedule, budget, seed)
            g, x, y = gsplat.get((key, step)), a.get((key, step)), b.get((key, step))
            if g is None or y is None:
                continue
            g_l.append(g[0])
            g_p.append(g[1])
            b_l.append(y[0])
            b_p.append(y[1])
            db.append((100 * (y[0] / g[0] - 1), y[1] - g[1]))
            if x is not None:
                a_l.append(x[0])
                a_p.append(x[1])
                da.append((100 * (x[0] / g[0] - 1), x[1] - g[1]))
                n += 1
                wins += y[0] < x[0]
        if not db:
            print(f"| {scene} | {schedule} | {budget:,} | {step} | no gsplat run at this step | | | | |")
            continue
        all_a += da
        all_b += db

        print(f"| {scene} | {schedule} | {budget:,} | {step} | "
              f"{avg(g_l, 4)} / {avg(a_l, 4)} / {avg(b_l, 4)} | "
              f"{mean(da, 0, 1)} / {mean(db, 0, 1)} | {avg(g_p, 2)} / {avg(a_p, 2)} / {avg(b_p, 2)} | "
              f"{mean(da, 1, 2)} / {mean(db, 1, 2)} | {wins}/{n} |")  # fmt: skip
    print(f"\nover the pairs: BASE {len(all_a)} pairs, ΔLPIPS {mean(all_a, 0, 1)} %, ΔPSNR "
          f"{mean(all_a, 1, 2)} dB; VARIANT {len(all_b)} pairs, ΔLPIPS {mean(all_b, 0, 1)} %, ΔPSNR "
          f"{mean(all_b, 1, 2)} dB")  # fmt: skip


def mean(v: list[tuple[float, float]], i: int, d: int) -> str:
    """The mean of the i-th member of paired differences, signed, d decimals."""
    return f"{statistics.mean(p[i] for p in v):+.{d}f}" if v else "—"


def avg(v: list[float], d: int) -> str:
    return f"{statistics.mean(v):.{d}f}" if v else "—"


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit("usage: compare.py BASE VARIANT [VARIANT ...]  (results folders; see the docstring)")
    main(Path(sys.argv[1]), [Path(p) for p in sys.argv[2:]])
