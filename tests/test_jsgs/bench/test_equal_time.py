"""The equal-time comparison (jsgs.bench.equal_time) on hand-made numbers: interpolation between gsplat's
evaluations, the refusal to extrapolate, the device-sharing rule, the summary and the report; the plan of a
gsplat run trained past its recipe (--gsplat-steps)."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import pytest

from jsgs.base.errors import JsgsError
from jsgs.bench import plan as plan_mod
from jsgs.bench.equal_time import interpolate, pairs, summary, table


def test_interpolation_never_extrapolates() -> None:
    curve = [(10.0, 1.0), (20.0, 3.0), (40.0, 4.0)]
    assert interpolate(curve, 15.0) == pytest.approx(2.0)
    assert interpolate(curve, 30.0) == pytest.approx(3.5)
    assert [interpolate(curve, t) for t in (10.0, 20.0, 40.0)] == [1.0, 3.0, 4.0]
    assert interpolate(curve, 9.99) is None and interpolate(curve, 40.01) is None
    assert interpolate([], 1.0) is None and interpolate([(5.0, 2.0)], 5.0) == 2.0


def _row(
    method: str, seed: int, step: int, seconds: float, lpips: float, psnr: float, **kw: Any
) -> dict[str, Any]:
    return {"scene": "a", "schedule": "gaussian", "method": method, "seed": seed, "strategy": "mcmc",
            "budget": 300, "step": step, "train_seconds": seconds, "lpips": lpips, "psnr": psnr,
            "runs_per_device": 1, "schedule_steps": 200, **kw}  # fmt: skip


def _hand_rows() -> list[dict[str, Any]]:
    """gsplat trained to 300 steps on a 200-step recipe; JSGS's 200 steps take 25 s (seed 0: between gsplat's
    20 s and 30 s), 35 s (seed 1: past gsplat's last evaluation), and seed 2 shared its device differently."""
    g = [(100, 10.0, 0.30, 20.0), (200, 20.0, 0.20, 22.0), (300, 30.0, 0.16, 23.0)]
    rows = [_row("gsplat", seed, st, t, lp, ps) for seed in (0, 1, 2) for st, t, lp, ps in g]
    rows += [_row("gsplat", 0, 200, 20.0, 0.10, 25.0, schedule="clean")]
    rows += [_row("jsgs", 0, 100, 12.5, 0.25, 21.0), _row("jsgs", 0, 200, 25.0, 0.17, 22.8)]
    rows += [_row("jsgs", 1, 200, 35.0, 0.15, 23.5)]
    rows += [_row("jsgs", 2, 200, 25.0, 0.19, 21.0, runs_per_device=2)]
    return rows


def test_each_jsgs_run_against_gsplat_at_the_same_seconds() -> None:
    ps = pairs(_hand_rows())
    assert [(p.method, p.seed) for p in ps] == [("jsgs", 0), ("jsgs", 1), ("jsgs", 2)]  # clean is no pair
    p0, p1, p2 = ps
    # seed 0: at 25 s gsplat is halfway between its 20 s and 30 s evaluations
    assert (p0.step, p0.seconds) == (200, 25.0) and p0.compared
    assert (p0.gsplat_lpips, p0.gsplat_psnr, p0.gsplat_step) == pytest.approx((0.18, 22.5, 250.0))
    assert p0.d_lpips == pytest.approx(100 * (0.17 / 0.18 - 1)) and p0.d_psnr == pytest.approx(0.3)
    # seed 1 ends after gsplat's last evaluation: refused, not extrapolated
    assert not p1.compared and "not extrapolated" in p1.note and "--gsplat-steps" in p1.note
    assert p1.gsplat_lpips is None and p1.d_lpips is None
    # seed 2 trained two to a device, gsplat alone: its seconds measure something else
    assert not p2.compared and "shared differently" in p2.note
    s = "\n".join(summary(ps))
    assert "| 1/1 (100 %) |" in s and f"| {100 * (0.17 / 0.18 - 1):+.1f} |" in s and "| +0.300 |" in s
    assert "| 2 | met |" in s  # two not compared; the targets over the compared pair
    t = "\n".join(table(ps))
    assert "0.1800" in t and "22.50" in t and "| 250 |" in t and t.count("not extrapolated") == 1


def test_a_loss_at_equal_time_fails_the_targets() -> None:
    rows = [r for r in _hand_rows() if r["seed"] == 0]
    worse = {"lpips": 0.19, "psnr": 22.0}
    rows = [r | worse if r["method"] == "jsgs" and r["step"] == 200 else r for r in rows]
    ps = pairs(rows)
    assert ps[0].d_lpips == pytest.approx(100 * (0.19 / 0.18 - 1)) and ps[0].d_psnr == pytest.approx(-0.5)
    assert "**not met**" in "\n".join(summary(ps))


def test_no_gsplat_run_and_jsgs_before_gsplats_first_evaluation() -> None:
    rows = [_row("jsgs", 0, 200, 25.0, 0.17, 22.8)]
    assert pairs(rows)[0].note == "no gsplat run"
    # its runs per device are its own (not "3 / None": there is no gsplat run to share with)
    alone = [_row("jsgs", 0, 200, 25.0, 0.17, 22.8, runs_per_device=3)]
    assert "| 3 | no gsplat run |" in "\n".join(table(pairs(alone)))
    rows += [_row("gsplat", 0, 100, 30.0, 0.30, 20.0), _row("gsplat", 0, 200, 40.0, 0.2, 22.0)]
    assert "before gsplat's first evaluation" in pairs(rows)[0].note


def test_a_stopped_jsgs_run_without_gsplat_is_listed_not_compared(tmp_path: Path) -> None:
    # a bench of JSGS alone whose run stopped before its recipe's end (the budgets' rule, cut by --time-limit)
    from jsgs.bench.equal_time import write_plots

    rows = [_row("jsgs", 0, 100, 12.5, 0.25, 21.0)]
    (p,) = pairs(rows)
    assert not p.compared and p.note == "stopped at step 100, before its recipe's end (200)"
    files = write_plots(rows, tmp_path)  # the curves are still drawn
    assert files and all(f.exists() for f in files)


def test_report_compares_steps_within_the_recipe_and_time_over_everything(tmp_path: Path) -> None:
    """The equal-budget tables compare gsplat at its recipe's end (step 200), not at the 300 steps it
    trained on for the equal-time table; the report has both sections and the time plots."""
    from jsgs.bench.budget import BudgetReport
    from jsgs.bench.markdown import write_report
    from jsgs.bench.results import within_recipe

    rows = _hand_rows()
    rep = BudgetReport(within_recipe(rows))
    assert rep.step == 200 and rep.values("a", "gaussian", "gsplat", 300, "lpips") == {0: 0.2, 1: 0.2, 2: 0.2}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a panel with nothing drawn gets no legend, nor matplotlib's warning
        text = write_report(rows, tmp_path, [], []).read_text()
    assert "## Equal Gaussian budget (gsplat's MCMCStrategy), step 200" in text
    assert "## Equal training time" in text and "runs per device: 1 (one run per GPU), 2" in text
    assert (tmp_path / "plots" / "a_time.png").stat().st_size > 1000


def test_plan_trains_gsplat_past_its_recipe(synth_scene: Path, tmp_path: Path) -> None:
    ev = plan_mod.default_eval_at(30_000)
    assert ev == [3000, 7000, 10_000, 15_000, 20_000, 25_000, 30_000]
    assert plan_mod.default_eval_at(10_000) == [3000, 7000, 10_000] and plan_mod.default_eval_at(500) == [500]
    plan = plan_mod.build_plan(plan_mod.BenchSettings(
        scenes=[synth_scene], out=tmp_path, schedules=["gaussian", "clean"], fixed=[],
        methods=["gsplat", "jsgs"], seeds=[0], iterations=30_000, eval_at=ev, strategy="mcmc",
        budgets=plan_mod.parse_budgets("300k"), gsplat_steps=1.8,
    ))  # fmt: skip
    runs = {(r.schedule, r.method): r for r in plan.runs}
    g = runs[("gaussian", "gsplat")]
    assert (g.iterations, g.schedule_steps) == (54_000, 30_000)
    assert g.eval_at == [*ev, 35_000, 40_000, 45_000, 50_000, 54_000]
    for key in (("gaussian", "jsgs"), ("clean", "gsplat")):  # JSGS and the clean ceiling: the recipe only
        assert (runs[key].iterations, runs[key].eval_at, runs[key].schedule_steps) == (30_000, ev, None)
    assert plan_mod.longer_run([3, 6], 6, 1.0) == (6, [3, 6])
    assert plan_mod.longer_run([6], 6, 2.0) == (12, [6, 12])
    with pytest.raises(JsgsError, match="--gsplat-steps 0.5"):
        plan_mod.build_plan(plan_mod.BenchSettings(
            scenes=[synth_scene], out=tmp_path, schedules=["gaussian"], fixed=[], methods=["gsplat"],
            seeds=[0], iterations=10, eval_at=[10], gsplat_steps=0.5,
        ))  # fmt: skip
