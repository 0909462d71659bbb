"""The checkpoint reader under random damage: a small real checkpoint's dict with a key dropped or added, a
value replaced (other types, NaN, Inf, huge or negative numbers, tensors of another shape or dtype or with
NaN), or its file's bytes flipped, read as ``--resume`` reads it (Trainer.read_checkpoint, Trainer.restore):
a one-line JsgsError naming the file, or a checkpoint that resumes; never anything else."""

from __future__ import annotations

import copy
import random
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from _train_scene import make_scene
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from jsgs.base.errors import JsgsError
from jsgs.train import checkpoint as ckpt
from jsgs.train.config import TrainConfig
from jsgs.train.trainer import Trainer, train


@pytest.fixture(scope="module")
def resumable(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Trainer, Path, dict[str, Any]]]:
    """A run stopped at step 2 of 4, a Trainer set up to resume it, its checkpoint's path and dict."""
    root = tmp_path_factory.mktemp("ckpt_fuzz")
    scene = make_scene(root / "scene")
    cfg = TrainConfig.from_preset("paper", method="gsplat", iterations=4, eval_at=[4], device="cpu")
    cfg.strategy.refine_start_iter = 10_000
    cfg.eval.fps_passes, cfg.eval.fps_warmup = 1, 0
    train(scene, root / "run", cfg, stop_at=2, progress=False, log=lambda s: None)
    path = root / "run" / "checkpoints" / "step_000002.pt"
    doc = ckpt.load_checkpoint(path)
    # the generators' states: restore() sets them, and later tests must not see that
    saved = torch.get_rng_state(), np.random.get_state(), random.getstate()
    trainer = Trainer(scene, root / "run", resume=True, log=lambda s: None)
    trainer.setup()
    yield trainer, path, doc
    assert trainer.lock is not None
    trainer.lock.release()
    torch.set_rng_state(saved[0])
    np.random.set_state(saved[1])
    random.setstate(saved[2])


def _paths(obj: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every key path into nested dicts and short lists (long ones, like the Python generator's 625 words,
    count as one value)."""
    out = [prefix] if prefix else []
    if isinstance(obj, dict):
        for k, v in obj.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(obj, list) and len(obj) <= 16:
        for i, v in enumerate(obj):
            out += _paths(v, (*prefix, i))
    return out


def _replacements(value: Any) -> list[Any]:
    out: list[Any] = [None, "x", -1, 2**70, float("nan"), float("inf"), True, [], {}, 0.5]
    if isinstance(value, torch.Tensor):
        t = value
        out += [t.double(), t.to(torch.int32), t.reshape(-1)[:-1] if t.numel() else torch.ones(2)]
        if t.is_floating_point() and t.numel():
            bad = t.clone()
            bad.reshape(-1)[0] = float("nan")
            out += [bad, -t.abs() - 1, t.reshape(-1)[:1]]
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        out += [-value - 1, value + 1, float(value) * 1e300]
    return out


@st.composite
def damaged(draw: st.DrawFn, doc: dict[str, Any]) -> tuple[dict[str, Any] | None, int | None]:
    """(a damaged copy of ``doc``, None) or (None, a byte offset of the file to flip)."""
    if draw(st.integers(0, 9)) == 0:
        return None, draw(st.integers(0, 1 << 20))
    d = copy.deepcopy(doc)
    for _ in range(draw(st.integers(1, 2))):
        paths = _paths(d)
        path = draw(st.sampled_from(paths))
        parent = d
        for k in path[:-1]:
            parent = parent[k]
        key = path[-1]
        op = draw(st.sampled_from(["delete", "replace", "replace", "replace", "add"]))
        if op == "delete":
            del parent[key]
        elif op == "add" and isinstance(parent, dict):
            parent["unexpected"] = 1
        else:
            parent[key] = draw(st.sampled_from(_replacements(parent[key])))
    return d, None


def _read_as_resume_does(trainer: Trainer, path: Path) -> None:
    """Read and restore the checkpoint; when that succeeds, what resuming does next must work too: a step
    and a valid metrics document."""
    from jsgs.base.schema import validate

    cfg = trainer.cfg
    assert cfg is not None
    trainer.restore(trainer.read_checkpoint(cfg))
    trainer.step(trainer.start_step)
    validate(trainer.metrics_doc("running", trainer.start_step + 1), "metrics", "metrics.json")


def test_strategy_sums_of_another_dtype_are_one_line(resumable: tuple[Trainer, Path, dict[str, Any]]) -> None:
    """DefaultStrategy's per-Gaussian sums in float64 (or int) are refused in one line, not passed on to
    gsplat's ``index_add_`` (a RuntimeError traceback); the fuzz test above found the float64 case."""
    trainer, path, doc = resumable
    sums = [k for k, v in doc["strategy"].items() if isinstance(v, torch.Tensor) and v.dim() == 1]
    assert sums, "the fixture's strategy has per-Gaussian sums"
    for k in sums:
        for cast in (torch.float64, torch.int64):
            d = copy.deepcopy(doc)
            d["strategy"][k] = d["strategy"][k].to(cast)
            torch.save(d, path)
            with pytest.raises(JsgsError, match=rf"strategy\.{k}: .*float32") as e:
                _read_as_resume_does(trainer, path)
            assert "\n" not in str(e.value)


def test_the_unharmed_checkpoint_resumes(resumable: tuple[Trainer, Path, dict[str, Any]]) -> None:
    trainer, path, doc = resumable
    ckpt.save_checkpoint(path, {k: v for k, v in doc.items() if k not in ("format", "format_version")})
    _read_as_resume_does(trainer, path)
    assert trainer.start_step == 2


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                   HealthCheck.too_slow])  # fmt: skip
@given(data=st.data())
def test_damaged_checkpoints_are_one_line(
    resumable: tuple[Trainer, Path, dict[str, Any]], data: st.DataObject
) -> None:
    trainer, path, doc = resumable
    d, flip = data.draw(damaged(doc))
    if d is not None:
        torch.save(d, path)
    else:
        ckpt.save_checkpoint(path, {k: v for k, v in doc.items() if k not in ("format", "format_version")})
        raw = bytearray(path.read_bytes())
        raw[flip % len(raw)] ^= 0xFF
        path.write_bytes(bytes(raw))
    try:
        _read_as_resume_does(trainer, path)
        event("resumes")
    except JsgsError as e:
        msg = str(e)
        assert msg.startswith(str(path)) and "\n" not in msg, msg
        event("one line")
