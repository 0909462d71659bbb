"""Per-phase wall time of training steps, device-synchronised at each phase boundary, and on CUDA each phase's
peak allocated device memory."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import torch

from jsgs.train.evaluate import reset_peak_allocated, synchronize


class Profiler:
    """Per-phase wall time (ms per step), device-synchronised at each phase boundary; a no-op unless enabled
    (synchronising every phase slows the GPU pipeline, so it is off for measured runs).

    With ``memory`` on a CUDA device it also keeps each phase's peak of ``torch.cuda.max_memory_allocated``
    over the steps (:meth:`peak_memory`: which part of a step holds the most): the device's peak statistics
    are reset as a phase begins and read as it ends (for a phase inside another, the outer one's peak is the
    larger of its own and the inner one's; :func:`jsgs.train.evaluate.peak_memory` still reports the
    run's). The trainer's profiler has it on; a method's own (nested in the trainer's phases) leaves it off,
    so the trainer's figures stay whole."""

    def __init__(self, enabled: bool, device: torch.device, memory: bool = False) -> None:
        self.enabled = enabled
        self.device = device
        self.memory = memory
        self.totals: dict[str, float] = {}
        self.peaks: dict[str, int] = {}
        self._open: list[int] = []  # the running peak of each phase now open, outermost first
        self.steps = 0

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        if not self.enabled:
            yield
            return
        synchronize(self.device)
        memory = self.memory and self.device.type == "cuda"
        if memory:
            self._enter()
        t0 = time.perf_counter()
        yield
        synchronize(self.device)
        self.totals[name] = self.totals.get(name, 0.0) + time.perf_counter() - t0
        if memory:
            peak = self._exit()
            self.peaks[name] = max(self.peaks.get(name, 0), peak)

    def _enter(self) -> None:
        so_far = int(torch.cuda.max_memory_allocated(self.device))
        self._open = [max(p, so_far) for p in self._open]
        reset_peak_allocated(self.device)
        self._open.append(int(torch.cuda.memory_allocated(self.device)))

    def _exit(self) -> int:
        peak = max(self._open.pop(), int(torch.cuda.max_memory_allocated(self.device)))
        self._open = [max(p, peak) for p in self._open]
        reset_peak_allocated(self.device)
        return peak

    def summary(self) -> dict[str, float] | None:
        if not self.enabled or self.steps == 0:
            return None
        return {k: 1000.0 * v / self.steps for k, v in self.totals.items()}

    def peak_memory(self) -> dict[str, int] | None:
        """Each phase's peak allocated device memory in bytes, the largest over the profiled steps; None
        unless profiling with ``memory`` on a CUDA device."""
        if not self.enabled or self.steps == 0 or not self.peaks:
            return None
        return dict(self.peaks)
