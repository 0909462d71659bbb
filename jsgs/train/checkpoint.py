"""Checkpoints: everything a run needs to continue bit for bit (on CPU) from the step it was written at.

Written with ``torch.save`` as a dict of tensors and plain Python values only, and read back with
``weights_only=True`` (no pickled code): parameters, Adam states, the means' LR scheduler, DefaultStrategy's
running state, every random generator the loop draws from (torch CPU/CUDA, numpy, Python, the view sampler),
the method hook's state, the accumulated training time, the evaluations so far and the partial log averages.
"""

from __future__ import annotations

import random
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from jsgs.errors import JsgsError
from jsgs.io import atomic_path

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
    try:
        doc = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises a variety of types for a damaged file
        raise JsgsError(f"{path}: not a readable checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(doc, dict) or doc.get("format") != CHECKPOINT_FORMAT:
        raise JsgsError(f"{path}: not a jsgs checkpoint")
    if doc.get("format_version") != CHECKPOINT_VERSION:
        raise JsgsError(f"{path}: checkpoint format version {doc.get('format_version')} is not supported")
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
