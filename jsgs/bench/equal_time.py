"""Quality against training time: each JSGS run against gsplat *at the same training seconds*, beside the
equal-step tables (a JSGS step costs more than a gsplat step, so equal steps favour JSGS in time).

For every JSGS run (and variant) on a JPEG schedule, at the end of its recipe (its last evaluation within
``schedule_steps``), gsplat's run of the same scene, schedule, strategy, budget and seed is read at the same
``train_seconds`` (training time up to the evaluation; evaluations excluded), linearly interpolated between
the two gsplat evaluations around that time. A JSGS run that ended after gsplat's last evaluation (or before
its first) is **not compared**: gsplat is never extrapolated; ``jsgs bench --gsplat-steps`` trains gsplat
past its recipe's length so that its evaluations reach JSGS's end. Runs whose devices were shared
differently (results.csv ``runs_per_device``) are not compared either: their seconds do not measure the same
thing.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from jsgs.bench.plots import METHOD_COLORS, SCHEDULE_STYLES
from jsgs.bench.stats import agg, mean_of
from jsgs.bench.tables import md_table, number

Curve = list[tuple[float, float]]  # (seconds, value), seconds increasing
#: scene, schedule, strategy, budget (None: DefaultStrategy), seed
PairKey = tuple[str, str, str, Any, int]


def interpolate(curve: Curve, t: float) -> float | None:
    """The value of the piecewise-linear ``curve`` at ``t``; None outside its first and last points (never
    extrapolated) or for an empty curve."""
    if not curve or t < curve[0][0] or t > curve[-1][0]:
        return None
    for (t0, v0), (t1, v1) in zip(curve, curve[1:], strict=False):
        if t0 <= t <= t1:
            return v0 if t1 == t0 else v0 + (v1 - v0) * (t - t0) / (t1 - t0)
    return curve[-1][1]  # a single point, at exactly t


@dataclass
class Pair:
    """One JSGS run's end against gsplat at the same seconds."""

    scene: str
    schedule: str
    strategy: str
    budget: Any
    method: str
    seed: int
    step: int  # JSGS's step
    seconds: float  # its training seconds there
    lpips: float | None  # JSGS
    psnr: float | None
    gsplat_lpips: float | None = None  # gsplat at ``seconds`` (None: not compared)
    gsplat_psnr: float | None = None
    gsplat_step: float | None = None  # the (interpolated) step gsplat had reached at ``seconds``
    share: int | None = None  # runs per device of the JSGS run
    gsplat_share: int | None = None
    note: str = ""  # why it is not compared (empty: compared)

    @property
    def compared(self) -> bool:
        return not self.note

    @property
    def d_lpips(self) -> float | None:
        """100 (JSGS / gsplat − 1), in %."""
        if not self.compared or self.lpips is None or not self.gsplat_lpips:
            return None
        return 100.0 * (self.lpips / self.gsplat_lpips - 1.0)

    @property
    def d_psnr(self) -> float | None:
        if not self.compared or self.psnr is None or self.gsplat_psnr is None:
            return None
        return self.psnr - self.gsplat_psnr


def _num(v: Any) -> float | None:
    return None if v is None or not math.isfinite(float(v)) else float(v)


def _within_recipe(r: dict[str, Any]) -> bool:
    return r.get("schedule_steps") is None or int(r["step"]) <= int(r["schedule_steps"])


def pairs(rows: list[dict[str, Any]]) -> list[Pair]:
    """Every JSGS run's end against gsplat at the same seconds (see the module docstring), sorted."""
    runs: dict[tuple[str, str, str, Any, str, int], list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        if r.get("train_seconds") is None:
            continue
        key = (r["scene"], r["schedule"], r.get("strategy") or "default", r.get("budget"), r["method"],
               int(r["seed"]))  # fmt: skip
        runs[key].append(r)
    # the recipe's end where results.csv does not give it: the last step any run of the strategy reached
    reached: dict[str, int] = defaultdict(int)
    for r in rows:
        if _within_recipe(r):
            strat = r.get("strategy") or "default"
            reached[strat] = max(reached[strat], int(r["step"]))
    out = []
    for (sc, sch, strat, b, m, seed), rs in sorted(runs.items(), key=lambda kv: str(kv[0])):
        if m == "gsplat" or sch == "clean":
            continue
        ends = [r for r in rs if _within_recipe(r)]
        if not ends:
            continue
        end = max(ends, key=lambda r: int(r["step"]))
        p = Pair(sc, sch, strat, b, m, seed, int(end["step"]), float(end["train_seconds"]),
                 _num(end.get("lpips")), _num(end.get("psnr")), share=end.get("runs_per_device"))  # fmt: skip
        g = sorted(runs.get((sc, sch, strat, b, "gsplat", seed), []), key=lambda r: int(r["step"]))
        recipe = int(end["schedule_steps"]) if end.get("schedule_steps") is not None else reached[strat]
        if p.step < recipe:
            p.note = f"stopped at step {p.step}, before its recipe's end ({recipe})"
        if not g:  # a bench of JSGS alone (the budgets' rule) compares nothing in time
            p.note = p.note or "no gsplat run"
            out.append(p)
            continue
        p.gsplat_share = g[-1].get("runs_per_device")
        first, last = float(g[0]["train_seconds"]), float(g[-1]["train_seconds"])
        if p.share is not None and p.gsplat_share is not None and p.share != p.gsplat_share:
            p.note = f"devices shared differently ({p.share} vs gsplat's {p.gsplat_share} runs per device)"
        elif p.seconds > last:
            p.note = (
                f"gsplat's last evaluation (step {g[-1]['step']}) is at {last:.0f} s, before JSGS's "
                f"{p.seconds:.0f} s: not extrapolated (train gsplat longer: --gsplat-steps)"
            )
        elif p.seconds < first:
            p.note = f"before gsplat's first evaluation ({first:.0f} s): not extrapolated"
        else:

            def at(key: str, g: list[dict[str, Any]] = g, t: float = p.seconds) -> float | None:
                curve = [(float(r["train_seconds"]), v) for r in g if (v := _num(r.get(key))) is not None]
                return interpolate(curve, t)

            p.gsplat_lpips, p.gsplat_psnr, p.gsplat_step = at("lpips"), at("psnr"), at("step")
        out.append(p)
    return out


def _budget(b: Any) -> str:
    if b is None:
        return "none"
    return f"{b:,}" if isinstance(b, int) else str(b)


def _share(p: Pair) -> str:
    if p.share is None and p.gsplat_share is None:
        return "unstated"
    if p.share == p.gsplat_share or p.gsplat_share is None:  # the same, or no gsplat run to share with
        return str(p.share)
    return f"{p.share} / {p.gsplat_share}"


def table(ps: list[Pair]) -> list[str]:
    """One row per JSGS run: its end, gsplat at the same seconds, the differences."""
    header = ["Scene", "Schedule", "Budget", "JSGS", "seed", "step", "train s", "gsplat's step then",
              "LPIPS gsplat", "LPIPS JSGS", "ΔLPIPS %", "PSNR gsplat", "PSNR JSGS", "ΔPSNR dB",
              "runs per device", "not compared because"]  # fmt: skip
    body = [
        [p.scene, p.schedule, _budget(p.budget), p.method, str(p.seed), str(p.step), number(p.seconds, 0),
         number(p.gsplat_step, 0), number(p.gsplat_lpips, 4), number(p.lpips, 4), number(p.d_lpips, 1, True),
         number(p.gsplat_psnr, 2), number(p.psnr, 2), number(p.d_psnr, 2, True), _share(p), p.note]
        for p in ps
    ]  # fmt: skip
    return md_table(header, body, "lllll" + "r" * 10 + "l") if body else ["No JSGS run on a JPEG schedule."]


def summary(ps: list[Pair]) -> list[str]:
    """Per strategy, budget and JSGS method: the pairs compared, LPIPS lower (target ≥ 90 %), the mean
    differences (mean ΔPSNR target ≥ 0), the pairs not compared."""
    groups: dict[tuple[str, str, str], list[Pair]] = defaultdict(list)
    for p in ps:
        groups[(p.strategy, _budget(p.budget), p.method)].append(p)
    header = ["Strategy", "Budget", "JSGS", "pairs compared", "LPIPS lower (target ≥ 90 %)", "mean ΔLPIPS %",
              "mean ΔPSNR dB (target ≥ 0)", "PSNR higher", "not compared", "targets"]  # fmt: skip
    body = []
    for (strat, b, m), group in sorted(groups.items()):
        done = [p for p in group if p.compared and p.d_lpips is not None]
        lower = sum(1 for p in done if (p.d_lpips or 0.0) < 0)
        psnr = [p.d_psnr for p in done if p.d_psnr is not None]
        won = 100.0 * lower / len(done) if done else None
        mps = mean_of(psnr)
        met = won is not None and won >= 90 and mps is not None and mps >= 0
        body.append([
            strat, b, m, str(len(done)), f"{lower}/{len(done)} ({number(won, 0)} %)",
            number(mean_of([p.d_lpips for p in done]), 1, True), number(mps, 3, True),
            f"{sum(1 for x in psnr if x > 0)}/{len(psnr)}", str(len(group) - len(done)),
            ("met" if met else "**not met**") if done else "n/a",
        ])  # fmt: skip
    return md_table(header, body, "lll" + "r" * 7) if body else ["No pairs."]


def markdown(rows: list[dict[str, Any]], plots: list[Path]) -> list[str]:
    """The report's equal-time section (empty without a JSGS run on a JPEG schedule)."""
    ps = pairs(rows)
    if not ps:
        return []
    shares = sorted({str(x) for p in ps for x in (p.share, p.gsplat_share) if x is not None})
    how = (
        "device sharing not stated by the runs"
        if not shares
        else "runs per device: " + ", ".join("1 (one run per GPU)" if s == "1" else s for s in shares)
    )
    md = [
        "## Equal training time",
        "",
        "Each JSGS run at the end of its recipe against gsplat *at the same training seconds* (the same "
        "scene, schedule, budget and seed; training time up to the evaluation, evaluations excluded), "
        "linearly interpolated between gsplat's two evaluations around that time, never extrapolated: a run "
        "that ends after gsplat's last evaluation is listed as not compared (train gsplat longer with "
        "--gsplat-steps). ΔLPIPS % = 100 (JSGS / gsplat − 1), ΔPSNR = JSGS − gsplat. Seconds compare only "
        f"between runs that shared their devices alike; {how}.",
        "",
        *summary(ps),
        "",
        *table(ps),
        "",
    ]
    md += [f"![{p.stem}](plots/{p.name})" for p in plots] + ([""] if plots else [])
    return md


def write_plots(rows: list[dict[str, Any]], outdir: Path) -> list[Path]:
    """Per scene: LPIPS and PSNR against training seconds, one line per method, schedule and budget (means
    over seeds at each evaluation step; gsplat's points past its recipe hollow), each JSGS run's end marked
    by the table's comparison; returns the files written (none without a JSGS run on a JPEG schedule)."""
    ps = pairs(rows)
    if not ps:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    outdir.mkdir(parents=True, exist_ok=True)
    colors, styles = METHOD_COLORS, SCHEDULE_STYLES
    written = []
    for sc in sorted({p.scene for p in ps}):
        lines: dict[tuple[str, str, str], dict[int, list[dict[str, Any]]]]
        lines = defaultdict(lambda: defaultdict(list))
        for r in rows:
            if r["scene"] == sc and r.get("train_seconds") is not None:
                lines[(r["schedule"], r["method"], _budget(r.get("budget")))][int(r["step"])].append(r)
        fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
        for (sch, m, b), steps in sorted(lines.items()):
            pts = sorted(steps)
            color = "gray" if sch == "clean" else colors.get(m, "black")
            for ax, key in zip(axes, ("lpips", "psnr"), strict=True):
                xy = [(agg([r["train_seconds"] for r in steps[s]]).mean,
                       agg([r.get(key) for r in steps[s]]).mean, _within_recipe(steps[s][0]))
                      for s in pts]  # fmt: skip
                xy = [(x, y, inside) for x, y, inside in xy if x is not None and y is not None]
                if not xy:
                    continue
                ax.plot([x for x, _, _ in xy], [y for _, y, _ in xy], styles.get(sch, "-"), color=color,
                        label=f"{m} {sch} {b}")  # fmt: skip
                ax.scatter([x for x, _, i in xy if i], [y for _, y, i in xy if i], s=12, color=color)
                past = [(x, y) for x, y, i in xy if not i]
                if past:
                    ax.scatter(*zip(*past, strict=True), s=16, facecolors="none", edgecolors=color)
        for ax, label in zip(axes, ("LPIPS", "PSNR (dB)"), strict=True):
            for p in ps:
                if p.scene == sc and p.compared:
                    ax.axvline(p.seconds, color="tab:red", alpha=0.15, lw=0.8)
            ax.set_xlabel("training time (s)")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        if axes[0].get_legend_handles_labels()[0]:  # none for an empty panel (matplotlib warns)
            axes[0].legend(fontsize=7)
        fig.suptitle(f"{sc}: test metrics against training time (means over seeds; faint: JSGS's ends)")
        fig.tight_layout()
        path = outdir / f"{sc}_time.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written
