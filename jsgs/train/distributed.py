"""One scene on several processes (torch.distributed): the Gaussians sharded, the views split.

Launched by ``torchrun --nproc-per-node N -m jsgs.cli train ...`` or by ``jsgs train --gpus N`` /
``--processes N`` (:mod:`jsgs.train.launch`); the processes find each other through torchrun's environment
variables (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR``, ``MASTER_PORT``). Without them a run
has one process and nothing here communicates.

How a step is shared (gsplat's simple_trainer with ``world_size``):

- each process owns a shard of the Gaussians (the initial points ``rank::world_size``) with its Adam state
  and its strategy state; the shards change size independently as the strategy grows and prunes them
  (every process holds every shard's size: gathered at setup and after each refinement step, the only
  steps that change them; :meth:`jsgs.train.strategy.Densifier.may_change_count`);
- each step draws ``world_size`` views from the shared sampler, rank r renders the r-th, from every
  Gaussian, and computes that view's loss with the method's per-view terms (JSGS's JO, DS and Gaussian
  Controller) on that process;
- the exchange: on CUDA, gsplat's ``rasterization(..., distributed=True)`` (non-packed: gsplat 1.5.3's
  packed distributed path tiles with the wrong image ids, :func:`jsgs.render.rasterize`) projects each
  shard on its owner for every process's camera, sends the projected Gaussians to the process that renders
  the camera and, in the backward, the gradients back to the owners; where that cannot render the run's views
  (the reference rasterizer, a method's extra channels, lens distortion, absgrad) the torch exchange does
  the same with whole parameters: every shard is gathered on every process (:func:`gather_gaussians`), each
  process's view's gradients over all of them are summed by a reduce-scatter that leaves each owner the
  sums of its own rows (:func:`reduce_gradients`). Either way a Gaussian's gradient is the mean over
  the step's views and the learning rates follow gsplat's batch rule for ``world_size`` views;
- per-Gaussian statistics reach the owner: DefaultStrategy's screen-space gradient sums, counts and radii
  (gsplat's projection runs on the owner, for every process's camera: :func:`per_camera_statistics`; the
  torch exchange sums them in the gradients' reduce-scatter, the radii's maximum in one of its own:
  :func:`share_strategy_statistics`)
  and the Gaussian Controller's (it runs on the view's process, over the gathered Gaussians, and its
  gradients travel back with the others);
- the strategies run per shard: DefaultStrategy densifies and prunes each shard on its own statistics,
  never to zero (:func:`keep_a_gaussian_per_shard`; neither exchange takes an empty shard);
  MCMCStrategy's global budget ``cap_max`` is split into shares (:func:`shard_cap`), each shard relocating
  and growing within its own, so the run's count never exceeds the budget;
- the logged values, the finiteness of every process's terms, gradients and parameters and the stop signals
  (Ctrl-C, SIGTERM) reach every process once per step and are read on the host once, after the optimizer's
  step is queued (:class:`StepGather`; a NaN or a signal anywhere stops all of them alike, after the same
  step): with the torch exchange in the gradients' reduce-scatter, which sums every process's row into
  every process's block (:meth:`StepGather.rider`), else in one all-gather of a tensor;
- rank 0 alone evaluates, writes the run folder (config.json, metrics.json, checkpoints, renders, PLY) and
  holds its lock: at each checkpoint point the shards (Gaussians, Adam moments, strategy sums, every
  process's generators) are gathered to it (:func:`merge_shards`) and written as one checkpoint in one
  process's layout with the shards' row counts; a resumed process reads its rows back
  (:func:`split_checkpoint`), on as many processes as the run had.

Errors: a setting or input error found while setting up on any process stops every process with that
process's one-line message (:func:`agree`); a process that dies later makes the others' next collective
fail, which stops them with :class:`PeerStopped`.
"""

from __future__ import annotations

import datetime
import math
import os
import struct
from collections.abc import Callable, Iterator, Sequence
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
    # on CUDA the group is bound to this process's GPU (its barriers and collectives use it, and torch
    # does not have to guess it)
    device_id = torch.device("cuda", world.local_rank) if use_cuda else None
    try:
        dist.init_process_group(
            backend="nccl" if use_cuda else "gloo", rank=world.rank, world_size=world.size, timeout=TIMEOUT,
            device_id=device_id,
        )  # fmt: skip
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


# -- the Gaussians' shards -------------------------------------------------------------------------------
#: DefaultStrategy's per-Gaussian running sums (the rest of a strategy's state is the same on every process)
PER_GAUSSIAN_STATE = ("grad2d", "count", "radii")


def shard_rows(n: int, world: World, where: str) -> Tensor:
    """The rows of ``n`` initial Gaussians this process owns: ``rank``, ``rank + size``, ... (gsplat's
    simple_trainer: ``points[world_rank::world_size]``), at least one on every process; fewer Gaussians than
    processes is a JsgsError naming ``where`` (a shard without Gaussians breaks both exchanges: gsplat
    1.5.3's distributed rasterisation and the torch exchange's gather, and never grows)."""
    if n < world.size:
        raise JsgsError(
            f"{where}: {n} initial Gaussian(s) cannot be shared by {world.size} processes (each needs at "
            f"least one); train on at most {n} process(es), or start from more points"
        )
    return torch.arange(n)[world.rank :: world.size]


def keep_a_gaussian_per_shard(strategy: Any, world: World) -> None:
    """DefaultStrategy on several processes prunes each shard on its own: a prune that would remove every
    Gaussian of this process's shard keeps its most opaque one (gsplat's pruning otherwise as it is), so
    no shard ever becomes empty (:func:`shard_rows`). That Gaussian's opacity is below ``prune_opa``
    (0.005 by default) or it is too large: it may grow again like any other. MCMCStrategy never removes
    Gaussians. This strategy object's prune step is wrapped (:func:`_prune_mask`, then gsplat's public
    ``remove``); gsplat's modules are left as they are."""
    if not world.enabled or strategy.type != "default":
        return
    from gsplat.strategy.ops import remove

    own_prune = strategy.gsplat._prune_gs

    def prune_gs(params: Any, optimizers: Any, state: dict[str, Any], step: int) -> int:
        mask = _prune_mask(own_prune, params, state, step)
        if mask.numel() > 0 and bool(mask.all()):
            mask[torch.argmax(params["opacities"].detach().flatten())] = False
        n_prune = int(mask.sum())
        if n_prune > 0:
            remove(params=params, optimizers=optimizers, state=state, mask=mask)
        return n_prune

    strategy.gsplat._prune_gs = prune_gs


#: the key of each Gaussian's row index in :func:`_prune_mask`'s stand-in state
_ROW = "jsgs_row"


def _prune_mask(prune: Any, params: Any, state: dict[str, Any], step: int) -> Tensor:
    """The rows gsplat's ``DefaultStrategy._prune_gs`` (``prune``, the bound method) removes at ``step``,
    found by running that method itself on stand-ins, so its rule is gsplat's own: the opacities and scales
    it reads (detached, without optimizers; its ``remove`` makes new tensors, the model's are untouched) and
    a shallow copy of the running state with each row's index added, which ``remove`` cuts like the others;
    the rows whose index is left are those it keeps."""
    opacities = params["opacities"]
    rows = torch.arange(opacities.shape[0], device=opacities.device)
    stand_in = {name: params[name].detach() for name in ("opacities", "scales")}
    kept = {**state, _ROW: rows}
    prune(stand_in, {}, kept, step)
    mask = torch.ones_like(rows, dtype=torch.bool)
    mask[kept[_ROW]] = False
    return mask


def shard_cap(cap: int, world: World) -> int:
    """This process's share of a global Gaussian budget (the shares sum to ``cap``)."""
    return cap // world.size + (1 if world.rank < cap % world.size else 0)


def _dist() -> Any:
    import torch.distributed as dist

    return dist


def _all_gather_tensor(out: Tensor, tensor: Tensor) -> None:
    """Every process's ``tensor`` (of one size) into ``out``, concatenated by rank along the first dimension:
    one collective (torch ≥ 2.13's ``all_gather_single``; ``all_gather_into_tensor`` before it)."""
    dist = _dist()
    gather_single = getattr(dist, "all_gather_single", None) or dist.all_gather_into_tensor
    gather_single(out, tensor)


def _reduce_scatter_tensor(out: Tensor, tensor: Tensor) -> None:
    """``out`` = this process's block of the sum of every process's ``tensor`` (``world_size`` equal blocks,
    by rank): one reduce-scatter, which moves half the bytes of an all-reduce of ``tensor``. NCCL has one;
    gloo since torch 2.13 (``reduce_scatter_single``); an older gloo all-reduces ``tensor`` in place and
    copies the block out (the same sums)."""
    dist = _dist()
    scatter_single = getattr(dist, "reduce_scatter_single", None)
    if scatter_single is None and dist.get_backend() != "nccl":
        dist.all_reduce(tensor)
        out.copy_(tensor.view(dist.get_world_size(), -1)[dist.get_rank()])
        return
    (scatter_single or dist.reduce_scatter_tensor)(out, tensor)


def gather_sizes(world: World, n: int, device: torch.device) -> list[int]:
    """Every process's number of Gaussians, by rank."""
    if not world.enabled:
        return [n]
    mine = torch.full((1,), n, dtype=torch.int64, device=device)  # a fill: no host-to-device copy, no wait
    out = mine.new_empty(world.size)
    with collective("the Gaussians' exchange"):
        _all_gather_tensor(out, mine)
    return out.tolist()  # one host read


def gather_rows(world: World, tensors: Sequence[Tensor], sizes: Sequence[int]) -> list[Tensor]:
    """Each tensor's rows of every process, concatenated by rank (not differentiable): one all-gather for
    all of them (padded to the largest shard, as gloo and NCCL gather equal sizes)."""
    if not world.enabled:
        return [t.detach() for t in tensors]
    n = tensors[0].shape[0]
    widths = [math.prod(t.shape[1:]) for t in tensors]
    flat = torch.cat([t.detach().reshape(n, w).float() for t, w in zip(tensors, widths, strict=True)], dim=1)
    rows = max(sizes)
    if n < rows:
        flat = torch.cat([flat, flat.new_zeros(rows - n, flat.shape[1])])
    out = flat.new_empty(world.size * rows, flat.shape[1])
    with collective("the Gaussians' exchange"):
        _all_gather_tensor(out, flat.contiguous())
    if rows * world.size != sum(sizes):  # the padding's rows out
        out = torch.cat([o[:s] for o, s in zip(out.split(rows), sizes, strict=True)])
    parts = out.split(widths, dim=1)
    total = sum(sizes)
    return [
        p.reshape(total, *t.shape[1:]).to(t.dtype).contiguous() for p, t in zip(parts, tensors, strict=True)
    ]


@dataclass
class Exchange:
    """One step's Gaussians of every process on this one (the torch exchange): ``params`` are fresh leaves
    (their gradients are this process's view's contributions to every Gaussian), ``sizes`` the shards' row
    counts by rank."""

    params: torch.nn.ParameterDict
    names: list[str]  # the order of reduce_gradients' shard (a ParameterDict sorts its keys)
    sizes: list[int]
    rank: int
    #: every process's :meth:`StepGather.rider` row, [world_size, length], as the gradients' reduce-scatter
    #: delivered them (on the device, unread), where the step sent them with its gradients
    riders: Tensor | None = None

    @property
    def rows(self) -> tuple[int, int]:
        """This process's rows in the gathered set."""
        start = sum(self.sizes[: self.rank])
        return start, start + self.sizes[self.rank]


def gather_gaussians(
    world: World,
    shard: torch.nn.ParameterDict,
    names: Sequence[str],
    sizes: Sequence[int] | None = None,
    sh_degree: int | None = None,
) -> Exchange:
    """The torch exchange's forward: every process's shard on every process (gloo on the CPU, or NCCL where
    the step's render needs the whole set: a method's extra channels). Its backward is
    :func:`reduce_gradients` with ``exchange``. ``sizes``: every process's number of Gaussians, by rank,
    where the caller knows them (the trainer keeps them: :func:`gather_sizes` at setup and after a strategy
    step that may change them); without them they are gathered first (one more collective and a host
    read). ``sh_degree``: the step's SH degree, where known: ``shN``'s bands above it, which the render
    reads none of and whose gradients are zeros, are left out of the exchange both ways (the gathered
    ``shN`` holds (sh_degree + 1)² − 1 bands; 45 of a Gaussian's 59 values at degree 0, 36 at 1, 21 at 2)."""
    n = int(shard[names[0]].shape[0])
    if sizes is None:
        sizes = gather_sizes(world, n, shard[names[0]].device)
    elif len(sizes) != world.size or sizes[world.rank] != n:
        raise RuntimeError(f"internal error: shard sizes {list(sizes)} held, this process has {n} Gaussians")
    sizes = list(sizes)
    bands = None if sh_degree is None else (sh_degree + 1) ** 2 - 1
    full = gather_rows(world, [shard[n][:, :bands] if n == "shN" else shard[n] for n in names], sizes)
    params = torch.nn.ParameterDict({n: torch.nn.Parameter(t) for n, t in zip(names, full, strict=True)})
    return Exchange(params, list(names), sizes, world.rank)


def reduce_gradients(
    world: World,
    shard: Sequence[Tensor],
    rendered: bool,
    exchange: Exchange | None = None,
    also: Tensor | None = None,
    rider: Tensor | None = None,
) -> bool:
    """Each shard's gradient (``shard``: in the order of ``exchange.names``), the mean over the step's
    ``world_size`` views; returns whether some process's view reached a Gaussian (``rendered``: this
    one's).

    With the torch ``exchange`` the gradients of the gathered set (one view's each) are summed over the
    processes, with the count of the views that rendered and ``also`` (a float32 [K, N_gathered] tensor of
    the step: the strategy's statistics, :func:`share_strategy_statistics`), in one reduce-scatter, so
    that each process receives the sums of its own rows only (half the bytes of an all-reduce): the buffer
    is one row per Gaussian (its gradients, its ``also`` and this process's rendered flag, whose sum is the
    count), one concatenation, each process's rows padded to the largest shard. ``also``'s rows of this
    process are overwritten with their sums (its other rows keep this process's own values). When no
    process rendered anything the gradients stay None, as on one process. The count is read on the host (a
    wait for the collective) only by a process whose own view rendered nothing: one whose view did knows
    the count is not 0. ``rider`` (this process's :meth:`StepGather.rider` row, float32, the same length on
    every process) travels in the flag column, which holds the count in each block's first row only: each
    block's entries after it hold every process's rider at its rank's place (zeros at the others'), so the
    sums each process receives are every process's riders, exactly (a value plus zeros: NaN and
    infinities arrive as sent, a -0.0 as 0.0), in ``exchange.riders``; blocks are padded to hold them. The
    gradients are summed in float32: finite views' gradients whose sum passes float32's range (only where
    their L1 norms together do) give Inf here, which the step's finiteness check (each view's norms, before
    the sum) does not see; the optimizer's step then makes the parameters non-finite, and the next check of
    the parameters stops the run. Without ``exchange`` (gsplat's ``distributed=True``
    rasterisation, where every process runs the backward: its all-to-all is a collective) the shards'
    gradients already hold every view's contribution, summed by gsplat's all-to-all backward: they are
    divided, and nothing travels."""
    if not world.enabled:
        return rendered
    if exchange is None:
        for p in shard:
            if p.grad is not None:
                p.grad.div_(world.size)
        return True
    full = [exchange.params[n] for n in exchange.names]
    device = shard[0].device
    sizes = exchange.sizes
    widths = [p[0].numel() for p in full]
    columns = [p.grad if p.grad is not None else torch.zeros_like(p) for p in full]
    if also is not None:
        widths.append(also.shape[0])
        columns.append(also.t())
    width, rows, total = sum(widths), max(sizes), sum(sizes)
    # one row per Gaussian: its gradients, its statistics and whether this process's view rendered (summed:
    # the count of the views that rendered); the processes' rows padded to the largest shard, so that each
    # process's block is ``rows`` rows
    if rider is None:  # the flag in every row, zeros in the padding
        flag = torch.full((total, 1), float(rendered), device=device)
    else:  # each block's flag column: the count's entry, then every process's rider at its rank's place
        length = rider.numel()
        rows = max(rows, 1 + world.size * length)
        before, after = world.rank * length, rows - 1 - (world.rank + 1) * length
        flag = rider.new_full((1,), float(rendered))
        column = torch.cat([flag, rider.new_zeros(before), rider, rider.new_zeros(after)])
        equal = rows * world.size == total
        flag = (column.repeat(world.size) if equal else torch.cat([column[:n] for n in sizes])).unsqueeze(1)
    table = torch.cat([*(c.reshape(total, w) for c, w in zip(columns, widths, strict=True)), flag], dim=1)
    if rows * world.size != total:  # each block's rows after its shard's: zeros, and the flag column's rest
        least = min(sizes)
        pad = table.new_zeros(rows - least, width + 1)
        if rider is not None:
            pad[:, -1] = column[least:]
        pieces, start = [], 0
        for n in sizes:
            pieces += [table[start : start + n], pad[n - least :]]
            start += n
        table = torch.cat(pieces)
    out = table.new_empty(rows, width + 1)
    with collective("the gradient reduce-scatter"):
        _reduce_scatter_tensor(out.view(-1), table.view(-1))
    if rider is not None:
        exchange.riders = out[1 : 1 + world.size * rider.numel(), -1].reshape(world.size, -1)
    if not rendered and int(round(out[0, -1].item())) == 0:
        for p in shard:
            p.grad = None
        return False
    start, stop = exchange.rows
    mine = out[: stop - start]
    offset = 0
    for p, q, w in zip(full, shard, widths[: len(shard)], strict=True):
        g = mine[:, offset : offset + w] / world.size
        if p.shape[1:] == q.shape[1:]:
            q.grad = g.reshape(q.shape).to(q.dtype).contiguous()
        else:  # shN's bands above the step's SH degree (gather_gaussians): not rendered, zero gradients
            q.grad = torch.zeros_like(q)
            q.grad[:, : p.shape[1]] = g.reshape(stop - start, *p.shape[1:])
        offset += w
    if also is not None:
        also[:, start:stop] = mine[:, offset:width].t()
    return True


def stop_request(signals: Sequence[str | None]) -> str | None:
    """The stop every process makes after this step: the first signal some process received ("SIGTERM to
    rank 1", from every process's ``signals`` by rank, which every process gathers), else None."""
    return next((f"{s} to rank {r}" for r, s in enumerate(signals) if s is not None), None)


class StepGather:
    """Every process's values of a step on every process (the logged values, the finiteness norms, the stop
    signals, the shard sizes): one all-gather of a fixed-size float64 row per process, on the step's device
    (NCCL gathers on the GPU; the host reads the result once, which is the step's one host read), no pickling.

    A row is ``[layout, length, *host values, *device values, padding]``. ``layout`` (a hashable, picklable
    description of what the values are, e.g. their names) travels as its index in a table every process
    holds alike; a layout not in it yet (the first step, a process whose view logs another statistic) is
    sent once, by an object gather that every process makes in the same step, seeing the same rows. The
    row's length grows (for every process alike, with a second all-gather in that step) when a process's
    values outgrow it. float64 holds float32 values and integers below 2**53 exactly.

    The torch exchange sends the same values without this all-gather: :meth:`rider` makes the row another
    collective carries (the gradients' reduce-scatter, :func:`reduce_gradients`) and :meth:`unpack` reads
    every process's back; a row that cannot ride (a new layout, too long) makes every process call this
    one in that step."""

    def __init__(self, world: World, capacity: int = 64) -> None:
        self.world = world
        self.capacity = capacity
        self.layouts: dict[Any, int] = {}  # the same on every process: extended only after a collective
        self.table: list[Any] = []
        #: the float32 values a :meth:`rider` row holds after its head (the same on every process)
        self.rider_capacity = capacity

    def rider(self, layout: Any, host: Sequence[float], values: Tensor) -> Tensor:
        """This process's row of the step for another collective to carry (:func:`reduce_gradients`'
        ``rider``), on ``values``' device, float32, ``3 + rider_capacity`` long: ``[layout, number of host
        values, number of values, *host values, zeros, *values]``, each host value as three float32 that
        sum to it exactly, ``values`` (1-D) as float32 (the trainer's are float32). A layout not in the
        table yet, a row longer than the capacity or a host value three normal float32 do not hold gives
        ``[-1, needed length, zeros]``: every process then makes :meth:`__call__` (:meth:`unpack`). Three
        normal float32 hold every float64 of magnitude 2**-74 (about 5.3e-23) to float32's largest, and 0;
        smaller ones only where their last bits allow, none below 2**-126 (so a loss weight that small sends
        the values by the all-gather every step, one more collective, the same values)."""
        index = self.layouts.get(layout, -1)
        pieces = [piece for x in host for piece in _three_float32(x)]
        values = values.detach().to(torch.float32)
        needed = len(pieces) + values.numel()
        exact = all(sum(pieces[i : i + 3]) == x for i, x in zip(range(0, len(pieces), 3), host, strict=True))
        exact = exact and all(p == 0.0 or abs(p) >= _FLOAT32_NORMAL for p in pieces)
        if index < 0 or needed > self.rider_capacity or not exact:
            head = [-1.0, float(needed), 0.0]
            values = values[:0]
        else:
            head = [float(index), float(len(host)), float(values.numel()), *pieces]
        head += [0.0] * (3 + self.rider_capacity - len(head) - values.numel())
        # from pinned memory, without waiting (as __call__'s head)
        device = values.device
        row = torch.tensor(head, dtype=torch.float32, pin_memory=device.type == "cuda")
        return torch.cat([row.to(device, non_blocking=True), values])

    def unpack(self, riders: Sequence[Sequence[float]]) -> list[tuple[Any, list[float]]] | None:
        """Every process's (layout, host values followed by values) from every process's :meth:`rider` row,
        by rank (read on the host), as :meth:`__call__` returns them; None where some process's row asks
        for the full gather (the capacity then grows, for every process alike, to the longest asked)."""
        if any(r[0] < 0 for r in riders):
            longest = max(int(r[1]) for r in riders if r[0] < 0)
            self.rider_capacity = max(self.rider_capacity, longest)
            return None
        out = []
        for r in riders:
            n_host, n_values = int(r[1]), int(r[2])
            host = [r[3 + 3 * i] + r[4 + 3 * i] + r[5 + 3 * i] for i in range(n_host)]
            out.append((self.table[int(r[0])], [*host, *r[len(r) - n_values :]]))
        return out

    def __call__(self, layout: Any, host: Sequence[float], values: Tensor) -> list[tuple[Any, list[float]]]:
        """Every process's (layout, host values followed by ``values``), by rank."""
        index = self.layouts.get(layout, -1)
        values = values.detach().reshape(-1).to(torch.float64)
        length = len(host) + values.numel()
        # from pinned memory, without waiting: a blocking host-to-device copy waits for the device's queue
        device = values.device
        head = torch.tensor(
            [float(index), float(length), *host], dtype=torch.float64, pin_memory=device.type == "cuda"
        ).to(device, non_blocking=True)
        rows = self._gather(torch.cat([head, values]))
        longest = max(int(r[1]) for r in rows)
        if longest > self.capacity:  # every process sees it: all of them gather again, longer
            self.capacity = longest
            rows = self._gather(torch.cat([head, values]))
        if any(r[0] < 0 for r in rows):
            layouts = gather(self.world, layout)
            for lay in layouts:
                if lay not in self.layouts:
                    self.layouts[lay] = len(self.table)
                    self.table.append(lay)
        else:
            layouts = [self.table[int(r[0])] for r in rows]
        return [(lay, r[2 : 2 + int(r[1])]) for lay, r in zip(layouts, rows, strict=True)]

    def _gather(self, row: Tensor) -> list[list[float]]:
        width = 2 + self.capacity
        row = row[:width]
        if row.numel() < width:
            row = torch.cat([row, row.new_zeros(width - row.numel())])
        out = row.new_empty(self.world.size * width)
        with collective("a training step"):
            _all_gather_tensor(out, row)
        return out.view(self.world.size, width).tolist()


#: float32's smallest normal value: a reduction may flush smaller ones to zero (CUDA's flush-to-zero)
_FLOAT32_NORMAL = 2.0**-126


def _three_float32(x: float) -> list[float]:
    """Three float32 values whose sum (left to right, in float64) is ``x`` where float32's range allows
    (53 bits of mantissa in 3 x 24)."""
    pieces = []
    rest = x
    for _ in range(3):
        try:
            piece = struct.unpack("f", struct.pack("f", rest))[0]
        except OverflowError:
            piece = math.nan
        pieces.append(piece)
        rest = rest - piece
    return pieces


def share_strategy_statistics(
    strategy: Any, world: World, rows: Callable[[], tuple[int, int]]
) -> Callable[[dict[str, Any], bool, int], Tensor | None]:
    """The torch exchange: DefaultStrategy's per-Gaussian statistics of the step's views, kept by the
    Gaussians' owners. Each process computes its view's contributions as gsplat does, over the gathered set
    (``info`` of the whole set), into a fresh state; they are summed (radii: the maximum) over the
    processes and each process adds its own rows (``rows()``, this step's) to its running state. (gsplat's
    ``distributed=True`` needs none of this: its projection, whose screen-space gradients the strategy
    reads, runs on the owner; :func:`per_camera_statistics`.) MCMCStrategy keeps no per-view statistics.

    Returns ``fold(info, packed, step)``: called after the step's backward, it computes the view's sums and
    counts and returns them (None in a step where the strategy reads none) for :func:`reduce_gradients`'
    ``also``, which sums this process's rows of them with the gradients in the same reduce-scatter; the
    strategy's update of that ``info`` then reads them instead of making an all-reduce of its own (the
    radii's maximum still does)."""
    if not world.enabled or strategy.type != "default":
        return lambda info, packed, step: None
    gs = strategy.gsplat
    own_update = gs._update_state
    folded: dict[str, Any] = {}  # the step's info, its fresh statistics and their sums

    def fresh_statistics(info: dict[str, Any], packed: bool) -> tuple[dict[str, Any], Tensor]:
        n_full = int(info["means2d"].shape[-2])
        fresh: dict[str, Any] = {"grad2d": None, "count": None, "radii": None}
        grad_key = info.get(gs.key_for_gradient)
        if grad_key is not None and grad_key.grad is not None:
            own_update({"means": torch.empty(n_full, 0)}, fresh, info, packed=packed)
        zeros = torch.zeros(n_full, device=info["means2d"].device)
        if fresh["radii"] is None:
            fresh["radii"] = zeros.clone()
        sums = torch.stack([
            fresh["grad2d"] if fresh["grad2d"] is not None else zeros,
            fresh["count"] if fresh["count"] is not None else zeros,
        ])  # fmt: skip
        return fresh, sums

    def fold(info: dict[str, Any], packed: bool, step: int) -> Tensor | None:
        folded.clear()
        if step >= gs.refine_stop_iter:  # (the strategy updates nothing: gsplat's step_post_backward)
            return None
        fresh, sums = fresh_statistics(info, packed)
        folded.update(info=info, fresh=fresh, sums=sums)
        return sums

    def update_state(params: Any, state: dict[str, Any], info: dict[str, Any], packed: bool = False) -> None:
        dist = _dist()
        if folded.get("info") is info:  # summed with the step's gradients
            fresh, sums = folded["fresh"], folded["sums"]
            folded.clear()
        else:
            fresh, sums = fresh_statistics(info, packed)
            with collective("the strategy's statistics"):
                dist.all_reduce(sums)
        device = sums.device
        start, stop = rows()
        n = stop - start
        for i, key in enumerate(("grad2d", "count")):
            if state[key] is None:
                state[key] = torch.zeros(n, device=device)
            state[key] += sums[i, start:stop]
        if gs.refine_scale2d_stop_iter > 0:
            radii = fresh["radii"]
            with collective("the strategy's statistics"):
                dist.all_reduce(radii, op=dist.ReduceOp.MAX)
            if state["radii"] is None:
                state["radii"] = torch.zeros(n, device=device)
            state["radii"] = torch.maximum(state["radii"], radii[start:stop])

    gs._update_state = update_state
    return fold


class _Grad:
    """A screen-space gradient as DefaultStrategy reads it (``info[key].grad``)."""

    def __init__(self, grad: Tensor) -> None:
        self.grad = grad


def per_camera_statistics(strategy: Any, world: World) -> None:
    """gsplat's exchange: DefaultStrategy's statistics of the step's views from the owner's projection
    (``info["means2d"]``, ``info["radii"]``: [world_size, N_shard, ...], one row per process's camera), one
    camera at a time, as one process adds them view after view. (In one call the largest radii of a
    Gaussian seen by several cameras would be kept by whichever duplicate index wins gsplat's scatter, not
    the largest.) Each row's gradient is one view's loss's, as on one process (``n_cameras`` is 1: each
    process renders one camera). MCMCStrategy keeps no per-view statistics."""
    if not world.enabled or strategy.type != "default":
        return
    gs = strategy.gsplat
    own_update = gs._update_state

    def update_state(params: Any, state: dict[str, Any], info: dict[str, Any], packed: bool = False) -> None:
        grad = info[gs.key_for_gradient].grad
        if packed or grad is None or grad.dim() != 3:
            own_update(params, state, info, packed=packed)
            return
        for c in range(grad.shape[0]):
            one = {**info, gs.key_for_gradient: _Grad(grad[c : c + 1]), "radii": info["radii"][c : c + 1]}
            own_update(params, state, one, packed=False)

    gs._update_state = update_state


# -- checkpoints: the shards gathered on rank 0, one file --------------------------------------------------
def _cpu(obj: Any) -> Any:
    if isinstance(obj, Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: _cpu(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_cpu(v) for v in obj)
    return obj


def gather_to_main(world: World, obj: Any) -> list[Any] | None:
    """``obj`` of every process on rank 0 (by rank; tensors moved to the CPU first), None elsewhere."""
    if not world.enabled:
        return [obj]
    out: list[Any] | None = [None] * world.size if world.is_main else None
    with collective("gathering the Gaussians for a checkpoint"):
        _dist().gather_object(_cpu(obj), out, dst=0)
    return out


def merge_shards(parts: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """One checkpoint's parts from the shards' (``splats``, ``optimizers``, ``strategy``, ``rng`` of each
    process): the Gaussians and their Adam moments and statistics concatenated by rank (the layout of one
    process's checkpoint), ``shards`` their row counts, ``rng`` rank 0's and ``rng_ranks`` every process's
    generators."""
    first = parts[0]
    splats = {n: torch.cat([p["splats"][n] for p in parts]) for n in first["splats"]}
    optimizers: dict[str, Any] = {}
    for name, sd in first["optimizers"].items():
        state = {}
        if 0 in sd["state"]:
            s0 = dict(sd["state"][0])
            for m in ("exp_avg", "exp_avg_sq"):
                s0[m] = torch.cat([p["optimizers"][name]["state"][0][m] for p in parts])
            state[0] = s0
        optimizers[name] = {"state": state, "param_groups": sd["param_groups"]}
    strategy = dict(first["strategy"])
    for k in PER_GAUSSIAN_STATE:
        if strategy.get(k) is not None:
            strategy[k] = torch.cat([p["strategy"][k] for p in parts])
    return {
        "splats": splats,
        "optimizers": optimizers,
        "strategy": strategy,
        "rng": first["rng"],
        "rng_ranks": [p["rng"] for p in parts],
        "shards": [int(p["splats"]["means"].shape[0]) for p in parts],
    }


def split_checkpoint(doc: dict[str, Any], world: World, path: str) -> dict[str, Any]:
    """This process's part of a checkpoint :func:`merge_shards` wrote (its rows, its generators)."""
    sizes = doc.get("shards")
    n = int(doc["splats"]["means"].shape[0])
    ranks = doc.get("rng_ranks")
    if sizes is None and ranks is None:  # several processes' before the Gaussians were sharded
        raise JsgsError(
            f"{path}: lacks shards and rng_ranks (each process's rows and generators): written before the "
            f"Gaussians were sharded across processes, {world.size} processes cannot resume it; start over "
            "with --force"
        )
    if (
        not isinstance(sizes, list)
        or len(sizes) != world.size
        or not all(isinstance(s, int) and s >= 1 for s in sizes)
        or sum(sizes) != n
        or not isinstance(ranks, list)
        or len(ranks) != world.size
    ):
        raise JsgsError(
            f"{path}: unusable checkpoint: shards: not the row counts of {world.size} processes' Gaussians, "
            f"at least one each ({n} in the file)"
        )
    start = sum(sizes[: world.rank])
    stop = start + sizes[world.rank]
    out = dict(doc)
    out["splats"] = {k: v[start:stop] for k, v in doc["splats"].items()}
    optimizers = {}
    for name, sd in doc["optimizers"].items():
        state = {}
        if 0 in sd["state"]:
            s0 = dict(sd["state"][0])
            for m in ("exp_avg", "exp_avg_sq"):
                s0[m] = s0[m][start:stop]
            state[0] = s0
        optimizers[name] = {"state": state, "param_groups": sd["param_groups"]}
    out["optimizers"] = optimizers
    strategy = dict(doc["strategy"])
    for k in PER_GAUSSIAN_STATE:
        if strategy.get(k) is not None:
            strategy[k] = strategy[k][start:stop]
    out["strategy"] = strategy
    out["rng"] = ranks[world.rank]
    return out


def barrier(world: World, what: str) -> None:
    if not world.enabled:
        return
    import torch.distributed as dist

    with collective(what):
        dist.barrier()
