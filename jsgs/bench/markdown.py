"""``RESULTS/report.md`` from the rows of ``results.csv``: the paper's Tables 1-4 layout, the damage
recovered, per-scene tables and the loss terms, at the bench's final evaluation step (and again at the last
step every run reached, when some stopped early), and the equal-time comparison
(:mod:`jsgs.bench.equal_time`). The numbers and their rules (seed means, spread, "within noise") are
:mod:`jsgs.bench.stats`'s; the figures are :mod:`jsgs.bench.plots`'s."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from jsgs.bench import equal_time, per_view
from jsgs.bench.budget import BudgetReport, StepKey, write_budget_plots
from jsgs.bench.plan import ABLATION_ALIAS, ABLATION_PARTS, ABLATION_SCHEDULE, MIXED_SCHEDULES
from jsgs.bench.plots import write_plots
from jsgs.bench.results import within_recipe
from jsgs.bench.stats import (
    DIGITS,
    HIGHER_BETTER,
    METHOD_NAMES,
    METRICS,
    NAMES,
    Agg,
    agg,
    by_seed,
    common_step,
    damage_recovered,
    last_step,
    mean_of,
    unfinished,
    worse_beyond_spread,
)
from jsgs.bench.tables import md_table as _table
from jsgs.bench.tables import number as _f


def _ms(a: Agg, digits: int) -> str:
    """mean ± sd (sd only with several seeds)."""
    if a.mean is None:
        return "n/a"
    return _f(a.mean, digits) + (f" ± {a.sd:.{digits}f}" if a.sd is not None else "")


class Report:
    def __init__(self, rows: list[dict[str, Any]], step: int | None = None):
        self.rows = rows
        self.step = last_step(rows) if step is None else step
        self.seeds = by_seed(rows, self.step)
        self.scenes = sorted({r["scene"] for r in rows})
        self.schedules = sorted({r["schedule"] for r in rows})

    def a(self, scene: str, schedule: str, method: str, key: str) -> Agg:
        return agg([r.get(key) for r in self.seeds.get((scene, schedule, method), [])])

    def common_scenes(self, schedule: str, methods: list[str]) -> list[str]:
        return [s for s in self.scenes if all((s, schedule, m) in self.seeds for m in methods)]

    def over_scenes(self, schedule: str, method: str, key: str, scenes: list[str]) -> float | None:
        return mean_of([self.a(s, schedule, method, key).mean for s in scenes])

    # -------------------------------------------------------------------------------------------------
    def table1(self) -> list[str]:
        scheds = [s for s in (*MIXED_SCHEDULES, "clean") if s in self.schedules]
        if not scheds:
            return ["No mixed-quality runs."]
        header = ["Method"] + [f"{s} {NAMES[k]}" for s in scheds for k in METRICS]
        out_rows = []
        for m in ("gsplat", "jsgs"):
            cells = [METHOD_NAMES[m]]
            for s in scheds:
                sc = self.common_scenes(s, ["gsplat", "jsgs"] if s != "clean" else ["gsplat"])
                for k in METRICS:
                    cells.append(
                        _f(self.over_scenes(s, m, k, sc), DIGITS[k]) if s != "clean" or m == "gsplat" else "—"
                    )
            out_rows.append(cells)
        counts = ", ".join(
            f"{s}: {len(self.common_scenes(s, ['gsplat', 'jsgs'] if s != 'clean' else ['gsplat']))}"
            for s in scheds
        )
        return _table(header, out_rows) + [
            "",
            f"Scenes in each mean (those with both methods): {counts}. `clean` = gsplat on the uncompressed "
            "training views (the ceiling).",
        ]

    def lpips_reduction(self, schedule: str, scenes: list[str]) -> tuple[float | None, float | None]:
        """(mean over scenes of 100 (1 - JSGS/gsplat), 100 (1 - mean JSGS / mean gsplat)) for LPIPS."""
        per = []
        for s in scenes:
            b, j = self.a(s, schedule, "gsplat", "lpips").mean, self.a(s, schedule, "jsgs", "lpips").mean
            if b and j is not None:
                per.append(100 * (1 - j / b))
        mb = self.over_scenes(schedule, "gsplat", "lpips", scenes)
        mj = self.over_scenes(schedule, "jsgs", "lpips", scenes)
        of_means = 100 * (1 - mj / mb) if mb and mj is not None else None
        return mean_of(per), of_means

    def damage(self) -> list[str]:
        scheds = [s for s in MIXED_SCHEDULES if s in self.schedules]
        lines: list[str] = []
        header = [
            "Scene", "Schedule", "LPIPS gsplat", "LPIPS JSGS", "LPIPS clean", "ΔLPIPS %", "R_LPIPS",
            "PSNR gsplat", "PSNR JSGS", "PSNR clean", "R_PSNR", "JSGS worse beyond spread?",
        ]  # fmt: skip
        body = []
        per_sched: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
        notes: dict[str, dict[str, list[str]]] = defaultdict(lambda: defaultdict(list))
        for sch in scheds:
            for sc in self.common_scenes(sch, ["gsplat", "jsgs"]):
                cells = [sc, sch]
                worse = []
                rs: dict[str, str] = {}
                for k in ("lpips", "psnr"):
                    b, j = self.a(sc, sch, "gsplat", k), self.a(sc, sch, "jsgs", k)
                    c = self.a(sc, "clean", "gsplat", k)
                    rec = damage_recovered(b, j, c, HIGHER_BETTER[k])
                    if rec.value is not None:
                        per_sched[sch][k].append(rec.value)
                        rs[k] = f"{rec.value:.2f}" + (f" ({rec.note})" if rec.note else "")
                    else:
                        notes[sch][k].append(sc)
                        gap = "" if rec.gap is None else f": gap {abs(rec.gap):.{DIGITS[k]}f}"
                        spr = "" if rec.spread is None else f" ≤ spread {rec.spread:.{DIGITS[k]}f}"
                        rs[k] = rec.note + gap + (spr if rec.note == "within noise" else "")
                    w = worse_beyond_spread(b, j, HIGHER_BETTER[k])
                    worse.append(f"{k}: " + ("unknown (1 seed)" if w is None else ("**yes**" if w else "no")))
                    if k == "lpips":
                        red = 100 * (1 - j.mean / b.mean) if b.mean and j.mean is not None else None
                        cells += [_ms(b, 4), _ms(j, 4), _ms(c, 4), _f(red, 1), rs[k]]
                    else:
                        cells += [_ms(b, 2), _ms(j, 2), _ms(c, 2), rs[k]]
                cells.append("; ".join(worse))
                body.append(cells)
        if not body:
            return ["No scene has both methods on a mixed schedule."]
        lines += _table(header, body, "ll" + "r" * 9 + "l")
        lines += ["", "Per schedule (means over scenes; R only over the scenes where it is defined):", ""]
        sh = ["Schedule", "LPIPS reduction % (mean of per-scene)", "LPIPS reduction % (of means)",
              "mean R_LPIPS", "mean R_PSNR", "target: R ≥ 0.5 in both"]  # fmt: skip
        sb = []
        for sch in scheds:
            sc = self.common_scenes(sch, ["gsplat", "jsgs"])
            per, ofm = self.lpips_reduction(sch, sc)
            cells = [sch, _f(per, 1), _f(ofm, 1)]
            ok = []
            for k in ("lpips", "psnr"):
                vals = per_sched[sch][k]
                mr = mean_of(vals)
                txt = _f(mr, 2) + f" (n = {len(vals)} of {len(sc)})"
                if notes[sch][k]:
                    txt += "; not computed for " + ", ".join(notes[sch][k])
                cells.append(txt)
                ok.append(mr is not None and mr >= 0.5)
            cells.append("met" if all(ok) else "**not met**")
            sb.append(cells)
        lines += _table(sh, sb, "lrrlll")
        return lines

    def table3(self) -> list[str]:
        fixed = sorted((s for s in self.schedules if s.startswith("fixed")), key=lambda s: int(s[5:]))
        if not fixed:
            return ["No fixed-quality runs."]
        header = ["Method"] + [f"q={s[5:]} {NAMES[k]}" for s in fixed for k in METRICS]
        body = []
        for m in ("gsplat", "jsgs"):
            cells = [METHOD_NAMES[m]]
            for s in fixed:
                sc = self.common_scenes(s, ["gsplat", "jsgs"])
                cells += [_f(self.over_scenes(s, m, k, sc), DIGITS[k]) for k in METRICS]
            body.append(cells)
        red = []
        for s in fixed:
            sc = self.common_scenes(s, ["gsplat", "jsgs"])
            per, ofm = self.lpips_reduction(s, sc)
            red.append(f"q={s[5:]}: {_f(per, 1)} % (of means {_f(ofm, 1)} %, {len(sc)} scenes)")
        return _table(header, body) + [
            "",
            "LPIPS reduction, JSGS vs gsplat (mean of per-scene): " + "; ".join(red),
        ]

    def table2(self) -> list[str]:
        scenes = [
            s
            for s in self.scenes
            if any((s, ABLATION_SCHEDULE, v) in self.seeds for v in ("jo", "jo_ds", "jo_gc"))
        ]
        if not scenes:
            return ["No ablation runs."]
        lines = []
        names = {
            "baseline": "Baseline",
            "jo": "JO only",
            "jo_ds": "JO + DS",
            "jo_gc": "JO + GC",
            "full": "Full JSGS",
        }
        for sc in scenes:
            body = []
            for v, parts in ABLATION_PARTS.items():
                m = ABLATION_ALIAS.get(v, v)
                cells = [names[v]] + ["✓" if p else "–" for p in parts]
                for k in METRICS:
                    a = self.a(sc, ABLATION_SCHEDULE, m, k)
                    cells.append(_f(a.mean, DIGITS[k]))
                body.append(cells)
            lines += [
                f"{sc}, {ABLATION_SCHEDULE} schedule, seed {self._first_seed(sc)} "
                "(Baseline = the gsplat run, Full = the jsgs run):",
                "",
            ]
            lines += _table(["Variant", "JO", "DS", "GC", *(NAMES[k] for k in METRICS)], body, "lcccrrr") + [
                ""
            ]
        return lines

    def _first_seed(self, scene: str) -> str:
        rs = self.seeds.get((scene, ABLATION_SCHEDULE, "jo"), [])
        return str(rs[0]["seed"]) if rs else "?"

    def table4(self) -> list[str]:
        scheds = [s for s in self.schedules if s in MIXED_SCHEDULES or s.startswith("fixed")]
        header = ["Method", "train time (min)", "time / iteration (ms)", "render FPS", "#Gaussians",
                  "peak memory (MiB)", "time / it × gsplat"]  # fmt: skip
        body = []
        pairs = [(sc, s) for s in scheds for sc in self.common_scenes(s, ["gsplat", "jsgs"])]
        if not pairs:
            return ["No runs with both methods."]
        base_tpi = mean_of([self.a(sc, s, "gsplat", "time_per_iteration_s").mean for sc, s in pairs])
        for m in ("gsplat", "jsgs"):

            def over(key: str, m: str = m) -> float | None:
                return mean_of([self.a(sc, s, m, key).mean for sc, s in pairs])

            tpi = over("time_per_iteration_s")
            t = over("train_seconds")
            body.append([
                METHOD_NAMES[m], _f(t / 60 if t is not None else None, 2), _f(tpi * 1000 if tpi else None, 2),
                _f(over("fps"), 0), _f(over("num_gaussians"), 0), _f(over("peak_memory_mb"), 0),
                _f(tpi / base_tpi if tpi and base_tpi else None, 3),
            ])  # fmt: skip
        ratios = [
            self.a(sc, s, "jsgs", "time_per_iteration_s").mean / b
            for sc, s in pairs
            if (b := self.a(sc, s, "gsplat", "time_per_iteration_s").mean)
        ]
        return _table(header, body) + [
            "",
            f"Means over {len(pairs)} scene × schedule pairs (mixed and fixed schedules, last step). Per "
            f"pair time/iteration ratio JSGS/gsplat: min {_f(min(ratios) if ratios else None, 3)}, max "
            f"{_f(max(ratios) if ratios else None, 3)} (target ≤ 1.2). Each run's time grows with the "
            "runs that shared its GPU (--jobs-per-gpu): compare times only between runs trained side by "
            "side.",
        ]

    def per_scene(self) -> list[str]:
        lines: list[str] = []
        for sc in self.scenes:
            body = []
            keys = sorted({(sch, m) for (s, sch, m) in self.seeds if s == sc})
            for sch, m in keys:
                cells = [sch, m, str(len(self.seeds[(sc, sch, m)]))]
                cells += [_ms(self.a(sc, sch, m, k), DIGITS[k]) for k in METRICS]
                cells += [
                    _f(self.a(sc, sch, m, "num_gaussians").mean, 0),
                    _f(self.a(sc, sch, m, "train_seconds").mean, 1),
                    _f(self.a(sc, sch, m, "fps").mean, 0),
                ]
                body.append(cells)
            lines += [f"### {sc}", ""]
            lines += _table(["Schedule", "Method", "seeds", *(NAMES[k] for k in METRICS), "#Gaussians",
                             "train s", "FPS"], body, "llrrrrrrr") + [""]  # fmt: skip
        return lines

    def terms(self) -> list[str]:
        keys = sorted({k for r in self.rows for k in r if k.startswith(("loss_", "stat_"))})
        keys = [k for k in keys if any(r.get(k) is not None for r in self.rows if r["method"] != "gsplat")]
        if not keys:
            return ["No method terms recorded."]
        body = []
        for (sc, sch, m), rs in sorted(self.seeds.items()):
            if m == "gsplat":
                continue
            body.append([sc, sch, m] + [_f(agg([r.get(k) for r in rs]).mean, 5) for k in keys])
        return _table(["Scene", "Schedule", "Method", *keys], body, "lll" + "r" * len(keys))


def _paper_sections(rows: list[dict[str, Any]], results_dir: Path, plots: bool) -> list[str]:
    """The paper-protocol part of the report (DefaultStrategy runs): Tables 1-4, damage recovered, per-scene
    results, loss terms, runs that stopped early, plots."""
    md: list[str] = []
    rep = Report(rows)
    pngs = write_plots(rep.rows, rep.seeds, results_dir / "plots") if plots and rows else []
    md += ["## Table 1: mixed-quality schedules (means over scenes, last step)", "", *rep.table1(), ""]
    md += ["## Damage recovered and relative LPIPS reduction", "",
           "R_LPIPS = (gsplat − JSGS) / (gsplat − clean), R_PSNR = (JSGS − gsplat) / (clean − gsplat), on "
           "seed means; ΔLPIPS % = 100 (1 − JSGS / gsplat), the paper's relative reduction. Where |gsplat − "
           "clean| is not larger than the seed spread (max − min over seeds, the larger of gsplat's and "
           "clean's), R is not computed: \"within noise\". Values are mean ± sd over seeds.", "",
           *rep.damage(), ""]  # fmt: skip
    md += ["## Table 2: ablation", "", *rep.table2(), ""]
    md += ["## Table 3: fixed quality (means over scenes, last step)", "", *rep.table3(), ""]
    md += ["## Table 4: training time and rendering speed", "", *rep.table4(), ""]
    md += ["## Per-scene results (last step; mean ± sd over seeds)", "", *rep.per_scene()]
    md += ["## Loss terms and GC statistics (means over the last evaluation interval, unweighted)", "",
           *rep.terms(), ""]  # fmt: skip
    late = unfinished(rows)
    if late:
        at = common_step(rows)
        md += [f"## Runs that stopped before step {rep.step} (not in the tables above)", ""]
        md += [f"- `{sc}/{sch}/{m}/s{seed}`: last evaluation at step {st}" for (sc, sch, m, seed), st in late]
        md += [""]
        if at:
            early = Report(rows, at)
            md += [f"## Table 1 and damage recovered at step {at}, the last step every run reached", "",
                   "The same tables with every run, compared at the same training length.", "",
                   *early.table1(), "", *early.damage(), ""]  # fmt: skip
    md += ["## Plots", ""]
    md += [f"![{p.stem}](plots/{p.name})" for p in pngs] or ["No plots (no results)."]
    return md


def write_report(
    rows: list[dict[str, Any]],
    results_dir: str | Path,
    header_lines: list[str],
    failures: list[dict[str, Any]],
    plots: bool = True,
    budget_step: int | Mapping[StepKey, int] | None = None,
) -> Path:
    """Write RESULTS/report.md (and RESULTS/plots/*.png); returns the report's path. The runs of
    ``--strategy mcmc`` get the equal-budget section (:mod:`jsgs.bench.budget`; at ``budget_step``, one step
    or one per scene or per scene and budget, default the last evaluation) and its per-test-view part
    (:mod:`jsgs.bench.per_view`, from ``results_dir``'s runs or views.json); the DefaultStrategy runs the
    paper's tables; both compare each run up to its recipe's length (:func:`within_recipe`). Then the
    equal-time section (:mod:`jsgs.bench.equal_time`) reads every evaluation."""
    results_dir = Path(results_dir)
    md: list[str] = ["# jsgs bench report", "", *header_lines, ""]
    timed = rows  # every evaluation, gsplat's past its recipe included: the equal-time comparison
    rows = within_recipe(rows)  # the equal-step tables: each run up to its recipe's length
    brep = BudgetReport(rows, budget_step)
    if brep.rows:
        bpngs = write_budget_plots(brep, results_dir / "plots") if plots else []
        md += brep.markdown(bpngs)
        late_b = sorted(
            (k, st) for k, c in brep.curves.items() if (st := c[-1][0]) < brep.step_at(k[0], k[3])
        )
        if late_b:
            md += [f"Budget runs that stopped before the compared {brep.step_label()} (not in the tables "
                   "above):", ""]  # fmt: skip
            md += [f"- `{sc}/{sch}/{m}/mcmc-{b}/s{seed}`: last evaluation at step {st}"
                   for (sc, sch, m, b, seed), st in late_b] + [""]  # fmt: skip
        md += per_view.markdown(brep, per_view.load(results_dir))
    rows = [r for r in rows if r.get("strategy") in (None, "default")]
    if brep.rows and rows:
        md += ["## DefaultStrategy runs", "",
               "The runs without a Gaussian cap (the paper's protocol; under --strategy mcmc, the clean "
               "references that budgets given as multiples are taken from).", ""]  # fmt: skip
    if rows or not brep.rows:
        md += _paper_sections(rows, results_dir, plots)
    time_plots = equal_time.write_plots(timed, results_dir / "plots") if plots else []
    md += ["", *equal_time.markdown(timed, time_plots)]
    md += ["", "## Failed runs", ""]
    # runs that never started (collected with --report-only, or stopped by --time-limit before they began)
    # are listed in one line each, without the empty log excerpt of a real failure
    not_run = [f for f in failures if str(f.get("error", "")).startswith("not ") and not f.get("stderr_tail")]
    failed = [f for f in failures if f not in not_run]
    for f in failed:
        md += [f"- `{f['id']}`: {f.get('error')} (log `{f.get('log')}`)", "", "```",
               *(f.get("stderr_tail") or "").strip().splitlines()[-15:], "```", ""]  # fmt: skip
    if not_run:
        md += [f"Not run ({len(not_run)}):", ""]
        md += [f"- `{f['id']}`: {f.get('error')}" for f in not_run]
    if not failures:
        md += ["None."]
    from jsgs.base.io import write_bytes_atomic

    path = results_dir / "report.md"
    write_bytes_atomic(path, ("\n".join(md) + "\n").encode())
    return path
