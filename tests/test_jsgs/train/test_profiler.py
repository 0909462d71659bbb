"""The trainer's phase profiler: each phase's peak allocated device memory on CUDA (a phase inside another
counts in both), over steps, without losing the run's peak that evaluation reports. torch's CUDA memory
statistics are replaced by a model allocator, so this runs on the CPU."""

from __future__ import annotations

from typing import Any

import pytest
import torch

import jsgs.train.evaluate as evaluate_module
import jsgs.train.profiler as profiler_module
from jsgs.train.profiler import Profiler


class _Allocator:
    """torch.cuda's allocated-memory statistics: ``current`` bytes and their peak since the last reset."""

    def __init__(self, start: int) -> None:
        self.current = self.peak = start

    def alloc(self, n: int) -> None:
        self.current += n
        self.peak = max(self.peak, self.current)

    def free(self, n: int) -> None:
        self.current -= n

    def reset(self, device: Any = None) -> None:
        self.peak = self.current


@pytest.fixture
def allocator(monkeypatch: pytest.MonkeyPatch) -> _Allocator:
    a = _Allocator(1000)
    monkeypatch.setattr(torch.cuda, "memory_allocated", lambda device=None: a.current)
    monkeypatch.setattr(torch.cuda, "max_memory_allocated", lambda device=None: a.peak)
    monkeypatch.setattr(torch.cuda, "reset_peak_memory_stats", a.reset)
    monkeypatch.setattr(profiler_module, "synchronize", lambda device: None)
    monkeypatch.setattr(evaluate_module, "_EARLIER_PEAKS", {})
    return a


def test_each_phase_keeps_its_own_peak_over_the_steps(allocator: _Allocator) -> None:
    device = torch.device("cuda", 0)
    evaluate_module.reset_peak_allocated(device, forget=True)
    prof = Profiler(True, device, memory=True)
    for step, extra in enumerate([50, 80, 20]):
        allocator.alloc(300)  # before any phase: in no phase's peak, in the run's
        allocator.free(300)
        with prof.phase("loss"):
            allocator.alloc(10)
            with prof.phase("inner"):
                allocator.alloc(extra)
                allocator.free(extra)
            allocator.free(10)
        with prof.phase("backward"):
            allocator.alloc(5 + step)
            allocator.free(5 + step)
        prof.steps += 1
    assert prof.peak_memory() == {"inner": 1000 + 10 + 80, "loss": 1000 + 10 + 80, "backward": 1000 + 7}
    assert evaluate_module.peak_memory(device) == (1300, "cuda_max_allocated")
    # a profiler without memory (a method's own, inside the trainer's phases) leaves the statistics alone
    quiet = Profiler(True, device)
    allocator.alloc(40)
    with quiet.phase("jo"):
        allocator.free(40)
    quiet.steps += 1
    assert quiet.peak_memory() is None and allocator.peak == 1040


def test_no_peaks_unless_profiling_on_cuda(allocator: _Allocator) -> None:
    for prof in (
        Profiler(False, torch.device("cuda", 0), memory=True),
        Profiler(True, torch.device("cpu"), memory=True),
    ):
        with prof.phase("loss"):
            allocator.alloc(10)
        prof.steps += 1
        assert prof.peak_memory() is None
