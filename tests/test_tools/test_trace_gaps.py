"""tools/diagnostics/trace_gaps.py: device-idle time attributed to Python frames and backward nodes, on a
hand-made Chrome trace whose answer is known (CI has no GPU to record a real one)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from conftest import load_benchmark

tg = load_benchmark("trace_gaps", "tools/diagnostics")


def _x(cat: str, name: str, ts: float, dur: float, tid: int = 1, **args: Any) -> dict[str, Any]:
    return {"ph": "X", "cat": cat, "name": name, "ts": ts, "dur": dur, "tid": tid, "pid": 1, "args": args}


def _trace(path: Path, events: list[dict[str, Any]]) -> Path:
    path.write_text(json.dumps({"traceEvents": events}))
    return path


def test_busy_intervals() -> None:
    b = tg.Busy([(0.0, 10.0), (5.0, 15.0), (20.0, 30.0)])  # overlapping streams merge
    assert b.prefix[-1] == 25.0
    assert b.idle(0.0, 30.0) == 5.0
    assert b.idle(12.0, 22.0) == 5.0
    assert b.idle(-5.0, 0.0) == 5.0
    assert b.idle(25.0, 40.0) == 10.0
    assert b.idle(3.0, 4.0) == 0.0


def test_attribution(tmp_path: Path, capsys: Any) -> None:
    # device busy 0-10 and 30-40 over two steps; the host runs step() 0-40 with a child launch() 10-20
    # (device idle all along) and a child wait() 20-35 (idle 20-30)
    events = [
        _x("kernel", "k1", 0.0, 10.0, tid=7),
        _x("gpu_memcpy", "copy", 30.0, 10.0, tid=8),
        _x("python_function", "loop.py(1): step", 0.0, 40.0, **{"Python id": 1, "Python parent id": None}),
        _x("python_function", "loop.py(2): launch", 10.0, 10.0, **{"Python id": 2, "Python parent id": 1}),
        _x("python_function", "loop.py(3): wait", 20.0, 15.0, **{"Python id": 3, "Python parent id": 1}),
        _x("python_function", "other thread", 0.0, 40.0, tid=2, **{"Python id": 4}),
        _x("cpu_op", "autograd::engine::evaluate_function: MulBackward0", 12.0, 4.0, tid=3),
        _x("cpu_op", "aten::mul", 12.0, 4.0),
    ]
    r = tg.analyse(_trace(tmp_path / "a.json", events), steps=2)
    assert (r["span_ms"], r["busy_ms"], r["idle_ms"]) == pytest.approx((0.020, 0.010, 0.010))
    assert r["total"] == pytest.approx({"loop.py(1): step": 0.010, "loop.py(2): launch": 0.005,
                                        "loop.py(3): wait": 0.005})  # fmt: skip
    assert r["self"] == pytest.approx({"loop.py(1): step": 0.0, "loop.py(2): launch": 0.005,
                                       "loop.py(3): wait": 0.005})  # fmt: skip
    assert r["backward"] == pytest.approx({"MulBackward0": 0.002})

    # the difference of two traces: the second has launch() 10 µs longer (and the device idle meanwhile)
    later = [dict(e) for e in events]
    later[1]["ts"] = 40.0
    later[2]["dur"] = 50.0
    later[3]["dur"] = 20.0
    later[4]["ts"] = 30.0
    assert tg.main([str(tmp_path / "a.json"), str(_trace(tmp_path / "b.json", later)), "--steps", "2"]) == 0
    out = capsys.readouterr().out
    assert "| a.json | 0.020 | 0.010 | 0.010 |" in out and "| b.json | 0.025 | 0.010 | 0.015 |" in out
    diff = out.split("b.json − a.json: top 25 Python frames by self extra device-idle ms/step")[1]
    assert diff.split("\n")[4] == "| loop.py(2): launch | 0.005 |"


def test_refusals(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="cannot read a Chrome trace"):
        tg.analyse(tmp_path / "missing.json", steps=1)
    with pytest.raises(SystemExit, match="no traceEvents list"):
        tg.analyse(_bad(tmp_path), steps=1)
    cpu_only = [_x("python_function", "f", 0.0, 1.0, **{"Python id": 1})]
    with pytest.raises(SystemExit, match="no device events or no Python frames"):
        tg.analyse(_trace(tmp_path / "cpu.json", cpu_only), steps=1)
    with pytest.raises(SystemExit):
        tg.main([str(tmp_path / "cpu.json"), "--steps", "0"])


def _bad(tmp_path: Path) -> Path:
    p = tmp_path / "bad.json"
    p.write_text(json.dumps({"events": []}))
    return p


def test_frame_names_compare_across_traces() -> None:
    assert tg.frame_name("<built-in method float of Tensor object at 0x7f66addaa9e0>") == (
        "<built-in method float of Tensor object>"
    )
    assert (
        tg.frame_name(
            "<built-in method rasterize_to_pixels_3dgs_bwd of pybind11_builtins.pybind11_detail_"
            "function_record_v1_system_libstdcpp_gxx_abi_1xxx_use_cxx11_abi_1 object at 0x7f69e>"
        )
        == "<built-in method rasterize_to_pixels_3dgs_bwd>"
    )
    assert tg.frame_name("jsgs/train/loop.py(545): <genexpr>") == "jsgs/train/loop.py(545): <genexpr>"
