"""Where one training step's memory goes, per method, on the CPU: the step's peak of live tensor bytes and
the tensors alive at that peak (shape, dtype, the op that made each, where in the code, which part).

    .venv/bin/python tools/diagnostics/step_memory.py                       # synthetic 504x378, mcmc preset
    .venv/bin/python tools/diagnostics/step_memory.py --manifest DATA/manifest.json --out step_memory.json

Each method (``--methods``) trains ``--warmup`` steps of ``--preset`` (``mcmc``, the equal-budget protocol,
at the fixed 300,000 Gaussians of the published figures unless ``--config`` or ``--cap-max N|auto`` say
otherwise, as in ``profile_step.py``; ``--config`` JSON over it; ``--cap-max`` over both; ``--jsgs-options``
over JSGS's ``method_options``) on the CPU from the same seed
on a synthetic scene (``profile_step.py``'s, ``--size``, ``--views``) or ``--manifest``, and the next step is
measured. The methods: ``gsplat``; ``jsgs`` (on the CPU its image terms run eagerly); ``jsgs-graph-layout``,
JSGS with its image terms arranged as on CUDA with ``method_options.speed.cuda_graph`` (:class:`GraphLayout`).
Its accounting is storage-level and the allocator's business is left out:

- resident: every tensor alive at the step's start (Python's cycle collector lists them), each storage
  once, by owner: the Gaussians with their gradients and optimiser state, the training images, the
  strategy's state, the method's hook, the rest;
- the step: a ``TorchDispatchMode`` sees every aten op; a storage an op returns that none of its inputs
  has is *made* by it, and lives until torch frees it (a weak reference's finaliser on the storage). The
  live bytes after each op, their peak (above the step's start: the step's own memory) and the storages
  alive at that peak. Temporaries that live and die inside one kernel are not seen.

Each made storage is charged to the op that made it, the innermost frame of the project (or gsplat) above
it and the part of :data:`PARTS` (``op_sources.py``'s) whose code that is; in the backward, to the frames
that run it where the project's code of a part does (the controller's hook), else (the engine runs it,
under ``backward()`` or ``torch.autograd.grad``, or a custom function's backward outside the parts) to where
its autograd node was made in the forward (anomaly mode records that, without its NaN checks), marked
"(backward)". Each is also classed by what its size scales with: ``pixels`` (a dimension of the image, at
8×8 blocks or 4:2:0 chroma too), ``gaussians`` (the number of Gaussians) or ``other`` (e.g. the reference
rasteriser's per-tile pair tensors).

For ``jsgs-graph-layout`` two peaks are kept: of everything, and of everything outside the graph's replay
(``step_peak_bytes``; on CUDA the replay's intermediates live in the graph's private pool, reserved but not
allocated memory; ``pool_peak_bytes`` is their largest live total). A third, ``backward_peak_bytes``, is the
largest live total outside the pool after an op the autograd engine runs (the backward's own peak; on the
CPU the step's peak is often in the forward, at ℓ_ph's SSIM, where on CUDA the fused SSIM saves far less).

This is the CPU reference path's accounting. On CUDA gsplat's rasteriser has its own buffers (tile bins,
sort buffers, per-pixel last-contributor ids) and none of the reference rasteriser's per-tile pair lists;
the fused SSIM kernel saves three maps where the CPU twin saves fifteen-channel planes; the caching
allocator rounds sizes and keeps segments; cuBLAS keeps a workspace per handle and stream. What carries
over are the JSGS-only tensors: the graph's buffers, the probe channels, the controller's outputs.
"""

from __future__ import annotations

import argparse
import gc
import json
import re
import shutil
import sys
import tempfile
import warnings
import weakref
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import Any

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_train_overhead import CAP_MAX_HELP, build_scene, report_header, start_config, variant_config  # noqa: E402
from op_sources import PARTS as OP_PARTS  # noqa: E402

from jsgs.base.errors import JsgsError, reports_user_errors  # noqa: E402
from jsgs.base.io import write_json_checked  # noqa: E402
from jsgs.method.graphed import GraphedImageTerms, _Recording  # noqa: E402
from jsgs.train.callbacks import Callback  # noqa: E402
from jsgs.train.config import PRESETS, TrainConfig  # noqa: E402
from jsgs.train.trainer import train  # noqa: E402

FORMAT = "jsgs-step-memory"
FORMAT_VERSION = 1
#: op_sources.py's parts, the strategy before the controller's kernels (on the CPU gsplat's MCMC relocation
#: runs twins in jsgs/kernels) and the optimiser apart from the trainer that calls it
PARTS = (
    *(p for p in OP_PARTS if p[1] not in ("GC", "rasteriser", "strategy", "trainer")),
    ("/strategy", "strategy"),
    *(p for p in OP_PARTS if p[1] in ("GC", "rasteriser")),
    ("torch/optim/", "optimiser"),
    ("trainer.py", "trainer"),
)
_TRACE_LINE = re.compile(r'File "(?P<file>[^"]+)", line (?P<line>\d+), in (?P<fn>\S+)')
_SELF = str(Path(__file__).resolve())

Frame = tuple[str, int, str]  # file, line, function


@dataclass
class Made:
    """One storage made during the step."""

    nbytes: int
    shape: list[int]
    dtype: str
    op: str
    phase: str  # forward or backward
    origin: str  # innermost project frame, path:line (function)
    part: str
    scale: str = "other"  # pixels, gaussians or other
    pool: bool = False  # made inside a GraphLayout replay


def _project(frame: Frame) -> bool:
    f = frame[0]
    return f != _SELF and (f.startswith(str(ROOT / "jsgs")) or "/gsplat/" in f)


def part_of(frames: Sequence[Frame]) -> str:
    """The first part of :data:`PARTS` that any of ``frames`` names (as ``file(line): function``)."""
    names = [f"{f}({n}): {fn}" for f, n, fn in frames]
    for key, part in PARTS:
        if any(key in s for s in names):
            return part
    return "other"


def origin_of(frames: Sequence[Frame]) -> str:
    """The innermost project frame of ``frames`` (innermost first), as ``path:line (function)``."""
    for f, n, fn in frames:
        if _project((f, n, fn)):
            path = Path(f)
            rel = path.relative_to(ROOT) if path.is_relative_to(ROOT) else Path(*path.parts[-3:])
            return f"{rel.as_posix()}:{n} ({fn})"
    return "-"


def _python_frames() -> list[Frame]:
    out, f = [], sys._getframe(2)
    while f is not None:
        out.append((f.f_code.co_filename, f.f_lineno, f.f_code.co_name))
        f = f.f_back
    return out


def _node_frames(node: Any) -> list[Frame]:
    """Where the autograd node was made in the forward (anomaly mode's traceback), innermost first."""
    lines = node.metadata.get("traceback_") or []
    found = [_TRACE_LINE.search(s) for s in lines]
    return [(m["file"], int(m["line"]), m["fn"]) for m in reversed(found) if m]


def _engine_run(frames: Sequence[Frame]) -> bool:
    """Whether the autograd engine runs the op: between it and the innermost project frame there is a call
    into autograd (``backward()``, ``torch.autograd.grad``), not a hook or a custom function's backward."""
    for f in frames:
        if _project(f):
            return False
        if "torch/autograd/" in f[0] or f[0].endswith("torch/_tensor.py"):
            return True
    return True


def _where(node: Any) -> tuple[str, str, str, bool]:
    """``(phase, origin, part, inside a graph replay)`` of the op running now (module docstring)."""
    frames = _python_frames()
    pool = any(fn == "_replay_in_pool" for _, _, fn in frames)
    if node is None:
        return "forward", origin_of(frames), part_of(frames), pool
    if _engine_run(frames) or part_of(frames) in ("trainer", "other"):  # where its node was made
        frames = _node_frames(node) or frames
    return "backward", origin_of(frames), f"{part_of(frames)} (backward)", pool


class LiveStorages(TorchDispatchMode):
    """The storages the ops under this mode make (module docstring), the live bytes after every op and two
    peaks, each with the storages alive at it: of everything, and of everything outside a graph replay
    (what a CUDA graph's private pool holds, :class:`GraphLayout`: on CUDA not allocated memory but the
    pool's reserved memory, whose size is the largest live total inside one replay, ``pool_peak``).
    ``scale_of(shape)`` classes a made tensor's shape."""

    def __init__(self, scale_of: Any) -> None:
        super().__init__()
        self.scale_of = scale_of
        self.made: list[Made] = []
        self.live: dict[int, int] = {}  # index into made -> bytes, while alive
        self._index: dict[int, int] = {}  # storage address -> index into made, while alive
        self.bytes = self.pool_bytes = self.ops = 0
        kinds = ("all", "outside_pool", "pool", "backward")
        self.peak = dict.fromkeys(kinds, 0)
        self.peak_op = dict.fromkeys(kinds, 0)
        self.at_peak: dict[str, list[int]] = {k: [] for k in kinds}
        self.peak_made = dict.fromkeys(kinds, -1)  # the last storage made at each peak

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        out = func(*args, **(kwargs or {}))
        self.ops += 1
        inputs = {t.untyped_storage()._cdata for t in tree_flatten((args, kwargs))[0] if torch.is_tensor(t)}
        for t in tree_flatten(out)[0]:
            if torch.is_tensor(t) and t.device.type != "meta":
                self._seen(t, str(func), inputs)
        outside = self.bytes - self.pool_bytes
        backward = outside if torch._C._current_autograd_node() is not None else 0
        for kind, b in (("all", self.bytes), ("outside_pool", outside), ("pool", self.pool_bytes),
                        ("backward", backward)):  # fmt: skip
            if b > self.peak[kind]:
                self.peak[kind], self.peak_op[kind], self.at_peak[kind] = b, self.ops, list(self.live)
                self.peak_made[kind] = len(self.made) - 1
        return out

    def _seen(self, t: torch.Tensor, op: str, inputs: set[int]) -> None:
        storage = t.untyped_storage()
        address = storage._cdata
        if address in inputs or address in self._index or storage.nbytes() == 0:
            return
        phase, origin, part, pool = _where(torch._C._current_autograd_node())
        i = len(self.made)
        self.made.append(Made(storage.nbytes(), list(t.shape), str(t.dtype).removeprefix("torch."), op,
                              phase, origin, part, self.scale_of(t.shape), pool))  # fmt: skip
        self._index[address] = i
        self.live[i] = storage.nbytes()
        self.bytes += storage.nbytes()
        self.pool_bytes += storage.nbytes() if pool else 0
        weakref.finalize(storage, self._freed, address, i)

    def _freed(self, address: int, i: int) -> None:
        if self._index.get(address) == i:
            del self._index[address]
        n = self.live.pop(i, 0)
        self.bytes -= n
        self.pool_bytes -= n if self.made[i].pool else 0


class GraphLayout(GraphedImageTerms):
    """The hook's CUDA-graph branch (``method_options.speed.cuda_graph``) on the CPU, for the accounting
    only: the graph's input and output buffers are kept as a recording keeps them, and each replay runs the
    recorded function (:func:`jsgs.method.image_terms.terms_with_gradient`) eagerly in
    :func:`_replay_in_pool` and copies its results into the outputs. What that function makes is what the
    graph's private pool holds on CUDA; the buffers are the graph's own (:meth:`GraphedImageTerms._buffer`:
    shared by the recordings of equal sizes, e.g. a scene's two orientations). The values and gradients are
    the eager chain's
    (``tests/test_jsgs/method/test_graphed.py`` tests this contract)."""

    def _record(
        self, x: torch.Tensor, y: torch.Tensor, tables: torch.Tensor, sampling: str, observation: bool
    ) -> _Recording:
        fn, inputs = self._recorded_function(x, y, tables, sampling, observation)
        outputs = fn()
        return _Recording(partial(_replay_in_pool, fn, outputs), inputs, outputs)


def _replay_in_pool(fn: Any, outputs: Sequence[torch.Tensor | None]) -> None:
    for buf, new in zip(outputs, fn(), strict=True):
        if buf is not None:
            buf.copy_(new)


def scale_classifier(width: int, height: int, n: int) -> Any:
    """``shape -> "gaussians" | "pixels" | "other"``: a dimension equal to ``n``; else one (above 16) that is
    a side of the image, padded to 8 or 16, halved (4:2:0 chroma) or in 8×8 blocks, or their product."""
    sides = set()
    for h, w in ((height, width), (-(-height // 8) * 8, -(-width // 8) * 8),
                 (-(-height // 16) * 16, -(-width // 16) * 16)):  # fmt: skip
        for d in (1, 2, 8, 16):
            sides |= {h // d, w // d, (h // d) * (w // d)}
    sides = {s for s in sides if s > 16}

    def scale_of(shape: Sequence[int]) -> str:
        if n in shape:
            return "gaussians"
        return "pixels" if any(s in sides for s in shape) else "other"

    return scale_of


def _tensors(obj: Any, visited: set[int], depth: int = 0) -> list[torch.Tensor]:
    """The tensors reachable from ``obj`` through containers, optimisers, modules and the project's objects
    (a parameter's gradient too)."""
    if torch.is_tensor(obj):
        return [obj] if obj.grad is None else [obj, obj.grad]
    if depth > 8 or id(obj) in visited:
        return []
    visited.add(id(obj))
    if isinstance(obj, torch.optim.Optimizer):
        items: Any = [obj.state, obj.param_groups]
    elif isinstance(obj, dict):
        items = [*obj.keys(), *obj.values()]
    elif isinstance(obj, (list, tuple, set, frozenset)):
        items = obj
    elif isinstance(obj, torch.nn.Module):
        items = [*obj.parameters(), *obj.buffers()]
    elif isinstance(obj, GraphedImageTerms) or (
        hasattr(obj, "__dict__") and type(obj).__module__.startswith(("jsgs", "gsplat"))
    ):
        items = list(vars(obj).values())
    else:
        return []
    return [t for item in items for t in _tensors(item, visited, depth + 1)]


def resident(trainer: Any, n: int) -> tuple[dict[str, int], int]:
    """Bytes of every tensor alive now, each storage once, by owner (the first that reaches it), and the
    bytes of those whose first dimension is the number of Gaussians ``n``."""
    with warnings.catch_warnings():  # torch's deprecated aliases warn when the collector's list is tested
        warnings.simplefilter("ignore")
        every = [o for o in gc.get_objects() if torch.is_tensor(o)]
    owners = {
        "gaussians, gradients, optimiser state": [trainer.splats, trainer.optimizers],
        "training images": [trainer.train_images],
        "strategy state": [trainer.strategy_state],
        "method hook": [trainer.hook],
        "other": every,
    }
    seen: set[int] = set()
    out, per_gaussian = {}, 0
    for owner, objs in owners.items():
        out[owner] = 0
        for t in _tensors(objs, set()):
            s = t.untyped_storage()
            if s._cdata in seen or t.device.type == "meta":
                continue
            seen.add(s._cdata)
            out[owner] += s.nbytes()
            per_gaussian += s.nbytes() if t.dim() and t.shape[0] == n else 0
    return out, per_gaussian


class MeasureStep(Callback):
    """Measures step ``step`` (module docstring): the resident tensors at its start, then everything its
    ops make, under :class:`LiveStorages` and anomaly mode (forward tracebacks only), until it ends."""

    def __init__(self, step: int) -> None:
        self.step = step
        self.mode: LiveStorages | None = None
        self.anomaly: Any = None
        self.info: dict[str, Any] = {}
        self.end_bytes = 0

    def on_step_begin(self, trainer: Any, step: int) -> None:
        if step != self.step:
            return
        gc.collect()
        n = int(trainer.splats["means"].shape[0])
        view = trainer.train_views[0]
        res, per_gaussian = resident(trainer, n)
        self.info = dict(num_gaussians=n, width=view.width, height=view.height, resident_bytes=res,
                         resident_per_gaussian_bytes=per_gaussian / max(n, 1))  # fmt: skip
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.anomaly = torch.autograd.detect_anomaly(check_nan=False)
        self.anomaly.__enter__()
        self.mode = LiveStorages(scale_classifier(view.width, view.height, n))
        self.mode.__enter__()

    def on_step_end(self, trainer: Any, result: Any) -> None:
        if self.mode is None or self.anomaly is None:
            return
        self.mode.__exit__(None, None, None)
        self.anomaly.__exit__(None, None, None)
        self.anomaly = None
        gc.collect()
        self.end_bytes = self.mode.bytes
        self.info["view"] = result.view


def _sums(items: Sequence[Made], key: str) -> dict[str, int]:
    out: dict[str, int] = {}
    for m in items:
        out[getattr(m, key)] = out.get(getattr(m, key), 0) + m.nbytes
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def _peak(mode: LiveStorages, kind: str, top: int) -> dict[str, Any]:
    """One peak of ``mode`` (``"all"``, ``"outside_pool"`` or ``"backward"``): its bytes, the op that
    reached it and what is alive at it, by part, scale and origin, and the largest storages."""
    at_peak = [mode.made[i] for i in mode.at_peak[kind]]
    origins: dict[tuple[str, str], list[int]] = {}
    for m in at_peak:
        o = origins.setdefault((m.origin, m.part), [0, 0])
        o[0], o[1] = o[0] + m.nbytes, o[1] + 1
    last = mode.made[mode.peak_made[kind]] if mode.peak_made[kind] >= 0 else None
    return {
        "bytes": mode.peak[kind],
        "after_op": mode.peak_op[kind],
        "reached_by": None
        if last is None
        else {k: getattr(last, k) for k in ("op", "phase", "origin", "part")},
        "by_part": _sums(at_peak, "part"),
        "by_scale": _sums(at_peak, "scale"),
        "by_origin": [
            {"origin": k[0], "part": k[1], "bytes": v[0], "count": v[1]}
            for k, v in sorted(origins.items(), key=lambda kv: -kv[1][0])[:top]
        ],
        "top": [asdict(m) for m in sorted(at_peak, key=lambda m: -m.nbytes)[:top]],
    }


def summary(cb: MeasureStep, top: int) -> dict[str, Any]:
    """One method's JSON entry: resident, the step's peaks and what is alive at them."""
    mode = cb.mode
    assert mode is not None
    resident_total = sum(cb.info["resident_bytes"].values())
    return {
        **cb.info,
        "resident_total_bytes": resident_total,
        "ops": mode.ops,
        "made": len(mode.made),
        "made_bytes": sum(m.nbytes for m in mode.made),
        "step_end_bytes": cb.end_bytes,
        "step_peak_bytes": mode.peak["outside_pool"],
        "peak_total_bytes": resident_total + mode.peak["outside_pool"],
        "pool_peak_bytes": mode.peak["pool"],
        "backward_peak_bytes": mode.peak["backward"],
        "peaks": {kind: _peak(mode, kind, top) for kind in ("all", "outside_pool", "backward")},
    }


def _graph_layout_hook(manifest: Path, cfg: TrainConfig) -> Any:
    """A JSGS hook whose image terms take the CUDA-graph branch with :class:`GraphLayout`."""
    from jsgs.train.data import load_training_scene
    from jsgs.train.hook import make_hook

    hook: Any = make_hook(cfg, load_training_scene(manifest, cfg), torch.device("cpu"))
    w = hook.weights()
    hook._graphed = GraphLayout(
        weights=(w["obs"], w.get("low", 0.0), w.get("mid", 0.0)), **hook._jpeg_settings
    )
    return hook


def measure(manifest: Path, work: Path, method: str, args: argparse.Namespace) -> dict[str, Any]:
    """Train ``args.warmup`` steps of ``method`` and measure the next (:class:`MeasureStep`)."""
    base = start_config(args.preset, args.config, args.cap_max)
    name = "jsgs" if method == "jsgs-graph-layout" else method
    extra = args.jsgs_options if name == "jsgs" else {}
    cfg = variant_config(base, name, {**base.method_options, **extra}, args.warmup + 1, "cpu")
    cfg.checkpoint_every = 0
    hook = _graph_layout_hook(manifest, cfg) if method == "jsgs-graph-layout" else None
    cb = MeasureStep(args.warmup)
    train(manifest, work / method, cfg, force=True, progress=False, log=lambda s: None, callbacks=[cb],
          hook=hook)  # fmt: skip
    return summary(cb, args.top)


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The JSON document (``jsgs/schemas/step_memory.schema.json``)."""
    torch.set_num_threads(args.threads)
    work = Path(tempfile.mkdtemp(prefix="step_memory."))
    try:
        if args.manifest is None:
            w, h = (int(v) for v in args.size.lower().split("x"))
            manifest = build_scene(work / "synthetic", (w, h), args.views)
        else:
            manifest = args.manifest
        results = {m: measure(manifest, work, m, args) for m in args.methods.split(",")}
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return report_header(FORMAT, FORMAT_VERSION, args, manifest, "cpu") | {
        "step": args.warmup,
        "results": results,
    }


def _mib(b: float) -> str:
    return f"{b / 2**20:.2f}"


def print_report(doc: dict[str, Any]) -> None:
    res = doc["results"]
    print(f"step {doc['step']} of {doc['manifest']}, CPU accounting (MiB; storages counted once)")
    print()
    print(
        "| method | Gaussians | resident | step peak | resident + peak | graph pool | backward peak | "
        "made in the step | left at its end |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for m, r in res.items():
        print(
            f"| {m} | {r['num_gaussians']} | {_mib(r['resident_total_bytes'])} "
            f"| {_mib(r['step_peak_bytes'])} | {_mib(r['peak_total_bytes'])} | {_mib(r['pool_peak_bytes'])} "
            f"| {_mib(r['backward_peak_bytes'])} | {_mib(r['made_bytes'])} | {_mib(r['step_end_bytes'])} |"
        )
    for m, r in res.items():
        pk = r["peaks"]["outside_pool"]
        by = pk["reached_by"] or {}
        print(
            f"\n{m}: resident by owner (MiB): "
            + ", ".join(f"{k} {_mib(v)}" for k, v in r["resident_bytes"].items())
        )
        print(
            f"{m}: the step's peak (outside graph replays) after op {pk['after_op']} of {r['ops']}, "
            f"{by.get('op')} ({by.get('phase')}, {by.get('origin')}, {by.get('part')}); alive at it (MiB):"
        )
        print("| part | MiB |\n|---|---:|")
        for part, b in pk["by_part"].items():
            print(f"| {part} | {_mib(b)} |")
        for scale, b in pk["by_scale"].items():
            print(f"| scale: {scale} | {_mib(b)} |")
        print(f"\n{m}: largest at that peak")
        print("| MiB | shape | dtype | op | phase | origin | part |\n|---:|---|---|---|---|---|---|")
        for t in pk["top"]:
            print(
                f"| {_mib(t['nbytes'])} | {t['shape']} | {t['dtype']} | {t['op']} | {t['phase']} "
                f"| {t['origin']} | {t['part']} |"
            )
        bw = r["peaks"]["backward"]
        print(f"\n{m}: the backward's peak after op {bw['after_op']}; alive at it (MiB): "
              + ", ".join(f"{part} {_mib(b)}" for part, b in bw["by_part"].items()))  # fmt: skip


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--manifest", type=Path, help="scene manifest (default: a synthetic scene)")
    ap.add_argument("--size", default="504x378", help="synthetic scene image size WxH [504x378]")
    ap.add_argument("--views", type=int, default=4, help="synthetic scene views [4]")
    ap.add_argument(
        "--methods",
        default="gsplat,jsgs,jsgs-graph-layout",
        help="comma-separated: gsplat, jsgs, jsgs-graph-layout [all three]",
    )
    ap.add_argument("--preset", default="mcmc", choices=sorted(PRESETS))
    ap.add_argument("--config", type=Path, help="JSON settings over the preset, for every method")
    ap.add_argument("--cap-max", metavar="N|auto", help=CAP_MAX_HELP)
    ap.add_argument("--warmup", type=int, default=2, help="steps before the measured one [2]")
    ap.add_argument("--jsgs-options", type=json.loads, default={}, help="JSON over JSGS's method_options")
    ap.add_argument("--top", type=int, default=15, help="tensors and origins listed at the peak [15]")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, help="write the JSON here")
    args = ap.parse_args(argv)
    if args.warmup < 1 or args.top < 1 or args.views < 2:
        raise JsgsError("step_memory.py: --warmup and --top must be >= 1, --views >= 2")
    if args.manifest is not None and not args.manifest.is_file():
        raise JsgsError(f"{args.manifest}: no such manifest")
    bad = set(args.methods.split(",")) - {"gsplat", "jsgs", "jsgs-graph-layout"}
    if bad:
        raise JsgsError(f"step_memory.py: --methods: unknown {sorted(bad)} (gsplat, jsgs, jsgs-graph-layout)")
    if not isinstance(args.jsgs_options, dict):
        raise JsgsError("step_memory.py: --jsgs-options must be a JSON object")
    if not re.fullmatch(r"\d+x\d+", args.size.lower()):
        raise JsgsError(f"step_memory.py: --size {args.size!r}: expected WxH, e.g. 504x378")
    return args


@reports_user_errors
def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    doc = run(args)
    print_report(doc)
    if args.out:
        write_json_checked(args.out, doc, "step_memory")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
