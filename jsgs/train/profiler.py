"""Per-phase wall time of training steps, device-synchronised at each phase boundary."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import torch

from jsgs.train.evaluate import synchronize


class Profiler:
    """Per-phase wall time (ms per step), device-synchronised at each phase boundary; a no-op unless enabled
    (synchronising every phase slows the GPU pipeline, so it is off for measured runs)."""

    def __init__(self, enabled: bool, device: torch.device) -> None:
        self.enabled = enabled
        self.device = device
        self.totals: dict[str, float] = {}
        self.steps = 0

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        if not self.enabled:
            yield
            return
        synchronize(self.device)
        t0 = time.perf_counter()
        yield
        synchronize(self.device)
        self.totals[name] = self.totals.get(name, 0.0) + time.perf_counter() - t0

    def summary(self) -> dict[str, float] | None:
        if not self.enabled or self.steps == 0:
            return None
        return {k: 1000.0 * v / self.steps for k, v in self.totals.items()}
