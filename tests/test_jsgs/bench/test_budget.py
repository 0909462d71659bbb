"""``jsgs bench --strategy mcmc --budgets``: budget parsing, the plan (reference runs for multiples, folders
per cap), cap resolution, the equal-budget statistics on hand-made numbers, and the whole bench on a tiny
synthetic scene on the CPU."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
from click.testing import CliRunner

from jsgs.base.errors import JsgsError
from jsgs.bench import plan as plan_mod
from jsgs.bench.budget import BudgetReport, mean_ci, t975
from jsgs.bench.tables import count_label


def test_parse_budgets() -> None:
    bs = plan_mod.parse_budgets("300k, 0.5x,1.5m,250000,1X")
    assert [(b.label, b.count, b.multiple) for b in bs] == [
        ("300k", 300_000, None), ("0.5x", None, 0.5), ("1.5m", 1_500_000, None), ("250000", 250_000, None),
        ("1X", None, 1.0),
    ]  # fmt: skip
    assert bs[1].cap(123_457.0) == 61_728 and bs[0].cap(None) == 300_000
    for bad, why in (("abc", "neither a count"), ("0x", "neither a count"), ("0.3", "whole number"),
                     ("0", "whole number"), ("2k,2k", "given twice"), ("-5", "neither")):  # fmt: skip
        with pytest.raises(JsgsError, match=why):
            plan_mod.parse_budgets(bad)


def test_plan_under_budgets(synth_scene: Path, tmp_path: Path) -> None:
    name = synth_scene.name
    budgets = plan_mod.parse_budgets("2k,0.5x")
    p = plan_mod.build_plan(plan_mod.BenchSettings(
        scenes=[synth_scene], out=tmp_path, schedules=["gaussian", "clean"], fixed=[],
        methods=["gsplat", "jsgs"], seeds=[0, 1], iterations=10, eval_at=[10], strategy="mcmc",
        budgets=budgets,
    ))  # fmt: skip
    refs = p.references()
    assert [r.id for r in refs] == [f"{name}/clean/gsplat/s0", f"{name}/clean/gsplat/s1"]
    assert all(r.strategy == "default" and r.cap is None for r in refs)
    mc = [r for r in p.runs if r.strategy == "mcmc"]
    assert len(mc) == 2 * 3 * 2  # budgets x (gaussian gsplat, gaussian jsgs, clean gsplat) x seeds
    fixed_cap = [r for r in mc if r.budget == "2k"]
    assert {r.cap for r in fixed_cap} == {2000}
    assert f"{name}/gaussian/jsgs/mcmc-2000/s1" in {r.id for r in fixed_cap}
    assert fixed_cap[0].out.endswith(f"runs/{name}/gaussian/gsplat/mcmc-2000/s0")
    argv = plan_mod.train_argv(fixed_cap[0], "cuda", None, resume=False)
    assert argv[argv.index("--preset") + 1] == "mcmc" and argv[argv.index("--cap-max") + 1] == "2000"
    ref_argv = plan_mod.train_argv(refs[0], "cuda", None, resume=False)
    assert ref_argv[ref_argv.index("--preset") + 1] == "paper" and "--cap-max" not in ref_argv
    # the multiples wait for the reference counts; a scene without one is returned unresolved
    pending = [r for r in mc if r.cap is None]
    assert len(pending) == 6 and all(r.out == "" for r in pending)
    assert plan_mod.resolve_caps(p, tmp_path, {name: None}) == pending
    assert plan_mod.resolve_caps(p, tmp_path, {name: 1001.0}) == []
    assert {r.cap for r in pending} == {500}  # round(0.5 x 1001) (ties to even)
    assert pending[0].out.endswith(f"/mcmc-500/s{pending[0].seed}")
    # the paper-protocol tables and inconsistent choices are refused in one line
    refused = (({"fixed": [30]}, "--fixed and --ablation"), ({"strategy": "default"}, "needs --strategy"),
               ({"strategy": "x"}, "unknown strategy"))  # fmt: skip
    for kw, why in refused:
        args = {"fixed": [], "strategy": "mcmc", "budgets": budgets} | kw
        with pytest.raises(JsgsError, match=why):
            plan_mod.build_plan(plan_mod.BenchSettings(
                scenes=[synth_scene], out=tmp_path, schedules=["gaussian"], fixed=args["fixed"],
                methods=["gsplat"], seeds=[0], iterations=10, eval_at=[10], strategy=args["strategy"],
                budgets=args["budgets"],
            ))  # fmt: skip


def test_plan_of_schedules_saved_twice(synth_scene: Path, tmp_path: Path) -> None:
    """``gaussian+r90``: the gaussian schedule's JPEGs saved once more at 90 (its own datasets, analysed);
    ``jsgs_eff``: JSGS with the effective tables, on the same files as gsplat and jsgs."""
    name = synth_scene.name
    p = plan_mod.build_plan(plan_mod.BenchSettings(
        scenes=[synth_scene], out=tmp_path, schedules=["gaussian+r90", "gaussian"], fixed=[],
        methods=["gsplat", "jsgs", "jsgs_eff"], seeds=[0], iterations=10, eval_at=[10], strategy="mcmc",
        budgets=plan_mod.parse_budgets("2k"),
    ))  # fmt: skip
    d = {x.schedule: x for x in p.datasets}
    assert (d["gaussian+r90"].compress_schedule, d["gaussian+r90"].recompress) == ("gaussian", 90)
    assert d["gaussian"].recompress is None and d["gaussian+r90"].out.endswith(f"{name}/gaussian+r90_s0")
    eff = next(r for r in p.runs if r.method == "jsgs_eff" and r.schedule == "gaussian+r90")
    assert eff.data == next(r for r in p.runs if r.method == "gsplat" and r.schedule == "gaussian+r90").data
    argv = plan_mod.train_argv(eff, "cuda", None, resume=False)
    assert argv[argv.index("--method") + 1] == "jsgs" and argv[argv.index("--tables") + 1] == "effective"
    for bad in ("clean+r90", "gaussian+r0", "gaussian+90"):
        with pytest.raises(JsgsError, match="--schedules"):
            plan_mod.build_plan(plan_mod.BenchSettings(
                scenes=[synth_scene], out=tmp_path, schedules=[bad], fixed=[], methods=["gsplat"],
                seeds=[0], iterations=10, eval_at=[10],
            ))


def _t_cdf(x: float, df: int) -> float:
    """Student's t CDF by Simpson integration of its density in float64 (a reference for the table)."""
    c = math.exp(math.lgamma((df + 1) / 2) - math.lgamma(df / 2)) / math.sqrt(df * math.pi)
    n = 20_000
    h = x / n
    f = [c * (1 + (i * h) ** 2 / df) ** (-(df + 1) / 2) for i in range(n + 1)]
    return 0.5 + h / 3 * (f[0] + f[-1] + 4 * sum(f[1:-1:2]) + 2 * sum(f[2:-1:2]))


def test_t_quantiles_match_the_distribution() -> None:
    for df in (1, 2, 3, 5, 10, 30):
        assert _t_cdf(t975(df), df) == pytest.approx(0.975, abs=2e-5), df
    assert t975(200) == 1.960
    m, h = mean_ci([1.0, 2.0, 3.0])
    assert m == 2.0 and h == pytest.approx(4.303 * 1.0 / math.sqrt(3))
    assert mean_ci([4.0]) == (4.0, None) and mean_ci([]) == (None, None)


def _row(sc: str, sch: str, m: str, b: int, seed: int, step: int, lp: float, ps: float) -> dict[str, object]:
    return {"scene": sc, "schedule": sch, "method": m, "seed": seed, "strategy": "mcmc", "budget": b,
            "step": step, "psnr": ps, "ssim": 0.8, "lpips": lp, "train_seconds": step / 10, "fps": 100.0,
            "num_gaussians": b, "peak_memory_mb": 1.0, "time_per_iteration_s": 0.01}  # fmt: skip


def _hand_rows() -> list[dict[str, object]]:
    rows = []
    for seed, (g, j, c) in enumerate([(0.10, 0.06, 0.04), (0.12, 0.08, 0.05), (0.11, 0.066, 0.045)]):
        for step, f in ((500, 1.6), (700, 1.2), (1000, 1.0)):
            rows.append(_row("a", "gaussian", "gsplat", 300, seed, step, g * f, 25.0 + seed))
            rows.append(_row("a", "gaussian", "jsgs", 300, seed, step, j * f, 25.5 + seed))
            rows.append(_row("a", "clean", "gsplat", 300, seed, step, c * f, 27.0 + seed))
    # a second budget where JSGS loses
    for seed in range(3):
        rows.append(_row("a", "gaussian", "gsplat", 100, seed, 1000, 0.2, 24.0))
        rows.append(_row("a", "gaussian", "jsgs", 100, seed, 1000, 0.3 + 0.01 * seed, 23.0))
        rows.append(_row("a", "clean", "gsplat", 100, seed, 1000, 0.1, 26.0))
    # DefaultStrategy rows are not part of the budget tables
    rows.append(_row("a", "gaussian", "jsgs", 300, 0, 1000, 0.001, 40.0) | {"strategy": "default"})
    return rows


def test_budget_statistics_on_hand_made_numbers() -> None:
    rep = BudgetReport(_hand_rows())
    assert rep.step == 1000 and rep.keys == [("a", "gaussian", 100), ("a", "gaussian", 300)]
    key = ("a", "gaussian", 300)
    d = rep.paired(key, "lpips", relative=True)
    assert d == pytest.approx([-40.0, 100 * (0.08 / 0.12 - 1), -40.0])
    assert rep.paired(key, "psnr") == pytest.approx([0.5, 0.5, 0.5])
    # gsplat's final LPIPS per seed: 0.10, 0.12, 0.11; JSGS at step 500 (x 1.6): 0.096, 0.128, 0.1056, at
    # step 700 (x 1.2): 0.072, 0.096, 0.0792
    assert rep.time_to_quality(key) == [500, 700, 500]
    assert rep.time_to_quality(("a", "gaussian", 100)) == [None, None, None]
    targets = "\n".join(rep.targets())
    lines = {ln.split("|")[1].strip(): ln for ln in targets.splitlines()[2:]}
    assert "100 %" in lines["300"] and "| met |" in lines["300"]
    assert "0 %" in lines["100"] and "**not met**" in lines["100"] and "a/gaussian lpips" in lines["100"]
    # the clean run against gsplat, seed by seed: the most a recipe could gain
    assert rep.ceiling(key) == pytest.approx([-60.0, 100 * (0.05 / 0.12 - 1), 100 * (0.045 / 0.11 - 1)])
    assert rep.ceiling(key, "psnr") == pytest.approx([2.0, 2.0, 2.0])
    ceiling = (-60.0 + 100 * (0.05 / 0.12 - 1) + 100 * (0.045 / 0.11 - 1)) / 3
    assert lines["300"].split("|")[5].strip() == f"{ceiling:+.1f}"
    assert lines["100"].split("|")[5].strip() == "-50.0"
    table = "\n".join(rep.comparison())
    # R_LPIPS on seed means: (0.11 - 0.0687) / (0.11 - 0.045)
    r = (0.11 - (0.06 + 0.08 + 0.066) / 3) / (0.11 - 0.045)
    assert f"{r:.2f}" in table and "3/3 / 3/3" in table and "0/3 / 0/3" in table
    # a JSGS variant gets its own rows beside jsgs (the targets stay those of jsgs)
    extra = [r | {"method": "jsgs_eff", "lpips": float(r["lpips"]) * 0.5} for r in _hand_rows()
             if r["method"] == "jsgs" and r["strategy"] == "mcmc"]  # fmt: skip
    rep2 = BudgetReport(_hand_rows() + extra)
    assert rep2.variants == ["jsgs", "jsgs_eff"]
    rows = [ln for ln in rep2.comparison()[2:] if "| 300 |" in ln]
    assert [ln.split("|")[4].strip() for ln in rows] == ["jsgs", "jsgs_eff"]
    half = [-70.0, 100 * (0.04 / 0.12 - 1), -70.0]
    assert rep2.paired(key, "lpips", relative=True, method="jsgs_eff") == pytest.approx(half)
    assert rep2.targets() == rep.targets()


def test_report_has_the_budget_section(tmp_path: Path) -> None:
    from jsgs.bench.markdown import write_report

    report = write_report(_hand_rows(), tmp_path, [], []).read_text()
    assert "## Equal Gaussian budget" in report and "### Time to quality" in report
    assert "## DefaultStrategy runs" in report
    assert (tmp_path / "plots" / "a_budgets.png").stat().st_size > 1000


def test_train_cap_max_needs_mcmc(tmp_path: Path, compressed_scene: Path) -> None:
    from jsgs.cli import main

    man = compressed_scene / "manifest.json"
    args = ["train", str(man), "--out", str(tmp_path / "r"), "--cap-max", "50", "--preset", "paper"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code != 0 and "--cap-max applies to strategy.type mcmc" in r.output
    assert not (tmp_path / "r").exists()


def test_bench_at_equal_budget_end_to_end(synth_scene: Path, tmp_path: Path) -> None:
    """Reference run first, the 0.5x budget resolved from its count, every run under that cap."""
    from jsgs.base.schema import validate
    from jsgs.cli import main
    from jsgs.method.recipes import RECIPES

    cfg = tmp_path / "tiny.json"
    tiny = {"init": {"type": "random", "num_points": 200, "scale": 0.3},
            "eval": {"fps_passes": 1, "fps_warmup": 0, "save_renders": False}}  # fmt: skip
    cfg.write_text(json.dumps(tiny))
    jcfg = tmp_path / "recipe.json"
    jcfg.write_text(json.dumps({"loss": {"base_weight": 0.5}, "method_options": {"base_noise_ref": 3.0}}))
    out = tmp_path / "results"
    args = [
        "bench", str(synth_scene), "--out", str(out), "--schedules", "gaussian,clean", "--methods",
        "gsplat,jsgs", "--strategy", "mcmc", "--budgets", "0.5x", "--seeds", "0", "--iterations", "4",
        "--eval-at", "2,4", "--jobs-per-gpu", "2", "--device", "cpu", "--config", str(cfg), "--jsgs-config",
        str(jcfg), "--gsplat-steps", "1.5", "--quiet",
    ]  # fmt: skip
    r = CliRunner().invoke(main, args, catch_exceptions=False)
    assert r.exit_code == 0, r.output
    doc = json.loads((out / "bench.json").read_text())
    validate(doc, "bench", "bench.json")
    name = synth_scene.name
    ref = json.loads((out / "runs" / name / "clean" / "gsplat" / "s0" / "metrics.json").read_text())
    cap = round(0.5 * ref["evals"][-1]["num_gaussians"])
    ids = {x["id"]: x for x in doc["runs"]}
    assert set(ids) == {f"{name}/clean/gsplat/s0"} | {
        f"{name}/{s}/{m}/mcmc-{cap}/s0" for s, m in (("gaussian", "gsplat"), ("gaussian", "jsgs"),
                                                     ("clean", "gsplat"))
    }  # fmt: skip
    assert all(x["status"] == "complete" for x in ids.values())
    for s, m in (("gaussian", "gsplat"), ("gaussian", "jsgs"), ("clean", "gsplat")):
        run = out / "runs" / name / s / m / f"mcmc-{cap}" / "s0"
        settings = json.loads((run / "config.json").read_text())["settings"]
        assert settings["strategy"]["type"] == "mcmc" and settings["strategy"]["cap_max"] == cap
        assert settings["init"]["num_points"] == 200  # the bench's --config under every run
        assert settings["loss"]["base_weight"] == (0.5 if m == "jsgs" else 1.0)  # the recipe: JSGS only
        # JSGS gets the mcmc preset's recipe, with --jsgs-config over it; gsplat takes no options
        recipe = {**RECIPES["mcmc"], "base_noise_ref": 3.0} if m == "jsgs" else {}
        assert settings["method_options"] == recipe
        metrics = json.loads((run / "metrics.json").read_text())
        assert metrics["num_gaussians"] <= cap and metrics["runs_per_device"] == 2
        # --gsplat-steps 1.5: gsplat on the JPEG views trains 6 steps on the 4-step recipe, evaluated past it
        longer = (s, m) == ("gaussian", "gsplat")
        assert metrics["iterations"] == (6 if longer else 4)
        assert [e["step"] for e in metrics["evals"]] == ([2, 4, 6] if longer else [2, 4])
        assert settings["optim"]["means_lr_decay_steps"] == (4 if longer else 0)
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert {(x["strategy"], x["budget"]) for x in rows} == {("default", ""), ("mcmc", str(cap))}
    assert list(rows[0])[3:6] == ["seed", "strategy", "budget"]
    past = [(x["method"], x["step"]) for x in rows if int(x["step"]) > int(x["schedule_steps"])]
    assert past == [("gsplat", "6")] and {x["runs_per_device"] for x in rows} == {"2"}
    report = (out / "report.md").read_text()
    assert "## Equal Gaussian budget" in report and f"| {cap:,} |" in report
    assert "step 4" in report.split("## Equal Gaussian budget")[1].splitlines()[0]
    assert "## Equal training time" in report and "runs per device: 2" in report
    # "Per test view" from the runs' metrics.json, at the tables' step 4 (gsplat's evaluation at 6 is past it)
    views = metrics["evals"][-1]["views"]  # the clean run's: the same test views
    per_view = report.split("## Per test view")[1].split("\n## ")[0]
    assert f"| {name} | gaussian | {cap:,} | jsgs | 0 | 4 | {len(views)} |" in per_view
    assert (out / "plots" / f"{name}_time.png").is_file()


def test_budget_report_at_an_earlier_step() -> None:
    # every run stopped early, one of them before the others: the tables compare the step all of them reached
    rows = [r for r in _hand_rows() if int(r["budget"]) == 300 and r["strategy"] == "mcmc"]
    rows = [r for r in rows if not (r["method"] == "gsplat" and r["seed"] == 0 and int(r["step"]) == 1000)]
    key = ("a", "gaussian", 300)
    assert BudgetReport(rows).values(*key[:2], "gsplat", 300, "lpips") == pytest.approx({1: 0.12, 2: 0.11})
    rep = BudgetReport(rows, step=700)
    assert rep.step == 700 and rep.keys == [key]
    assert rep.values(*key[:2], "gsplat", 300, "lpips") == pytest.approx({0: 0.12, 1: 0.144, 2: 0.132})
    # JSGS at step 700 is 0.6x gsplat at step 700 on every seed; evaluations after step 700 are not used
    assert rep.paired(key, "lpips", relative=True) == pytest.approx([-40.0, -100 / 3, -40.0])
    assert rep.time_to_quality(key) == [500, 500, 500]


def test_budget_report_at_a_step_per_scene(tmp_path: Path) -> None:
    # scene "a" complete at 1,000; scene "b" (the same numbers) with one run stopped at 700: common_steps
    # finds 1,000 and 700, and each scene is compared there, targets pooled over both
    from jsgs.bench.budget import common_steps
    from jsgs.bench.markdown import write_report

    a = [r for r in _hand_rows() if int(r["budget"]) == 300 and r["strategy"] == "mcmc"]
    stopped = ("gsplat", 0, 1000)
    b = [r | {"scene": "b"} for r in a if (r["method"], r["seed"], r["step"]) != stopped]
    steps = common_steps(a + b)
    assert steps == {("a", 300): 1000, ("b", 300): 700}
    rep = BudgetReport(a + b, steps)
    assert rep.step_at("a", 300) == 1000 and rep.step_at("b", 300) == 700
    assert rep.step_at("other", 300) == rep.step_at("b") == rep.step == 1000
    assert rep.paired(("a", "gaussian", 300), "lpips", relative=True) == pytest.approx(
        [-40.0, 100 * (0.08 / 0.12 - 1), -40.0]
    )
    d = rep.paired(("b", "gaussian", 300), "lpips", relative=True)
    assert d == pytest.approx([-40.0, -100 / 3, -40.0])
    assert rep.time_to_quality(("b", "gaussian", 300)) == [500, 500, 500]
    targets = "\n".join(rep.targets())
    assert "| 6 |" in targets and "100 %" in targets
    report = write_report(a + b, tmp_path, [], [], budget_step=steps).read_text()
    assert "steps: a 1000; b 700" in report and "stopped before" not in report


def test_budget_report_at_a_step_per_scene_and_budget(tmp_path: Path) -> None:
    # one scene at two budgets: at 300 one run stopped at 700, at 100 every run reached 1,000; each budget is
    # compared at its own step, and the report says which
    from jsgs.bench.budget import common_steps
    from jsgs.bench.markdown import write_report

    rows = [r for r in _hand_rows() if r["strategy"] == "mcmc"]
    rows = [r for r in rows if (r["budget"], r["method"], r["seed"], r["step"]) != (300, "gsplat", 0, 1000)]
    steps = common_steps(rows)
    assert steps == {("a", 300): 700, ("a", 100): 1000}
    rep = BudgetReport(rows, steps)
    d = rep.paired(("a", "gaussian", 300), "lpips", relative=True)
    assert d == pytest.approx([-40.0, -100 / 3, -40.0])
    assert rep.paired(("a", "gaussian", 100), "psnr") == pytest.approx([-1.0, -1.0, -1.0])
    assert rep.step_label() == "steps: a 1000 (100), 700 (300)"
    report = write_report(rows, tmp_path, [], [], budget_step=steps).read_text()
    assert "steps: a 1000 (100), 700 (300)" in report and "stopped before" not in report


def test_count_label_keeps_counts_short() -> None:
    assert [count_label(v) for v in (0, 950, 100_000, 100_682, 125_000, 300_000, 1_500_000)] == [
        "0", "950", "100k", "101k", "125k", "300k", "1.5M"]  # fmt: skip
