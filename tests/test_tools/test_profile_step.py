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
    from jsgs.schemas import validate

    cfg = tmp_path / "tiny.json"
    cfg.write_text(json.dumps(TINY))
    out = tmp_path / "out" / "profile.json"
    work = tmp_path / "work"
    argv = [
        "--size", "48x32", "--views", "6", "--warmup", "3", "--settle", "1", "--steps", "2",
        "--device", "cpu", "--config", str(cfg), "--top", "5", "--workdir", str(work), "--out", str(out),
        "--python-top", "4", "--trace", str(tmp_path / "traces"),
    ]  # fmt: skip
    assert ps.main(argv) == 0
    printed = capsys.readouterr().out
    header = "| method | wall ms/step (unprofiled) | the same, run not resumed | wall ms/step (profiled) |"
    assert header in printed
    assert "jsgs − gsplat: top 5 kernels by extra" in printed
    assert "jsgs: Python functions by self time (cProfile" in printed

    doc = json.loads(out.read_text())
    validate(doc, "profile_step", str(out))
    assert doc["format"] == "jsgs-profile-step" and doc["steps"] == 2 and doc["warmup"] == 3
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
        assert 0 < len(r["kernels"]) <= 5
        assert r["num_gaussians"] == r["num_gaussians_profiled"]  # both copies trained the same Gaussians
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
    from jsgs.schemas import validate

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
