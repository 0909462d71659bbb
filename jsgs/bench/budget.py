"""The equal-budget part of a bench report: the runs of ``jsgs bench --strategy mcmc --budgets ...``, where
gsplat, JSGS and the clean ceiling train with the same Gaussian cap (``budget`` in results.csv).

Everything is compared at the bench's final evaluation step (or a step given per report or per scene, for
runs that stopped early), per scene × schedule × budget:

- the metrics of each method (mean ± sd over seeds), its final #Gaussians and training time;
- the damage recovered against the clean run *at the same budget* (:func:`jsgs.bench.stats.damage_recovered`);
- paired differences JSGS − gsplat over seeds (the same dataset and seed): mean and 95 % t-interval;
- wins: the scene × schedule × seed pairs where JSGS's LPIPS (PSNR) is better;
- time to quality: the first evaluation step at which JSGS reaches gsplat's final LPIPS of the same seed.
"""

from __future__ import annotations

import math
import statistics
from collections import defaultdict
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from jsgs.bench.plots import METHOD_COLORS, SCHEDULE_STYLES
from jsgs.bench.stats import HIGHER_BETTER, agg, damage_recovered, mean_of, worse_beyond_spread
from jsgs.bench.tables import count_label, md_table, number

#: two-sided 95 % quantiles of Student's t with 1..30 degrees of freedom (beyond: the normal's 1.960)
T975 = (
    12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145, 2.131,
    2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042,
)  # fmt: skip

Budget = int | str  # a cap, or "auto" (the scene-sized budget: each run's own, see num_gaussians)
Key = tuple[str, str, Budget]  # scene, schedule, budget
StepKey = str | tuple[str, Budget]  # a scene, or (scene, budget)


#: the scene-sized budget's label (jsgs.bench.plan.AUTO)
AUTO = "auto"
#: the auto rule's target: LPIPS within this of the best fixed budget's ...
AUTO_LPIPS_SLACK = 0.005
#: ... with at most this many times the Gaussians of the smallest fixed budget within the slack
AUTO_SIZE_SLACK = 1.1


def budget_of(r: dict[str, Any]) -> Budget:
    """A row's budget: its cap, or ``auto``."""
    b = r["budget"]
    return b if isinstance(b, str) and not b.isdigit() else int(b)


def label(b: Budget) -> str:
    """``300,000``, or ``auto``."""
    return f"{b:,}" if isinstance(b, int) else str(b)


def order(b: Budget) -> tuple[int, int, str]:
    """Sort key: caps by size, then auto."""
    return (0, b, "") if isinstance(b, int) else (1, 0, b)


def t975(df: int) -> float:
    """The 97.5 % quantile of Student's t with ``df`` ≥ 1 degrees of freedom."""
    return T975[df - 1] if df <= len(T975) else 1.960


def mean_ci(values: list[float]) -> tuple[float | None, float | None]:
    """(mean, half-width of its 95 % t-interval); the half-width is None with fewer than two values."""
    if not values:
        return None, None
    m = statistics.fmean(values)
    if len(values) < 2:
        return m, None
    return m, t975(len(values) - 1) * statistics.stdev(values) / math.sqrt(len(values))


def budget_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows of mcmc runs (results.csv's ``strategy`` mcmc, with a budget)."""
    return [r for r in rows if r.get("strategy") == "mcmc" and r.get("budget") is not None]


def common_steps(rows: list[dict[str, Any]]) -> dict[tuple[str, Budget], int]:
    """Per scene and budget, the last evaluation step every one of its equal-budget runs reached (the step to
    compare runs that stopped at different points): ``{(scene, budget): step}``."""
    last: dict[tuple[str, str, str, Budget, int], int] = {}
    for r in budget_rows(rows):
        k = (r["scene"], r["schedule"], r["method"], budget_of(r), int(r["seed"]))
        last[k] = max(last.get(k, 0), int(r["step"]))
    out: dict[tuple[str, Budget], int] = {}
    for (scene, _, _, budget, _), st in last.items():
        out[(scene, budget)] = min(out.get((scene, budget), st), st)
    return out


def _differences(
    base: dict[int, float], other: dict[int, float], relative: bool, within: Iterable[int] | None = None
) -> list[float]:
    """``other`` − ``base`` per seed both hold (and ``within``, if given), in seed order; ``relative``:
    100 (other / base − 1), in %, leaving out seeds where ``base`` is 0."""
    seeds = sorted(set(base) & set(other) if within is None else set(base) & set(other) & set(within))
    if relative:
        return [100.0 * (other[s] / base[s] - 1.0) for s in seeds if base[s]]
    return [other[s] - base[s] for s in seeds]


def _ci(m: float | None, h: float | None, digits: int) -> str:
    if m is None:
        return "n/a"
    return number(m, digits, True) + (f" ± {h:.{digits}f}" if h is not None else " (1 seed)")


def _table(header: list[str], body: list[list[str]], left: int = 3) -> list[str]:
    """The first ``left`` columns (scene, schedule, budget, method...) on the left, numbers on the right."""
    return md_table(header, body, "l" * left + "r" * (len(header) - left))


class BudgetReport:
    """The equal-budget tables of one bench's mcmc rows (see the module docstring)."""

    def __init__(self, rows: list[dict[str, Any]], step: int | Mapping[StepKey, int] | None = None):
        """``step``: the evaluation step the tables compare (default: the last one), or one per scene or per
        scene and budget (``{scene: step}``, ``{(scene, budget): step}``, e.g. :func:`common_steps`; those not
        named use the last one); evaluations after it are left out, so runs that stopped early can be
        compared where every one of them got to."""
        rows = budget_rows(rows)
        last = max((int(r["step"]) for r in rows), default=0)
        #: compare steps per scene or (scene, budget) (empty: every scene at ``step``)
        self.scene_steps: dict[StepKey, int] = dict(step) if isinstance(step, Mapping) else {}
        self.step = last if step is None or isinstance(step, Mapping) else step
        self.rows = [r for r in rows if int(r["step"]) <= self.step_at(r["scene"], budget_of(r))]
        # (scene, schedule, method, budget) -> {seed: final row}
        self.final: dict[tuple[str, str, str, Budget], dict[int, dict[str, Any]]] = defaultdict(dict)
        # (scene, schedule, method, budget, seed) -> [(step, row)]
        self.curves: dict[tuple[str, str, str, Budget, int], list[tuple[int, dict[str, Any]]]]
        self.curves = defaultdict(list)
        for r in self.rows:
            k = (r["scene"], r["schedule"], r["method"], budget_of(r))
            self.curves[(*k, int(r["seed"]))].append((int(r["step"]), r))
            if int(r["step"]) == self.step_at(r["scene"], budget_of(r)):
                self.final[k][int(r["seed"])] = r
        for c in self.curves.values():
            c.sort(key=lambda x: x[0])
        self.keys: list[Key] = sorted(
            {(sc, sch, b) for (sc, sch, m, b) in self.final if sch != "clean" and m == "gsplat"},
            key=lambda k: (k[0], k[1], order(k[2])),
        )
        #: the JSGS methods compared with gsplat: jsgs first, then its variants (jsgs_eff, ...)
        methods = {m for (_, _, m, _) in self.final if m != "gsplat"}
        self.variants = sorted(methods, key=lambda m: (m != "jsgs", m))

    def step_at(self, scene: str, budget: Budget | None = None) -> int:
        """The evaluation step the tables compare for ``scene`` (at ``budget``)."""
        if budget is not None and (scene, budget) in self.scene_steps:
            return self.scene_steps[(scene, budget)]
        return self.scene_steps.get(scene, self.step)

    def step_label(self) -> str:
        """``step N``, or the steps per scene and budget (``steps: a 10000; b 9000 (300,000), 10000
        (100,000)``)."""
        if not self.scene_steps:
            return f"step {self.step}"
        return "steps: " + "; ".join(f"{sc} {self.scene_step_label(sc)}"
                                     for sc in sorted({r["scene"] for r in self.rows}))  # fmt: skip

    def scene_step_label(self, scene: str) -> str:
        """The step ``scene`` is compared at (``10000``), or one per budget where they differ (``9000
        (300,000), 10000 (100,000)``)."""
        budgets = sorted({budget_of(r) for r in self.rows if r["scene"] == scene}, key=order)
        steps = {b: self.step_at(scene, b) for b in budgets}
        if len(set(steps.values())) <= 1:
            return str(self.step_at(scene, budgets[0] if budgets else None))
        return ", ".join(f"{st} ({label(b)})" for b, st in steps.items())

    def values(self, scene: str, schedule: str, method: str, budget: Budget, metric: str) -> dict[int, float]:
        """seed -> the metric at the final step."""
        rows = self.final.get((scene, schedule, method, budget), {})
        return {s: float(r[metric]) for s, r in rows.items() if r.get(metric) is not None}

    def paired(
        self, key: Key, metric: str, relative: bool = False, method: str = "jsgs",
        within: Iterable[int] | None = None,
    ) -> list[float]:
        """``method`` − gsplat per common seed (``relative``: 100 (method / gsplat − 1), in %); ``within``:
        only those seeds (e.g. the ones another method also holds), else every common seed."""
        sc, sch, b = key
        g, j = self.values(sc, sch, "gsplat", b, metric), self.values(sc, sch, method, b, metric)
        return _differences(g, j, relative, within)

    def ceiling(self, key: Key, metric: str = "lpips") -> list[float]:
        """The clean run − gsplat per common seed at ``key``'s budget (LPIPS: 100 (clean / gsplat − 1), in %):
        what a recipe would gain by removing all of the JPEG damage."""
        sc, sch, b = key
        g, c = self.values(sc, sch, "gsplat", b, metric), self.values(sc, "clean", "gsplat", b, metric)
        return _differences(g, c, relative=metric == "lpips")

    def time_to_quality(self, key: Key, method: str = "jsgs") -> list[int | None]:
        """Per seed with both runs: the first evaluation step at which ``method``'s LPIPS is at most gsplat's
        final LPIPS of the same seed (None: not reached)."""
        sc, sch, b = key
        g = self.values(sc, sch, "gsplat", b, "lpips")
        out: list[int | None] = []
        for seed in sorted(g):
            curve = self.curves.get((sc, sch, method, b, seed))
            if not curve or curve[-1][0] != self.step_at(sc, b):
                continue
            reached = (st for st, r in curve if r.get("lpips") is not None and r["lpips"] <= g[seed])
            out.append(next(reached, None))
        return out

    # -------------------------------------------------------------------------------------------------
    def comparison(self) -> list[str]:
        header = [
            "Scene", "Schedule", "Budget", "JSGS", "seeds", "LPIPS gsplat", "LPIPS JSGS", "LPIPS clean",
            "ΔLPIPS % (95 % CI)", "R_LPIPS", "PSNR gsplat", "PSNR JSGS", "PSNR clean", "ΔPSNR dB (95 % CI)",
            "R_PSNR", "wins LPIPS / PSNR", "JSGS worse beyond spread?",
        ]  # fmt: skip
        body = []
        for key, v in ((k, v) for k in self.keys for v in self.variants):
            sc, sch, b = key
            lp, ps = self.paired(key, "lpips", method=v), self.paired(key, "psnr", method=v)
            if not lp:
                continue
            cells = [sc, sch, label(b), v, str(len(lp))]
            worse = []
            for metric, digits in (("lpips", 4), ("psnr", 2)):
                g = agg(list(self.values(sc, sch, "gsplat", b, metric).values()))
                j = agg(list(self.values(sc, sch, v, b, metric).values()))
                c = agg(list(self.values(sc, "clean", "gsplat", b, metric).values()))
                d = self.paired(key, "lpips", relative=True, method=v) if metric == "lpips" else ps
                rec = damage_recovered(g, j, c, HIGHER_BETTER[metric])
                r_txt = number(rec.value, 2) + (f" ({rec.note})" if rec.note else "")
                if rec.value is None:
                    r_txt = rec.note
                cells += [number(g.mean, digits), number(j.mean, digits), number(c.mean, digits),
                          _ci(*mean_ci(d), 1 if metric == "lpips" else 2), r_txt]  # fmt: skip
                w = worse_beyond_spread(g, j, HIGHER_BETTER[metric])
                verdict = "unknown (1 seed)" if w is None else ("**yes**" if w else "no")
                worse.append(f"{metric}: {verdict}")
            lw, pw = sum(1 for x in lp if x < 0), sum(1 for x in ps if x > 0)
            cells += [f"{lw}/{len(lp)} / {pw}/{len(ps)}", "; ".join(worse)]
            body.append(cells)
        return _table(header, body, 4) if body else ["No budget has both gsplat and JSGS runs."]

    def targets(self) -> list[str]:
        """Per budget: the project's targets over every scene × schedule × seed pair, met or not."""
        budgets = sorted({b for _, _, b in self.keys}, key=order)
        header = [
            "Budget", "pairs", "LPIPS lower (target ≥ 90 %)", "mean ΔLPIPS % (target ≤ −25 %)",
            "clean's mean ΔLPIPS % (the ceiling)", "worse beyond spread (target: none)",
            "mean ΔPSNR dB (target ≥ 0)", "all met",
        ]  # fmt: skip
        body = []
        for b in budgets:
            keys = [k for k in self.keys if k[2] == b]
            lp = [x for k in keys for x in self.paired(k, "lpips", relative=True)]
            ceiling = mean_of([x for k in keys for x in self.ceiling(k)])
            ps = [x for k in keys for x in self.paired(k, "psnr")]
            worse = []
            for sc, sch, _ in keys:
                for metric in ("lpips", "psnr"):
                    g = agg(list(self.values(sc, sch, "gsplat", b, metric).values()))
                    j = agg(list(self.values(sc, sch, "jsgs", b, metric).values()))
                    if worse_beyond_spread(g, j, HIGHER_BETTER[metric]):
                        worse.append(f"{sc}/{sch} {metric}")
            won = 100.0 * sum(1 for x in lp if x < 0) / len(lp) if lp else None
            mlp, mps = mean_of(lp), mean_of(ps)
            ok = [won is not None and won >= 90, mlp is not None and mlp <= -25, not worse,
                  mps is not None and mps >= 0]  # fmt: skip
            body.append([
                label(b), str(len(lp)), number(won, 0) + " %", number(mlp, 1, True), number(ceiling, 1, True),
                ", ".join(worse) or "none", number(mps, 3, True), "met" if all(ok) else "**not met**",
            ])  # fmt: skip
        return _table(header, body) if body else ["No pairs."]

    def quality_time(self) -> list[str]:
        header = ["Scene", "Schedule", "Budget", "JSGS", "step reaching gsplat's final LPIPS, per seed",
                  "fraction of the steps (median)", "target ≤ 0.70"]  # fmt: skip
        body = []
        for key, v in ((k, v) for k in self.keys for v in self.variants):
            steps = self.time_to_quality(key, v)
            if not steps:
                continue
            fr = sorted((s / self.step_at(key[0], key[2])) if s is not None else math.inf for s in steps)
            med = fr[len(fr) // 2]
            per_seed = ", ".join("not reached" if s is None else str(s) for s in steps)
            body.append([
                key[0], key[1], label(key[2]), v, per_seed,
                "not reached" if math.isinf(med) else f"{med:.2f}", "met" if med <= 0.70 else "**not met**",
            ])  # fmt: skip
        return _table(header, body, 4) if body else ["No JSGS run with gsplat at the same budget."]

    def auto_rule(self, method: str = "jsgs") -> list[str]:
        """The scene-sized budget against fixed ones, per scene and schedule where ``method`` trained at
        ``auto`` and at least one fixed budget, on the seeds every one of those runs has: LPIPS at each
        budget, the best fixed one, the smallest fixed budget within :data:`AUTO_LPIPS_SLACK` of it, and
        whether auto meets the target (LPIPS within the slack of the best, at most
        :data:`AUTO_SIZE_SLACK` × the Gaussians of that smallest budget)."""
        cells = sorted({(sc, sch) for (sc, sch, m, b) in self.final if m == method and b == AUTO})
        body = []
        for sc, sch in cells:
            fixed = sorted(b for (s, h, m, b) in self.final if (s, h, m) == (sc, sch, method) and b != AUTO)
            runs = {b: self.final[(sc, sch, method, b)] for b in [*fixed, AUTO]}
            seeds = sorted(set.intersection(*(set(v) for v in runs.values())))
            if not fixed or not seeds or any(runs[b][s].get("lpips") is None for b in runs for s in seeds):
                continue  # LPIPS not measured (no backbone weights, or views too small for AlexNet)

            def mean(b: Budget, k: str, runs: dict[Budget, Any] = runs, seeds: list[int] = seeds) -> float:
                return statistics.fmean(float(runs[b][s][k]) for s in seeds)

            lp = {b: mean(b, "lpips") for b in runs}
            best = min(fixed, key=lambda b: lp[b])
            enough = min(b for b in fixed if lp[b] <= lp[best] + AUTO_LPIPS_SLACK)
            size = mean(AUTO, "num_gaussians")
            close, small = lp[AUTO] <= lp[best] + AUTO_LPIPS_SLACK, size <= AUTO_SIZE_SLACK * int(enough)
            body.append([
                sc, sch, ", ".join(map(str, seeds)),
                "; ".join(f"{label(b)}: {lp[b]:.4f}" for b in fixed), label(best), label(enough),
                number(size, 0), f"{lp[AUTO]:.4f}", f"{lp[AUTO] - lp[best]:+.4f}",
                f"{size / int(enough):.2f}", "met" if close and small else "**not met**",
            ])  # fmt: skip
        header = ["Scene", "Schedule", "seeds", "LPIPS at the fixed budgets", "best",
                  "smallest within 0.005", "auto #Gaussians", "auto LPIPS", "auto − best",
                  "auto / smallest (≤ 1.1)", "target"]  # fmt: skip
        return _table(header, body) if body else []

    def size_time(self) -> list[str]:
        header = ["Scene", "Schedule", "Budget", "Method", "seeds", "#Gaussians", "train s", "time / it ms",
                  "render FPS"]  # fmt: skip
        body = []
        items = sorted(self.final.items(), key=lambda kv: (*kv[0][:3], order(kv[0][3])))
        for (sc, sch, m, b), seeds in items:
            rs = list(seeds.values())

            def mean(k: str, rs: list[dict[str, Any]] = rs) -> float | None:
                return agg([r.get(k) for r in rs]).mean

            tpi = mean("time_per_iteration_s")
            body.append([sc, sch, label(b), m, str(len(rs)), number(mean("num_gaussians"), 0),
                         number(mean("train_seconds"), 1), number(tpi * 1000 if tpi else None, 2),
                         number(mean("fps"), 0)])  # fmt: skip
        return _table(header, body) if body else ["No runs."]

    def markdown(self, plots: list[Path]) -> list[str]:
        if not self.rows:
            return []
        intro = (
            "Every method and the clean ceiling (gsplat on the lossless views) trained with the same cap; "
            "budget = strategy.cap_max. ΔLPIPS % = 100 (JSGS / gsplat − 1) per seed, ΔPSNR = JSGS − gsplat "
            "per seed: paired over seeds (same dataset), mean ± half-width of the 95 % t-interval. R against "
            'the clean run at the same budget, on seed means ("within noise" where the damage is not larger '
            "than the seed spread)."
        )
        md = [f"## Equal Gaussian budget (gsplat's MCMCStrategy), {self.step_label()}", "", intro, ""]
        md += [*self.comparison(), ""]
        md += ["### Targets at each budget (jsgs; every scene × schedule × seed pair)", ""]
        md += [*self.targets(), ""]
        md += ["### Time to quality", "", *self.quality_time(), ""]
        rule = self.auto_rule()
        if rule:
            md += ["### The scene-sized budget (auto) against fixed budgets (JSGS)", "",
                   "Target: auto's LPIPS within 0.005 of the best fixed budget's, with at most 1.1 × the "
                   "Gaussians of the smallest fixed budget that comes within 0.005 of the best (means over "
                   "the seeds every budget has).", "", *rule, ""]  # fmt: skip
        md += [
            "### Model size and time",
            "",
            "Each run's time grows with the runs that shared its GPU (`--jobs-per-gpu`, or other benches on "
            "the same machine): compare times only between runs trained side by side; they are not speed "
            "figures.",
        ]
        md += ["", *self.size_time(), ""]
        if plots:
            md += [f"![{p.stem}](plots/{p.name})" for p in plots] + [""]
        return md


def write_budget_plots(rep: BudgetReport, outdir: Path) -> list[Path]:
    """Per scene: LPIPS and PSNR at the final step against #Gaussians and against training time, one line per
    method and schedule through its budgets (means over seeds); returns the files written."""
    if not rep.rows:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, MaxNLocator

    from jsgs.base.io import write_with_atomic

    outdir.mkdir(parents=True, exist_ok=True)
    colors, styles = METHOD_COLORS, SCHEDULE_STYLES
    written = []
    for sc in sorted({k[0] for k in rep.final}):
        fig, axes = plt.subplots(2, 2, figsize=(11, 8))
        series = sorted({(sch, m) for (s, sch, m, _) in rep.final if s == sc})
        sizes: set[float] = set()  # the mean #Gaussians of every point drawn
        for sch, m in series:
            pts = []
            for b in sorted({k[3] for k in rep.final if k[:3] == (sc, sch, m)}, key=order):
                rs = list(rep.final[(sc, sch, m, b)].values())
                pts.append(tuple(agg([r.get(k) for r in rs]).mean
                                 for k in ("num_gaussians", "train_seconds", "lpips", "psnr")))  # fmt: skip
            color = "gray" if sch == "clean" else colors.get(m, "black")
            sizes.update(p[0] for p in pts if p[0] is not None)
            for ax, (xi, yi) in zip(axes.flat, [(0, 2), (0, 3), (1, 2), (1, 3)], strict=True):
                xy = [(p[xi], p[yi]) for p in pts if p[xi] is not None and p[yi] is not None]
                if xy:
                    ax.plot(*zip(*xy, strict=True), styles.get(sch, "-"), marker="o", ms=4, color=color,
                            label=f"{m} {sch}")  # fmt: skip
        labels = [("#Gaussians", "LPIPS"), ("#Gaussians", "PSNR (dB)"), ("training time (s)", "LPIPS"),
                  ("training time (s)", "PSNR (dB)")]  # fmt: skip
        for ax, (xl, yl) in zip(axes.flat, labels, strict=True):
            ax.set_xlabel(xl)
            ax.set_ylabel(yl)
            ax.grid(alpha=0.3)
        for ax in axes[0]:  # counts as 100k, 1.5M (six-digit tick labels run into each other), ticked at the
            # budgets' sizes where there are few
            if len(sizes) <= 6:
                ax.set_xticks(sorted(sizes))
            else:
                ax.xaxis.set_major_locator(MaxNLocator(nbins=6))
            ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: count_label(v)))
        if axes[0, 0].get_legend_handles_labels()[0]:  # none for an empty panel (matplotlib warns)
            axes[0, 0].legend(fontsize=7)
        fig.suptitle(f"{sc}: step {rep.scene_step_label(sc)} at each Gaussian budget (means over seeds)")
        fig.tight_layout()
        path = outdir / f"{sc}_budgets.png"
        write_with_atomic(path, lambda p, fig=fig: fig.savefig(p, dpi=110, format="png"))
        plt.close(fig)
        written.append(path)
    return written
