"""``jsgs bench`` (jsgs.bench): the harness end to end on a tiny synthetic scene on the CPU (1 scene x the
gaussian schedule + clean x 2 methods, 6 iterations), rerun skipping, a failing run, and the damage-recovered
arithmetic with its noise rule on hand-made numbers."""

from __future__ import annotations

import contextlib
import csv
import json
import os
import threading
from pathlib import Path

import pytest
from click.testing import CliRunner

from jsgs.bench import plan as plan_mod
from jsgs.bench.stats import Agg, damage_recovered, worse_beyond_spread

TINY = {
    "init": {"type": "random", "num_points": 200, "scale": 0.3},
    "eval": {"fps_passes": 1, "fps_warmup": 0, "save_renders": False},
}
LEADING = (
    "scene,schedule,method,seed,strategy,budget,step,psnr,ssim,lpips,train_seconds,fps,num_gaussians,"
    "peak_memory_mb".split(
        ","
    )
)


def _bench(scene: Path, out: Path, cfg: Path) -> object:
    from jsgs.cli import main

    args = [
        "bench", str(scene), "--out", str(out), "--schedules", "gaussian,clean", "--fixed", "",
        "--methods", "gsplat,jsgs", "--seeds", "0", "--iterations", "6", "--eval-at", "3,6",
        "--jobs-per-gpu", "2", "--device", "cpu", "--config", str(cfg), "--quiet",
    ]  # fmt: skip
    return CliRunner().invoke(main, args, catch_exceptions=False)


def test_bench_end_to_end(synth_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from jsgs.base.schema import validate

    cfg = tmp_path / "tiny.json"
    cfg.write_text(json.dumps(TINY))
    out = tmp_path / "results"
    name = synth_scene.name
    # one run is made to fail (a broken argument for jsgs on the gaussian schedule); the others complete
    real = plan_mod.train_argv

    def broken(run: plan_mod.Run, device: str, config: str | None, resume: bool) -> list[str]:
        argv = real(run, device, config, resume)
        return argv + ["--jpeg-mode", "nonsense"] if run.method == "jsgs" else argv

    monkeypatch.setattr(plan_mod, "train_argv", broken)
    r = _bench(synth_scene, out, cfg)
    assert r.exit_code == 1, r.output
    assert "1 failed" in r.output
    doc = json.loads((out / "bench.json").read_text())
    validate(doc, "bench", "bench.json")
    status = {x["id"]: x["status"] for x in doc["runs"]}
    assert status == {
        f"{name}/gaussian/gsplat/s0": "complete",
        f"{name}/gaussian/jsgs/s0": "failed",
        f"{name}/clean/gsplat/s0": "complete",
    }
    failed = next(x for x in doc["runs"] if x["status"] == "failed")
    assert "nonsense" in failed["stderr_tail"] and failed["returncode"] != 0
    report = (out / "report.md").read_text()
    assert "## Failed runs" in report and f"`{name}/gaussian/jsgs/s0`" in report

    # the rerun trains only the failed run, skips the finished ones
    monkeypatch.setattr(plan_mod, "train_argv", real)
    r = _bench(synth_scene, out, cfg)
    assert r.exit_code == 0, r.output
    doc = json.loads((out / "bench.json").read_text())
    validate(doc, "bench", "bench.json")
    status = {x["id"]: x["status"] for x in doc["runs"]}
    assert status[f"{name}/gaussian/jsgs/s0"] == "complete"
    assert status[f"{name}/gaussian/gsplat/s0"] == status[f"{name}/clean/gsplat/s0"] == "skipped"
    assert doc["summary"]["failed"] == 0 and doc["status"] == "complete"

    # the same compressed files for both methods, in the documented layout
    for m in ("gsplat", "jsgs"):
        cfg_doc = json.loads((out / "runs" / name / "gaussian" / m / "s0" / "config.json").read_text())
        assert str(out / "data" / name / "gaussian_s0" / "manifest.json") in json.dumps(cfg_doc)
    rec = json.loads((out / "data" / name / "clean_s0" / "compress.json").read_text())
    assert rec["settings"]["schedule"] == "clean"

    with open(out / "results.csv", newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0][: len(LEADING)] == LEADING
    body = [dict(zip(rows[0], r, strict=True)) for r in rows[1:]]
    got = sorted((b["schedule"], b["method"], b["seed"], b["step"]) for b in body)
    assert got == sorted(
        (s, m, "0", st) for s, m in [("gaussian", "gsplat"), ("gaussian", "jsgs"), ("clean", "gsplat")]
        for st in ("3", "6")
    )  # fmt: skip
    for b in body:
        assert float(b["psnr"]) > 0 and int(b["num_gaussians"]) > 0 and float(b["train_seconds"]) > 0
    assert any(k.startswith("loss_obs") for k in rows[0])  # JSGS's per-term loss means as extra columns

    report = (out / "report.md").read_text()
    for section in (
        "## Table 1", "## Damage recovered", "## Table 2", "## Table 3", "## Table 4", "## Per-scene results",
        "## Plots", "## Failed runs",
    ):  # fmt: skip
        assert section in report, section
    assert f"### {name}" in report and "R_LPIPS" in report
    assert (out / "plots" / f"{name}.png").stat().st_size > 1000


def _a(*v: float) -> Agg:
    return Agg(list(v))


def test_damage_recovered_and_noise_rule() -> None:
    # LPIPS: baseline 0.10, clean 0.05, JSGS 0.075 -> half the damage recovered; spreads 0.002 << gap 0.05
    r = damage_recovered(_a(0.099, 0.101), _a(0.074, 0.076), _a(0.049, 0.051), higher_is_better=False)
    assert r.value == pytest.approx(0.5) and r.note == "" and r.spread == pytest.approx(0.002)
    # PSNR: baseline 25.7, clean 26.7, JSGS 26.45 -> 0.75
    r = damage_recovered(_a(25.6, 25.8), _a(26.4, 26.5), _a(26.6, 26.8), higher_is_better=True)
    assert r.value == pytest.approx(0.75) and r.gap == pytest.approx(1.0)
    # JSGS worse than the baseline: negative R
    r = damage_recovered(_a(25.7, 25.7), _a(25.2, 25.2), _a(26.7, 26.7), higher_is_better=True)
    assert r.value == pytest.approx(-0.5)
    # baseline within noise of the ceiling: gap 0.05 dB, seed spread 0.3 dB -> not divided
    r = damage_recovered(_a(25.6, 25.9), _a(26.0, 26.1), _a(25.75, 25.8), higher_is_better=True)
    assert r.value is None and r.note == "within noise" and r.spread == pytest.approx(0.3)
    # the clean run's spread counts too
    r = damage_recovered(_a(0.10, 0.10), _a(0.09, 0.09), _a(0.08, 0.13), higher_is_better=False)
    assert r.value is None and r.note == "within noise"
    # one seed: no spread known, R computed and marked
    r = damage_recovered(_a(0.10), _a(0.08), _a(0.06), higher_is_better=False)
    assert r.value == pytest.approx(0.5) and r.note == "1 seed"
    # identical baseline and clean with one seed: nothing to divide by
    assert damage_recovered(_a(0.1), _a(0.08), _a(0.1), higher_is_better=False).value is None
    # no clean run
    assert damage_recovered(_a(0.1), _a(0.08), _a(), higher_is_better=False).note == "no clean run"
    # worse beyond the spread
    assert worse_beyond_spread(_a(0.10, 0.101), _a(0.11, 0.111), higher_is_better=False) is True
    assert worse_beyond_spread(_a(0.10, 0.12), _a(0.11, 0.111), higher_is_better=False) is False
    assert worse_beyond_spread(_a(0.10), _a(0.11), higher_is_better=False) is None


def test_plan_layout_and_ablation(tmp_path: Path, synth_scene: Path) -> None:
    p = plan_mod.build_plan(plan_mod.BenchSettings(
        scenes=[synth_scene], out=tmp_path, schedules=["uniform", "gaussian", "clean"], fixed=[30, 50],
        methods=["gsplat", "jsgs"], ablation=synth_scene.name, seeds=[0, 1], iterations=100,
        eval_at=[50, 100],
    ))  # fmt: skip
    ids = [r.id for r in p.runs]
    assert len(ids) == len(set(ids))
    n = synth_scene.name
    # 2 mixed x 2 seeds x 2 methods + clean x 2 seeds + 2 fixed x 2 methods + 3 ablation-only variants
    assert len(ids) == 8 + 2 + 4 + 3
    assert f"{n}/clean/jsgs/s0" not in ids and f"{n}/fixed30/jsgs/s1" not in ids
    jo = next(r for r in p.runs if r.method == "jo")
    assert jo.train_method == "jsgs" and jo.flags == ["--no-ds", "--no-gc"] and jo.schedule == "gaussian"
    assert jo.manifest == next(r for r in p.runs if r.id == f"{n}/gaussian/gsplat/s0").manifest
    fixed = next(d for d in p.datasets if d.schedule == "fixed30")
    assert (fixed.compress_schedule, fixed.quality, fixed.seed) == ("fixed", 30, 0)
    assert len(p.datasets) == 3 * 2 + 2
    argv = plan_mod.train_argv(jo, "cuda", None, resume=False)
    assert argv[-3:] == ["--no-ds", "--no-gc", "--force"] and "--seed" in argv
    with pytest.raises(Exception, match="unknown schedule"):
        plan_mod.build_plan(plan_mod.BenchSettings(
            scenes=[synth_scene], out=tmp_path, schedules=["mixed"], fixed=[], methods=["gsplat"],
            seeds=[0], iterations=10, eval_at=[10],
        ))


def test_prepare_only_then_plan_without_the_source(synth_scene: Path, tmp_path: Path) -> None:
    """The CPU half of a GPU session compresses; the GPU machine (no ../shared) plans on the prepared data."""
    from jsgs.base.errors import JsgsError
    from jsgs.cli import main

    out = tmp_path / "results"
    args = [
        "bench", str(synth_scene), "--out", str(out), "--schedules", "gaussian", "--fixed", "",
        "--methods", "gsplat", "--seeds", "0", "--iterations", "2", "--device", "cpu", "--prepare-only",
        "--quiet",
    ]  # fmt: skip
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    data = out / "data" / synth_scene.name / "gaussian_s0"
    assert (data / "manifest.json").is_file() and not (out / "runs").exists()
    assert json.loads((out / "bench.json").read_text())["status"] == "prepared"
    gone = tmp_path / "elsewhere" / synth_scene.name
    plan = plan_mod.build_plan(plan_mod.BenchSettings(
        scenes=[gone], out=out, schedules=["gaussian"], fixed=[], methods=["gsplat"], seeds=[0],
        iterations=2, eval_at=[2],
    ))
    assert [d.out for d in plan.datasets] == [str(data)]
    with pytest.raises(JsgsError, match="scene folder not found"):
        plan_mod.build_plan(plan_mod.BenchSettings(
            scenes=[tmp_path / "nope"], out=out, schedules=["gaussian"], fixed=[], methods=["gsplat"],
            seeds=[0], iterations=2, eval_at=[2],
        ))


def test_prepare_derives_from_the_clean_base(
    synth_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A GPU machine carries only data/<scene>/clean_s0/{manifest.json,compress.json,reference/}: the other
    datasets are derived from it with Pillow (no compress), and the clean base gets its images/ back."""
    import shutil

    import jsgstools.compress
    from jsgs.base.manifest import load_manifest
    from jsgs.bench.harness import prepare_datasets
    from jsgs.cli import main

    out = tmp_path / "results"
    args = [
        "bench", str(synth_scene), "--out", str(out), "--schedules", "clean", "--fixed", "",
        "--methods", "gsplat", "--seeds", "0", "--iterations", "2", "--device", "cpu", "--prepare-only",
        "--quiet",
    ]  # fmt: skip
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    base = out / "data" / synth_scene.name / "clean_s0"
    shutil.rmtree(base / "images")  # not carried

    def no_compress(*a: object, **k: object) -> None:
        raise AssertionError("compress must not be called")

    monkeypatch.setattr(jsgstools.compress, "compress", no_compress)
    gone = tmp_path / "elsewhere" / synth_scene.name
    plan = plan_mod.build_plan(plan_mod.BenchSettings(
        scenes=[gone], out=out, schedules=["gaussian", "clean"], fixed=[30], methods=["gsplat"],
        seeds=[0], iterations=2, eval_at=[2],
    ))
    status = prepare_datasets(plan, progress=False)
    assert {k: v["status"] for k, v in status.items()} == {
        f"{synth_scene.name}/gaussian_s0": "complete",
        f"{synth_scene.name}/clean_s0": "skipped",
        f"{synth_scene.name}/fixed30_s0": "complete",
    }, status
    for d in plan.datasets:
        m = load_manifest(d.manifest)  # every image and reference resolves
        train = m.train_views
        if d.schedule == "clean":
            assert all(v.jpeg is None and v.image.is_file() for v in train)
        else:
            assert all(v.jpeg is not None and v.image.suffix == ".jpg" for v in train)
            if d.schedule == "fixed30":
                assert all(v.jpeg is not None and v.jpeg.quality == 30 for v in train)
            assert not (Path(d.out) / "reference").exists()
    assert all(v["status"] == "skipped" for v in prepare_datasets(plan, progress=False).values())  # rerun


def test_report_only_collects_what_is_there(synth_scene: Path, tmp_path: Path) -> None:
    """--report-only trains nothing: runs copied back from elsewhere are collected, the others listed as
    not run (the way results from several GPU calls are merged into one report)."""
    from jsgs.base.schema import validate
    from jsgs.cli import main

    cfg = tmp_path / "tiny.json"
    cfg.write_text(json.dumps(TINY))
    out = tmp_path / "results"
    args = [
        "bench", str(synth_scene), "--out", str(out), "--schedules", "gaussian", "--fixed", "",
        "--methods", "gsplat", "--seeds", "0,1", "--iterations", "4", "--eval-at", "4",
        "--device", "cpu", "--config", str(cfg), "--quiet",
    ]  # fmt: skip
    r = CliRunner().invoke(main, [*args, "--report-only"], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    assert "collected 0 of 2 runs (2 not run)" in r.output
    assert not (out / "data").exists() and not (out / "runs").exists()  # nothing compressed or trained
    r = CliRunner().invoke(main, [*args, "--seeds", "0"], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, [*args, "--report-only"], catch_exceptions=False)
    assert r.exit_code == 0 and "collected 1 of 2 runs (1 not run)" in r.output
    doc = json.loads((out / "bench.json").read_text())
    validate(doc, "bench", "bench.json")
    assert doc["settings"]["report_only"] is True
    name = synth_scene.name
    assert {x["id"]: x["status"] for x in doc["runs"]} == {
        f"{name}/gaussian/gsplat/s0": "skipped",
        f"{name}/gaussian/gsplat/s1": "failed",
    }
    with open(out / "results.csv", newline="") as f:
        assert [row["seed"] for row in csv.DictReader(f)] == ["0"]
    report = (out / "report.md").read_text()
    # listed once, on one line, with no empty log excerpt after it
    assert "Not run (1):" in report and f"- `{name}/gaussian/gsplat/s1`: not run" in report
    assert "```\n```" not in report


def test_slots_follow_cuda_visible_devices(monkeypatch: pytest.MonkeyPatch) -> None:
    from jsgs.bench.workers import detect_slots

    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "1,3")
    assert detect_slots("cuda", 2) == ["1", "1", "3", "3"]
    assert detect_slots("cpu", 2) == [None, None]


def test_no_run_starts_that_the_time_limit_would_cut(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Once a run of a scene and method took longer than what the --time-limit leaves, its like are not
    started (a cut run is lost work on a machine that is given back); JSGS runs are queued first."""
    import time

    from jsgs.bench import workers as pool

    started: list[str] = []

    def fake_run_one(run: plan_mod.Run, gpu: object, *a: object, **k: object) -> dict[str, object]:
        started.append(run.id)
        return {"id": run.id, "status": "complete", "seconds": 1000.0, "resumed": False}

    monkeypatch.setattr(pool, "run_one", fake_run_one)

    def mk(scene: str, method: str, seed: int, steps: int = 10, schedule: str = "gaussian") -> plan_mod.Run:
        d = tmp_path / scene / schedule / method / str(seed)
        return plan_mod.Run(scene, schedule, method, seed, method, [], "k", "m", str(d), str(d) + ".log",
                            steps, [steps])  # fmt: skip

    runs = [mk("a", "gsplat", 0), mk("a", "gsplat", 1), mk("a", "jsgs", 0), mk("b", "gsplat", 0),
            mk("a", "gsplat", 0, 20, "uniform")]  # fmt: skip
    recs = pool.run_pool(runs, [None], "cpu", None, progress=False, deadline=time.time() + 500)
    # jsgs first; then a/gsplat s0 (nothing known yet), not a/gsplat s1 (like runs took 1000 s > 500 s left);
    # a gsplat run of another length is not judged by them
    assert started == ["a/gaussian/jsgs/s0", "a/gaussian/gsplat/s0", "b/gaussian/gsplat/s0",
                       "a/uniform/gsplat/s0"]  # fmt: skip
    assert recs["a/gaussian/gsplat/s1"]["status"] == "failed"
    assert "more than the --time-limit leaves" in str(recs["a/gaussian/gsplat/s1"]["error"])


def test_runs_that_stopped_early_are_kept_out_of_the_final_tables(tmp_path: Path) -> None:
    """A run cut at step 7000 is not compared at 7000 with runs finished at 10000: it is listed apart, and
    the tables are repeated at the last step every run reached."""
    from jsgs.bench.markdown import write_report
    from jsgs.bench.stats import common_step, final_rows, unfinished

    def row(sc: str, m: str, step: int, lp: float) -> dict[str, object]:
        return {"scene": sc, "schedule": "gaussian", "method": m, "seed": 0, "step": step, "psnr": 25.0,
                "ssim": 0.8, "lpips": lp, "train_seconds": step / 100, "fps": 100.0,
                "num_gaussians": 1000, "peak_memory_mb": 10.0}  # fmt: skip

    rows = [row("a", "gsplat", 7000, 0.12), row("a", "gsplat", 10000, 0.11), row("a", "jsgs", 7000, 0.09),
            row("b", "gsplat", 7000, 0.2), row("b", "gsplat", 10000, 0.19), row("b", "jsgs", 7000, 0.18),
            row("b", "jsgs", 10000, 0.17)]  # fmt: skip
    assert set(final_rows(rows)) == {("a", "gaussian", "gsplat", 0), ("b", "gaussian", "gsplat", 0),
                                     ("b", "gaussian", "jsgs", 0)}  # fmt: skip
    assert unfinished(rows) == [(("a", "gaussian", "jsgs", 0), 7000)]
    assert common_step(rows) == 7000
    report = write_report(rows, tmp_path, [], [], plots=False).read_text()
    assert "`a/gaussian/jsgs/s0`: last evaluation at step 7000" in report
    assert "## Table 1 and damage recovered at step 7000" in report
    # scene a's JSGS enters only the step-7000 table: 0.09 there, never against gsplat's 0.11 at 10000
    main, early = report.split("## Table 1 and damage recovered at step 7000")
    assert "0.0900" not in main.split("## Runs that stopped")[0] and "0.0900" in early


def test_weight_sweep_configs_and_summary(tmp_path: Path) -> None:
    """Every config of the loss-weight sweep loads as `jsgs train --config` for --method jsgs and differs
    from the paper's weights; the summary reads the committed results (gsplat, clean, paper-weights JSGS)."""
    import subprocess
    import sys

    from jsgs.method.options import parse_options
    from jsgs.train.config import TrainConfig, load_config_file

    root = Path(__file__).resolve().parents[3]
    paper = TrainConfig.from_preset("paper")  # the sweeps' configs apply over the paper's protocol
    configs = sorted((root / "benchmarks" / "weight_sweep").glob("*.json"))
    assert len(configs) >= 4
    for folder in ("weight_sweep", "densify_control"):
        seen = set()
        for c in sorted((root / "benchmarks" / folder).glob("*.json")):
            cfg = load_config_file(c, paper)
            o = parse_options(cfg.method_options)
            if c.stem.startswith("gsplat_"):  # a baseline control: no JSGS options
                assert not cfg.method_options, c.name
            lam = (c.stem.startswith("gsplat_"), cfg.loss.base_weight, o.lambda_obs, o.lambda_low,
                   o.lambda_mid, o.lambda_fro, cfg.strategy.grow_grad2d)  # fmt: skip
            assert lam != (False, 1.0, 0.2, 0.02, 0.03, 0.05, 0.0002) and lam not in seen, c.name
            seen.add(lam)
    ref = root / "docs" / "results" / "paper_protocol" / "results.csv"
    script = root / "benchmarks" / "weight_sweep.py"
    r = subprocess.run(
        [sys.executable, str(script), str(tmp_path), "--reference", str(ref)],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    assert "| gsplat (reference) |" in r.stdout
    assert "| jsgs, paper weights (reference) | 1 | 0.2 |" in r.stdout
    assert r.stdout.count("not run") == len(configs)
    control = sorted((root / "benchmarks" / "densify_control").glob("*.json"))
    r = subprocess.run(
        [sys.executable, str(script), str(tmp_path), "--reference", str(ref), "--configs",
         str(root / "benchmarks" / "densify_control"), "--scenes", "llff_flower,llff_fern", "--seed", "1"],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    assert r.stdout.count("not run") == 2 * len(control)
    assert "llff_fern, gaussian schedule, seed 1" in r.stdout
    assert "| gsplat_base2.1 | 2.1 | – | – | – | – | 0.0002 | not run |" in r.stdout


def test_time_limit_must_be_positive(tmp_path: Path) -> None:
    from jsgs.base.errors import JsgsError
    from jsgs.bench.harness import bench

    with pytest.raises(JsgsError, match="--time-limit -1: must be a positive number of seconds"):
        bench(plan_mod.BenchSettings(
            scenes=[str(tmp_path / "scene")], out=tmp_path / "out", schedules=["gaussian"], fixed=[],
            methods=["gsplat"], seeds=[0], iterations=10, time_limit=-1.0,
        ))  # fmt: skip


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_bad_settings_files_are_one_line_before_anything_is_written(
    synth_scene: Path, tmp_path: Path
) -> None:
    """--config and --jsgs-config are read as jsgs train reads a settings file: a FIFO is refused at once
    (never waited on), deep nesting and NaN in one line, not a traceback."""
    from jsgs.cli import main

    fifo, deep, nan = tmp_path / "fifo.json", tmp_path / "deep.json", tmp_path / "nan.json"
    os.mkfifo(fifo)  # nobody writes it: a reader that opened it would wait forever
    deep.write_text("[" * 100_000 + "]" * 100_000)
    nan.write_text('{"seed": NaN}')
    out = tmp_path / "results"
    cases = [(option, path, needle) for option in ("--config", "--jsgs-config")
             for path, needle in ((deep, "nested deeper than 64 levels"), (nan, "not a finite number"),
                                  (fifo, "is a FIFO (named pipe), not a regular file"))]  # fmt: skip
    outputs: list[tuple[int, str]] = []

    def invoke() -> None:
        for option, path, _ in cases:
            args = ["bench", str(synth_scene), "--out", str(out), option, str(path), "--device", "cpu",
                    "--report-only", "--quiet"]  # fmt: skip
            r = CliRunner().invoke(main, args)
            outputs.append((r.exit_code, r.output))

    t = threading.Thread(target=invoke, daemon=True)
    t.start()
    t.join(120)  # seconds each; a reader waiting on the FIFO would never return
    if t.is_alive():
        with contextlib.suppress(OSError):
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))  # let it go before failing
        pytest.fail(f"a settings file that is a FIFO was waited on ({len(outputs)} of {len(cases)} done)")
    for (code, output), (_, path, needle) in zip(outputs, cases, strict=True):
        assert code == 1 and output.startswith(f"error: {path}: ") and needle in output, output
        assert output.count("\n") == 1, output
    assert not out.exists()
