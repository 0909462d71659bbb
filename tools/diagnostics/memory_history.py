"""The live CUDA allocations of a window, grouped by the frame that allocated them, from torch's allocator
history: ``torch.cuda.memory._record_memory_history()`` on, then ``torch.cuda.memory._snapshot()``, whose
dictionary holds ``device_traces[d]``, device ``d``'s allocator events in order, each a dictionary with
``action`` ("alloc", "free_requested", "free_completed", "segment_alloc", "segment_free", "oom",
"snapshot", ...), ``addr``, ``size`` and ``frames`` (the stack that made it, innermost first, each
``{"filename", "line", "name"}``; Python frames and, with ``stacks="all"``, C++ ones). An ``alloc`` entry's
size is the size asked for (the allocator's own statistics count its block, rounded up to 512 B); a
``snapshot`` entry is recorded by every ``_snapshot()`` call, so one call at a window's start marks it.

:func:`summarise` replays the trace: the bytes live at the window's start (the first ``snapshot`` entry)
and at the window's peak (the most bytes live after any event up to the next ``snapshot`` entry, or the
trace's end), each grouped by where the allocation was made (:func:`where`). It is pure Python over the
dictionary (no CUDA), so it is tested on a hand-made one; ``profile_step.py --memory-history`` records the
history on a GPU. Only the summary is kept (a snapshot of a few steps runs to hundreds of MB)."""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import PurePosixPath
from typing import Any

#: A C++ frame of an autograd node's ``apply`` (``torch::autograd::generated::MulBackward0::apply``,
#: ``torch::autograd::AccumulateGrad::apply``, a C++ extension's ``CppNode<ns::Function>::apply``):
#: allocations of the backward made by the autograd engine's device thread have no Python frame.
NODE = re.compile(r"(\w+Backward\w*|AccumulateGrad)::apply|CppNode<([\w:]+)>::apply")

#: (the innermost Python frame outside the libraries, the frame beneath it that says more), see :func:`where`
Key = tuple[str, str]


def frame_text(f: dict[str, Any]) -> str:
    """``parent/file.py:line(function)``: the frame's file with its folder, its line and its function."""
    p = PurePosixPath(str(f.get("filename", "?")))
    name = "/".join(p.parts[-2:]) if len(p.parts) > 1 else p.name
    return f"{name}:{f.get('line', 0)}({f.get('name', '?')})"


def where(frames: Sequence[dict[str, Any]], library: Callable[[str], bool]) -> Key:
    """Where an allocation was made, from its frames (innermost first): the innermost Python frame whose
    file is not a library's (``library(filename)`` false: the project's code, gsplat's, a test's), and
    beneath it the autograd node whose backward made it (a C++ frame, with ``stacks="all"``) or else the
    innermost Python frame (a library's, e.g. ``optim/adam.py``) where that is another frame. Without any
    Python frame outside the libraries: ``"autograd engine"`` where a node is named (the engine's device
    thread runs a backward with no Python frame), else ``"no Python frame"``."""
    python = [f for f in frames if str(f.get("filename", "")).endswith(".py")]
    own = next((f for f in python if not library(str(f["filename"]))), None)
    found = (NODE.search(str(f.get("name", ""))) for f in frames)
    node = next((m.group(1) or m.group(2) for m in found if m), None)
    outer = frame_text(own) if own is not None else ("autograd engine" if node else "no Python frame")
    if node:
        return outer, node
    inner = python[0] if python else None
    return outer, "" if inner is None or inner is own else frame_text(inner)


@dataclass
class Group:
    """The allocations of one :data:`Key` live at one moment: their bytes (asked for) and how many."""

    bytes: int = 0
    blocks: int = 0
    largest: int = 0

    def add(self, size: int) -> None:
        self.bytes += size
        self.blocks += 1
        self.largest = max(self.largest, size)


def group(
    live: Iterable[tuple[int, Sequence[dict[str, Any]]]], library: Callable[[str], bool]
) -> dict[Key, Group]:
    """``(size, frames)`` of live allocations -> their :class:`Group` by :func:`where`."""
    out: dict[Key, Group] = {}
    for size, frames in live:
        out.setdefault(where(frames, library), Group()).add(size)
    return out


def rows(groups: dict[Key, Group], top: int) -> list[dict[str, Any]]:
    """The ``top`` groups by bytes, as the document's rows."""
    ranked = sorted(groups.items(), key=lambda kv: (-kv[1].bytes, kv[0]))[:top]
    return [
        {"where": k[0], "via": k[1], "bytes": g.bytes, "blocks": g.blocks, "largest_bytes": g.largest}
        for k, g in ranked
    ]


@dataclass
class Summary:
    """What :func:`summarise` found in one device's trace (bytes are the sizes asked for)."""

    entries: int
    window_entries: int
    start_bytes: int
    peak_bytes: int
    peak_entry: int  # the event after which the peak is reached, counted from the window's start
    freed_unrecorded_bytes: int  # frees in the trace of allocations made before the recording began
    start: dict[Key, Group] = field(default_factory=dict)
    peak: dict[Key, Group] = field(default_factory=dict)

    def doc(self, top: int) -> dict[str, Any]:
        """The summary for a JSON document: the totals and the ``top`` groups at the start and the peak."""
        return {
            "trace_entries": self.entries,
            "window_entries": self.window_entries,
            "freed_unrecorded_bytes": self.freed_unrecorded_bytes,
            "start": {"bytes": self.start_bytes, "groups": rows(self.start, top)},
            "peak": {"bytes": self.peak_bytes, "entry": self.peak_entry, "groups": rows(self.peak, top)},
        }


def _window(trace: Sequence[dict[str, Any]]) -> tuple[int, int]:
    """The indices of the window's first ``snapshot`` entry (its start) and of its end (the next ``snapshot``
    entry, or the trace's length)."""
    marks = [i for i, e in enumerate(trace) if e.get("action") == "snapshot"]
    if not marks:
        raise ValueError(
            "the allocator's trace has no 'snapshot' entry to mark the window's start (was "
            "torch.cuda.memory._snapshot() called at the window's start, with the history recorded, and did "
            "the trace keep it: max_entries)"
        )
    return marks[0], marks[1] if len(marks) > 1 else len(trace)


@dataclass
class Replay:
    """The trace replayed up to an index: the bytes live after each event, the live set ``{addr: alloc
    entry}`` at the end and at one chosen index, and the bytes freed in the trace of allocations it never
    saw made (made before the recording began: not in any live set)."""

    totals: list[int] = field(default_factory=list)
    live: dict[int, Any] = field(default_factory=dict)
    live_at: dict[int, Any] = field(default_factory=dict)
    unrecorded: int = 0


def replay(trace: Sequence[dict[str, Any]], stop: int, keep: int = -1) -> Replay:
    """Apply the events of ``trace[:stop]`` in order (:class:`Replay`), keeping the live set after event
    ``keep`` too. An ``alloc`` adds its entry, a ``free_requested`` removes it (torch's allocated-bytes
    statistic drops there, not when the free completes); other events change nothing."""
    out = Replay()
    total = 0
    for i in range(stop):
        e = trace[i]
        action = e.get("action")
        if action == "alloc":
            out.live[e["addr"]] = e
            total += int(e["size"])
        elif action == "free_requested":
            done = out.live.pop(e["addr"], None)
            if done is None:
                out.unrecorded += int(e.get("size", 0))
            else:
                total -= int(done["size"])
        out.totals.append(total)
        if i == keep:
            out.live_at = dict(out.live)
    return out


def summarise(snapshot: dict[str, Any], device: int, library: Callable[[str], bool]) -> Summary:
    """Replay ``snapshot["device_traces"][device]`` (module docstring): the live allocations at the window's
    start and at its peak, grouped by :func:`where` with ``library`` naming the libraries' files."""
    traces = snapshot.get("device_traces") or []
    if device >= len(traces):
        raise ValueError(f"the snapshot has no trace of device {device} ({len(traces)} devices)")
    trace = traces[device]
    start, end = _window(trace)
    whole = replay(trace, end)
    totals = whole.totals
    # the peak counts what is live at the start too (as max_memory_allocated after a reset): the first event
    # from the start on with the most bytes live
    peak_at = max(range(start, end), key=lambda i: (totals[i], -i))
    at_peak = replay(trace, peak_at + 1, keep=start)

    def groups(live: dict[int, Any]) -> dict[Key, Group]:
        return group(((int(e["size"]), e.get("frames") or []) for e in live.values()), library)

    return Summary(
        entries=len(trace),
        window_entries=end - start - 1,
        start_bytes=totals[start],
        peak_bytes=totals[peak_at],
        peak_entry=peak_at - start,
        freed_unrecorded_bytes=whole.unrecorded,
        start=groups(at_peak.live_at),
        peak=groups(at_peak.live),
    )


def under(roots: Iterable[str]) -> Callable[[str], bool]:
    """A ``library`` for :func:`where`: true for a file under one of the folders ``roots``."""
    prefixes = tuple(str(r).rstrip("/") + "/" for r in roots)
    return lambda filename: filename.startswith(prefixes)


def difference(method: dict[Key, Group], baseline: dict[Key, Group], top: int) -> list[dict[str, Any]]:
    """Group by group, ``method``'s bytes minus ``baseline``'s (a group either lacks counts as 0): the
    ``top`` groups with the most extra bytes (positive, largest first), then the ``top`` groups the baseline
    holds more of (negative, most negative first). One allocation made under two different frames (the
    first cuBLAS call of each method makes the device's cuBLAS workspace: ``gsplat/rendering.py``'s camera
    inverse in one, ``render/backend.py``'s matrix product in the other) is a positive row and a negative
    row of the same size, which cancel: the positive rows alone would count it as the method's extra."""
    keys = sorted(set(method) | set(baseline))
    extra = [(method.get(k, Group()).bytes - baseline.get(k, Group()).bytes, k) for k in keys]
    more = sorted(((d, k) for d, k in extra if d > 0), key=lambda dk: -dk[0])[:top]
    fewer = sorted(((d, k) for d, k in extra if d < 0), key=lambda dk: dk[0])[:top]
    return [
        {"where": k[0], "via": k[1], "bytes": d, "method_bytes": method.get(k, Group()).bytes,
         "baseline_bytes": baseline.get(k, Group()).bytes}
        for d, k in more + fewer
    ]  # fmt: skip
