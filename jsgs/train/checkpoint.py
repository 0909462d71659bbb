"""Checkpoints: everything a run needs to continue bit for bit (on CPU) from the step it was written at.

Written with ``torch.save`` as a dict of tensors and plain Python values only, and read back with
``weights_only=True`` (no pickled code): parameters, Adam states, the means' LR scheduler, DefaultStrategy's
running state, every random generator the loop draws from (torch CPU/CUDA, numpy, Python, the view sampler),
the method hook's state, the accumulated training time, the evaluations so far and the partial log averages.

A checkpoint is checked before anything of it is used (:func:`check_structure`, :func:`check_state`): every
key present, every tensor of the dtype and shape the run's settings and the fresh optimizers, scheduler and
strategy give, every number finite, the step non-negative and the one in the file's name. Any defect is one
JsgsError naming the file and the key.

A checkpoint written by an earlier version reads as today's (:func:`fields_of_today`): a field added since
takes the value that does what the code before it did (:data:`EARLIER_FIELDS`), named in one note; the
settings it holds read as a run's config.json does (:func:`jsgs.train.config.settings_of_today`). A field
missing that no earlier version lacked is refused by the checks, in one line naming the file and the field.
"""

from __future__ import annotations

import copy
import json
import math
import random
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from jsgs.base.errors import JsgsError
from jsgs.base.io import atomic_path

CHECKPOINT_FORMAT = "jsgs-checkpoint"
CHECKPOINT_VERSION = 1
_NAME = re.compile(r"^step_(\d+)\.pt$")


def checkpoint_path(folder: Path, step: int) -> Path:
    return folder / f"step_{step:06d}.pt"


def list_checkpoints(folder: Path) -> list[tuple[int, Path]]:
    """(step, path) of the checkpoints in ``folder``, by step."""
    if not folder.is_dir():
        return []
    out = []
    for p in folder.iterdir():
        m = _NAME.match(p.name)
        if m:
            out.append((int(m.group(1)), p))
    return sorted(out)


def rng_state() -> dict[str, Any]:
    """The global generators' states as tensors/lists (loadable with weights_only=True)."""
    np_state = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": [np_state[0], torch.from_numpy(np_state[1].astype(np.int64)), *map(float, np_state[2:])],
        "python": _py_state_to_lists(random.getstate()),
    }


def _py_state_to_lists(state: tuple[Any, ...]) -> list[Any]:
    version, internal, gauss = state
    return [version, list(internal), gauss]


def set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    if state["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), int(pos), int(has_gauss), float(cached)))
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))


def _to_cpu(obj: Any) -> Any:
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu().clone()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_to_cpu(v) for v in obj)
    return obj


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """Write atomically (a crash never leaves a truncated checkpoint under the final name)."""
    doc = {"format": CHECKPOINT_FORMAT, "format_version": CHECKPOINT_VERSION, **_to_cpu(payload)}
    with atomic_path(path) as tmp:
        torch.save(doc, tmp)


def load_checkpoint(path: Path) -> dict[str, Any]:
    from jsgs.base.io import open_regular

    try:
        with open_regular(path) as f:  # a FIFO named like a checkpoint is refused, not waited on
            doc = torch.load(f, map_location="cpu", weights_only=True)
    except JsgsError:
        raise
    except Exception as e:  # torch raises a variety of types for a damaged file, with multi-line messages
        from jsgs.base.errors import one_line

        why = one_line(e)
        why = why if len(why) <= 200 else why[:197] + "..."
        raise JsgsError(f"{path}: not a readable checkpoint ({why})") from None
    if not isinstance(doc, dict) or doc.get("format") != CHECKPOINT_FORMAT:
        raise JsgsError(f"{path}: not a jsgs checkpoint")
    if doc.get("format_version") != CHECKPOINT_VERSION:
        version = repr(doc.get("format_version"))[:40]
        raise JsgsError(f"{path}: checkpoint format version {version} is not supported")
    return doc


def to_device(obj: Any, device: torch.device) -> Any:
    """Tensors in a nested structure moved to ``device`` (dtype kept)."""
    if isinstance(obj, torch.Tensor):
        return obj.to(device)
    if isinstance(obj, dict):
        return {k: to_device(v, device) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(to_device(v, device) for v in obj)
    return obj


# ---------------------------------------------------------------------------------------------------------
# checkpoints of earlier versions

#: Fields of a checkpoint added after its first version (dotted; ``*``: each key of the dict above), and the
#: value that does what the code before them did: the log kept no per-view sums of the interval, then
#: per-view sums of the loss and terms only (no statistics, which metrics.json does not report per view), and
#: counted no skipped terms (the Gaussian Controller's fro term was logged on every step); so those start
#: empty. Nothing of what the run trains depends on them.
EARLIER_FIELDS: dict[str, Any] = {
    "log.per_view": {},
    "log.skipped": {},
    "log.per_view.*.stats": {},
    "log.per_view.*.per_view": {},
    "log.per_view.*.skipped": {},
}


def fields_of_today(doc: Any) -> list[str]:
    """Give ``doc`` (a loaded checkpoint, changed in place) each field of :data:`EARLIER_FIELDS` it lacks,
    with that value; returns them as ``field value`` texts (empty for a checkpoint of today). Parts that are
    not dicts are left for the checks to name."""
    filled: list[str] = []

    def fill(part: Any, keys: list[str], where: str, value: Any) -> None:
        if not isinstance(part, dict):
            return
        head, rest = keys[0], keys[1:]
        if head == "*":
            for k in part:
                fill(part[k], rest, where, value)
        elif not rest:
            if head not in part:
                part[head] = copy.deepcopy(value)
                if where not in filled:
                    filled.append(where)
        elif head in part:
            fill(part[head], rest, where, value)

    for field, value in EARLIER_FIELDS.items():
        fill(doc, field.split("."), field, value)
    return [f"{f} {json.dumps(EARLIER_FIELDS[f])}" for f in filled]


# ---------------------------------------------------------------------------------------------------------
# checks before use

#: the keys of a checkpoint (``Trainer.checkpoint_state``), besides format and format_version
KEYS = (
    "step", "settings", "manifest_sha256", "splats", "optimizers", "scheduler", "strategy", "rng", "sampler",
    "hook", "evals", "log", "train_time_s",
)  # fmt: skip
#: each parameter's shape after the row count N (``shN``'s band count comes from render.sh_degree)
PARAM_TAILS: dict[str, tuple[int, ...]] = {
    "means": (3,), "scales": (3,), "quats": (4,), "opacities": (), "sh0": (1, 3), "shN": (-1, 3)
}  # fmt: skip


class _Bad(Exception):
    """A defect at a key path (turned into the one-line JsgsError by the public checks)."""

    def __init__(self, where: str, what: str) -> None:
        super().__init__(f"at {where}: {what}")


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_num(x: Any) -> bool:
    return (_is_int(x) or isinstance(x, float)) and math.isfinite(x)


def _finite_tensor(t: Any, where: str, dtype: torch.dtype | None = None) -> torch.Tensor:
    if not isinstance(t, torch.Tensor):
        raise _Bad(where, f"expected a tensor, found {type(t).__name__}")
    if dtype is not None and t.dtype != dtype:
        raise _Bad(where, f"dtype {str(t.dtype).removeprefix('torch.')}, expected "
                          f"{str(dtype).removeprefix('torch.')}")  # fmt: skip
    if (t.is_floating_point() or t.is_complex()) and not bool(torch.isfinite(t).all()):
        raise _Bad(where, "non-finite values (NaN/Inf)")
    return t


def _like(value: Any, template: Any, where: str) -> None:
    """``value`` has ``template``'s structure: the same keys, list lengths, Python types (any finite number
    for a float), tensor dtypes and shapes; floating tensors and numbers finite."""
    if isinstance(template, torch.Tensor):
        t = _finite_tensor(value, where, template.dtype)
        if t.shape != template.shape:
            raise _Bad(where, f"shape {tuple(t.shape)}, expected {tuple(template.shape)}")
    elif isinstance(template, Mapping):
        if not isinstance(value, Mapping):
            raise _Bad(where, f"expected a dict, found {type(value).__name__}")
        if set(value) != set(template):
            missing = sorted(map(str, set(template) - set(value)))
            extra = sorted(map(str, set(value) - set(template)))
            raise _Bad(where, f"missing key {missing[0]!r}" if missing else f"unexpected key {extra[0]!r}")
        for k in template:
            _like(value[k], template[k], f"{where}.{k}")
    elif isinstance(template, (list, tuple)):
        if not isinstance(value, (list, tuple)) or len(value) != len(template):
            raise _Bad(where, f"expected a list of {len(template)}")
        for i, (v, t) in enumerate(zip(value, template, strict=True)):
            _like(v, t, f"{where}[{i}]")
    elif isinstance(template, bool) or template is None or isinstance(template, str):
        if type(value) is not type(template):
            raise _Bad(where, f"expected {type(template).__name__}, found {type(value).__name__}")
    elif isinstance(template, float):
        if not _is_num(value):
            raise _Bad(where, f"expected a finite number, found {value!r}"[:200])
    elif _is_int(template):
        if not _is_int(value):
            raise _Bad(where, f"expected an integer, found {value!r}"[:200])


def _one_line(path: Path, e: Exception) -> JsgsError:
    what = " ".join(str(e).split())  # one line, whatever the keys hold
    what = what if len(what) <= 300 else what[:297] + "..."
    return JsgsError(f"{path}: not a usable checkpoint ({what}); remove it to resume from the one before, or "
                     "start over with --force")  # fmt: skip


def unusable(path: Path, e: Exception) -> JsgsError:
    """The one-line error for a checkpoint that passed the checks but could not be applied (``e``)."""
    from jsgs.base.errors import one_line

    return _one_line(path, Exception(f"it does not fit the run: {one_line(e)}"))


def check_structure(doc: dict[str, Any], path: Path, file_step: int | None = None) -> None:
    """What can be checked without the run: every key, ``step`` a non-negative integer (the one in the
    file's name), ``settings`` an object, ``manifest_sha256`` a string."""
    try:
        for k in KEYS:
            if k not in doc:
                raise _Bad(k, "missing")
        step = doc["step"]
        if not _is_int(step) or step < 0:
            raise _Bad("step", f"{step!r} is not a non-negative integer"[:200])
        if file_step is not None and step != file_step:
            raise _Bad("step", f"{step} but the file is named for step {file_step}")
        if not isinstance(doc["settings"], dict):
            raise _Bad("settings", "not an object")
        if not isinstance(doc["manifest_sha256"], str):
            raise _Bad("manifest_sha256", "not a string")
        for k in ("splats", "optimizers", "scheduler", "strategy", "rng", "sampler", "hook", "log"):
            if not isinstance(doc[k], dict):
                raise _Bad(k, "not a dict")
        if not isinstance(doc["evals"], list):
            raise _Bad("evals", "not a list")
        t = doc["train_time_s"]
        if not _is_num(t) or t < 0:
            raise _Bad("train_time_s", f"{t!r} is not a finite non-negative number"[:200])
    except _Bad as e:
        raise _one_line(path, e) from None


def check_splats(doc: dict[str, Any], path: Path, sh_rest: int) -> None:
    """The Gaussians: float32, finite, every parameter with the same row count and its shape
    (:data:`PARAM_TAILS`; ``shN`` with ``sh_rest`` = (sh_degree + 1)² - 1 bands)."""
    try:
        splats = doc["splats"]
        n: int | None = None
        for name, tail in PARAM_TAILS.items():
            where = f"splats.{name}"
            if name not in splats:
                raise _Bad(where, "missing")
            t = _finite_tensor(splats[name], where, torch.float32)
            want = tuple(sh_rest if d == -1 else d for d in tail)
            if t.dim() != 1 + len(want) or tuple(t.shape[1:]) != want:
                raise _Bad(where, f"shape {tuple(t.shape)}, expected (N, {', '.join(map(str, want))})"
                           .replace(", )", ")"))  # fmt: skip
            if n is None:
                n = t.shape[0]
            elif t.shape[0] != n:
                raise _Bad(where, f"{t.shape[0]} rows, but splats.means has {n}")
    except _Bad as e:
        raise _one_line(path, e) from None


def check_state(
    doc: dict[str, Any],
    path: Path,
    *,
    optimizers: Mapping[str, Mapping[str, Any]],
    scheduler: Mapping[str, Any],
    strategy: Mapping[str, Any],
    rng: Mapping[str, Any],
    sampler: Mapping[str, Any],
    num_views: int,
    eval_schema: Mapping[str, Any] | None = None,
) -> None:
    """Everything besides the Gaussians against the fresh objects' states (``optimizers``: each parameter's
    Adam ``state_dict()`` before any step; ``scheduler``, ``strategy``, ``rng``, ``sampler``: fresh states):
    the same structure, Adam moments of the parameter's shape and finite, the view order a permutation of
    the ``num_views`` training views, the log sums finite, the evaluations as metrics.json holds them."""
    try:
        splats, step = doc["splats"], doc["step"]
        n = splats["means"].shape[0]
        for name, fresh in optimizers.items():
            where = f"optimizers.{name}"
            od = doc["optimizers"].get(name)
            if not isinstance(od, Mapping) or set(od) != {"state", "param_groups"}:
                raise _Bad(where, "not an optimizer state (state, param_groups)")
            _check_group(od["param_groups"], fresh["param_groups"], f"{where}.param_groups")
            st = od["state"]
            if not isinstance(st, Mapping) or set(st) - {0}:
                raise _Bad(f"{where}.state", "expected the state of one parameter (key 0)")
            if 0 in st:
                s0 = st[0]
                if not isinstance(s0, Mapping) or set(s0) != {"step", "exp_avg", "exp_avg_sq"}:
                    raise _Bad(f"{where}.state[0]", "expected step, exp_avg, exp_avg_sq")
                k = _finite_tensor(s0["step"], f"{where}.state[0].step", torch.float32)
                if k.dim() != 0 or not 0 <= float(k) <= step:
                    raise _Bad(f"{where}.state[0].step", f"not a count in 0..{step}")
                shape = tuple(splats[name].shape)
                for m in ("exp_avg", "exp_avg_sq"):
                    t = _finite_tensor(s0[m], f"{where}.state[0].{m}", torch.float32)
                    if tuple(t.shape) != shape:
                        raise _Bad(f"{where}.state[0].{m}", f"shape {tuple(t.shape)}, expected {shape}")
                if bool((s0["exp_avg_sq"] < 0).any()):
                    raise _Bad(f"{where}.state[0].exp_avg_sq", "negative values")
        _check_scheduler(doc["scheduler"], scheduler, step)
        _check_strategy(doc["strategy"], strategy, n)
        _check_rng(doc["rng"], rng)
        _check_sampler(doc["sampler"], sampler, num_views)
        _check_log(doc["log"], "log")
        _check_evals(doc["evals"], step, eval_schema)
    except _Bad as e:
        raise _one_line(path, e) from None


def _same(a: Any, b: Any) -> bool:
    """Equal as JSON would hold them (a tuple equals the list of its items; 1 equals 1.0)."""
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return type(a) is type(b) and a == b or (_is_num(a) and _is_num(b) and a == b)


def _check_group(value: Any, fresh: Sequence[Mapping[str, Any]], where: str) -> None:
    """Adam's one parameter group: what the settings fix (betas, eps, weight decay, the initial learning
    rate, the flags) equal to a fresh optimizer's; the current learning rate a finite number >= 0."""
    if not isinstance(value, list) or len(value) != 1 or not isinstance(value[0], Mapping):
        raise _Bad(where, "expected one parameter group")
    g, f = value[0], fresh[0]
    if set(g) != set(f):
        raise _Bad(f"{where}[0]", f"expected the keys {sorted(f)}")
    for k, v in f.items():
        if k == "lr":
            if not _is_num(g[k]) or g[k] < 0:
                raise _Bad(f"{where}[0].lr", f"{g[k]!r} is not a learning rate"[:200])
        elif not _same(g[k], v):
            raise _Bad(f"{where}[0].{k}", f"{g[k]!r}, but the settings give {v!r}"[:200])


def _check_scheduler(value: Any, fresh: Mapping[str, Any], step: int) -> None:
    """The means' exponential decay: its factor and base rate as the settings give them, at the step."""
    _like(value, fresh, "scheduler")
    for k in ("gamma", "base_lrs"):
        if not _same(value[k], fresh[k]):
            raise _Bad(f"scheduler.{k}", f"{value[k]!r}, but the settings give {fresh[k]!r}"[:200])
    if value["last_epoch"] != step or value["_step_count"] != step + 1:
        raise _Bad("scheduler.last_epoch", f"{value['last_epoch']}, expected the step {step}")
    if not all(x >= 0 for x in value["_last_lr"]):
        raise _Bad("scheduler._last_lr", "negative")


def _check_strategy(value: Any, fresh: Mapping[str, Any], n: int) -> None:
    """DefaultStrategy's per-Gaussian sums (None before the first step, then N-row tensors) and scalars;
    MCMCStrategy's fixed tables."""
    if not isinstance(value, Mapping) or set(value) != set(fresh):
        raise _Bad("strategy", f"expected the keys {sorted(fresh)}")
    for k, t in fresh.items():
        where, v = f"strategy.{k}", value[k]
        if t is None:
            if v is not None:
                v = _finite_tensor(v, where)
                if v.dim() != 1 or v.shape[0] != n or v.dtype != torch.float32:
                    raise _Bad(where, f"expected a float32 vector of the {n} Gaussians")
        else:
            _like(v, t, where)


def _check_rng(value: Any, fresh: Mapping[str, Any]) -> None:
    """The generators' states as :func:`rng_state` writes them (CUDA states, of any number of devices, are
    used only where CUDA is; Python's cached Gaussian is None or a number)."""
    if not isinstance(value, Mapping) or set(value) != set(fresh):
        raise _Bad("rng", f"expected the keys {sorted(fresh)}")
    _like(value["torch"], fresh["torch"], "rng.torch")
    _like(value["numpy"], fresh["numpy"], "rng.numpy")
    cuda = value["cuda"]
    if not isinstance(cuda, list) or not all(
        isinstance(t, torch.Tensor) and t.dtype == torch.uint8 and t.dim() == 1 for t in cuda
    ):
        raise _Bad("rng.cuda", "expected a list of byte tensors")
    py = value["python"]
    if not isinstance(py, list) or len(py) != 3:
        raise _Bad("rng.python", "expected [version, state, gauss]")
    _like(py[:2], fresh["python"][:2], "rng.python")
    if py[2] is not None and not _is_num(py[2]):
        raise _Bad("rng.python[2]", "expected None or a finite number")


def _check_sampler(value: Any, fresh: Mapping[str, Any], num_views: int) -> None:
    _like(value.get("generator"), fresh["generator"], "sampler.generator")
    if set(value) != {"generator", "perm", "pos"}:
        raise _Bad("sampler", "expected generator, perm, pos")
    perm, pos = value["perm"], value["pos"]
    if not (isinstance(perm, list) and all(_is_int(i) for i in perm)) or (
        perm and sorted(perm) != list(range(num_views))
    ):
        raise _Bad("sampler.perm", f"not an order of the {num_views} training views")
    if not _is_int(pos) or not 0 <= pos <= len(perm):
        raise _Bad("sampler.pos", f"{pos!r} is not a position in the order"[:200])


def _check_log(value: Any, where: str) -> None:
    if not isinstance(value, Mapping) or not {"steps", "loss", "terms", "stats"} <= set(value):
        raise _Bad(where, "expected steps, loss, terms, stats")
    if not _is_int(value["steps"]) or value["steps"] < 0:
        raise _Bad(f"{where}.steps", "not a non-negative integer")
    if not _is_num(value["loss"]):
        raise _Bad(f"{where}.loss", "not a finite number")
    for part in ("terms", "stats"):
        d = value[part]
        if not isinstance(d, Mapping) or not all(isinstance(k, str) and _is_num(v) for k, v in d.items()):
            raise _Bad(f"{where}.{part}", "expected names with finite numbers")
    skipped = value.get("skipped")
    if not isinstance(skipped, Mapping) or not all(
        isinstance(k, str) and _is_int(v) and 0 <= v <= value["steps"] for k, v in skipped.items()
    ):
        raise _Bad(f"{where}.skipped", "expected names with step counts")
    per_view = value.get("per_view")
    if not isinstance(per_view, Mapping):
        raise _Bad(f"{where}.per_view", "not a dict")
    for name, acc in per_view.items():
        if not isinstance(name, str):
            raise _Bad(f"{where}.per_view", "view names must be strings")
        _check_log(acc, f"{where}.per_view.{name}")


def _check_evals(evals: Sequence[Any], step: int, schema: Mapping[str, Any] | None) -> None:
    last = 0
    for i, e in enumerate(evals):
        if not isinstance(e, Mapping) or not _is_int(e.get("step")) or not last < e["step"] <= step:
            raise _Bad(f"evals[{i}].step", f"not an increasing step in 1..{step}")
        last = e["step"]
    if schema is not None:
        import jsonschema

        err = jsonschema.exceptions.best_match(jsonschema.Draft202012Validator(schema).iter_errors(evals))
        if err is not None:
            loc = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in err.absolute_path)
            raise _Bad(f"evals{loc}", err.message[:200])
