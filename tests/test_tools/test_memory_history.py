"""tools/diagnostics/memory_history.py on hand-made snapshots of the layout torch.cuda.memory._snapshot()
returns (``device_traces[d]``: the allocator's events in order, frames innermost first), and
profile_step.py's --memory-history window and tables with torch's recording functions stood in (CI has no
GPU)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import torch
from conftest import load_benchmark

mh = load_benchmark("memory_history", "tools/diagnostics")
ps = load_benchmark("profile_step", "tools/diagnostics")

TORCH = "/opt/venv/lib/python3.12/site-packages/torch"
LIBRARY = mh.under([TORCH, "/usr/lib/python3.12"])


def py(path: str, line: int, name: str) -> dict[str, Any]:
    return {"filename": path, "line": line, "name": name}


ADAM = [py(f"{TORCH}/optim/adam.py", 40, "_init_group"), py("/repo/jsgs/train/trainer.py", 300, "step")]
GRAPH = [
    py("/repo/jsgs/method/graphed.py", 120, "_buffer"),
    py("/usr/lib/python3.12/contextlib.py", 81, "inner"),
]
PAD = [py(f"{TORCH}/nn/functional.py", 5000, "pad"), py("/repo/jsgs/method/hook.py", 77, "__call__")]
RENDER = [py("/repo/jsgs/render/backend.py", 210, "_rasterize_gsplat")]
# the engine's device thread: C++ frames only (stacks="all"), one of them the node's apply
MUL_BACKWARD = [
    {"filename": "??", "line": 0, "name": "c10::cuda::CUDACachingAllocator::Native::malloc(...)"},
    {"filename": "/pytorch/torch/csrc/autograd/generated/Functions.cpp", "line": 10,
     "name": "torch::autograd::generated::MulBackward0::apply(std::vector<at::Tensor>&&)"},
]  # fmt: skip
GSPLAT_BACKWARD = [
    py("/tmp/site/gsplat/cuda/_wrapper.py", 900, "backward"),
    py(f"{TORCH}/autograd/function.py", 300, "apply"),
]


def alloc(addr: int, size: int, frames: list[dict[str, Any]]) -> dict[str, Any]:
    return {"action": "alloc", "addr": addr, "size": size, "stream": 0, "frames": frames}


def free(addr: int, size: int, completed: bool = False) -> dict[str, Any]:
    action = "free_completed" if completed else "free_requested"
    return {"action": action, "addr": addr, "size": size, "stream": 0, "frames": []}


def mark(size: int) -> dict[str, Any]:
    return {"action": "snapshot", "addr": 0, "size": size, "stream": 0, "frames": []}


def trace(graph_bytes: int = 4000) -> list[dict[str, Any]]:
    """Held: Adam's state (1000) and the graph's buffer; a scratch pad freed before the window; a free of
    memory allocated before the recording (512); then the window: the render (2000), a backward node's
    gradient (3000) and gsplat's backward (500) live at once (the peak, event 3 of the window), a later
    smaller high (4000 after the render and the gradient are freed), and an allocation after the window's
    end that must not count."""
    return [
        {"action": "segment_alloc", "addr": 0x1000, "size": 2 << 20, "stream": 0, "frames": []},
        alloc(0x1000, 1000, ADAM),
        alloc(0x2000, graph_bytes, GRAPH),
        alloc(0x3000, 96, PAD),
        free(0x3000, 96),
        free(0x3000, 96, completed=True),
        free(0x9000, 512),
        mark(1000 + graph_bytes),
        alloc(0x4000, 2000, RENDER),
        alloc(0x5000, 3000, MUL_BACKWARD),
        alloc(0x6000, 500, GSPLAT_BACKWARD),
        free(0x4000, 2000),
        free(0x5000, 3000),
        alloc(0x7000, 4000, PAD),
        free(0x7000, 4000),
        free(0x6000, 500),
        mark(1000 + graph_bytes),
        alloc(0x8000, 99_999, RENDER),
    ]


def snapshot(graph_bytes: int = 4000) -> dict[str, Any]:
    return {"segments": [], "device_traces": [[], trace(graph_bytes)]}


def test_where_names_the_projects_frame_and_what_is_beneath_it() -> None:
    assert mh.frame_text(GRAPH[0]) == "method/graphed.py:120(_buffer)"
    assert mh.where(ADAM, LIBRARY) == ("train/trainer.py:300(step)", "optim/adam.py:40(_init_group)")
    assert mh.where(GRAPH, LIBRARY) == ("method/graphed.py:120(_buffer)", "")
    assert mh.where(MUL_BACKWARD, LIBRARY) == ("autograd engine", "MulBackward0")
    assert mh.where(GSPLAT_BACKWARD, LIBRARY) == ("cuda/_wrapper.py:900(backward)", "")
    # a backward run on the calling thread: the node beneath the project's line that called backward()
    on_caller = [
        *MUL_BACKWARD,
        py(f"{TORCH}/autograd/__init__.py", 200, "backward"),
        py("/r/jsgs/t.py", 9, "f"),
    ]
    assert mh.where(on_caller, LIBRARY) == ("jsgs/t.py:9(f)", "MulBackward0")
    cpp_node = [{"filename": "??", "line": 0, "name": "torch::autograd::CppNode<jsgs::Ssim>::apply(x)"}]
    assert mh.where(cpp_node, LIBRARY) == ("autograd engine", "jsgs::Ssim")
    accumulate = [{"filename": "??", "line": 0, "name": "torch::autograd::AccumulateGrad::apply(x)"}]
    assert mh.where(accumulate, LIBRARY) == ("autograd engine", "AccumulateGrad")
    assert mh.where([], LIBRARY) == ("no Python frame", "")
    assert mh.where(PAD[:1], LIBRARY) == ("no Python frame", "nn/functional.py:5000(pad)")


def test_summarise_finds_the_window_its_start_and_its_peak() -> None:
    s = mh.summarise(snapshot(), 1, LIBRARY)
    assert (s.entries, s.window_entries) == (18, 8)
    assert s.start_bytes == 5000 and s.peak_bytes == 10_500 and s.peak_entry == 3
    assert s.freed_unrecorded_bytes == 512
    start = {k: (g.bytes, g.blocks) for k, g in s.start.items()}
    assert start == {
        ("train/trainer.py:300(step)", "optim/adam.py:40(_init_group)"): (1000, 1),
        ("method/graphed.py:120(_buffer)", ""): (4000, 1),
    }
    assert sum(g.bytes for g in s.peak.values()) == s.peak_bytes
    doc = s.doc(top=3)
    assert [(r["where"], r["via"], r["bytes"]) for r in doc["peak"]["groups"]] == [
        ("method/graphed.py:120(_buffer)", "", 4000),
        ("autograd engine", "MulBackward0", 3000),
        ("render/backend.py:210(_rasterize_gsplat)", "", 2000),
    ]
    assert doc["start"]["bytes"] == 5000 and doc["peak"]["entry"] == 3


def test_the_window_without_its_end_mark_runs_to_the_traces_end() -> None:
    t = trace()[:-2]  # no closing snapshot: the peak may be anywhere after the start
    s = mh.summarise({"device_traces": [t]}, 0, LIBRARY)
    assert s.window_entries == len(t) - 8 and s.peak_bytes == 10_500


def test_summarise_refuses_a_trace_without_its_mark() -> None:
    t = [e for e in trace() if e["action"] != "snapshot"]
    with pytest.raises(ValueError, match="no 'snapshot' entry"):
        mh.summarise({"device_traces": [t]}, 0, LIBRARY)
    with pytest.raises(ValueError, match="no trace of device 2"):
        mh.summarise(snapshot(), 2, LIBRARY)


def test_difference_lists_the_groups_a_method_holds_more_of() -> None:
    a = mh.summarise(snapshot(graph_bytes=4000), 1, LIBRARY)
    b = mh.summarise(snapshot(graph_bytes=1500), 1, LIBRARY)
    rows = mh.difference(a.peak, b.peak, top=5)
    assert rows == [
        {"where": "method/graphed.py:120(_buffer)", "via": "", "bytes": 2500, "method_bytes": 4000,
         "baseline_bytes": 1500},
    ]  # fmt: skip
    # the other way round the same group is a negative row, not left out
    assert [(r["where"], r["bytes"]) for r in mh.difference(b.peak, a.peak, top=5)] == [
        ("method/graphed.py:120(_buffer)", -2500)
    ]


#: the device's cuBLAS workspace, made by each method's first cuBLAS call: gsplat's camera inverse, and the
#: matrix product of JSGS's render (the same 32 MiB under two frames)
WORKSPACE = 32 << 20
GSPLAT_INVERSE = [py("/tmp/site/gsplat/rendering.py", 491, "rasterization")]
JSGS_MATMUL = [py("/repo/jsgs/render/backend.py", 280, "_rasterize_gsplat")]


def test_difference_shows_one_allocation_under_two_frames_as_rows_that_cancel() -> None:
    """The positive rows alone counted the workspace as the method's extra (32 MiB that gsplat holds too):
    its baseline row is listed, negative, so that the rows sum to the difference of the totals."""
    method = mh.group([(WORKSPACE, JSGS_MATMUL), (4000, GRAPH), (3000, MUL_BACKWARD)], LIBRARY)
    baseline = mh.group([(WORKSPACE, GSPLAT_INVERSE), (3000, MUL_BACKWARD), (700, PAD)], LIBRARY)
    rows = mh.difference(method, baseline, top=5)
    assert [(r["where"], r["bytes"]) for r in rows] == [
        ("render/backend.py:280(_rasterize_gsplat)", WORKSPACE),
        ("method/graphed.py:120(_buffer)", 4000),
        ("gsplat/rendering.py:491(rasterization)", -WORKSPACE),
        ("method/hook.py:77(__call__)", -700),
    ]
    total = sum(g.bytes for g in method.values()) - sum(g.bytes for g in baseline.values())
    assert sum(r["bytes"] for r in rows) == total == 3300
    assert rows[2]["method_bytes"] == 0 and rows[2]["baseline_bytes"] == WORKSPACE
    # ``top`` applies to each side: the largest extra and the largest shortfall
    assert [r["bytes"] for r in mh.difference(method, baseline, top=1)] == [WORKSPACE, -WORKSPACE]


class FakeMemory:
    """torch.cuda.memory's recording functions, stood in: what was asked, and the hand-made snapshot."""

    def __init__(self) -> None:
        self.calls: list[Any] = []

    def _record_memory_history(
        self, enabled: str | None = "all", context: str | None = "all", stacks: str = "all",
        max_entries: int = 0, clear_history: bool = False,
    ) -> None:  # fmt: skip
        self.calls.append(("record", enabled, clear_history))

    def _snapshot(self) -> dict[str, Any]:
        self.calls.append(("snapshot",))
        return {"segments": [], "device_traces": [trace()]}


def test_the_history_window_marks_its_start_and_summarises_at_its_end(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    fake = FakeMemory()
    monkeypatch.setattr(torch.cuda, "memory", fake)
    w = ps.HistoryWindow(torch.device("cpu", 0), settle=2, steps=3, library=LIBRARY)
    for _ in range(2):
        w()
    assert fake.calls == []
    w()  # the window's start: one snapshot call, the mark
    assert fake.calls == [("snapshot",)]
    for _ in range(3):
        w()  # the last one closes the window: the snapshot summarised, the recording off
    assert fake.calls == [("snapshot",), ("snapshot",), ("record", None, False)]
    assert w.summary is not None and w.summary.peak_bytes == 10_500 and w.ms_per_step() >= 0


def test_profile_steps_memory_history_document_and_tables(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: Any
) -> None:
    """memory_histories with the recorded window stood in (one summary per method): the document's object
    validates against the schema, the difference names the graph's buffer, and the tables print."""
    from jsgs.base.schema import load_schema, validate

    def fake_window(manifest: Path, run: Path, device: Any, settle: int, steps: int, stacks: str) -> Any:
        graph = 4000 if "jsgs" in str(run) else 1500
        recordings = 1 if "jsgs" in str(run) else 0  # a second image shape first drawn inside the window
        clock = SimpleNamespace(
            summary=mh.summarise(snapshot(graph), 1, LIBRARY), peak_allocated=11_264, recordings=recordings
        )
        return {"num_gaussians": 7593}, clock, {"allocated": 0, "reserved": 0}

    monkeypatch.setattr(ps, "history_window", fake_window)
    for m in ("gsplat", "jsgs"):
        (tmp_path / m / "warm").mkdir(parents=True)
    args = SimpleNamespace(memory_history=4, memory_steps=3, memory_stacks="all")
    h = ps.memory_histories(tmp_path / "m.json", tmp_path, ["gsplat", "jsgs"], torch.device("cpu"), 2, args)
    assert not (tmp_path / "jsgs" / "history").exists()
    assert h["difference"]["jsgs"]["peak"][0]["bytes"] == 2500
    assert h["by_method"]["jsgs"]["max_memory_allocated_bytes"] == 11_264
    assert h["by_method"]["jsgs"]["graph_recordings_in_window"] == 1
    assert len(h["by_method"]["gsplat"]["peak"]["groups"]) == 4
    schema = load_schema("profile_step")
    old = json.loads(
        (Path(__file__).resolve().parents[2] / "docs/results/speed/equal_budget/flower_1500.json").read_text()
    )
    validate(old | {"memory_history": h}, "profile_step", "with_history.json")
    assert "memory_history" in schema["properties"]
    ps.print_memory_history({"memory_history": h})
    out = capsys.readouterr().out
    assert "jsgs − gsplat: live at the window's peak, the most extra bytes" in out
    assert "| method/graphed.py:120(_buffer) | – | 0.00 | 0.00 | 0.00 |" in out
    assert "autograd engine | MulBackward0 |" in out
    assert "note: jsgs: 1 CUDA graph recording(s) inside the measured window" in out
    assert "note: gsplat:" not in out


def test_the_history_window_fits_in_the_profiles_window(capsys: Any) -> None:
    """The history's run is the profile's checkpoint resumed for its configured steps: a longer window than
    ``--steps`` would never close, so it is refused in one line."""
    with pytest.raises(SystemExit):
        ps.parse_args(["--steps", "4", "--memory-history", "5", "--memory-steps", "5"])
    assert "--memory-steps from 1 to --steps (4), got 5 and 5" in capsys.readouterr().err
    assert ps.parse_args(["--steps", "4", "--memory-history", "5", "--memory-steps", "4"]).memory_steps == 4
    assert ps.parse_args(["--steps", "4"]).memory_steps == 4 and ps.parse_args([]).memory_steps == 8
