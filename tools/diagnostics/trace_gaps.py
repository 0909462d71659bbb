"""Where the GPU waits for the host: device idle time in a Chrome trace of training steps, attributed to the
Python functions the host was running meanwhile.

    .venv/bin/python tools/diagnostics/profile_step.py --manifest M --device cuda --trace traces/  # GPU
    .venv/bin/python tools/diagnostics/trace_gaps.py traces/gsplat.trace.json traces/jsgs.trace.json \
        --steps 40

A step is host-bound wherever no kernel, copy or memset runs on any stream: every microsecond of that is
time the host spent launching, deciding, or waiting. This reads the trace ``torch.profiler`` writes with
``with_stack=True`` (``profile_step.py --trace``), merges the device activity into busy intervals and, for
every Python frame of the main host thread, measures how much of its duration the device sat idle: *self*
idle time (minus its child frames') says which function kept the device waiting, *total* idle time which
call tree did. The backward runs on autograd's own device thread, inside the main thread's ``run_backward``:
its nodes (``autograd::engine::evaluate_function``, any thread) get a table of their own. With two traces
(baseline first) it also prints the per-frame and per-node differences. Numbers are per step,
in ms; the profiler's own overhead inflates host time, so read them as shares, not as wall times.
"""

from __future__ import annotations

import argparse
import bisect
import json
import re
import sys
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

DEVICE_CATS = ("kernel", "gpu_memcpy", "gpu_memset")
# "<built-in method float of Tensor object at 0x7f..>": one name per function, not per object
_ADDRESS = re.compile(
    r" of (?:pybind11_builtins\.)?pybind11_detail_function_record\S* object at 0x[0-9a-f]+| at 0x[0-9a-f]+"
)


def frame_name(name: str) -> str:
    """A Python frame's name without object addresses (and pybind's record type), so traces compare."""
    return _ADDRESS.sub("", name)


class Busy:
    """The union of device intervals (µs) with prefix sums, for the idle time inside any span."""

    def __init__(self, spans: list[tuple[float, float]]) -> None:
        merged: list[list[float]] = []
        for a, b in sorted(spans):
            if merged and a <= merged[-1][1]:
                merged[-1][1] = max(merged[-1][1], b)
            else:
                merged.append([a, b])
        self.starts = [m[0] for m in merged]
        self.ends = [m[1] for m in merged]
        self.prefix = [0.0]
        for a, b in merged:
            self.prefix.append(self.prefix[-1] + b - a)

    def busy_before(self, t: float) -> float:
        """Busy µs in (-inf, t)."""
        i = bisect.bisect_right(self.starts, t)  # intervals starting at or before t
        if i == 0:
            return 0.0
        done = self.prefix[i - 1]
        return done + min(t, self.ends[i - 1]) - self.starts[i - 1]

    def idle(self, a: float, b: float) -> float:
        return (b - a) - (self.busy_before(b) - self.busy_before(a))


def load(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise SystemExit(f"error: {path}: cannot read a Chrome trace ({e})") from None
    events = doc.get("traceEvents") if isinstance(doc, dict) else None
    if not isinstance(events, list):
        raise SystemExit(f"error: {path}: no traceEvents list (not a torch.profiler Chrome trace)")
    return doc


def analyse(path: Path, steps: int) -> dict[str, Any]:
    """Idle device time per step, and per Python frame (self and total, ms per step)."""
    events = [e for e in load(path)["traceEvents"] if e.get("ph") == "X" and "dur" in e]
    dev = [(float(e["ts"]), float(e["ts"]) + float(e["dur"])) for e in events if e.get("cat") in DEVICE_CATS]
    py = [e for e in events if e.get("cat") == "python_function"]
    if not dev or not py:
        raise SystemExit(
            f"error: {path}: no device events or no Python frames (record it with --trace on a GPU)"
        )
    busy = Busy(dev)
    # the host thread that ran training: the one with the most Python frames
    counts: dict[Any, int] = defaultdict(int)
    for e in py:
        counts[e.get("tid")] += 1
    tid = max(counts, key=lambda k: counts[k])
    py = [e for e in py if e.get("tid") == tid]
    t0 = min(a for a, _ in dev)
    t1 = max(b for _, b in dev)
    per_step = 1e-3 / steps  # µs in the trace -> ms per step
    prefix = "autograd::engine::evaluate_function: "
    nodes: dict[str, float] = defaultdict(float)
    for e in events:
        if e.get("cat") == "cpu_op" and e["name"].startswith(prefix):
            a, b = float(e["ts"]), float(e["ts"]) + float(e["dur"])
            nodes[e["name"][len(prefix) :]] += busy.idle(a, b) * per_step
    by_id: dict[Any, dict[str, Any]] = {}
    for e in py:
        args = e.get("args", {})
        a, b = max(float(e["ts"]), t0), min(float(e["ts"]) + float(e["dur"]), t1)
        idle = busy.idle(a, b) if b > a else 0.0
        parent = args.get("Python parent id")
        by_id[args.get("Python id")] = {"name": frame_name(e["name"]), "idle": idle, "parent": parent}
    child_idle: dict[Any, float] = defaultdict(float)
    for node in by_id.values():
        if node["parent"] in by_id:
            child_idle[node["parent"]] += node["idle"]
    self_ms: dict[str, float] = defaultdict(float)
    total_ms: dict[str, float] = defaultdict(float)
    for pid, node in by_id.items():
        self_ms[node["name"]] += (node["idle"] - child_idle.get(pid, 0.0)) * per_step
        total_ms[node["name"]] += node["idle"] * per_step
    return {
        "span_ms": (t1 - t0) * per_step,
        "busy_ms": busy.prefix[-1] * per_step,
        "idle_ms": busy.idle(t0, t1) * per_step,
        "self": dict(self_ms),
        "total": dict(total_ms),
        "backward": dict(nodes),
    }


def _short(name: str, width: int = 90) -> str:
    name = name.replace("|", "/")
    return name if len(name) <= width else "…" + name[-(width - 1) :]


def _table(title: str, column: str, values: dict[str, float], top: int) -> None:
    print(f"\n{title}\n")
    print(f"| frame | {column} |\n|---|---:|")
    for name, v in sorted(values.items(), key=lambda kv: -kv[1])[:top]:
        print(f"| {_short(name)} | {v:.3f} |")


def report(paths: Sequence[Path], steps: int, top: int) -> None:
    results = [analyse(p, steps) for p in paths]
    print("| trace | device span ms/step | busy ms/step | idle ms/step |")
    print("|---|---:|---:|---:|")
    for p, r in zip(paths, results, strict=True):
        print(f"| {p.name} | {r['span_ms']:.3f} | {r['busy_ms']:.3f} | {r['idle_ms']:.3f} |")
    what = {
        "self": "Python frames by self",
        "total": "Python frames by total",
        "backward": "backward nodes by",
    }
    for key in what:
        for p, r in zip(paths, results, strict=True):
            _table(f"{p.name}: top {top} {what[key]} device-idle ms/step", "ms/step", r[key], top)
    if len(results) == 2:
        base, other = results
        for key in what:
            names = set(base[key]) | set(other[key])
            diff = {n: other[key].get(n, 0.0) - base[key].get(n, 0.0) for n in names}
            title = f"{paths[1].name} − {paths[0].name}: top {top} {what[key]} extra device-idle ms/step"
            _table(title, "extra ms/step", diff, top)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("traces", type=Path, nargs="+", help="Chrome traces (baseline first for a difference)")
    ap.add_argument("--steps", type=int, required=True, help="training steps in each trace's window")
    ap.add_argument("--top", type=int, default=25, help="frames per table [25]")
    args = ap.parse_args(argv)
    if args.steps < 1 or args.top < 1:
        ap.error("--steps and --top must be >= 1")
    report(args.traces, args.steps, args.top)
    return 0


if __name__ == "__main__":
    sys.exit(main())
