"""One scene on several processes (torch.distributed): data parallel over the training views.

Launched by ``torchrun --nproc-per-node N -m jsgs.cli train ...`` or by ``jsgs train --gpus N`` /
``--processes N`` (:mod:`jsgs.train.launch`); the processes find each other through torchrun's environment
variables (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR``, ``MASTER_PORT``). Without them a run
has one process and nothing here communicates.

How a step is shared (replicated Gaussians, DDP-style):

- every process holds all the Gaussians, the optimizers and the strategy's state, and keeps them identical
  to the others': same seed, same view sampler (each step draws ``world_size`` views, rank r renders the
  r-th), same random draws in the same order (MCMC's relocation and noise use the global generator), and
  the same averaged gradients;
- each process renders its own view and computes that view's loss, with the method's per-view terms (JSGS's
  JO, DS and Gaussian Controller) on the process that renders the view;
- the gradients (and two flags: the view was empty, a stop was requested) are summed over the processes in
  one all-reduce and divided by ``world_size``; the learning rates follow gsplat's batch rule for a batch of
  ``world_size`` views (lr·√B, eps/√B, betas 1 − B(1 − β));
- DefaultStrategy's per-Gaussian statistics (screen-space gradient sums, counts, largest radii) are reduced
  over the processes every step, so every process densifies and prunes the same Gaussians;
- the logged values of every view are gathered to every process (NaN/Inf stops all of them alike);
- rank 0 alone evaluates, writes the run folder (config.json, metrics.json, checkpoints, renders, PLY) and
  holds its lock; the others only read (resume reads the same checkpoint on every process).

Errors: a setting or input error found while setting up on any process stops every process with that
process's one-line message (:func:`agree`); a process that dies later makes the others' next collective
fail, which stops them with :class:`PeerStopped`.
"""

from __future__ import annotations

import datetime
import math
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from jsgs.base.errors import JsgsError
from jsgs.train.launch import PEER_PREFIX

#: torchrun's variables this module reads
ENV_VARS = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
#: how long a collective waits for a process that neither answers nor exits (evaluation and checkpoints on
#: rank 0 keep the others waiting that long at most)
TIMEOUT = datetime.timedelta(minutes=30)


class PeerStopped(JsgsError):
    """Another process of the run stopped (an error, a kill): this one stops too."""


@dataclass
class World:
    """This process's place in the run: ``rank`` of ``size`` processes, ``local_rank`` on its machine."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def _env_int(name: str, default: int) -> int:
    raw = os.environ.get(name)
    if raw is None or raw == "":
        return default
    try:
        return int(raw)
    except ValueError:
        raise JsgsError(f"environment variable {name}: expected an integer (got {raw!r})") from None


def world_from_environment() -> World:
    """The process's rank and the run's size from torchrun's variables (one process when unset)."""
    size = _env_int("WORLD_SIZE", 1)
    rank = _env_int("RANK", 0)
    local = _env_int("LOCAL_RANK", rank)
    if size < 1 or not 0 <= rank < size:
        raise JsgsError(
            f"environment variables RANK={rank}, WORLD_SIZE={size}: RANK must lie in 0..WORLD_SIZE-1"
        )
    if size > 1:
        missing = [v for v in ("MASTER_ADDR", "MASTER_PORT") if not os.environ.get(v)]
        if missing:
            raise JsgsError(
                f"environment variable {missing[0]} is not set: start a run on several processes with "
                "torchrun or `jsgs train --gpus N`"
            )
    return World(rank, size, local)


def is_main_process() -> bool:
    """Whether this process is rank 0 of its run (or alone)."""
    return world_from_environment().is_main


def start(world: World, use_cuda: bool) -> None:
    """Join the process group (NCCL with one GPU per process, ``cuda:LOCAL_RANK``; gloo on the CPU)."""
    import torch.distributed as dist

    if not world.enabled or dist.is_initialized():
        return
    if use_cuda:
        if world.local_rank >= torch.cuda.device_count():
            raise JsgsError(
                f"LOCAL_RANK {world.local_rank}: this machine has {torch.cuda.device_count()} GPU(s); "
                "start at most that many processes per machine"
            )
        torch.cuda.set_device(world.local_rank)
    try:
        dist.init_process_group(
            backend="nccl" if use_cuda else "gloo", rank=world.rank, world_size=world.size, timeout=TIMEOUT
        )
    except (RuntimeError, ValueError) as e:
        raise JsgsError(f"cannot join the run's other processes ({_first_line(e)})") from None


def stop() -> None:
    """Leave the process group (at the end of a run)."""
    import torch.distributed as dist

    if dist.is_initialized():
        dist.destroy_process_group()


def local_device(world: World, device: torch.device) -> torch.device:
    """``cuda`` as this process's own GPU (``cuda:LOCAL_RANK``, made current by :func:`start`)."""
    if world.enabled and device.type == "cuda":
        return torch.device("cuda", torch.cuda.current_device())
    return device


def align_cuda_rng(world: World, rng: dict[str, Any], device: torch.device) -> None:
    """On resume: give this process's GPU generator the state of rank 0's GPU (``rng["cuda"][0]``, what the
    checkpoint's writer drew from), so that every process draws the same numbers again."""
    if world.enabled and device.type == "cuda" and rng.get("cuda"):
        torch.cuda.set_rng_state(rng["cuda"][0], device=device)


def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return text[0] if text else type(e).__name__


@contextmanager
def collective(what: str) -> Iterator[None]:
    """Turn the failure of a collective (another process died or stopped) into :class:`PeerStopped`."""
    try:
        yield
    except PeerStopped:
        raise
    except (RuntimeError, ConnectionError, ValueError) as e:
        raise PeerStopped(f"{PEER_PREFIX} during {what} ({_first_line(e)})") from None


def agree(world: World, error: JsgsError | None) -> None:
    """Every process reports whether it failed (``error``); when one did, every process raises: the failing
    ones their own error, the others :class:`PeerStopped` with the lowest failing rank's message."""
    if not world.enabled:
        if error is not None:
            raise error
        return
    import torch.distributed as dist

    reports: list[Any] = [None] * world.size
    with collective("setup"):
        dist.all_gather_object(reports, None if error is None else str(error))
    if error is not None:
        raise error
    for rank, message in enumerate(reports):
        if message is not None:
            raise PeerStopped(f"{PEER_PREFIX}: rank {rank}: {message}")


def gather(world: World, obj: Any) -> list[Any]:
    """``obj`` of every process, by rank (a small picklable value)."""
    if not world.enabled:
        return [obj]
    import torch.distributed as dist

    out: list[Any] = [None] * world.size
    with collective("a training step"):
        dist.all_gather_object(out, obj)
    return out


def pick_view(world: World, draw: Callable[[], int]) -> int:
    """The view index of this process for the step: ``world_size`` draws of the shared sampler, the
    ``rank``-th of them (one draw, as on one process, when alone)."""
    picks = [draw() for _ in range(world.size)]
    return picks[world.rank]


def scale_optimizers(optimizers: dict[str, torch.optim.Optimizer], batch: int) -> None:
    """gsplat's rule for a batch of ``batch`` views (simple_trainer with world_size): lr·√B, eps/√B, betas
    1 − B(1 − β). Call before the schedulers are made (they start from these learning rates)."""
    if batch == 1:
        return
    root = math.sqrt(batch)
    for opt in optimizers.values():
        for group in opt.param_groups:
            group["lr"] = group["lr"] * root
            group["eps"] = group["eps"] / root
            b1, b2 = group["betas"]
            group["betas"] = (max(0.0, 1.0 - batch * (1.0 - b1)), max(0.0, 1.0 - batch * (1.0 - b2)))
            if "initial_lr" in group:
                group["initial_lr"] = group["initial_lr"] * root


@dataclass
class StepFlags:
    """What every process learns from the others in the gradient all-reduce."""

    rendered: int  # processes whose view reached a Gaussian (gradients were summed over these)
    stop: str | None  # a stop signal some process received ("SIGTERM to rank 1"), else None


def average_gradients(
    world: World, params: list[Tensor], rendered: bool, signal_name: str | None
) -> StepFlags:
    """Sum every parameter's gradient over the processes and divide by ``world_size`` (a process whose view
    was empty adds zeros), in one all-reduce with the flags (the view was empty; the stop signal this
    process received, ``signal_name``, by rank). When no process rendered anything the gradients stay
    None, as on one process."""
    import signal

    if not world.enabled:
        return StepFlags(int(rendered), signal_name)
    import torch.distributed as dist

    device = params[0].device
    flat = [
        (p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1).float() for p in params
    ]
    flags = torch.zeros(1 + world.size, device=device)
    flags[0] = float(rendered)
    if signal_name is not None:
        flags[1 + world.rank] = float(signal.Signals[signal_name].value)
    buf = torch.cat([*flat, flags])
    with collective("the gradient all-reduce"):
        dist.all_reduce(buf)
    tail = buf[-(1 + world.size) :].tolist()
    n_rendered = int(round(tail[0]))
    stop = next(
        (f"{signal.Signals(int(v)).name} to rank {r}" for r, v in enumerate(tail[1:]) if v > 0), None
    )
    if n_rendered == 0:
        for p in params:
            p.grad = None
        return StepFlags(0, stop)
    buf = buf[: -(1 + world.size)].div_(world.size)
    offset = 0
    for p in params:
        n = p.numel()
        p.grad = buf[offset : offset + n].view_as(p).to(p.dtype)
        offset += n
    return StepFlags(n_rendered, stop)


def share_strategy_statistics(strategy: Any, world: World) -> None:
    """Make gsplat's DefaultStrategy reduce its per-Gaussian statistics over the processes every step: the
    view's own contributions (gradient norm sums, counts, largest normalised radii) are computed as gsplat
    does into a fresh state, then summed (radii: the maximum) over the processes and added to the running
    state, which therefore stays identical on every process. A process whose view was empty contributes
    zeros. MCMCStrategy keeps no per-view statistics: nothing to do."""
    if not world.enabled or strategy.type != "default":
        return
    import torch.distributed as dist

    gs = strategy.gsplat
    own_update = gs._update_state

    def update_state(params: Any, state: dict[str, Any], info: dict[str, Any], packed: bool = False) -> None:
        n = len(params["means"])
        device = params["means"].device
        fresh: dict[str, Any] = {"grad2d": None, "count": None, "radii": None}
        grad_key = info.get(gs.key_for_gradient)
        if grad_key is not None and grad_key.grad is not None:
            own_update(params, fresh, info, packed=packed)
        zeros = torch.zeros(n, device=device)
        sums = torch.stack([
            fresh["grad2d"] if fresh["grad2d"] is not None else zeros,
            fresh["count"] if fresh["count"] is not None else zeros,
        ])  # fmt: skip
        with collective("the strategy's statistics"):
            dist.all_reduce(sums)
        for i, key in enumerate(("grad2d", "count")):
            if state[key] is None:
                state[key] = torch.zeros(n, device=device)
            state[key] += sums[i]
        if gs.refine_scale2d_stop_iter > 0:
            radii = fresh["radii"] if fresh["radii"] is not None else zeros.clone()
            with collective("the strategy's statistics"):
                dist.all_reduce(radii, op=dist.ReduceOp.MAX)
            if state["radii"] is None:
                state["radii"] = torch.zeros(n, device=device)
            state["radii"] = torch.maximum(state["radii"], radii)

    gs._update_state = update_state


def check_replicas(world: World, params: list[Tensor], step: int) -> None:
    """Every process must hold the same Gaussians (checked at checkpoints: counts and a checksum)."""
    if not world.enabled:
        return
    import torch.distributed as dist

    with torch.no_grad():
        parts = [torch.tensor(float(params[0].shape[0]), device=params[0].device)]
        parts += [p.detach().double().sum().reshape(()) for p in params]
        parts += [p.detach().double().abs().sum().reshape(()) for p in params]
        mine = torch.stack([x.double() for x in parts])
    everyone = [torch.empty_like(mine) for _ in range(world.size)]
    with collective("the replica check"):
        dist.all_gather(everyone, mine)
    for rank, theirs in enumerate(everyone):
        if not torch.equal(theirs, mine):
            raise JsgsError(
                f"after step {step}: the Gaussians of rank {rank} differ from those of rank {world.rank} "
                "(the processes' updates were not identical); the run stops, its last checkpoint is good"
            )


def barrier(world: World, what: str) -> None:
    if not world.enabled:
        return
    import torch.distributed as dist

    with collective(what):
        dist.barrier()
