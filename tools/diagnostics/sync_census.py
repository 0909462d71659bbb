"""Where the host-device synchronisations of a training step come from (CUDA only).

    python3 tools/diagnostics/sync_census.py --manifest DATA/manifest.json [--methods gsplat,jsgs] \
        [--start 650]
        [--steps 20]

Trains each method from scratch to step ``--start`` and then turns on
``torch.cuda.set_sync_debug_mode("warn")`` for ``--steps`` steps. Every synchronising call is counted under
its innermost four frames in jsgs or gsplat. Prints, per method, the syncs per step and their call sites.
A sync stops the host from running ahead of the GPU, so every one on the step's path shows in its wall time.
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import traceback
import warnings
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench_train_overhead import variant_config  # noqa: E402
from profile_step import StepCallback  # noqa: E402

from jsgs.train.config import TrainConfig  # noqa: E402
from jsgs.train.trainer import train  # noqa: E402


def census(manifest: Path, method: str, start: int, steps: int) -> collections.Counter[str]:
    """Call site -> number of synchronising calls over the window."""
    counts: collections.Counter[str] = collections.Counter()
    calls = [0]

    def record(message: Any, *_: Any, **__: Any) -> None:
        if "synchroniz" not in str(message):
            return
        ours = ("/jsgs/", "gsplat")
        frames = [f for f in traceback.extract_stack()[:-1] if any(o in f.filename for o in ours)]
        counts[" <- ".join(f"{Path(f.filename).name}:{f.lineno}" for f in reversed(frames[-4:]))] += 1

    def tick() -> None:  # called at the start of every step
        calls[0] += 1
        if calls[0] == start + 1:
            torch.cuda.set_sync_debug_mode("warn")
        elif calls[0] == start + steps + 1:
            torch.cuda.set_sync_debug_mode("default")

    cfg = variant_config(TrainConfig.from_preset("paper"), method, {}, start + steps + 1, "cuda")
    cfg.checkpoint_every = 0
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = record
        train(
            manifest, Path(tmp) / "run", cfg, force=True, progress=False, log=lambda _: None,
            callbacks=[StepCallback(tick)],
        )  # fmt: skip
    return counts


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--manifest", type=Path, required=True)
    ap.add_argument("--methods", default="gsplat,jsgs")
    ap.add_argument("--start", type=int, default=650, help="steps trained before the window [650]")
    ap.add_argument("--steps", type=int, default=20, help="steps in the window [20]")
    a = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("error: sync_census needs CUDA (host syncs are a GPU matter)", file=sys.stderr)
        return 1
    for method in a.methods.split(","):
        counts = census(a.manifest, method, a.start, a.steps)
        print(f"\n{method}: syncs per step over {a.steps} steps from step {a.start}: "
              f"{sum(counts.values()) / a.steps:.2f}")
        for site, n in counts.most_common():
            print(f"  {n / a.steps:5.2f}  {site}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
