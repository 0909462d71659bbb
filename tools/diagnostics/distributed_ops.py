"""What one ordinary training step costs on N processes beyond one process, counted on the CPU (gloo, the
torch exchange): the aten ops per step (1 process against N, by op name) and every collective of the step
with the bytes it hands to the process group, also per Gaussian of the run.

    PYTHONPATH=. .venv/bin/python tools/diagnostics/distributed_ops.py --manifest DATA/manifest.json \
        [--method gsplat] [--processes 2] [--cap 200] [--steps 12]

Trains the method on the `mcmc` preset with `strategy.cap_max` = ``--cap`` and the SH degree raised every
step (so degree 3 from the fourth step: the exchange's full width) and counts the steps from the seventh on
that are not refinement steps. An aten op on a GPU costs the host a few microseconds whether or not it
launches a kernel (views, slices); the collectives' bytes are those of the call (an all-gather's input, a
reduce-scatter's input, an all-reduce's tensor), which NCCL's ring moves (N − 1)/N of (an all-reduce twice
that). Gaussians in this run: every process's; the bytes per Gaussian scale to any model size.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import socket
import sys
import tempfile
from pathlib import Path
from typing import Any

import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))


class OpCount(TorchDispatchMode):
    """Every aten op dispatched on this thread, by name."""

    def __init__(self) -> None:
        super().__init__()
        self.ops: collections.Counter[str] = collections.Counter()

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        self.ops[str(func.overloadpacket.__name__)] += 1
        return func(*args, **(kwargs or {}))


def _worker(rank: int, world: int, port: int, args: argparse.Namespace, out: str) -> None:
    torch.set_num_threads(1)
    if world > 1:
        os.environ.update(RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE=str(world),
                          MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))  # fmt: skip
    import torch.distributed as dist

    from jsgs.train import distributed as dd
    from jsgs.train.config import TrainConfig
    from jsgs.train.trainer import Trainer

    cfg = TrainConfig.from_preset("mcmc", device="cpu", method=args.method, iterations=args.steps, eval_at=[])
    cfg.strategy.cap_max, cfg.strategy.cap_max_auto = args.cap, False
    cfg.render.sh_degree_interval = 1
    trainer = Trainer(Path(args.manifest), Path(out) / f"run{world}", cfg, log=lambda s: None)
    trainer.setup()
    calls: list[tuple[str, int]] = []
    own = {"all_gather": dd._all_gather_tensor, "reduce_scatter": dd._reduce_scatter_tensor,
           "all_reduce": dist.all_reduce}  # fmt: skip

    def counted(name: str, pick: int) -> Any:
        def call(*a: Any, **k: Any) -> Any:
            calls.append((name, a[pick].numel() * a[pick].element_size()))
            return own[name](*a, **k)

        return call

    ops: collections.Counter[str] = collections.Counter()
    collectives: collections.Counter[str] = collections.Counter()
    counted_steps, gaussians = 0, 0
    for step in range(args.steps):
        calls.clear()
        dd._all_gather_tensor = counted("all_gather", 1)
        dd._reduce_scatter_tensor = counted("reduce_scatter", 1)
        dist.all_reduce = counted("all_reduce", 0)
        try:
            with OpCount() as count:
                trainer.step(step)
        finally:
            dd._all_gather_tensor, dd._reduce_scatter_tensor = own["all_gather"], own["reduce_scatter"]
            dist.all_reduce = own["all_reduce"]
        if step >= 6 and not trainer.strategy.may_change_count(step):
            counted_steps += 1
            ops.update(count.ops)
            for name, size in calls:
                collectives[f"{name} {size}"] += 1
            gaussians = trainer.num_gaussians()
    if rank == 0:
        doc = {"steps": counted_steps, "gaussians": gaussians, "ops": dict(ops),
               "collectives": dict(collectives)}  # fmt: skip
        (Path(out) / f"counts{world}.json").write_text(json.dumps(doc))
    if trainer.lock is not None:
        trainer.lock.release()
    if world > 1:
        dist.barrier()
        os._exit(0)  # (as the several-process tests: gloo's threads and the interpreter's teardown)


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Both runs' counts per counted step: {1: ..., N: ...} (the N processes started as this script's
    ``--rank`` workers)."""
    import subprocess

    with tempfile.TemporaryDirectory() as out:
        _worker(0, 1, 0, args, out)
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        common = [sys.executable, __file__, "--manifest", args.manifest, "--method", args.method,
                  "--processes", str(args.processes), "--cap", str(args.cap), "--steps", str(args.steps),
                  "--port", str(port), "--out", out]  # fmt: skip
        procs = [subprocess.Popen([*common, "--rank", str(r)]) for r in range(args.processes)]
        if any(proc.wait(timeout=600) != 0 for proc in procs):
            raise RuntimeError("a counting process failed (its error is above)")
        docs = {w: json.loads((Path(out) / f"counts{w}.json").read_text()) for w in (1, args.processes)}
    for doc in docs.values():
        n = doc["steps"]
        doc["ops"] = {k: v / n for k, v in doc["ops"].items()}
        doc["collectives"] = {k: v / n for k, v in doc["collectives"].items()}
    return docs


def report(docs: dict[int, dict[str, Any]]) -> str:
    one, many = docs[1], docs[max(docs)]
    n = max(docs)
    extra = {k: many["ops"].get(k, 0.0) - one["ops"].get(k, 0.0) for k in set(one["ops"]) | set(many["ops"])}
    ranked = sorted(extra.items(), key=lambda kv: -kv[1])
    lines = [
        f"aten ops per ordinary step: {sum(one['ops'].values()):.1f} on 1 process, "
        f"{sum(many['ops'].values()):.1f} on {n} ({sum(extra.values()):+.1f}; {one['steps']} and "
        f"{many['steps']} steps counted)",
        "extra ops by name: "
        + ", ".join(f"{k} {v:+.1f}" for k, v in ranked if abs(v) >= 0.5),
        f"collectives per ordinary step on {n} processes ({many['gaussians']} Gaussians in all):",
    ]
    for key, times in sorted(many["collectives"].items()):
        name, size = key.rsplit(" ", 1)
        per = int(size) / many["gaussians"]
        lines.append(f"  {name}: {times:.1f} x {int(size)} B ({per:.1f} B per Gaussian)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--manifest", required=True)
    p.add_argument("--method", default="gsplat", choices=("gsplat", "jsgs"))
    p.add_argument("--processes", type=int, default=2)
    p.add_argument("--cap", type=int, default=200, help="strategy.cap_max")
    p.add_argument("--steps", type=int, default=12)
    p.add_argument("--rank", type=int, default=None, help=argparse.SUPPRESS)  # one of measure's processes
    p.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--out", default="", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.rank is not None:
        _worker(args.rank, args.processes, args.port, args, args.out)
        return
    if args.processes < 2 or args.steps < 8:
        sys.exit("--processes must be at least 2 and --steps at least 8")
    print(report(measure(args)))


if __name__ == "__main__":
    main()
