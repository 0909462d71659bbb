"""tools/diagnostics/profile_step.py: the whole benchmark on a tiny synthetic scene on the CPU (gsplat and
jsgs, a few steps each), its JSON against schemas/profile_step.schema.json, and the reading of CUDA profiler
events on hand-made ones (CI has no GPU)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import torch
from conftest import load_benchmark

ps = load_benchmark("profile_step", "tools/diagnostics")

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = {
    "init": {"type": "random", "num_points": 200, "scale": 0.3},
    "eval": {"fps_passes": 1, "fps_warmup": 0, "save_renders": False},
}


def test_cpu_end_to_end(tmp_path: Path, capsys: Any) -> None:
    from jsgs.base.schema import validate

    cfg = tmp_path / "tiny.json"
    cfg.write_text(json.dumps(TINY))
    out = tmp_path / "out" / "profile.json"
    work = tmp_path / "work"
    argv = [
        "--size", "48x32", "--views", "6", "--warmup", "3", "--settle", "1", "--steps", "2",
        "--device", "cpu", "--config", str(cfg), "--top", "5", "--workdir", str(work), "--out", str(out),
        "--python-top", "4", "--trace", str(tmp_path / "traces"), "--memory-history", "3",
    ]  # fmt: skip
    assert ps.main(argv) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert "note: profile_step: --memory-history: CUDA only; not recorded" in captured.err
    header = "| method | wall ms/step (unprofiled) | the same, run not resumed | wall ms/step (profiled) |"
    assert header in printed
    assert "jsgs − gsplat: top 5 kernels by extra" in printed
    assert "jsgs: Python functions by self time (cProfile" in printed
    assert "| peak allocated MiB | peak reserved MiB | allocated at the start MiB | #Gaussians |" in printed
    assert "; peak memory: CUDA only" in printed

    doc = json.loads(out.read_text())
    validate(doc, "profile_step", str(out))
    assert doc["format"] == "jsgs-profile-step" and doc["steps"] == 2 and doc["warmup"] == 3
    assert doc["format_version"] == 4
    # the default paper preset: DefaultStrategy, no budget
    assert doc["budget"] == {"strategy": "default", "cap_max": None, "cap_max_auto": False}
    assert all(r["cap_max"] is None and r["budget_rule"] is None for r in doc["results"].values())
    res = doc["results"]
    assert list(res) == ["gsplat", "jsgs"]
    for r in res.values():
        assert r["kernel_launches_per_step"] > 0 and r["host_op_ms_per_step"] > 0
        top = r["python_top"]
        assert len(top) == 4 and top[0]["self_ms_per_step"] >= top[-1]["self_ms_per_step"] > 0
        assert all(t["cumulative_ms_per_step"] >= t["self_ms_per_step"] for t in top)
        assert min(r["wall_ms_per_step"], r["wall_ms_per_step_profiled"], r["wall_ms_per_step_fresh"]) > 0
        assert r["graph_launches_per_step"] == 0  # CPU: no graphs, and no device-only numbers
        assert r["device_kernel_ms_per_step"] is None and r["syncs_per_step"] is None
        # peak memory: CUDA only, recorded as null (present, not invented)
        assert r["peak_memory_allocated_bytes"] is None and r["peak_memory_reserved_bytes"] is None
        assert "peak_memory_allocated_bytes" in r and "peak_memory_reserved_bytes" in r
        assert r["start_memory_allocated_bytes"] is None and r["start_memory_reserved_bytes"] is None
        assert 0 < len(r["kernels"]) <= 5
        assert r["num_gaussians"] == r["num_gaussians_profiled"]  # both copies trained the same Gaussians
        assert r["graph_recordings_in_window"] == 0  # counted (no graphs on the CPU), not left out
    # JSGS adds ops to the baseline's step
    assert res["jsgs"]["kernel_launches_per_step"] > res["gsplat"]["kernel_launches_per_step"]
    diff = doc["differences"]["jsgs"]
    assert diff["baseline"] == "gsplat" and list(doc["differences"]) == ["jsgs"]
    assert diff["by_launches"] and all(r["extra_launches_per_step"] > 0 for r in diff["by_launches"])
    assert all(r["name"].startswith("aten::") for r in diff["by_launches"])

    # the Chrome traces of the profiled windows, with Python frames (tools/diagnostics/trace_gaps.py reads
    # them)
    traces = sorted(p.name for p in (tmp_path / "traces").iterdir())
    assert traces == ["gsplat.trace.json", "jsgs.trace.json"]
    events = json.loads((tmp_path / "traces" / "jsgs.trace.json").read_text())["traceEvents"]
    assert any(e.get("cat") == "python_function" for e in events)
    assert any(e.get("name", "").startswith("autograd::engine::evaluate_function") for e in events)

    # nothing left behind: no partial JSON beside the output, the runs' temporary folder removed
    assert [p.name for p in out.parent.iterdir()] == ["profile.json"]
    assert list(work.iterdir()) == []


def _ev(
    name: str, cuda: bool = False, id: int = 0, us: float = 0.0, parent: Any = None, t: float = 10.0
) -> Any:
    """A stand-in for a profiler event (the attributes window_stats reads), starting at ``t`` µs."""
    dev = torch.autograd.DeviceType.CUDA if cuda else torch.autograd.DeviceType.CPU
    return SimpleNamespace(
        name=name, device_type=dev, id=id, is_async=False, cpu_parent=parent,
        is_user_annotation=name.startswith(("ProfilerStep", ps.WINDOW_END)),
        self_cpu_time_total=0.0 if cuda else us, cpu_time_total=0.0 if cuda else us,
        time_range=SimpleNamespace(start=t, end=t + us, elapsed_us=lambda: us),
    )  # fmt: skip


def test_cuda_event_reading() -> None:
    events = [
        _ev("ProfilerStep*", us=400.0, t=0.0),  # two recorded steps; their self time is Python, not ops
        _ev("ProfilerStep*", us=600.0, t=400.0),
        _ev("aten::mul", us=20.0),
        _ev("cudaLaunchKernel", id=11, us=5.0),
        _ev("cudaLaunchKernel", id=12, us=5.0),
        _ev("cuLaunchKernel", id=13, us=5.0),
        _ev("cudaGraphLaunch", id=14, us=8.0),
        _ev("cudaStreamSynchronize", id=15, us=30.0, t=500.0),
        _ev(ps.WINDOW_END, us=50.0, t=900.0),
        _ev("cudaDeviceSynchronize", id=16, us=2.0, t=910.0),  # the window's own closing sync
        _ev("cudaDeviceSynchronize", id=17, us=2.0, t=1100.0),  # the profiler's stop, after the last step
        _ev("mul_kernel", cuda=True, id=11, us=3.0),
        _ev("mul_kernel", cuda=True, id=12, us=3.0),
        _ev("triton_fused", cuda=True, id=13, us=5.0),
        _ev("mul_kernel", cuda=True, id=14, us=1.0),  # replayed from the graph
        _ev("dct_kernel", cuda=True, id=14, us=2.0),
        _ev("Memcpy DtoH (Device -> Pageable)", cuda=True, id=15, us=1.5),
        _ev("ProfilerStep*", cuda=True, us=900.0, t=0.0),  # GPU-side annotations: not device work
        _ev(ps.WINDOW_END, cuda=True, us=50.0, t=900.0),
    ]
    s = ps.window_stats(events, cuda=True)
    assert (s.launches, s.graph_launches, s.syncs) == (3, 1, 1)
    assert s.device_us == pytest.approx(15.5)
    assert s.host_us == pytest.approx(20.0 + 15.0 + 8.0 + 30.0)
    k = s.kernels
    assert (k["mul_kernel"].runs, k["mul_kernel"].launched, k["mul_kernel"].time_us) == (3, 2, 7.0)
    assert (k["dct_kernel"].runs, k["dct_kernel"].launched) == (1, 0)
    copy = k["Memcpy DtoH (Device -> Pageable)"]
    assert (copy.runs, copy.launched) == (1, 0)

    base = ps.window_stats(events[:4] + events[11:12], cuda=True)  # one mul launch
    assert (base.launches, base.syncs) == (1, 0)
    d = ps.kernel_difference(s.kernels, base.kernels, steps=1, top=10)
    by_launch = {r["name"]: r["extra_launches_per_step"] for r in d["by_launches"]}
    assert by_launch == {"mul_kernel": 1.0, "triton_fused": 1.0}  # graph replays, copies: no kernel launch
    by_time = [r["name"] for r in d["by_time"]]
    assert by_time == ["triton_fused", "mul_kernel", "dct_kernel", "Memcpy DtoH (Device -> Pageable)"]


def test_cpu_counting_rule() -> None:
    # a composite op counts as what it runs; views and allocations are free; nested ops of a counted op are
    # part of it
    linear = _ev("aten::linear", us=10.0)
    addmm = _ev("aten::addmm", us=9.0, parent=linear)
    copy = _ev("aten::copy_", us=1.0, parent=addmm)
    t = _ev("aten::t", us=0.5, parent=linear)
    view = _ev("aten::view", us=0.1)
    empty = _ev("aten::empty", us=0.1)
    to = _ev("aten::to", us=0.1)  # same dtype: dispatches to nothing
    s = ps.window_stats([linear, addmm, copy, t, view, empty, to], cuda=False)
    assert s.launches == 1 and list(s.kernels) == ["aten::addmm"]
    assert s.device_us is None and s.syncs is None


def test_bad_arguments() -> None:
    with pytest.raises(SystemExit):
        ps.parse_args(["--steps", "0"])
    with pytest.raises(SystemExit):
        ps.parse_args(["--jsgs-options", "[1]"])
    parsed = ps.parse_args(["--jsgs-options", '{"speed": {"cuda_graph": false}}']).jsgs_options
    assert parsed == {"speed": {"cuda_graph": False}}


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
def test_sync_census_refuses_without_cuda(capsys: Any) -> None:
    sc = load_benchmark("sync_census", "tools/diagnostics")
    assert sc.main(["--manifest", "missing.json"]) == 1
    assert capsys.readouterr().err.strip() == "error: sync_census needs CUDA (host syncs are a GPU matter)"


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
def test_bench_graph_host_refuses_without_cuda(capsys: Any) -> None:
    bg = load_benchmark("bench_graph_host", "tools/diagnostics")
    assert bg.main(["--steps", "1"]) == 1
    assert capsys.readouterr().err.strip() == (
        "error: bench_graph_host needs CUDA (it times host launches of GPU work)"
    )


def test_pairs_interleave_and_report_medians(tmp_path: Path, capsys: Any) -> None:
    from jsgs.base.schema import validate

    abba = [["gsplat", "jsgs"], ["jsgs", "gsplat"], ["gsplat", "jsgs"]]
    assert ps.pair_order(["gsplat", "jsgs"], 3) == abba
    cfg = tmp_path / "tiny.json"
    cfg.write_text(json.dumps(TINY))
    out = tmp_path / "profile.json"
    work = tmp_path / "work"
    argv = [
        "--size", "48x32", "--views", "6", "--warmup", "3", "--settle", "1", "--steps", "2",
        "--device", "cpu", "--config", str(cfg), "--top", "3", "--workdir", str(work), "--out", str(out),
        "--pairs", "3", "--no-fresh",
    ]  # fmt: skip
    assert ps.main(argv) == 0
    printed = capsys.readouterr().out
    assert "3 interleaved windows per method, resumed from the same checkpoint (order: gsplat, jsgs; jsgs, " \
           "gsplat; gsplat, jsgs)" in printed  # fmt: skip
    doc = json.loads(out.read_text())
    validate(doc, "profile_step", str(out))
    walls = {m: r["paired_wall_ms_per_step"] for m, r in doc["results"].items()}
    # --no-fresh: no run from step 0, so no such column value
    assert not any("wall_ms_per_step_fresh" in r for r in doc["results"].values())
    for r in doc["results"].values():  # CPU: no peak memory per window, recorded as null
        assert r["paired_peak_memory_allocated_bytes"] is None
        assert r["paired_peak_memory_reserved_bytes"] is None
        assert r["paired_start_memory_allocated_bytes"] is None
        assert r["paired_start_memory_reserved_bytes"] is None
        assert r["peak_memory_allocated_bytes"] is None
    assert "peak_memory" in doc["pairs"] and doc["pairs"]["peak_memory"] is None
    assert "peak memory of the windows: CUDA only" in printed
    assert all(len(v) == 3 and min(v) > 0 for v in walls.values())
    pairs = doc["pairs"]
    assert pairs["count"] == 3 and list(pairs["ratio"]) == ["jsgs"]
    # the numbers are the medians and ratios of the windows themselves
    per_pair = [j / g for j, g in zip(walls["jsgs"], walls["gsplat"], strict=True)]
    assert pairs["ratio"]["jsgs"]["per_pair"] == pytest.approx(per_pair)
    assert pairs["ratio"]["jsgs"]["median"] == pytest.approx(sorted(per_pair)[1])
    # three pairs: the median's distribution-free interval is (min, max), covering 1 - 2/8
    assert pairs["ratio"]["jsgs"]["interval"] == pytest.approx([min(per_pair), max(per_pair)])
    assert pairs["ratio"]["jsgs"]["interval_coverage"] == pytest.approx(0.75)
    assert "(75.0 %) |" in printed
    assert pairs["median_ms_per_step"]["gsplat"] == pytest.approx(sorted(walls["gsplat"])[1])
    assert f"| jsgs | {', '.join(f'{v:.2f}' for v in walls['jsgs'])} |" in printed
    assert list(work.iterdir()) == []


def test_pairs_must_not_be_negative(capsys: Any) -> None:
    with pytest.raises(SystemExit):
        ps.parse_args(["--pairs", "-1"])
    assert "--pairs must be >= 0, got -1" in capsys.readouterr().err


def test_preset_mcmc_is_the_equal_budget_protocol(tmp_path: Path) -> None:
    """``--preset mcmc`` starts every method from gsplat's MCMC recipe (the default paper preset does not),
    and ``--config`` applies over the preset."""
    paper = ps.base_config(ps.parse_args([]))
    mcmc = ps.base_config(ps.parse_args(["--preset", "mcmc"]))
    assert (paper.strategy.type, mcmc.strategy.type) == ("default", "mcmc")
    over = tmp_path / "over.json"
    over.write_text(json.dumps({"strategy": {"cap_max": 1234}}))
    assert ps.base_config(ps.parse_args(["--preset", "mcmc", "--config", str(over)])).strategy.cap_max == 1234


def test_cap_max_is_read_as_jsgs_trains_and_over_preset_and_config(tmp_path: Path, capsys: Any) -> None:
    """``--cap-max``: jsgs train's reading (a number or auto), over ``--preset mcmc`` and ``--config``;
    without it the fixed 300,000 of the published profiles, unless ``--config`` gives a budget; refused (one
    line) with another strategy or an unreadable value."""

    def strategy(*argv: str) -> tuple[int, bool]:
        s = ps.base_config(ps.parse_args(list(argv))).strategy
        return s.cap_max, s.cap_max_auto

    over = tmp_path / "over.json"
    over.write_text(json.dumps({"strategy": {"cap_max": 1234}}))
    auto = tmp_path / "auto.json"
    auto.write_text(json.dumps({"strategy": {"cap_max_auto": True}}))
    assert ps.TrainConfig.from_preset("mcmc").strategy.cap_max_auto  # the preset's own default: the scene's
    assert strategy("--preset", "mcmc") == (300_000, False)
    assert strategy("--preset", "mcmc", "--config", str(over)) == (1234, False)
    assert strategy("--preset", "mcmc", "--config", str(auto))[1] is True
    assert strategy("--preset", "mcmc", "--cap-max", "auto")[1] is True
    assert strategy("--preset", "mcmc", "--config", str(over), "--cap-max", "AUTO")[1] is True
    assert strategy("--preset", "mcmc", "--config", str(auto), "--cap-max", "5000") == (5000, False)
    for argv, message in (
        (["--cap-max", "300000"], "--cap-max applies to strategy.type mcmc (--preset mcmc); it is 'default'"),
        (["--preset", "mcmc", "--cap-max", "lots"], "--cap-max: expected a number of Gaussians or auto"),
        (["--preset", "mcmc", "--cap-max", "0"], "cap_max"),
    ):
        assert ps.main([*argv, "--device", "cpu"]) != 0
        err = capsys.readouterr().err.strip()
        assert message in err and "\n" not in err and "Traceback" not in err


def _budget_profile(tmp_path: Path, cap_max: str) -> dict[str, Any]:
    """gsplat alone profiled on a tiny synthetic scene under the mcmc preset with ``--cap-max``."""
    cfg = tmp_path / "tiny.json"
    cfg.write_text(json.dumps({"eval": TINY["eval"]}))
    out = tmp_path / f"profile_{cap_max}.json"
    argv = [
        "--size", "48x32", "--views", "6", "--warmup", "2", "--settle", "1", "--steps", "1", "--top", "2",
        "--device", "cpu", "--preset", "mcmc", "--config", str(cfg), "--methods", "gsplat", "--no-fresh",
        "--cap-max", cap_max, "--workdir", str(tmp_path / "work"), "--out", str(out),
    ]  # fmt: skip
    assert ps.main(argv) == 0
    return json.loads(out.read_text())


def test_cap_max_reaches_the_profiled_runs_and_the_json(tmp_path: Path, capsys: Any) -> None:
    """``--cap-max 300000`` profiles at that fixed budget, ``--cap-max auto`` at the scene-sized rule's choice
    for the scene (jsgs.train.budget.auto_budget of its SfM points and training views): in the runs'
    settings (the JSON's per-method cap_max, read from the run's config.json), the JSON's budget and the
    header line."""
    from jsgs.base.schema import validate
    from jsgs.train.budget import auto_budget

    fixed = _budget_profile(tmp_path, "300000")
    validate(fixed, "profile_step", "fixed.json")
    assert fixed["format_version"] == 4 and fixed["settings"]["cap_max"] == "300000"
    assert fixed["budget"] == {"strategy": "mcmc", "cap_max": 300_000, "cap_max_auto": False}
    assert fixed["results"]["gsplat"]["cap_max"] == 300_000
    assert fixed["results"]["gsplat"]["budget_rule"] is None
    assert "; strategy mcmc, a fixed budget of 300000 Gaussians" in capsys.readouterr().out

    auto = _budget_profile(tmp_path, "auto")
    validate(auto, "profile_step", "auto.json")
    assert auto["budget"] == {"strategy": "mcmc", "cap_max": None, "cap_max_auto": True}
    r = auto["results"]["gsplat"]
    rule = r["budget_rule"]
    pixels_per_view = 48 * 32
    expected = auto_budget(rule["sfm_points"], [(48, 32)] * rule["train_views"])
    assert rule["train_pixels"] == pixels_per_view * rule["train_views"] and 0 < rule["train_views"] < 6
    assert r["cap_max"] == rule["cap_max"] == expected.cap_max < 300_000
    assert r["num_gaussians"] <= r["cap_max"]
    printed = capsys.readouterr().out
    assert f"; strategy mcmc, the budget sized to the scene (--cap-max auto): {expected.cap_max}" in printed


def test_committed_profiles_validate() -> None:
    """Every profile_step JSON under docs/results/speed validates against today's schema (its versions before
    the budget was recorded included)."""
    from jsgs.base.schema import validate

    root = Path(__file__).resolve().parents[2] / "docs" / "results" / "speed"
    profiles = []
    for path in sorted(root.rglob("*.json")):
        doc = json.loads(path.read_text())
        if isinstance(doc, dict) and doc.get("format") == ps.FORMAT:
            validate(doc, "profile_step", str(path))
            profiles.append(doc["format_version"])
    assert len(profiles) > 10 and {1, 3} <= set(profiles)


def test_pairs_doc_on_hand_made_numbers(capsys: Any) -> None:
    """The pairs summary from given windows: medians, the median of the per-round ratios and its interval,
    for the wall times and for both peak memory figures, and the tables printed from them."""
    import jsonschema

    from jsgs.base.schema import load_schema

    order = ps.pair_order(["gsplat", "jsgs"], 5)
    walls = {"gsplat": [10.0, 12.0, 11.0, 9.0, 10.0], "jsgs": [13.0, 12.0, 16.5, 9.9, 12.0]}
    mib = 2**20
    alloc = {"gsplat": [100, 110, 105, 100, 120], "jsgs": [108, 121, 105, 130, 126]}
    reserved = {"gsplat": [200, 200, 220, 200, 210], "jsgs": [220, 230, 220, 200, 252]}
    peaks = {m: {"allocated": [v * mib for v in alloc[m]], "reserved": [v * mib for v in reserved[m]]}
             for m in walls}  # fmt: skip
    # what each window's run found on the device: rising by 20 MiB a window (as if runs were left behind)
    start_alloc = {"gsplat": [0, 60, 80, 140, 160], "jsgs": [20, 40, 100, 120, 180]}
    start_res = {"gsplat": [50, 50, 50, 50, 50], "jsgs": [50, 50, 50, 50, 50]}
    starts = {m: {"allocated": [v * mib for v in start_alloc[m]], "reserved": [v * mib for v in start_res[m]]}
              for m in walls}  # fmt: skip
    doc = ps.pairs_doc(order, walls, peaks, starts)
    assert doc["count"] == 5 and doc["order"] == order
    assert doc["median_ms_per_step"] == {"gsplat": 10.0, "jsgs": 12.0}
    # per round 1.3, 1.0, 1.5, 1.1, 1.2: the median 1.2 (not 12.0 / 10.0 of the medians by chance alone)
    t = doc["ratio"]["jsgs"]
    assert t["per_pair"] == pytest.approx([1.3, 1.0, 1.5, 1.1, 1.2]) and t["median"] == pytest.approx(1.2)
    assert t["interval"] == pytest.approx([1.0, 1.5]) and t["interval_coverage"] == pytest.approx(1 - 2 / 32)
    a = doc["peak_memory"]["allocated"]
    assert a["median_bytes"] == {"gsplat": 105 * mib, "jsgs": 121 * mib}
    # per round 1.08, 1.1, 1.0, 1.3, 1.05: the median 1.08, the medians' ratio 121/105 = 1.152 would differ
    assert a["ratio"]["jsgs"]["per_pair"] == pytest.approx([1.08, 1.1, 1.0, 1.3, 1.05])
    assert a["ratio"]["jsgs"]["median"] == pytest.approx(1.08)
    assert a["ratio"]["jsgs"]["interval"] == pytest.approx([1.0, 1.3])
    r = doc["peak_memory"]["reserved"]
    assert r["median_bytes"] == {"gsplat": 200 * mib, "jsgs": 220 * mib}
    assert r["ratio"]["jsgs"]["median"] == pytest.approx(1.1)
    assert list(doc["ratio"]) == list(a["ratio"]) == ["jsgs"]  # no ratio of the baseline to itself
    # the increments (peak - start): gsplat 100, 50, 25, -40, -40; jsgs 88, 81, 5, 10, -54 MiB
    assert a["start_median_bytes"] == {"gsplat": 80 * mib, "jsgs": 100 * mib}
    assert a["increment_median_bytes"] == {"gsplat": 25 * mib, "jsgs": 10 * mib}
    assert a["increment_ratio"] == {}  # a window's peak below its start: no ratio of the increments
    ri = r["increment_ratio"]["jsgs"]  # reserved: 150, 150, 170, 150, 160 and 170, 180, 170, 150, 202
    assert ri["per_pair"] == pytest.approx([170 / 150, 180 / 150, 1.0, 1.0, 202 / 160])
    assert ri["median"] == pytest.approx(170 / 150)
    assert r["increment_median_bytes"] == {"gsplat": 150 * mib, "jsgs": 170 * mib}

    # one method without peaks (the CPU): no peak memory summary at all, the times unchanged
    cpu = ps.pairs_doc(order, walls, {"gsplat": None, "jsgs": None}, {"gsplat": None, "jsgs": None})
    assert cpu["peak_memory"] is None and cpu["ratio"] == doc["ratio"]

    # the printed tables and the schema, on a document around it
    results = {
        m: {"paired_wall_ms_per_step": walls[m],
            **{f"paired_peak_memory_{k}_bytes": peaks[m][k] for k in ps.MEMORY_KINDS},
            **{f"paired_start_memory_{k}_bytes": starts[m][k] for k in ps.MEMORY_KINDS}}
        for m in walls
    }  # fmt: skip
    ps.print_pairs({"results": results, "pairs": doc})
    printed = capsys.readouterr().out
    assert "| gsplat | allocated | peak | 100.0, 110.0, 105.0, 100.0, 120.0 | 105.0 | 1 |  |" in printed
    jsgs_alloc = "| jsgs | allocated | peak | 108.0, 121.0, 105.0, 130.0, 126.0 | 121.0 | 1.080 |"
    assert f"{jsgs_alloc} 1.000–1.300 (93.8 %) |" in printed
    assert "| jsgs | allocated | start | 20.0, 40.0, 100.0, 120.0, 180.0 | 100.0 |  |  |" in printed
    assert "| jsgs | allocated | peak − start | 88.0, 81.0, 5.0, 10.0, -54.0 | 10.0 | – |  |" in printed
    assert "| jsgs | reserved | peak | 220.0, 230.0, 220.0, 200.0, 252.0 | 220.0 | 1.100 |" in printed
    assert "| jsgs | reserved | peak − start | 170.0, 180.0, 170.0, 150.0, 202.0 | 170.0 | 1.133 |" in printed
    gsplat_inc = "| gsplat | reserved | peak − start | 150.0, 150.0, 170.0, 150.0, 160.0 | 150.0 | 1 |  |"
    assert gsplat_inc in printed
    assert "| jsgs | 13.00, 12.00, 16.50, 9.90, 12.00 | 12.00 | 1.200 | 1.000–1.500 (93.8 %) |" in printed
    # the schema's pairs object takes both
    schema = load_schema("profile_step")
    pairs_schema = {"$defs": schema["$defs"], **schema["properties"]["pairs"]}
    for d in (doc, cpu):
        jsonschema.Draft202012Validator(pairs_schema).validate(d)


def test_step_window_reads_peak_memory_over_the_window(monkeypatch: Any) -> None:
    """On CUDA the window resets the peak statistics after the synchronisation that opens it and reads both
    peaks after the one that closes it; on the CPU there is no peak (None). torch.cuda stood in for (CI has
    no GPU)."""
    calls: list[str] = []
    monkeypatch.setattr(ps, "synchronize", lambda d: calls.append(f"sync {d.type}"))
    monkeypatch.setattr(torch.cuda, "reset_peak_memory_stats", lambda d=None: calls.append("reset"))
    monkeypatch.setattr(torch.cuda, "max_memory_allocated", lambda d=None: calls.append("alloc") or 300)
    monkeypatch.setattr(torch.cuda, "max_memory_reserved", lambda d=None: calls.append("reserved") or 512)
    win = ps.StepWindow(torch.device("cuda"), settle=2, steps=3)
    for _ in range(2):
        win()
    assert calls == []  # the settling steps: nothing reset, nothing read
    win()
    assert calls == ["sync cuda", "reset"]
    for _ in range(3):
        win()
    assert calls == ["sync cuda", "reset", "sync cuda", "alloc", "reserved"]
    assert win.peak_memory() == {"allocated": 300, "reserved": 512}

    cpu = ps.StepWindow(torch.device("cpu"), settle=1, steps=1)
    for _ in range(3):
        cpu()
    assert cpu.peak_memory() is None
    assert calls[-2:] == ["sync cpu", "sync cpu"]  # no torch.cuda call on the CPU
    with pytest.raises(ps.JsgsError, match="the measured window was not reached"):
        ps.StepWindow(torch.device("cuda"), settle=1, steps=1).peak_memory()


def test_step_window_counts_the_graph_recordings_inside_it(monkeypatch: Any, capsys: Any) -> None:
    """``graphed.record_graph`` is counted while the counter is installed (and restored after); a window
    counts only the recordings between its start and its end: one made while settling is not the window's,
    one of a shape first drawn inside it is, and the report says so in one line."""
    from jsgs.method import graphed

    made: list[str] = []
    monkeypatch.setattr(graphed, "record_graph", lambda fn, *a, **k: made.append("rec") or ("graph", fn()))
    counter = ps.GraphRecordings()
    win = ps.StepWindow(torch.device("cpu"), settle=2, steps=3, counter=counter)
    with counter.installed():
        assert graphed.record_graph(lambda: 1) == ("graph", 1)  # the wrapped function's result
        win()  # settling: the recording above (the first shape's) is before the window
        win()
        win()  # the window's first step
        assert win.recordings is not None and win.recordings <= 0  # open: not a count yet
        win()
        graphed.record_graph(lambda: 2)  # a second shape drawn inside the window
        win()
        win()  # closes the window
        graphed.record_graph(lambda: 3)  # after the window: not its
    assert made == ["rec"] * 3 and counter.count == 3 and win.recordings == 1
    assert graphed.record_graph(lambda: 4) == ("graph", 4) and counter.count == 3  # restored: not counted
    assert ps.recordings_note(0, 2) == "" and ps.recordings_note(None, 2) == ""
    assert "1 CUDA graph recording(s) inside the measured window" in ps.recordings_note(1, 2)
    assert "a larger --settle than 2" in ps.recordings_note(1, 2)


#: a stored version 1 profile with pairs (no peak memory)
V1_PROFILE = "docs/results/speed/gc_every_paper_preset/camera_jpeg_mouse_1500_K1.json"


def test_schema_requires_peak_memory_from_version_2() -> None:
    """Version 2 documents must carry the peak memory (null allowed: the CPU); the stored version 1 files
    (without it) still validate."""
    from jsgs.base.schema import validate

    root = Path(__file__).resolve().parents[2]
    old = json.loads((root / V1_PROFILE).read_text())
    assert old["format_version"] == 1 and "peak_memory_allocated_bytes" not in old["results"]["jsgs"]
    validate(old, "profile_step", "camera_jpeg_mouse_1500_K1.json")
    new = json.loads(json.dumps(old)) | {"format_version": 2}
    new["pairs"]["peak_memory"] = None
    with pytest.raises(ps.JsgsError, match="'peak_memory_allocated_bytes' is a required property"):
        validate(new, "profile_step", "new.json")
    for r in new["results"].values():
        r["peak_memory_allocated_bytes"] = r["peak_memory_reserved_bytes"] = None
    validate(new, "profile_step", "new.json")
    del new["pairs"]["peak_memory"]
    with pytest.raises(ps.JsgsError, match="at pairs: 'peak_memory' is a required property"):
        validate(new, "profile_step", "new.json")


def test_schema_requires_start_memory_from_version_3() -> None:
    """Version 3 documents must carry the memory at each run's start and, with pairs, the increments; version
    2 documents (peaks only) still validate."""
    from jsgs.base.schema import validate

    root = Path(__file__).resolve().parents[2]
    v2 = json.loads((root / V1_PROFILE).read_text())
    v2["format_version"] = 2
    v2["pairs"]["peak_memory"] = None
    for r in v2["results"].values():
        r["peak_memory_allocated_bytes"] = r["peak_memory_reserved_bytes"] = None
    validate(v2, "profile_step", "v2.json")
    v3 = json.loads(json.dumps(v2)) | {"format_version": 3}
    with pytest.raises(ps.JsgsError, match="'start_memory_allocated_bytes' is a required property"):
        validate(v3, "profile_step", "v3.json")
    mib = 2**20
    for r in v3["results"].values():
        r["start_memory_allocated_bytes"], r["start_memory_reserved_bytes"] = 3 * mib, 4 * mib
        n = len(r["paired_wall_ms_per_step"])
        for k in ps.MEMORY_KINDS:
            r[f"paired_peak_memory_{k}_bytes"] = [100 * mib] * n
    with pytest.raises(ps.JsgsError, match="'paired_start_memory_allocated_bytes' is a dependency"):
        validate(v3, "profile_step", "v3.json")
    for r in v3["results"].values():
        for k in ps.MEMORY_KINDS:
            r[f"paired_start_memory_{k}_bytes"] = [mib] * len(r["paired_wall_ms_per_step"])
    peaks = {"allocated": [100 * mib] * 2, "reserved": [200 * mib] * 2}
    same = {"gsplat": peaks, "jsgs": peaks}
    memory = ps.pairs_doc([["gsplat", "jsgs"]] * 2, {"gsplat": [1.0] * 2, "jsgs": [1.0] * 2}, same, same)[
        "peak_memory"
    ]
    assert memory["allocated"]["increment_ratio"] == {}  # increments of 0: no ratio
    v3["pairs"]["peak_memory"] = memory
    validate(v3, "profile_step", "v3.json")
    del v3["pairs"]["peak_memory"]["reserved"]["increment_median_bytes"]
    with pytest.raises(ps.JsgsError, match="'increment_median_bytes' is a required property"):
        validate(v3, "profile_step", "v3.json")


class _Trainer:
    """A stand-in for the trainer a callback sees (weak references to it can be taken)."""


def test_plain_window_releases_and_reads_memory_on_a_cuda_stand_in(monkeypatch: Any) -> None:
    """A plain window frees what earlier runs left (cycle collector, synchronisation, cuBLAS workspaces,
    empty_cache) before it reads the memory at the run's start, and again after the run; the start is read
    before the run allocates anything, the peaks at the window's end. torch.cuda and the run stood in for
    (CI has no GPU)."""
    calls: list[str] = []
    held = {"bytes": 7}  # what the stand-in device holds
    monkeypatch.setattr(ps.gc, "collect", lambda: calls.append("collect") or 0)
    monkeypatch.setattr(ps, "synchronize", lambda d: calls.append("window sync"))
    monkeypatch.setattr(torch.cuda, "synchronize", lambda d=None: calls.append("sync"))
    monkeypatch.setattr(torch.cuda, "empty_cache", lambda: calls.append("empty"))
    clear = lambda: calls.append("workspaces")  # noqa: E731
    monkeypatch.setattr(torch._C, "_cuda_clearCublasWorkspaces", clear, raising=False)
    monkeypatch.setattr(torch.cuda, "memory_allocated", lambda d=None: calls.append("read") or held["bytes"])
    monkeypatch.setattr(torch.cuda, "memory_reserved", lambda d=None: held["bytes"] + 1)
    monkeypatch.setattr(torch.cuda, "reset_peak_memory_stats", lambda d=None: None)
    monkeypatch.setattr(torch.cuda, "max_memory_allocated", lambda d=None: 300)
    monkeypatch.setattr(torch.cuda, "max_memory_reserved", lambda d=None: 512)

    def run(manifest: Path, out: Path, *, callbacks: Any, **kw: Any) -> dict[str, Any]:
        calls.append("train")
        held["bytes"] = 100  # the run's model and data
        trainer = _Trainer()
        for step in range(4):  # settle 1 + steps 2 + 1
            for cb in callbacks:
                cb.on_step_begin(trainer, step)
        return {"num_gaussians": 1}

    monkeypatch.setattr(ps, "train", run)
    doc, w = ps.plain_window(Path("m.json"), Path("run"), torch.device("cuda"), 1, 2, "jsgs (pair 1)")
    assert doc == {"num_gaussians": 1}
    release = ["collect", "sync", "workspaces", "empty"]
    assert calls == [*release, "read", "train", "window sync", "window sync", *release]
    assert w.start == {"allocated": 7, "reserved": 8} and w.peak == {"allocated": 300, "reserved": 512}
    assert w.released and w.ms_per_step >= 0  # the stand-in trainer died with the run

    calls.clear()
    ps.release_memory(torch.device("cpu"))
    assert calls == ["collect"] and ps.device_memory(torch.device("cpu")) is None  # no torch.cuda call


def test_a_finished_window_leaves_nothing_referenced(tmp_path: Path, monkeypatch: Any, capsys: Any) -> None:
    """What a window's run held (the trainer, its model, optimisers, data, the JSGS hook) is freed before the
    next window starts, even where a reference cycle ties it together: here a callback ties the trainer into
    one and Python's automatic collector is off, so only profile_step's own release can free it. The CPU
    cannot see CUDA memory; a dead weak reference to the trainer is what it can see. As a control, with the
    release replaced by nothing the trainer survives and a note line says so."""
    import gc
    import shutil

    manifest = ps.build_scene(tmp_path / "synthetic", (48, 32), 6)
    cfg_file = tmp_path / "tiny.json"
    cfg_file.write_text(json.dumps(TINY))
    base = ps.base_config(ps.parse_args(["--config", str(cfg_file)]))
    cfg = ps.variant_config(base, "jsgs", dict(base.method_options), 3 + 1 + 1 + 1, "cpu")
    cfg.checkpoint_every = 0
    warm = tmp_path / "warm"
    ps.train(manifest, warm, cfg, force=True, stop_at=3, progress=False, log=ps._quiet)

    class Cyclic(ps.StepCallback):
        def on_step_begin(self, trainer: Any, step: int) -> None:
            self.held = trainer  # the trainer -> its callbacks -> this -> the trainer
            super().on_step_begin(trainer, step)

    monkeypatch.setattr(ps, "StepCallback", Cyclic)
    cpu = torch.device("cpu")
    gc.collect()
    gc.disable()
    try:
        shutil.copytree(warm, tmp_path / "pair0")
        _, w = ps.plain_window(manifest, tmp_path / "pair0", cpu, 1, 1, "jsgs (pair 1)")
        assert w.released and w.ms_per_step > 0 and w.start is None and w.peak is None
        monkeypatch.setattr(ps, "release_memory", lambda d: None)
        shutil.copytree(warm, tmp_path / "pair1")
        _, kept = ps.plain_window(manifest, tmp_path / "pair1", cpu, 1, 1, "jsgs (pair 2)")
        assert not kept.released
    finally:
        gc.enable()
        gc.collect()
    err = capsys.readouterr().err
    assert "note: profile_step: jsgs (pair 2): the run's trainer is still referenced after its window" in err
    assert "pair 1" not in err
