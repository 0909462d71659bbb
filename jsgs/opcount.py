"""Counting the kernels a piece of torch code launches, on any device.

At the image sizes of real scenes (504 x 378) the JSGS terms are launch-bound on a GPU: each eager op costs
10-20 µs of host dispatch and launch, far more than its arithmetic. The number of kernels is then the cost
model, and it is the same on the CPU as on the GPU, so it can be measured and tested without a GPU.

:class:`KernelCounter` counts the aten ops dispatched inside it that produce new data (views, detaches and
aliases are free: they launch nothing). Ops that autograd runs in the backward are counted when the backward
runs inside the counter on the same thread (always on CPU).
"""

from __future__ import annotations

from collections import Counter
from typing import Any

from torch.utils._python_dispatch import TorchDispatchMode

#: aten ops that are not views by schema but launch no kernel either.
FREE_OPS = frozenset({"aten.detach", "aten._unsafe_view", "aten.t", "aten.lift_fresh", "aten.alias"})


class KernelCounter(TorchDispatchMode):
    """``with KernelCounter() as k: ...`` then ``k.total`` (kernels) and ``k.ops`` (Counter by aten op)."""

    def __init__(self) -> None:
        super().__init__()
        self.ops: Counter[str] = Counter()

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        name = str(func.overloadpacket)
        if not func.is_view and name not in FREE_OPS:
            self.ops[name] += 1
        return func(*args, **(kwargs or {}))

    @property
    def total(self) -> int:
        return sum(self.ops.values())
