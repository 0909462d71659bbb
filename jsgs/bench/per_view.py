"""The "Per test view" part of an equal-budget report: each run's metrics per test view (metrics.json
``evals[].views``), compared JSGS against gsplat of the same scene, schedule, budget and seed at the step the
equal-budget tables use, and the views whose PSNR collapsed during training.

A mean over a handful of test views can be decided by one or two of them: a view whose PSNR falls by 10 dB
while the others improve moves the mean by more than the methods differ. So per pair: on how many views
JSGS's PSNR is higher and its LPIPS lower, the medians of the per-view differences, and the **collapsed**
views of each run (gsplat, JSGS, and the clean run of the same scene, budget and seed): PSNR at the compared
step at least :data:`COLLAPSE_DB` below the view's best at an earlier evaluation.

The views come from the runs' folders (``RESULTS/runs/<scene>/<schedule>/<method>/mcmc-<budget>/s<seed>/
metrics.json``, a bench's layout) or from ``RESULTS/views.json`` (:data:`VIEWS_FILE`, schema
``jsgs/schemas/views.schema.json``: what ``tools/results/build_report.py`` keeps of the runs it gathers, whose
folders do not travel); a folder with neither gets one line saying the section is skipped."""

from __future__ import annotations

import json
import statistics
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from jsgs.bench.budget import Budget, BudgetReport, label
from jsgs.bench.tables import md_table, number

#: a view collapsed: its PSNR at the compared step at least this many dB below its best earlier evaluation
COLLAPSE_DB = 5.0
#: the per-view metrics file of a gathered results folder
VIEWS_FILE = "views.json"
#: its ``format``
FORMAT = "jsgs-views"
#: decimals kept per metric in views.json (PSNR in dB; SSIM and LPIPS in [0, 1])
DECIMALS = {"psnr": 4, "ssim": 6, "lpips": 6}

View = dict[str, Any]  # {"name", "psnr", "ssim", "lpips"} (a metric None where it was not finite)
RunViews = dict[int, list[View]]  # evaluation step -> its views
Pair = tuple[str, str, Budget, str, int]  # scene, schedule, budget, the method against gsplat, seed


def run_key(scene: str, schedule: str, method: str, budget: Budget, seed: int) -> str:
    """The run's folder under ``runs/`` (and its key in views.json and configs.json)."""
    return f"{scene}/{schedule}/{method}/mcmc-{budget}/s{seed}"


def _view(v: Mapping[str, Any]) -> View:
    """One view's name and metrics, rounded to :data:`DECIMALS`."""
    out: View = {"name": str(v["name"])}
    for k, d in DECIMALS.items():
        x = v.get(k)
        out[k] = None if x is None else round(float(x), d)
    return out


def views_of_metrics(doc: Mapping[str, Any]) -> RunViews:
    """A metrics.json document's views per evaluation step (evaluations without views left out)."""
    return {int(e["step"]): [_view(v) for v in e["views"]] for e in doc.get("evals", []) if e.get("views")}


def read_runs(runs_dir: Path) -> dict[str, RunViews]:
    """The views of every equal-budget run under ``runs_dir`` (``runs/``), by run key; a metrics.json that
    cannot be read (a run still writing it) is left out, as results.csv leaves it out."""
    out: dict[str, RunViews] = {}
    for p in sorted(runs_dir.glob("*/*/*/mcmc-*/s*/metrics.json")):
        try:
            views = views_of_metrics(json.loads(p.read_text()))
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if views:
            out[p.parent.relative_to(runs_dir).as_posix()] = views
    return out


def to_doc(runs: Mapping[str, RunViews]) -> dict[str, Any]:
    """views.json's document: the runs in key order, each one's evaluations in step order."""
    body = {k: [{"step": s, "views": runs[k][s]} for s in sorted(runs[k])] for k in sorted(runs)}
    return {"format": FORMAT, "format_version": 1, "runs": body}


def read_file(path: Path) -> dict[str, RunViews]:
    """A views.json's runs; JsgsError (one line naming ``path``) where it is not one."""
    from jsgs.base.errors import JsgsError
    from jsgs.base.schema import validate

    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise JsgsError(f"{path}: not readable as JSON ({e})") from None
    validate(doc, "views", str(path))
    return {k: {int(e["step"]): e["views"] for e in evals} for k, evals in doc["runs"].items()}


def write_file(path: Path, runs: Mapping[str, RunViews]) -> None:
    """Write views.json (checked against its schema, atomically)."""
    from jsgs.base.io import write_json_checked

    write_json_checked(path, to_doc(runs), "views")


def load(results_dir: Path) -> dict[str, RunViews]:
    """The views of a results folder: its views.json, then the runs under its ``runs/`` (which win)."""
    f = results_dir / VIEWS_FILE
    found = read_file(f) if f.is_file() else {}
    return {**found, **read_runs(results_dir / "runs")}


def differences(base: list[View], other: list[View], metric: str) -> list[float]:
    """``other`` − ``base`` on each view both name with a value of ``metric``, in name order."""
    a = {v["name"]: v[metric] for v in base if v.get(metric) is not None}
    b = {v["name"]: v[metric] for v in other if v.get(metric) is not None}
    return [b[n] - a[n] for n in sorted(a.keys() & b.keys())]


def collapsed(run: RunViews, step: int, drop: float = COLLAPSE_DB) -> list[tuple[str, float, int, float]]:
    """The views of ``run`` whose PSNR at ``step`` is at least ``drop`` dB below their best at an earlier
    evaluation: (name, best PSNR, its step, PSNR at ``step``), in name order."""
    out = []
    for v in sorted(run.get(step, []), key=lambda v: v["name"]):
        earlier = [(w["psnr"], s) for s, vs in run.items() if s < step for w in vs
                   if w["name"] == v["name"] and w.get("psnr") is not None]  # fmt: skip
        if v.get("psnr") is None or not earlier:
            continue
        best, at = max(earlier, key=lambda t: (t[0], -t[1]))
        # the drop at the metrics' own decimals: 20.0037 − 15.0037 is 4.999999999999998 in binary
        if round(best - v["psnr"], DECIMALS["psnr"]) >= drop:
            out.append((v["name"], best, at, v["psnr"]))
    return out


def pairs(rep: BudgetReport) -> list[Pair]:
    """Every scene × schedule × budget × seed where gsplat and a JSGS variant reached the compared step."""
    out = []
    for (sc, sch, b), v in ((k, v) for k in rep.keys for v in rep.variants):
        seeds = rep.final.get((sc, sch, "gsplat", b), {}).keys() & rep.final.get((sc, sch, v, b), {}).keys()
        out += [(sc, sch, b, v, s) for s in sorted(seeds)]
    return out


def pair_runs(p: Pair) -> dict[str, str]:
    """The runs a pair compares, by the name the section gives them: gsplat, the variant, the clean run."""
    sc, sch, b, v, s = p
    return {"gsplat": run_key(sc, sch, "gsplat", b, s), v: run_key(sc, sch, v, b, s),
            "clean": run_key(sc, "clean", "gsplat", b, s)}  # fmt: skip


def pair_row(p: Pair, step: int, views: Mapping[str, RunViews]) -> list[str] | None:
    """The table's row of one pair at ``step``; None where either run has no views at that step."""
    sc, sch, b, v, s = p
    runs = pair_runs(p)
    g, j = views.get(runs["gsplat"], {}).get(step), views.get(runs[v], {}).get(step)
    if not g or not j:
        return None
    dp, dl = differences(g, j, "psnr"), differences(g, j, "lpips")
    gone = [str(len(collapsed(views[r], step))) if views.get(r, {}).get(step) else "–" for r in runs.values()]
    return [
        sc, sch, label(b), v, str(s), f"{step:,}", str(len({x["name"] for x in g} & {x["name"] for x in j})),
        f"{sum(1 for x in dp if x > 0)}/{len(dp)}", f"{sum(1 for x in dl if x < 0)}/{len(dl)}",
        number(statistics.median(dp), 2, True) if dp else "n/a",
        number(statistics.median(dl), 4, True) if dl else "n/a", " / ".join(gone),
    ]  # fmt: skip


def collapse_lines(rep: BudgetReport, compared: list[Pair], views: Mapping[str, RunViews]) -> list[str]:
    """One line per collapsed view of the compared pairs' runs (each run once)."""
    seen: dict[str, int] = {}
    for p in compared:
        for r in pair_runs(p).values():
            if r in views:
                seen[r] = rep.step_at(p[0], p[2])
    return [f"- `{r}` `{name}`: {best:.2f} dB at step {at:,} → {now:.2f} dB at {st:,} ({now - best:+.2f})"
            for r, st in sorted(seen.items()) for name, best, at, now in collapsed(views[r], st)]  # fmt: skip


def markdown(rep: BudgetReport, views: Mapping[str, RunViews]) -> list[str]:
    """The section's lines: one table of the pairs, then the collapsed views."""
    md = [f"## Per test view (equal budget, {rep.step_label()})", ""]
    if not views:
        return md + ["Skipped: no per-view metrics here (no `runs/.../metrics.json`, no `views.json`).", ""]
    md += [
        "Each pair of runs (same scene, schedule, budget and seed) on each test view, from its metrics.json "
        "`views` at the compared step: the views where JSGS's PSNR is higher and its LPIPS lower than "
        "gsplat's, the median per-view ΔPSNR and ΔLPIPS (JSGS − gsplat), and how many views collapsed in "
        "each run (gsplat / JSGS / clean; – no views): PSNR at the compared step ≥ "
        f"{COLLAPSE_DB:g} dB below the view's best at an earlier evaluation.",
        "",
    ]
    body, compared, missing = [], [], []
    for p in pairs(rep):
        row = pair_row(p, rep.step_at(p[0], p[2]), views)
        if row is None:
            missing.append(p)
        else:
            body.append(row)
            compared.append(p)
    header = ["Scene", "Schedule", "Budget", "JSGS", "seed", "step", "views", "PSNR higher", "LPIPS lower",
              "median ΔPSNR dB", "median ΔLPIPS", "collapsed"]  # fmt: skip
    md += md_table(header, body, "lllll" + "r" * 7) if body else ["No pair has per-view metrics."]
    if missing:
        names = ", ".join(f"`{run_key(sc, sch, v, b, s)}`" for sc, sch, b, v, s in missing)
        md += ["", f"Without per-view metrics at the compared step: {names}."]
    lines = collapse_lines(rep, compared, views)
    md += ["", "Collapsed views:" if lines else "Collapsed views: none.", *([""] + lines if lines else [])]
    return md + [""]
