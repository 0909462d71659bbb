"""Kernel-level profile of one training step of ``--method jsgs`` against ``--method gsplat``: is a step
launch-bound (the host issuing many small kernels) or device-bound (the kernels themselves), and which kernels
does JSGS add?

    .venv/bin/python tools/diagnostics/profile_step.py                  # synthetic scene, CPU or CUDA (auto)
    .venv/bin/python tools/diagnostics/profile_step.py --manifest DATA/manifest.json --device cuda \
        --warmup 600 --steps 50 --jsgs-options '{"speed": {"cuda_graph": false}}' --out profile_step.json

Without ``--manifest`` a synthetic scene is built in a temporary folder, as ``bench_train_overhead.py``
builds it (``--size``, ``--views``). Every method runs the same settings (``--preset``, default ``paper``;
``--preset mcmc`` is the equal-budget protocol, gsplat's MCMC recipe with JSGS's recipe for it; ``--config``
JSON over the preset; no evaluation, no intermediate checkpoints; ``--jsgs-options`` over ``method_options``
for jsgs) from the same seed.

The budget (``strategy.type mcmc``): ``--cap-max N`` or ``--cap-max auto``, read as ``jsgs train --cap-max``
reads it (:func:`jsgs.train.config.cap_max_settings`), applies over ``--preset`` and ``--config`` for every
method. Without it the budget is the fixed :data:`jsgs.train.config.MCMC_CAP_MAX` = 300,000 Gaussians, under
``--config`` (a config file or run's config.json that gives a budget keeps it), not the mcmc preset's
scene-sized default: the published step profiles (docs/performance.md, docs/results/speed/) all ran at
300,000 ("the full budget" there is 300,000, and their ``--warmup`` points, 6,000 steps on flower and 9,300
on jpeg_mouse ÷2, are where the runs reach it), so a documented command run again measures the same model
size, and both methods always get one fixed budget whatever the scene. ``--cap-max auto`` profiles at the
budget ``jsgs train`` would choose for the scene (:mod:`jsgs.train.budget`; the same for every method).
The budget is printed in the header line and recorded in the JSON (``budget``: the settings' ``cap_max``
and ``cap_max_auto``; per method ``cap_max``, what its run trained with, and under auto ``budget_rule``,
the choice and its inputs). ``--cap-max`` with another strategy (``--preset paper``, the default) is an
error, as for ``jsgs train``.

Per method:

1. train ``--warmup`` steps and stop there with a checkpoint (600 by default: densification has begun, the
   Gaussians are no longer the initial point cloud; gsplat's JIT build and the allocator are warm);
2. copy that run twice and resume each copy for ``--settle`` + ``--steps`` + 1 steps: the ``--settle``
   steps absorb what a fresh process does once (CUDA-graph recording, ``torch.compile``, the profiler's own
   warm-up), the next ``--steps`` steps are the measured window, the last step only closes it. One copy runs
   plain (the honest wall time), the other under ``torch.profiler`` (CPU activity, plus CUDA on a GPU). Both
   start from the same checkpoint, so they train the same Gaussians on the same views.

The measured steps are the 0-based steps ``warmup + settle`` to ``warmup + settle + steps - 1``. A
densification step among them (every ``strategy.refine_every`` = 100 steps from ``refine_start_iter`` = 500)
is averaged into the window, and so is, for JSGS with CUDA graphs, the controller graph's re-recording on the
step after it; with the defaults the window holds none (the densification at step 600 and the re-recording
at 601 fall on the settling steps). The image terms' graph is recorded once per image shape, on the first
step that draws it: a scene whose views come in two orientations may draw the second only after the
settling steps. Every window counts JSGS's graph recordings inside it (``graph_recordings_in_window``; a
``note:`` line where there are any): each runs its chain eagerly and captures it, so its time and memory
are in the window's; a larger ``--settle`` (one epoch of the views) moves them before it.

The window is delimited at step boundaries (the device is synchronised at its two ends only): each timer is a
training callback (:class:`StepCallback`, ``on_step_begin``) passed to :func:`jsgs.train.trainer.train`.

Columns (per training step, averaged over the window):

- wall ms/step (unprofiled): the plain copy's device-synchronised wall time; the number to quote;
- the same, run not resumed: the same window timed in a third run trained from step 0 in this process
  (a check that resuming from the checkpoint does not change the step; ``--no-fresh`` skips it: "–");
- wall ms/step (profiled): the same window under the profiler (inflated by its bookkeeping, more so for
  launch-heavy code);
- kernel launches/step: on CUDA, host calls of ``cudaLaunchKernel`` / ``cudaLaunchKernelExC`` /
  ``cuLaunchKernel`` (Triton) and the like; on the CPU, the aten ops that produce data (views, aliases and
  allocations are free; an op that only dispatches to others, e.g. ``aten::linear``, counts as the ops it
  runs: the rule of ``jsgs.apps.opcount.KernelCounter``);
- graph launches/step: ``cudaGraphLaunch`` calls (each replays many kernels for one launch);
- device kernel ms/step: the summed duration of everything the GPU ran (kernels, copies, fills), CUDA only;
- device busy %: device kernel ms / unprofiled wall ms. Well below 100 % with many launches per step means
  launch-bound: the GPU waits for the host; near 100 % means device-bound;
- host op ms/step: the host's time inside torch ops (their self times summed over threads: dispatch, the
  CUDA runtime calls, and on the CPU the arithmetic itself), from the profiled run: compare it with the
  profiled wall time, the rest of which is Python (and, on a GPU, waiting in syncs counts as op time);
- syncs/step: host-device synchronisations (``cudaStreamSynchronize``, ``cudaDeviceSynchronize``,
  ``cudaEventSynchronize``, blocking ``cudaMemcpy``; not the one that closes the window); CUDA only;
- peak allocated / reserved MiB: the plain copy's peak device memory over the window,
  ``torch.cuda.max_memory_allocated`` (tensors) and ``max_memory_reserved`` (the caching allocator's
  segments), their statistics reset at the window's start (so: what the device held then, the run's model,
  optimisers and data included, and the window's own highs; the JSON has bytes);
- allocated at the start MiB: ``torch.cuda.memory_allocated`` when the plain copy's run began (the JSON also
  has the reserved figure): what earlier runs of this process left on the device, which the peak includes.
  Every run starts after :func:`release_memory` (Python's cycle collector, a device synchronisation,
  ``torch.cuda.empty_cache``), so this is the same small baseline for every run unless something of a
  finished run is still referenced (then a ``note:`` line says so). Peak and start: CUDA only, null on the
  CPU, where there are no such numbers.

With ``--pairs K``, after every method is profiled, each method's checkpoint is resumed K more times, plain,
interleaved in alternating order (baseline first, then last, ...: gsplat, jsgs, jsgs, gsplat, gsplat, jsgs
for K = 3), so that drift of the machine falls on both: the K wall times per method, their median, and the
median over the K pairs of each method's time over the baseline's in the same pair (the ratio to quote),
with a distribution-free interval for that median (two order statistics of the K ratios, at least 95 %
from 6 pairs on; below that (min, max) and its coverage, e.g. 93.8 % for 5 pairs:
:func:`jsgs.bench.stats.median_interval`). On CUDA, per window and kind (allocated, reserved), also the
device memory at the run's start (after :func:`release_memory`), the window's peak, and the peak's increment
over the start (the window's own memory, whatever earlier windows left): the K values per method, their
medians, and for the peak and the increment the median ratio to the baseline's with its interval.

With ``--memory-history N`` (CUDA only), after the rest is printed and written, each method's checkpoint is
resumed once more with the CUDA allocator's history recorded (``torch.cuda.memory._record_memory_history``,
from before the run loads anything, so every tensor it holds has the stack that made it) over a window of
``--memory-steps`` steps after ``--settle``: the bytes live at the window's start (what a step finds held)
and at its peak, grouped by where they were made (the innermost Python frame outside torch and the standard
library, and the autograd node or library frame beneath it: ``memory_history.py``), the ``N`` largest
groups of each method, and each method's groups minus the first method's (the ``N`` most extra, then the
``N`` most negative: one allocation made under two frames, such as the cuBLAS workspace of each method's
first matrix call, is a row and a negative row that cancel). Only that summary is kept, never the snapshot.
``--memory-stacks all`` records C++ frames too, which name the autograd node of a backward allocation (the
engine's device thread has no Python frame); set ``TORCH_SYMBOLIZE_MODE=fast`` for it.

Then, for every method against the first (normally jsgs − gsplat), the ``--top`` kernels by extra device
time per step and by extra host launches per step. Kernels replayed from a CUDA graph count as runs, not as
host launches. On the CPU the "kernels" are the counted aten ops and their time is the op's own host time.
"""

from __future__ import annotations

import argparse
import cProfile
import gc
import inspect
import json
import math
import os
import pstats
import shutil
import statistics
import sys
import sysconfig
import tempfile
import time
import weakref
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import memory_history  # noqa: E402
from bench_train_overhead import CAP_MAX_HELP, build_scene, report_header, start_config, variant_config  # noqa: E402

from jsgs.apps.opcount import FREE_OPS  # noqa: E402
from jsgs.base.errors import JsgsError, reports_user_errors  # noqa: E402
from jsgs.base.io import write_json_checked  # noqa: E402
from jsgs.bench.stats import median_interval  # noqa: E402
from jsgs.method import graphed  # noqa: E402
from jsgs.train.callbacks import Callback  # noqa: E402
from jsgs.train.config import PRESETS, TrainConfig, read_run_config  # noqa: E402
from jsgs.train.evaluate import synchronize  # noqa: E402
from jsgs.train.render_view import resolve_device  # noqa: E402
from jsgs.train.trainer import Trainer, train  # noqa: E402

FORMAT = "jsgs-profile-step"
#: The peak device memory figures of a window (:meth:`StepWindow.peak_memory`), in the order printed.
MEMORY_KINDS = ("allocated", "reserved")
FORMAT_VERSION = 4
#: ``--memory-history``: the allocator history's ring buffer, in events (a step makes a few thousand; the
#: window's start must not be overwritten before its end)
HISTORY_MAX_ENTRIES = 2_000_000
#: The profiler annotation around the synchronisation that closes the window (not the steps' own work).
WINDOW_END = "profile_step: window end"

#: Host-side CUDA runtime / driver calls that launch one kernel each.
LAUNCH_CALLS = frozenset(
    {
        "cudaLaunchKernel",
        "cudaLaunchKernelExC",
        "cudaLaunchCooperativeKernel",
        "cudaLaunchCooperativeKernelMultiDevice",
        "cuLaunchKernel",
        "cuLaunchKernelEx",
        "cuLaunchCooperativeKernel",
    }
)
#: Host-side calls that replay a recorded CUDA graph.
GRAPH_CALLS = frozenset({"cudaGraphLaunch", "cuGraphLaunch"})
#: Host-side calls that wait for the device.
SYNC_CALLS = frozenset(
    {
        "cudaStreamSynchronize",
        "cudaDeviceSynchronize",
        "cudaEventSynchronize",
        "cudaMemcpy",
        "cuStreamSynchronize",
        "cuCtxSynchronize",
        "cuEventSynchronize",
        "cuMemcpy",
    }
)
#: aten ops that launch nothing although their schema is not a view's (jsgs.apps.opcount's, plus allocations
#: and the conjugate/negative-bit resolvers, which return their input unless a bit is set).
FREE_ATEN = frozenset(n.replace("aten.", "aten::") for n in FREE_OPS) | {
    "aten::empty",
    "aten::empty_strided",
    "aten::empty_like",
    "aten::resolve_conj",
    "aten::resolve_neg",
    "aten::set_",
    "aten::record_stream",
}


def _quiet(_: str) -> None:
    pass


# ------------------------------------------------------------------------------------------------------------
# Step boundaries


class GraphRecordings:
    """Counts JSGS's CUDA graph recordings (``jsgs.method.graphed.record_graph``: the image terms' graph, one
    per image shape and training image stack on the first step that draws it, and the controller's graph
    where it has one) while :meth:`installed`. A recording runs its chain eagerly (warm-ups) and captures it,
    so one inside a measured window is in that window's time and peak memory: a resumed process records
    again, and ``--settle`` steps may not draw every image shape (:class:`StepWindow` counts them)."""

    def __init__(self) -> None:
        self.count = 0

    @contextmanager
    def installed(self) -> Iterator[GraphRecordings]:
        """``graphed.record_graph`` wrapped to count each call (a recording that fails counts too), then
        restored; ``graphed``'s callers look it up at each call."""
        original = graphed.record_graph

        def counted(*args: Any, **kwargs: Any) -> Any:
            self.count += 1
            return original(*args, **kwargs)

        graphed.record_graph = counted
        try:
            yield self
        finally:
            graphed.record_graph = original


#: the process's counter, installed by :func:`run`
RECORDINGS = GraphRecordings()


class StepWindow:
    """Called at the start of every step of a resumed segment of ``settle + steps + 1`` steps: synchronises
    the device and reads the clock at the start of step ``settle`` and of step ``settle + steps``, and steps
    the torch profiler (if any) at every call, whose schedule records exactly the steps in between. On CUDA
    it also resets the device's peak memory statistics at the window's start and reads them at its end
    (:meth:`peak_memory`), and counts the graph recordings in between (``recordings``, from ``counter``)."""

    def __init__(
        self, device: torch.device, settle: int, steps: int, prof: torch.profiler.profile | None = None,
        counter: GraphRecordings = RECORDINGS,
    ) -> None:  # fmt: skip
        self.device = device
        self.counter = counter
        self.recordings: int | None = None  # JSGS's graph recordings inside the window, once it has ended
        self.settle = settle
        self.steps = steps
        self.prof = prof
        self.calls = 0
        self.t0: float | None = None
        self.t1: float | None = None
        self.peak_allocated: int | None = None
        self.peak_reserved: int | None = None

    def __call__(self) -> None:
        i = self.calls
        self.calls += 1
        cuda = self.device.type == "cuda"
        if i == self.settle:
            synchronize(self.device)  # before the recording starts: the wait is not in the trace
            if cuda:  # the peak from here on: what the device holds now, then the window's own highs
                torch.cuda.reset_peak_memory_stats(self.device)
            if self.prof is not None:
                self.prof.step()
            self.recordings = -self.counter.count
            self.t0 = time.perf_counter()
        elif i == self.settle + self.steps:
            with torch.profiler.record_function(WINDOW_END):  # recorded: window_stats leaves it out
                synchronize(self.device)
            self.t1 = time.perf_counter()
            self.recordings = self.counter.count + (self.recordings or 0)
            if cuda:
                self.peak_allocated = int(torch.cuda.max_memory_allocated(self.device))
                self.peak_reserved = int(torch.cuda.max_memory_reserved(self.device))
            if self.prof is not None:
                self.prof.step()
        elif self.prof is not None:
            self.prof.step()

    def ms_per_step(self) -> float:
        if self.t0 is None or self.t1 is None:
            raise JsgsError(
                f"the measured window was not reached: the trainer asked its view sampler {self.calls} times "
                f"(expected {self.settle + self.steps + 1}, once per step)"
            )
        return 1000.0 * (self.t1 - self.t0) / self.steps

    def peak_memory(self) -> dict[str, int] | None:
        """The window's peak device memory in bytes, ``{"allocated": ..., "reserved": ...}``: torch's
        ``max_memory_allocated`` (tensors) and ``max_memory_reserved`` (the caching allocator's segments)
        since the window's start, read at its end; None on the CPU (CUDA only)."""
        self.ms_per_step()  # the window was reached (else one line)
        if self.peak_allocated is None or self.peak_reserved is None:
            return None
        return {"allocated": self.peak_allocated, "reserved": self.peak_reserved}

    @staticmethod
    def schedule(settle: int, steps: int) -> Callable[[int], Any]:
        """The profiler's schedule: step number 0 is the run's setup, number k the segment's step k - 1; the
        segment's step ``settle - 1`` is the profiler's warm-up, the next ``steps`` are recorded."""
        return torch.profiler.schedule(wait=settle, warmup=1, active=steps, repeat=1)


class PythonWindow(StepWindow):
    """A :class:`StepWindow` that runs ``cProfile`` over the window instead of the torch profiler: where the
    host's Python time goes (function self times; a sync shows up as the time of the call that waits)."""

    def __init__(self, device: torch.device, settle: int, steps: int) -> None:
        super().__init__(device, settle, steps)
        self.profiler = cProfile.Profile()

    def __call__(self) -> None:
        i = self.calls
        super().__call__()
        if i == self.settle:
            self.profiler.enable()
        elif i == self.settle + self.steps:
            self.profiler.disable()

    def top(self, n: int) -> list[dict[str, Any]]:
        """The ``n`` functions with the most self time: name, calls, self and cumulative ms per step."""
        rows = []
        for (file, line, func), (_, calls, tt, ct, _) in pstats.Stats(self.profiler).stats.items():  # type: ignore[attr-defined]
            name = f"{func}" if file == "~" else f"{Path(file).name}:{line}({func})"
            rows.append((tt, name, calls, ct))
        rows.sort(reverse=True)
        s = self.steps
        return [
            {"function": name, "calls_per_step": calls / s, "self_ms_per_step": 1e3 * tt / s,
             "cumulative_ms_per_step": 1e3 * ct / s}
            for tt, name, calls, ct in rows[:n]
        ]  # fmt: skip


class HistoryWindow(StepWindow):
    """A :class:`StepWindow` whose run records the CUDA allocator's history (:func:`history_window`): at the
    window's start a ``torch.cuda.memory._snapshot()`` call marks it in the history (its result is dropped),
    and at its end, after the peaks are read, a snapshot is summarised (:func:`memory_history.summarise`:
    ``summary``) and the recording stops."""

    def __init__(self, device: torch.device, settle: int, steps: int, library: Callable[[str], bool]) -> None:
        super().__init__(device, settle, steps)
        self.library = library
        self.summary: memory_history.Summary | None = None

    def __call__(self) -> None:
        i = self.calls
        if i == self.settle:
            synchronize(self.device)
            torch.cuda.memory._snapshot()  # records the "snapshot" event that marks the window's start
        super().__call__()
        if i == self.settle + self.steps:
            snapshot = torch.cuda.memory._snapshot()
            torch.cuda.memory._record_memory_history(enabled=None)
            index = self.device.index if self.device.index is not None else torch.cuda.current_device()
            self.summary = memory_history.summarise(snapshot, index, self.library)


def library_files() -> Callable[[str], bool]:
    """torch's package and Python's standard library: the frames :func:`memory_history.where` looks past."""
    paths = sysconfig.get_paths()
    here = Path(torch.__file__).parent
    return memory_history.under({str(here), str(here.resolve()), paths["stdlib"], paths["platstdlib"]})


class StepCallback(Callback):
    """A training callback that calls ``fn`` at the start of every step (a :class:`StepWindow`'s clock).
    ``trainer``: a weak reference to the trainer it served (None before the first step): dead once the run
    and everything it held are freed (:func:`plain_window` checks it)."""

    def __init__(self, fn: Callable[[], None]) -> None:
        self.fn = fn
        self.trainer: weakref.ref[Trainer] | None = None

    def on_step_begin(self, trainer: Trainer, step: int) -> None:
        if self.trainer is None:
            self.trainer = weakref.ref(trainer)
        self.fn()


# ------------------------------------------------------------------------------------------------------------
# Device memory between windows


def device_memory(device: torch.device) -> dict[str, int] | None:
    """What the device holds now, in bytes: ``{"allocated": torch.cuda.memory_allocated (tensors),
    "reserved": memory_reserved (the caching allocator's segments)}``; None on the CPU (CUDA only)."""
    if device.type != "cuda":
        return None
    return {
        "allocated": int(torch.cuda.memory_allocated(device)),
        "reserved": int(torch.cuda.memory_reserved(device)),
    }


def release_memory(device: torch.device) -> None:
    """Free what finished runs left behind, so that every window starts from the same baseline: Python's
    cycle collector (a trainer, its model, optimisers, data on the device and the JSGS hook's CUDA graphs
    with their memory pool are freed at once only where nothing refers to them; a reference cycle keeps
    them until a collection), then on CUDA a device synchronisation (frees in flight complete), torch's
    cuBLAS workspaces and ``torch.cuda.empty_cache`` (the allocator's free segments, freed graph pools
    included, go back to the driver, so the reserved figure starts from what is still in use).

    The workspaces: torch keeps one per cuBLAS handle and stream, allocated through the caching allocator
    on the stream's first matrix product and held until the process ends or they are cleared. The JSGS
    graphs record on one side stream per device (``jsgs.method.graphed.side_stream``), whose workspace a
    finished JSGS run would leave to the next window's start, not to gsplat's (torch's own leak checks clear
    them too before they compare memory). Cleared between runs only: no graph of a finished run replays
    again, and the next run allocates its own."""
    gc.collect()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        clear_workspaces = getattr(torch._C, "_cuda_clearCublasWorkspaces", None)
        if clear_workspaces is not None:
            clear_workspaces()
        torch.cuda.empty_cache()


@dataclass
class PlainWindow:
    """One plain (unprofiled) resumed window (:func:`plain_window`): its wall time, what the device held at
    the run's start after :func:`release_memory` (``start``) and the window's peaks (``peak``), in bytes
    by :data:`MEMORY_KINDS` (both None on the CPU), and whether the run's trainer was freed after it."""

    ms_per_step: float
    start: dict[str, int] | None
    peak: dict[str, int] | None
    released: bool
    recordings: int | None = None  # JSGS's graph recordings inside the window (StepWindow.recordings)


def plain_window(
    manifest: Path, run: Path, device: torch.device, settle: int, steps: int, label: str
) -> tuple[dict[str, Any], PlainWindow]:
    """Resume the run folder ``run`` for one plain window, between two :func:`release_memory` calls:
    ``(the run's metrics document, its PlainWindow)``. A trainer still referenced after the second call
    (its memory would count in the next window's start) is one ``note:`` line on stderr naming ``label``."""
    release_memory(device)
    start = device_memory(device)
    clock = StepWindow(device, settle, steps)
    callback = StepCallback(clock)
    doc = train(manifest, run, resume=True, progress=False, log=_quiet, callbacks=[callback])
    trainer = callback.trainer
    del callback  # the trainer's own list held it; nothing of the run is referenced from here on
    release_memory(device)
    released = trainer is None or trainer() is None
    if not released:
        print(
            f"note: profile_step: {label}: the run's trainer is still referenced after its window; its "
            "memory counts in the next window's start",
            file=sys.stderr,
        )
    return doc, PlainWindow(clock.ms_per_step(), start, clock.peak_memory(), released, clock.recordings)


def history_window(
    manifest: Path, run: Path, device: torch.device, settle: int, steps: int, stacks: str
) -> tuple[dict[str, Any], HistoryWindow, dict[str, int] | None]:
    """Resume the run folder ``run`` for one window with the CUDA allocator's history recorded from before
    the run loads anything (cleared first, so it holds this run's events only), between two
    :func:`release_memory` calls: ``(the run's metrics document, its HistoryWindow, the device memory at the
    start)``."""
    record = torch.cuda.memory._record_memory_history
    if "clear_history" not in inspect.signature(record).parameters:
        raise JsgsError(
            f"--memory-history: torch {torch.__version__}'s _record_memory_history cannot clear it"
        )
    if stacks == "all":  # torch's own C++ symboliser, seconds instead of minutes of addr2line
        os.environ.setdefault("TORCH_SYMBOLIZE_MODE", "fast")
    release_memory(device)
    start = device_memory(device)
    clock = HistoryWindow(device, settle, steps, library_files())
    record(enabled="all", context="alloc", stacks=stacks, max_entries=HISTORY_MAX_ENTRIES, clear_history=True)
    try:
        doc = train(manifest, run, resume=True, progress=False, log=_quiet, callbacks=[StepCallback(clock)])
    finally:
        record(enabled=None)
    release_memory(device)
    return doc, clock, start


def memory_histories(
    manifest: Path, work: Path, methods: Sequence[str], device: torch.device, settle: int,
    args: argparse.Namespace,
) -> dict[str, Any]:  # fmt: skip
    """``--memory-history``: each method's checkpoint (``work/METHOD/warm``) resumed once more for
    ``--memory-steps`` steps with the history recorded (:func:`history_window`): the document's
    ``memory_history`` object (each method's summary, the allocator's own peak over the same window, and each
    method's groups minus the first method's at the window's start and peak)."""
    top, steps = args.memory_history, args.memory_steps
    summaries: dict[str, memory_history.Summary] = {}
    out: dict[str, Any] = {"settle": settle, "steps": steps, "stacks": args.memory_stacks, "top": top}
    out["by_method"], out["difference"] = {}, {}
    for m in methods:
        copy = work / m / "history"
        shutil.copytree(work / m / "warm", copy)
        doc, clock, start = history_window(manifest, copy, device, settle, steps, args.memory_stacks)
        shutil.rmtree(copy)
        if clock.summary is None:
            raise JsgsError(f"{m}: --memory-history: the window's end was not reached")
        summaries[m] = clock.summary
        out["by_method"][m] = clock.summary.doc(top) | {
            "num_gaussians": int(doc["num_gaussians"]),
            "max_memory_allocated_bytes": clock.peak_allocated,
            "graph_recordings_in_window": clock.recordings,
            "start_memory_allocated_bytes": None if start is None else start["allocated"],
        }
    base = methods[0]
    for m in methods[1:]:
        a, b = summaries[m], summaries[base]
        out["difference"][m] = {
            "baseline": base,
            "start": memory_history.difference(a.start, b.start, top),
            "peak": memory_history.difference(a.peak, b.peak, top),
        }
    return out


# ------------------------------------------------------------------------------------------------------------
# Reading the profiler's events


@dataclass
class KernelStat:
    """One kernel name's runs in the window: ``runs``, of which ``launched`` by a kernel-launch call of the
    host (the others: replayed from a CUDA graph, or copies and fills), and ``time_us``: device time (CUDA),
    or the op's host time, its children included (CPU)."""

    runs: int = 0
    launched: int = 0
    time_us: float = 0.0

    def add(self, time_us: float, launched: bool = True) -> None:
        self.runs += 1
        self.launched += int(launched)
        self.time_us += time_us


@dataclass
class WindowStats:
    """Totals over the recorded window (divide by the number of steps); ``syncs`` and ``device_us`` are None
    on the CPU."""

    launches: int = 0
    graph_launches: int = 0
    syncs: int | None = None
    device_us: float | None = None
    host_us: float = 0.0
    kernels: dict[str, KernelStat] = field(default_factory=dict)


@cache
def aten_kind(name: str) -> str:
    """``"free"`` (a view or an op that launches nothing), ``"composite"`` (only dispatches to other aten ops:
    count those instead) or ``"kernel"``, for a profiler event name like ``aten::add``. Decided on the op's
    schemas (all overloads but the ``out=`` ones must agree); unknown names are kernels."""
    if name in FREE_ATEN:
        return "free"
    try:
        packet = getattr(torch.ops.aten, name.split("::", 1)[1])
        overloads = [getattr(packet, o) for o in packet.overloads()]
    except (AttributeError, RuntimeError, IndexError):
        return "kernel"
    # the overloads that return a new tensor (not the out= ones, not TorchScript's str/int/list ones)
    functional = [
        o
        for o in overloads
        if not any(a.is_out for a in o._schema.arguments)
        and o._schema.returns
        and "Tensor" in str(o._schema.returns[0].type)
    ] or overloads
    key = torch._C.DispatchKey.CompositeImplicitAutograd
    composite: list[bool] = []
    for o in functional:
        try:
            composite.append(o.has_kernel_for_dispatch_key(key))
        except RuntimeError:  # an overload the dispatcher does not know (TorchScript's prim_* ones)
            continue
    if composite and all(composite):
        return "composite"
    if functional and all(o.is_view for o in functional):
        return "free"
    return "kernel"


def _is_cpu(e: Any) -> bool:
    return e.device_type == torch.autograd.DeviceType.CPU


def _annotation(e: Any) -> bool:
    return bool(getattr(e, "is_user_annotation", False)) or e.name.startswith("ProfilerStep")


def _recorded(events: Sequence[Any]) -> list[Any]:
    """The host events that belong to the recorded steps: those that start within the profiler's step
    annotations (``ProfilerStep#k``; on any thread, e.g. CUDA's autograd thread) but not within the window's
    closing synchronisation (:data:`WINDOW_END`), nor the profiler's own stop after the last step."""
    cpu = [e for e in events if _is_cpu(e)]
    steps = [e.time_range for e in cpu if e.name.startswith("ProfilerStep")]
    closing = [e.time_range for e in cpu if e.name == WINDOW_END]
    lo = min((r.start for r in steps), default=-math.inf)
    hi = max((r.end for r in steps), default=math.inf)
    return [
        e
        for e in cpu
        if not _annotation(e)
        and e.name != WINDOW_END
        and lo <= e.time_range.start <= hi
        and not any(r.start <= e.time_range.start <= r.end for r in closing)
    ]


def window_stats(events: Sequence[Any], cuda: bool) -> WindowStats:
    """Launches, syncs, device and host time and per-kernel numbers from ``torch.profiler``'s events of the
    recorded window (``prof.events()``)."""
    out = WindowStats()
    cpu_events = _recorded(events)
    out.host_us = sum(e.self_cpu_time_total for e in cpu_events if not e.is_async)
    if cuda:
        via: dict[int, bool] = {}  # correlation id of a launching call -> whether it launches one kernel
        syncs = 0
        for e in cpu_events:
            if e.name in LAUNCH_CALLS:
                out.launches += 1
                via[e.id] = True
            elif e.name in GRAPH_CALLS:
                out.graph_launches += 1
                via[e.id] = False
            elif e.name in SYNC_CALLS:
                syncs += 1
        out.syncs = syncs
        out.device_us = 0.0
        for e in events:
            if _is_cpu(e) or _annotation(e):
                continue
            dur = float(e.time_range.elapsed_us())
            out.device_us += dur
            out.kernels.setdefault(e.name, KernelStat()).add(dur, via.get(e.id, False))
        return out
    for e in cpu_events:
        if not e.name.startswith("aten::") or aten_kind(e.name) != "kernel":
            continue
        p = e.cpu_parent
        while p is not None and not (p.name.startswith("aten::") and aten_kind(p.name) != "composite"):
            p = p.cpu_parent
        if p is not None:
            continue  # inside a counted (or free) op: part of that one
        out.launches += 1
        out.kernels.setdefault(e.name, KernelStat()).add(float(e.cpu_time_total))
    return out


def kernel_rows(kernels: dict[str, KernelStat], steps: int, top: int) -> list[dict[str, Any]]:
    """The ``top`` kernels by time, per step."""
    ranked = sorted(kernels.items(), key=lambda kv: -kv[1].time_us)[:top]
    return [
        {
            "name": n,
            "runs_per_step": k.runs / steps,
            "launches_per_step": k.launched / steps,
            "ms_per_step": k.time_us / 1000.0 / steps,
        }
        for n, k in ranked
    ]


def kernel_difference(
    a: dict[str, KernelStat], b: dict[str, KernelStat], steps: int, top: int
) -> dict[str, list[dict[str, Any]]]:
    """``a`` minus ``b`` per kernel name, per step: the ``top`` names by extra time and by extra host
    launches (positive differences only)."""
    rows = []
    for name in sorted(set(a) | set(b)):
        ka, kb = a.get(name, KernelStat()), b.get(name, KernelStat())
        ms_a, ms_b = ka.time_us / 1000.0 / steps, kb.time_us / 1000.0 / steps
        la, lb = ka.launched / steps, kb.launched / steps
        rows.append(
            {
                "name": name,
                "ms_per_step": ms_a,
                "baseline_ms_per_step": ms_b,
                "extra_ms_per_step": ms_a - ms_b,
                "launches_per_step": la,
                "baseline_launches_per_step": lb,
                "extra_launches_per_step": la - lb,
                "extra_runs_per_step": (ka.runs - kb.runs) / steps,
            }
        )
    by_time = [r for r in sorted(rows, key=lambda r: -r["extra_ms_per_step"]) if r["extra_ms_per_step"] > 0]
    by_launches = sorted(rows, key=lambda r: (-r["extra_launches_per_step"], -r["extra_ms_per_step"]))
    by_launches = [r for r in by_launches if r["extra_launches_per_step"] > 0]
    return {"by_time": by_time[:top], "by_launches": by_launches[:top]}


# ------------------------------------------------------------------------------------------------------------
# Runs


def profile_method(
    manifest: Path,
    work: Path,
    cfg: TrainConfig,
    device: torch.device,
    warmup: int,
    settle: int,
    steps: int,
    python_top: int = 0,
    trace: Path | None = None,
    fresh: bool = True,
) -> tuple[dict[str, Any], WindowStats]:
    """Warm-up run, then the plain and the profiled copy of the window (module docstring); with
    ``python_top``, a third copy under cProfile; with ``trace``, the profiled copy also records Python stacks
    and its Chrome trace is written there (``tools/diagnostics/trace_gaps.py`` reads it); with ``fresh``
    (default), the window is also timed in a run trained from step 0 (``wall_ms_per_step_fresh``)."""
    warm = work / "warm"
    release_memory(device)
    train(manifest, warm, cfg, force=True, stop_at=warmup, progress=False, log=_quiet)
    cuda = device.type == "cuda"
    trained = run_budget(warm)

    plain = work / "plain"
    shutil.copytree(warm, plain)
    doc, window = plain_window(manifest, plain, device, settle, steps, f"{cfg.method} (plain copy)")
    wall, peak, start = window.ms_per_step, window.peak, window.start

    # the same window timed inside a run from step 0 (no resume): a check that resuming does not change
    # the step
    wall_fresh = None
    if fresh:
        fresh_clock = StepWindow(device, warmup + settle, steps)
        release_memory(device)
        train(
            manifest, work / "fresh", cfg, force=True, progress=False, log=_quiet,
            callbacks=[StepCallback(fresh_clock)],
        )  # fmt: skip
        wall_fresh = fresh_clock.ms_per_step()

    profiled = work / "profiled"
    shutil.copytree(warm, profiled)
    activities = [torch.profiler.ProfilerActivity.CPU]
    if cuda:
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    captured: dict[str, Any] = {}

    def ready(p: torch.profiler.profile) -> None:
        captured["events"] = p.events()
        if trace is not None:
            p.export_chrome_trace(str(trace))

    release_memory(device)
    with torch.profiler.profile(
        activities=activities, schedule=StepWindow.schedule(settle, steps), on_trace_ready=ready,
        with_stack=trace is not None,
    ) as prof:  # fmt: skip
        pclock = StepWindow(device, settle, steps, prof)
        pdoc = train(
            manifest, profiled, resume=True, progress=False, log=_quiet, callbacks=[StepCallback(pclock)]
        )
    wall_prof = pclock.ms_per_step()
    if "events" not in captured:
        raise JsgsError(f"{cfg.method}: the profiler delivered no trace for the window")
    stats = window_stats(captured.pop("events"), cuda)
    pclock.prof = None
    del prof  # the profiler's results (host memory) go before the next run, with its events
    device_ms = None if stats.device_us is None else stats.device_us / 1000.0 / steps

    result = {
        "wall_ms_per_step": wall,
        "wall_ms_per_step_profiled": wall_prof,
        "kernel_launches_per_step": stats.launches / steps,
        "graph_launches_per_step": stats.graph_launches / steps,
        "device_kernel_ms_per_step": device_ms,
        "device_busy_percent": None if device_ms is None else 100.0 * device_ms / wall,
        "host_op_ms_per_step": stats.host_us / 1000.0 / steps,
        "syncs_per_step": None if stats.syncs is None else stats.syncs / steps,
        **{f"peak_memory_{k}_bytes": None if peak is None else peak[k] for k in MEMORY_KINDS},
        **{f"start_memory_{k}_bytes": None if start is None else start[k] for k in MEMORY_KINDS},
        "num_gaussians": int(doc["num_gaussians"]),
        "num_gaussians_profiled": int(pdoc["num_gaussians"]),
        "graph_recordings_in_window": window.recordings,
        "device_name": doc["device_name"],
        "backend": doc["backend"],
        **trained,
    }
    if wall_fresh is not None:
        result["wall_ms_per_step_fresh"] = wall_fresh
    if python_top > 0:
        py = work / "python"
        shutil.copytree(warm, py)
        pywin = PythonWindow(device, settle, steps)
        release_memory(device)
        train(manifest, py, resume=True, progress=False, log=_quiet, callbacks=[StepCallback(pywin)])
        result["python_wall_ms_per_step"] = pywin.ms_per_step()
        result["python_top"] = pywin.top(python_top)
    return result, stats


def run_budget(run: Path) -> dict[str, Any]:
    """What the run in folder ``run`` trained with, from its config.json: ``cap_max`` (null for a strategy
    other than mcmc) and ``budget_rule``, the scene-sized choice and its inputs (null with a fixed budget)."""
    recorded = read_run_config(run)
    strategy = recorded.settings.strategy
    return {
        "cap_max": strategy.cap_max if strategy.type == "mcmc" else None,
        "budget_rule": recorded.doc["derived"].get("budget"),
    }


def pair_order(methods: Sequence[str], pairs: int) -> list[list[str]]:
    """The methods' order in each of ``pairs`` rounds: as given, then reversed, alternately (ABBA...)."""
    return [list(methods) if i % 2 == 0 else list(reversed(methods)) for i in range(pairs)]


def _ratio_doc(per_pair: list[float]) -> dict[str, Any]:
    """The pairs document's entry for one method: the ratios, their median and its distribution-free interval
    (:func:`jsgs.bench.stats.median_interval`, at least 95 % where there are enough pairs)."""
    lo, hi, cov = median_interval(per_pair)
    return {"per_pair": per_pair, "median": statistics.median(per_pair), "interval": [lo, hi],
            "interval_coverage": cov}  # fmt: skip


def _ratios(values: dict[str, list[float]]) -> dict[str, dict[str, Any]]:
    """:func:`_ratio_doc` of each method but the first: its values over the first method's, round by round;
    a method left out where a value of its own or the first method's is not positive (no ratio there)."""
    base, *others = values
    return {
        m: _ratio_doc([a / b for a, b in zip(values[m], values[base], strict=True)])
        for m in others
        if min(values[m] + values[base]) > 0
    }


#: A method's memory figure over the rounds: kind (:data:`MEMORY_KINDS`) -> bytes per round; None on the CPU.
Peaks = dict[str, list[int]] | None


def pairs_doc(
    order: list[list[str]], walls: dict[str, list[float]], peaks: dict[str, Peaks], starts: dict[str, Peaks]
) -> dict[str, Any]:
    """The document's ``pairs`` object from each method's wall times (ms/step), peak memory and memory at the
    start per round (``walls``, ``peaks`` and ``starts`` by method, the baseline first): the medians, and the
    median over the rounds of each method's figure over the baseline's in the same round, with its interval,
    for the wall time, the peak and the peak's increment over the start (the window's own memory, whatever
    was left on the device before it). ``peak_memory`` is None unless every method has its peaks and starts
    (CUDA only)."""
    memory = None
    known = {m: (p, starts[m]) for m, p in peaks.items() if p is not None and starts[m] is not None}
    if len(known) == len(peaks):
        memory = {}
        for k in MEMORY_KINDS:
            inc = {m: [float(a - b) for a, b in zip(p[k], s[k], strict=True)] for m, (p, s) in known.items()}
            memory[k] = {
                "median_bytes": {m: statistics.median(p[k]) for m, (p, _) in known.items()},
                "ratio": _ratios({m: [float(b) for b in p[k]] for m, (p, _) in known.items()}),
                "start_median_bytes": {m: statistics.median(s[k]) for m, (_, s) in known.items()},
                "increment_median_bytes": {m: statistics.median(v) for m, v in inc.items()},
                "increment_ratio": _ratios(inc),
            }
    return {
        "count": len(order),
        "order": order,
        "median_ms_per_step": {m: statistics.median(v) for m, v in walls.items()},
        "ratio": _ratios(walls),
        "peak_memory": memory,
    }


def interleaved_windows(
    manifest: Path, work: Path, methods: Sequence[str], device: torch.device, settle: int, steps: int,
    pairs: int,
) -> tuple[dict[str, list[PlainWindow]], dict[str, Any]]:  # fmt: skip
    """``pairs`` more plain windows per method, each resumed from ``work/METHOD/warm`` (left by
    :func:`profile_method`), in :func:`pair_order`, each between two :func:`release_memory` calls
    (:func:`plain_window`): ``({method: its windows in round order}, the document's ``pairs`` object)``
    (:func:`pairs_doc`)."""
    order = pair_order(methods, pairs)
    windows: dict[str, list[PlainWindow]] = {m: [] for m in methods}
    for i, round_ in enumerate(order):
        for m in round_:
            copy = work / m / f"pair{i}"
            shutil.copytree(work / m / "warm", copy)
            _, window = plain_window(manifest, copy, device, settle, steps, f"{m} (pair {i + 1})")
            windows[m].append(window)
            shutil.rmtree(copy)
    walls = {m: [w.ms_per_step for w in ws] for m, ws in windows.items()}
    return windows, pairs_doc(order, walls, _per_kind(windows, "peak"), _per_kind(windows, "start"))


def _per_kind(windows: dict[str, list[PlainWindow]], figure: str) -> dict[str, Peaks]:
    """Each method's ``figure`` ("peak" or "start") of its windows by memory kind; None unless every window
    has it (CUDA only)."""
    out: dict[str, Peaks] = {}
    for m, ws in windows.items():
        values = [getattr(w, figure) for w in ws]
        known = [v for v in values if v is not None]
        out[m] = {k: [v[k] for v in known] for k in MEMORY_KINDS} if len(known) == len(values) else None
    return out


# ------------------------------------------------------------------------------------------------------------
# Output


def _cell(x: float | None, fmt: str = ".2f") -> str:
    return "–" if x is None else format(x, fmt)


def _mib(n: float | None) -> float | None:
    return None if n is None else n / 2**20


def _interval(q: dict[str, Any]) -> str:
    """A ratio document's interval and coverage, as printed."""
    return f"{q['interval'][0]:.3f}–{q['interval'][1]:.3f} ({100 * q['interval_coverage']:.1f} %)"


def _name(n: str, width: int = 60) -> str:
    n = n.replace("|", "\\|").replace("\n", " ")
    return n if len(n) <= width else n[: width - 1] + "…"


def recordings_note(count: int | None, settle: int) -> str:
    """The line that says a window held graph recordings ("" where it held none or was not counted)."""
    if not count:
        return ""
    return (
        f"{count} CUDA graph recording(s) inside the measured window (a graph per image shape is recorded on "
        f"the first step that draws it; its eager warm-ups and capture are in the window's time and peak "
        f"memory): a larger --settle than {settle} moves them before the window"
    )


def print_report(doc: dict[str, Any]) -> None:
    res = doc["results"]
    first = next(iter(res.values()))
    cuda = doc["device"].startswith("cuda")
    print(
        f"device {first['device_name']} ({doc['device']}, backend {first['backend']}), torch {doc['torch']}, "
        f"jsgs {doc['version']}, {torch.get_num_threads()} CPU threads"
    )
    print(
        f"scene {doc['manifest']}: {doc['warmup']} warm-up steps, {doc['settle']} settling steps, "
        f"{doc['steps']} measured steps{describe_budget(doc)}"
        + ("" if cuda else "; CPU: kernels are aten ops, their time is host time; peak memory: CUDA only")
    )
    print()
    print(
        "| method | wall ms/step (unprofiled) | the same, run not resumed | wall ms/step (profiled) | "
        "kernel launches/step | graph launches/step | device kernel ms/step | device busy % | "
        "host op ms/step | syncs/step | peak allocated MiB | peak reserved MiB | "
        "allocated at the start MiB | #Gaussians |"
    )
    print("|---|" + "---:|" * 13)
    for m, r in res.items():
        cells = [
            _cell(r["wall_ms_per_step"]),
            _cell(r.get("wall_ms_per_step_fresh")),
            _cell(r["wall_ms_per_step_profiled"]),
            _cell(r["kernel_launches_per_step"], ".1f"),
            _cell(r["graph_launches_per_step"], ".1f"),
            _cell(r["device_kernel_ms_per_step"]),
            _cell(r["device_busy_percent"], ".1f"),
            _cell(r["host_op_ms_per_step"]),
            _cell(r["syncs_per_step"], ".1f"),
            *(_cell(_mib(r[f"peak_memory_{k}_bytes"]), ".1f") for k in MEMORY_KINDS),
            _cell(_mib(r["start_memory_allocated_bytes"]), ".1f"),
            str(r["num_gaussians"]),
        ]
        print(f"| {m} | " + " | ".join(cells) + " |")
    for m, r in res.items():
        note = recordings_note(r.get("graph_recordings_in_window"), doc["settle"])
        if note:
            print(f"note: {m}: {note}")
    unit = "device ms" if cuda else "op ms (host)"
    for m, d in doc["differences"].items():
        b = d["baseline"]
        print()
        print(f"{m} − {b}: top {doc['settings']['top']} kernels by extra {unit} per step")
        print()
        print(f"| kernel | {m} {unit}/step | {b} {unit}/step | extra {unit}/step | extra launches/step |")
        print("|---|---:|---:|---:|---:|")
        for r in d["by_time"]:
            print(
                f"| {_name(r['name'])} | {r['ms_per_step']:.3f} | {r['baseline_ms_per_step']:.3f} | "
                f"{r['extra_ms_per_step']:.3f} | {r['extra_launches_per_step']:.1f} |"
            )
        print()
        print(f"{m} − {b}: top {doc['settings']['top']} kernels by extra host launches per step")
        print()
        print(f"| kernel | {m} launches/step | {b} launches/step | extra launches/step | extra {unit}/step |")
        print("|---|---:|---:|---:|---:|")
        for r in d["by_launches"]:
            print(
                f"| {_name(r['name'])} | {r['launches_per_step']:.1f} | "
                f"{r['baseline_launches_per_step']:.1f} | {r['extra_launches_per_step']:.1f} | "
                f"{r['extra_ms_per_step']:.3f} |"
            )


def print_pairs(doc: dict[str, Any]) -> None:
    """The ``--pairs`` table: each method's interleaved windows, their median, the median ratio."""
    pairs = doc.get("pairs")
    if not pairs:
        return
    base = next(iter(doc["results"]))
    order = "; ".join(", ".join(r) for r in pairs["order"])
    print()
    n = pairs["count"]
    print(f"{n} interleaved windows per method, resumed from the same checkpoint (order: {order})")
    print()
    print(
        f"| method | wall ms/step, each window | median | median over the pairs of ms/step ÷ {base}'s | "
        "its interval (coverage) |"
    )
    print("|---|---|---:|---:|---|")
    for m, r in doc["results"].items():
        each = ", ".join(f"{v:.2f}" for v in r["paired_wall_ms_per_step"])
        ratio, interval = "1", ""
        if m != base:
            q = pairs["ratio"][m]
            ratio, interval = f"{q['median']:.3f}", _interval(q)
        print(f"| {m} | {each} | {pairs['median_ms_per_step'][m]:.2f} | {ratio} | {interval} |")
    memory = pairs["peak_memory"]
    print()
    if memory is None:
        print("peak memory of the windows: CUDA only")
        return
    print(
        "device memory of each window: at the run's start after freeing what earlier runs left "
        "(torch.cuda.memory_allocated / memory_reserved), the peak over the window "
        "(max_memory_allocated / max_memory_reserved since the window's start), and the peak's increment "
        "over the start (the window's own memory)"
    )
    print()
    print(
        f"| method | memory | figure | MiB, each window | median | median over the pairs of the figure ÷ "
        f"{base}'s | its interval (coverage) |"
    )
    print("|---|---|---|---|---:|---:|---|")
    figures = (("start", "start_median_bytes", None), ("peak", "median_bytes", "ratio"),
               ("peak − start", "increment_median_bytes", "increment_ratio"))  # fmt: skip
    for k in MEMORY_KINDS:
        for m, r in doc["results"].items():
            start, peak = r[f"paired_start_memory_{k}_bytes"], r[f"paired_peak_memory_{k}_bytes"]
            values = {
                "start": start,
                "peak": peak,
                "peak − start": [a - b for a, b in zip(peak, start, strict=True)],
            }
            for figure, median_key, ratio_key in figures:
                each = ", ".join(f"{v / 2**20:.1f}" for v in values[figure])
                ratio, interval = "", ""
                if ratio_key is not None:
                    q = memory[k][ratio_key].get(m)
                    ratio = "1" if m == base else "–" if q is None else f"{q['median']:.3f}"
                    interval = "" if q is None else _interval(q)
                median = memory[k][median_key][m] / 2**20
                print(f"| {m} | {k} | {figure} | {each} | {median:.1f} | {ratio} | {interval} |")


def print_python(doc: dict[str, Any]) -> None:
    for m, r in doc["results"].items():
        if "python_top" not in r:
            continue
        print()
        wall = r["python_wall_ms_per_step"]
        print(f"{m}: Python functions by self time (cProfile; wall {wall:.2f} ms/step under it)")
        print()
        print("| function | calls/step | self ms/step | cumulative ms/step |")
        print("|---|---:|---:|---:|")
        for row in r["python_top"]:
            cells = (row["calls_per_step"], row["self_ms_per_step"], row["cumulative_ms_per_step"])
            print(f"| {_name(row['function'], 80)} | {cells[0]:.1f} | {cells[1]:.3f} | {cells[2]:.3f} |")


def _history_table(title: str, groups: list[dict[str, Any]], columns: Sequence[tuple[str, str]]) -> None:
    print()
    print(title)
    print()
    print("| where (innermost frame outside torch) | via (autograd node or library frame) | " + " | ".join(
        c for c, _ in columns) + " |")  # fmt: skip
    print("|---|---|" + "---:|" * len(columns))
    for g in groups:
        cells = [f"{g[k] / 2**20:.2f}" if k.endswith("bytes") else str(g[k]) for _, k in columns]
        print(f"| {_name(g['where'], 70)} | {_name(g['via'], 50) or '–'} | " + " | ".join(cells) + " |")


def print_memory_history(doc: dict[str, Any]) -> None:
    """The ``--memory-history`` tables: each method's live allocations at the window's peak and start by
    where they were made, then each method's groups minus the first method's."""
    h = doc.get("memory_history")
    if not h:
        return
    print()
    print(
        f"live CUDA allocations by where they were made (--memory-history: a window of {h['steps']} steps "
        f"after {h['settle']} resumed, the allocator's history with {h['stacks']} stacks; MiB asked for, "
        "the allocator rounds each block up to 512 B)"
    )
    own = (("MiB", "bytes"), ("blocks", "blocks"), ("largest MiB", "largest_bytes"))
    for m, r in h["by_method"].items():
        peak, start = r["peak"], r["start"]
        print()
        print(
            f"{m}: {r['num_gaussians']} Gaussians; at the window's start {start['bytes'] / 2**20:.2f} MiB, "
            f"its peak {peak['bytes'] / 2**20:.2f} MiB after event {peak['entry']} of {r['window_entries']} "
            f"(max_memory_allocated over the window {_cell(_mib(r['max_memory_allocated_bytes']))} MiB; "
            f"allocated before the recording {_cell(_mib(r['start_memory_allocated_bytes']))} MiB, of which "
            f"{r['freed_unrecorded_bytes'] / 2**20:.2f} freed in the trace; {r['trace_entries']} events)"
        )  # fmt: skip
        note = recordings_note(r.get("graph_recordings_in_window"), h["settle"])
        if note:
            print(f"note: {m}: {note}")
        _history_table(f"{m}: live at the window's peak, top {h['top']}", peak["groups"], own)
        _history_table(
            f"{m}: live at the window's start (held between steps), top {h['top']}", start["groups"], own
        )
    for m, d in h["difference"].items():
        b = d["baseline"]
        cols = (("extra MiB", "bytes"), (f"{m} MiB", "method_bytes"), (f"{b} MiB", "baseline_bytes"))
        for moment in ("peak", "start"):
            net = (h["by_method"][m][moment]["bytes"] - h["by_method"][b][moment]["bytes"]) / 2**20
            _history_table(
                f"{m} − {b}: live at the window's {moment}, the most extra bytes, then the most fewer "
                f"(negative; a row and a negative row of one size may be one allocation made under two "
                f"frames); all groups together {net:+.2f} MiB", d[moment], cols,
            )  # fmt: skip


def _json_arg(text: str) -> dict[str, Any]:
    try:
        value = json.loads(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"not JSON: {e}") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError("must be a JSON object")
    return value


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--manifest", type=Path, help="scene manifest (default: a synthetic scene)")
    ap.add_argument("--size", default="160x120", help="synthetic scene image size WxH [160x120]")
    ap.add_argument("--views", type=int, default=16, help="synthetic scene views [16]")
    ap.add_argument("--methods", default="gsplat,jsgs", help="comma-separated; the first is the baseline")
    ap.add_argument(
        "--preset", default="paper", choices=list(PRESETS),
        help="the preset every method starts from (mcmc: the equal-budget protocol) [paper]",
    )  # fmt: skip
    ap.add_argument("--config", type=Path, help="JSON settings over the preset, for every method")
    ap.add_argument("--cap-max", metavar="N|auto", help=CAP_MAX_HELP)
    ap.add_argument(
        "--jsgs-options",
        type=_json_arg,
        default={},
        help="JSON over method_options for jsgs, e.g. '{\"speed\": {\"cuda_graph\": false}}'",
    )
    ap.add_argument("--warmup", type=int, default=600, help="steps trained before the window [600]")
    ap.add_argument("--settle", type=int, default=2, help="resumed steps before the window (>= 1) [2]")
    ap.add_argument("--steps", type=int, default=50, help="steps in the measured window [50]")
    ap.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    ap.add_argument("--top", type=int, default=15, help="kernels in each difference table [15]")
    ap.add_argument(
        "--python-top", type=int, default=0,
        help="also resume a copy under cProfile and list this many functions by self time [0: no]",
    )  # fmt: skip
    ap.add_argument(
        "--trace", type=Path,
        help="write each method's Chrome trace of the profiled window (with Python stacks) into this folder",
    )  # fmt: skip
    ap.add_argument(
        "--pairs", type=int, default=0,
        help="then resume each method's checkpoint this many more times, interleaved, and report medians [0]",
    )  # fmt: skip
    ap.add_argument(
        "--no-fresh", dest="fresh", action="store_false",
        help="skip the check run trained from step 0 (it costs another --warmup steps per method)",
    )  # fmt: skip
    ap.add_argument(
        "--memory-history", type=int, default=0, metavar="N",
        help="CUDA: then resume each method once more with the allocator's history recorded and list the N "
        "largest groups of live allocations at the window's start and peak by where they were made [0: no]",
    )  # fmt: skip
    ap.add_argument(
        "--memory-steps", type=int, help="steps of the --memory-history window [8, or --steps if fewer]"
    )  # fmt: skip
    ap.add_argument(
        "--memory-stacks", choices=["python", "all"], default="python",
        help="--memory-history's stacks: Python frames, or C++ too (names a backward's autograd node) "
        "[python]",
    )  # fmt: skip
    ap.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    ap.add_argument("--workdir", type=Path, help="the runs' temporary folder goes here [system's]")
    ap.add_argument("--out", type=Path, help="write the results as JSON here")
    args = ap.parse_args(argv)
    if args.warmup < 1 or args.settle < 1 or args.steps < 1 or args.top < 1:
        ap.error("--warmup, --settle, --steps and --top must be >= 1")
    if args.pairs < 0:
        ap.error(f"--pairs must be >= 0, got {args.pairs}")
    if args.memory_steps is None:
        args.memory_steps = min(8, args.steps)
    if args.memory_history < 0 or not 1 <= args.memory_steps <= args.steps:
        ap.error(
            f"--memory-history must be >= 0 and --memory-steps from 1 to --steps ({args.steps}), got "
            f"{args.memory_history} and {args.memory_steps}"
        )
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    if not methods or len(set(methods)) != len(methods):
        ap.error(f"--methods {args.methods!r}: give distinct method names")
    args.methods = ",".join(methods)
    return args


def base_config(args: argparse.Namespace) -> TrainConfig:
    """The settings every method starts from: ``--preset``, with an mcmc strategy the fixed budget of
    :data:`jsgs.train.config.MCMC_CAP_MAX` over it, ``--config`` over that and ``--cap-max`` over all
    (module docstring, "The budget"; :func:`bench_train_overhead.start_config`)."""
    return start_config(args.preset, args.config, args.cap_max)


def budget_doc(cfg: TrainConfig) -> dict[str, Any]:
    """The JSON's ``budget``: the strategy every method starts from and, for mcmc, its budget settings
    (``cap_max`` null where ``cap_max_auto`` chooses it per run, or another strategy has none)."""
    mcmc = cfg.strategy.type == "mcmc"
    auto = mcmc and cfg.strategy.cap_max_auto
    return {
        "strategy": cfg.strategy.type,
        "cap_max": cfg.strategy.cap_max if mcmc and not auto else None,
        "cap_max_auto": auto,
    }


def describe_budget(doc: dict[str, Any]) -> str:
    """The header's words for the budget the methods trained with (empty for a file without it)."""
    budget = doc.get("budget")
    if budget is None:
        return ""
    if budget["strategy"] != "mcmc":
        return f"; strategy {budget['strategy']}"
    if not budget["cap_max_auto"]:
        return f"; strategy mcmc, a fixed budget of {budget['cap_max']} Gaussians"
    chosen = sorted({r["cap_max"] for r in doc["results"].values()})
    return f"; strategy mcmc, the budget sized to the scene (--cap-max auto): {', '.join(map(str, chosen))}"


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Profile every method; returns the output document (jsgs/schemas/profile_step.schema.json)."""
    if args.threads:
        torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    base = base_config(args)
    methods = args.methods.split(",")
    iterations = args.warmup + args.settle + args.steps + 1
    results: dict[str, dict[str, Any]] = {}
    stats: dict[str, WindowStats] = {}
    if args.workdir:
        args.workdir.mkdir(parents=True, exist_ok=True)
    if args.trace:
        args.trace.mkdir(parents=True, exist_ok=True)
    with RECORDINGS.installed(), tempfile.TemporaryDirectory(prefix="profile_step.", dir=args.workdir) as tmp:
        work = Path(tmp)
        if args.manifest is None:
            w, h = (int(v) for v in args.size.lower().split("x"))
            manifest = build_scene(work / "synthetic", (w, h), args.views)
        else:
            manifest = args.manifest
        for m in methods:
            opts = {**base.method_options, **args.jsgs_options} if m == "jsgs" else dict(base.method_options)
            cfg = variant_config(base, m, opts, iterations, str(device))
            cfg.checkpoint_every = 0  # nothing but training inside the window
            results[m], stats[m] = profile_method(
                manifest,
                work / m,
                cfg,
                device,
                args.warmup,
                args.settle,
                args.steps,
                args.python_top,
                None if args.trace is None else args.trace / f"{m}.trace.json",
                args.fresh,
            )
            results[m]["kernels"] = kernel_rows(stats[m].kernels, args.steps, args.top)
        pairs = None
        if args.pairs > 0:
            windows, pairs = interleaved_windows(
                manifest, work, methods, device, args.settle, args.steps, args.pairs
            )
            peaks, starts = _per_kind(windows, "peak"), _per_kind(windows, "start")
            for m in methods:
                results[m]["paired_wall_ms_per_step"] = [w.ms_per_step for w in windows[m]]
                for k in MEMORY_KINDS:
                    p, s0 = peaks[m], starts[m]
                    results[m][f"paired_peak_memory_{k}_bytes"] = None if p is None else p[k]
                    results[m][f"paired_start_memory_{k}_bytes"] = None if s0 is None else s0[k]
        doc = document(args, manifest, device, results, stats, pairs)
        if args.memory_history > 0 and device.type != "cuda":
            print("note: profile_step: --memory-history: CUDA only; not recorded", file=sys.stderr)
        elif args.memory_history > 0:  # the rest first: a history that does not finish loses nothing else
            report(doc, args)
            doc["memory_history"] = memory_histories(manifest, work, methods, device, args.settle, args)
    return doc


def document(
    args: argparse.Namespace, manifest: Path | str, device: torch.device, results: dict[str, dict[str, Any]],
    stats: dict[str, WindowStats], pairs: dict[str, Any] | None,
) -> dict[str, Any]:  # fmt: skip
    """The output document of the profiles and the pairs: every method's kernels against the first's."""
    methods = list(results)
    baseline = methods[0]
    differences = {}
    for m in methods[1:]:
        diff = kernel_difference(stats[m].kernels, stats[baseline].kernels, args.steps, args.top)
        differences[m] = {"baseline": baseline, **diff}
    return (
        report_header(FORMAT, FORMAT_VERSION, args, manifest, str(device))
        | {
            "warmup": args.warmup,
            "settle": args.settle,
            "steps": args.steps,
            "budget": budget_doc(base_config(args)),
            "results": results,
            "differences": differences,
        }
        | ({"pairs": pairs} if pairs is not None else {})
    )


def report(doc: dict[str, Any], args: argparse.Namespace) -> None:
    """Print the profiles' tables and write the document (``--out``)."""
    print_report(doc)
    print_pairs(doc)
    print_python(doc)
    if args.out:
        write_json_checked(args.out, doc, "profile_step")


@reports_user_errors
def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    doc = run(args)
    if "memory_history" not in doc:
        report(doc, args)
        return 0
    print_memory_history(doc)  # the rest was reported before the history was recorded (run)
    if args.out:
        write_json_checked(args.out, doc, "profile_step")
    return 0


if __name__ == "__main__":
    sys.exit(main())
