"""The report's "Per test view" section (:mod:`jsgs.bench.per_view`) on hand-made metrics.json: the views
where JSGS wins, the medians of the per-view differences, collapsed views (≥ 5 dB below the view's best at an
earlier evaluation; a 4.9 dB drop and a best after the compared step are not), and the skip line where the
runs' metrics.json are absent."""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import pytest

from jsgs.base.errors import JsgsError
from jsgs.bench import per_view
from jsgs.bench.budget import BudgetReport
from jsgs.bench.markdown import write_report

NAMES = [f"v{i}.png" for i in range(7)]
# gsplat's PSNR per view at the compared step (1000); JSGS is 1 dB above on six views and 0.5 below on v3
G_PSNR = [20.0, 21.0, 22.0, 23.0, 24.0, 25.0, 26.0]
J_PSNR = [p + (-0.5 if i == 3 else 1.0) for i, p in enumerate(G_PSNR)]
# LPIPS: JSGS lower on five views (v0-v4), higher on v5 and v6
G_LPIPS = [0.20, 0.22, 0.24, 0.26, 0.28, 0.30, 0.32]
J_LPIPS = [0.15, 0.20, 0.21, 0.25, 0.20, 0.31, 0.40]


def _row(method: str, schedule: str, step: int) -> dict[str, object]:
    return {"scene": "a", "schedule": schedule, "method": method, "seed": 0, "strategy": "mcmc",
            "budget": 300, "step": step, "psnr": 25.0, "ssim": 0.8, "lpips": 0.2, "train_seconds": step / 10,
            "fps": 100.0, "num_gaussians": 300, "peak_memory_mb": 1.0, "time_per_iteration_s": 0.01,
            "schedule_steps": 1000}  # fmt: skip


def _views(psnr: list[float], lpips: list[float]) -> list[dict[str, object]]:
    return [{"name": n, "psnr": p, "ssim": 0.8, "lpips": lp}
            for n, p, lp in zip(NAMES, psnr, lpips, strict=True)]  # fmt: skip


def _run(results: Path, schedule: str, method: str, evals: dict[int, list[dict[str, object]]]) -> None:
    """A run's metrics.json under ``results/runs/`` with ``evals`` (step -> views) and nothing else."""
    run = results / "runs" / per_view.run_key("a", schedule, method, 300, 0)
    run.mkdir(parents=True)
    doc = {"evals": [{"step": s, "psnr": 0.0, "views": v} for s, v in sorted(evals.items())]}
    (run / "metrics.json").write_text(json.dumps(doc))


def _bench(results: Path) -> list[dict[str, object]]:
    """gsplat and JSGS at steps 500 and 1000 (gsplat on to 1500, past its recipe) and the clean run; rows
    and, in ``results/runs``, their metrics.json. gsplat's v0 falls 5.1 dB from step 500, v1 4.9 dB, v2
    exactly 5.0; v6 is 8 dB higher at step 1500, after the compared step (no collapse at 1000)."""
    early_g = [p + d for p, d in zip(G_PSNR, [5.1, 4.9, 5.0, 0.0, 0.0, 0.0, -1.0], strict=True)]
    late_g = [p + (8.0 if i == 6 else 0.0) for i, p in enumerate(G_PSNR)]
    _run(results, "gaussian", "gsplat", {500: _views(early_g, G_LPIPS), 1000: _views(G_PSNR, G_LPIPS),
                                         1500: _views(late_g, G_LPIPS)})  # fmt: skip
    _run(results, "gaussian", "jsgs", {500: _views(J_PSNR, J_LPIPS), 1000: _views(J_PSNR, J_LPIPS)})
    _run(results, "clean", "gsplat", {500: _views(G_PSNR, G_LPIPS), 1000: _views(G_PSNR, G_LPIPS)})
    rows = [_row(m, sch, s) for m, sch in (("gsplat", "gaussian"), ("jsgs", "gaussian"), ("gsplat", "clean"))
            for s in (500, 1000)]  # fmt: skip
    return rows + [_row("gsplat", "gaussian", 1500)]


def _section(report: str) -> str:
    return report.split("## Per test view", 1)[1].split("\n## ", 1)[0]


def test_a_pair_where_jsgs_wins_six_of_seven_views(tmp_path: Path) -> None:
    section = _section(write_report(_bench(tmp_path), tmp_path, [], [], plots=False).read_text())
    row = [ln for ln in section.splitlines() if ln.startswith("| a |")]
    assert len(row) == 1
    cells = [c.strip() for c in row[0].strip("|").split("|")]
    d_lpips = statistics.median(j - g for g, j in zip(G_LPIPS, J_LPIPS, strict=True))  # −0.02 (v1)
    assert cells == ["a", "gaussian", "300", "jsgs", "0", "1,000", "7", "6/7", "5/7", "+1.00",
                     f"{d_lpips:+.4f}", "2 / 0 / 0"]  # fmt: skip
    assert d_lpips == pytest.approx(-0.02)


def test_collapsed_views_at_five_db_not_at_four_point_nine(tmp_path: Path) -> None:
    _bench(tmp_path)
    views = per_view.load(tmp_path)
    g = views[per_view.run_key("a", "gaussian", "gsplat", 300, 0)]
    got = per_view.collapsed(g, 1000)
    assert [(n, best, at) for n, best, at, _ in got] == [("v0.png", 25.1, 500), ("v2.png", 27.0, 500)]
    assert [now for *_, now in got] == [20.0, 22.0]
    # v6 is 8 dB higher at step 1500, after the compared step: no collapse (above). A best only after the
    # compared step never counts; the same drop from an earlier best does
    assert per_view.collapsed({1000: g[1000], 1200: g[1500]}, 1200) == []
    assert [n for n, *_ in per_view.collapsed({1000: g[1500], 1200: g[1000]}, 1200)] == ["v6.png"]
    section = _section(write_report(_bench(tmp_path / "b"), tmp_path / "b", [], [], plots=False).read_text())
    listed = [ln for ln in section.splitlines() if ln.startswith("- ")]
    assert listed == [
        "- `a/gaussian/gsplat/mcmc-300/s0` `v0.png`: 25.10 dB at step 500 → 20.00 dB at 1,000 (-5.10)",
        "- `a/gaussian/gsplat/mcmc-300/s0` `v2.png`: 27.00 dB at step 500 → 22.00 dB at 1,000 (-5.00)",
    ]


def test_without_metrics_the_section_is_one_skip_line(tmp_path: Path) -> None:
    rows = _bench(tmp_path / "with")
    report = write_report(rows, tmp_path / "without", [], [], plots=False).read_text()
    section = _section(report)
    assert [ln for ln in section.splitlines() if ln.strip()][1:] == [
        "Skipped: no per-view metrics here (no `runs/.../metrics.json`, no `views.json`)."
    ]
    assert "## Equal training time" in report  # the rest of the report is there


def test_views_file_round_trip_and_a_pair_without_views(tmp_path: Path) -> None:
    rows = _bench(tmp_path / "bench")
    views = per_view.read_runs(tmp_path / "bench" / "runs")
    jsgs = per_view.run_key("a", "gaussian", "jsgs", 300, 0)
    per_view.write_file(tmp_path / "gathered" / per_view.VIEWS_FILE, views)
    assert per_view.load(tmp_path / "gathered") == views
    # JSGS's views gone: the pair is named as without per-view metrics, the clean run's views still read
    del views[jsgs]
    per_view.write_file(tmp_path / "partial" / per_view.VIEWS_FILE, views)
    section = _section(write_report(rows, tmp_path / "partial", [], [], plots=False).read_text())
    assert "No pair has per-view metrics." in section
    assert f"Without per-view metrics at the compared step: `{jsgs}`." in section
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / per_view.VIEWS_FILE).write_text(json.dumps({"format": "jsgs-views", "runs": {}}))
    with pytest.raises(JsgsError, match="bad/views.json: not a valid views file"):
        per_view.load(tmp_path / "bad")


def test_the_pairs_are_compared_at_the_equal_budget_tables_step(tmp_path: Path) -> None:
    """At step 500 (the tables' step for the scene): JSGS's views then, and no collapse (no earlier one)."""
    rows = _bench(tmp_path)
    assert per_view.pairs(BudgetReport(rows, {("a", 300): 500})) == [("a", "gaussian", 300, "jsgs", 0)]
    report = write_report(rows, tmp_path, [], [], plots=False, budget_step={("a", 300): 500}).read_text()
    row = [ln for ln in _section(report).splitlines() if ln.startswith("| a |")]
    cells = [c.strip() for c in row[0].strip("|").split("|")]
    # at 500 gsplat's v0-v2 are 5.1, 4.9 and 5.0 dB higher than at 1000: JSGS above it on v4-v6 only (v3 is
    # 0.5 below)
    assert cells[5:9] == ["500", "7", "3/7", "5/7"] and cells[-1] == "0 / 0 / 0"
    assert "Collapsed views: none." in report


def test_a_drop_of_exactly_five_db_at_four_decimals_is_a_collapse() -> None:
    # 20.0037 − 15.0037 is 4.999999999999998 in binary floating point: the rule reads the difference at the
    # metrics' 4 decimals (views.json's), where it is 5 dB
    run = {500: [{"name": "v", "psnr": 20.0037}], 1000: [{"name": "v", "psnr": 15.0037}]}
    assert [n for n, *_ in per_view.collapsed(run, 1000)] == ["v"]
    run = {500: [{"name": "v", "psnr": 20.0037}], 1000: [{"name": "v", "psnr": 15.0038}]}
    assert per_view.collapsed(run, 1000) == []


def test_a_clean_run_without_views_at_the_compared_step_is_a_dash(tmp_path: Path) -> None:
    rows = _bench(tmp_path)
    clean = tmp_path / "runs" / per_view.run_key("a", "clean", "gsplat", 300, 0) / "metrics.json"
    doc = json.loads(clean.read_text())
    doc["evals"] = [e for e in doc["evals"] if e["step"] != 1000]  # views at step 500 only
    clean.write_text(json.dumps(doc))
    section = _section(write_report(rows, tmp_path, [], [], plots=False).read_text())
    row = [ln for ln in section.splitlines() if ln.startswith("| a |")]
    assert [c.strip() for c in row[0].strip("|").split("|")][-1] == "2 / 0 / –"
