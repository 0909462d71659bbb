"""A checkpoint written by an earlier version: ``jsgs train --resume`` fills the fields added since with the
value that does what that version did (the log's per-view sums, their statistics and skipped counts), with
one note naming them, and continues to the same Gaussians as from today's checkpoint; a field no version
lacked is refused in one line naming the file and the field, never a traceback. ``jsgs export`` / ``render``
/ ``view`` read RUN/point_cloud.ply and config.json, not the checkpoints."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from _train_scene import invoke_afresh as invoke
from _train_scene import train_tiny_run

from jsgs.base.errors import JsgsError
from jsgs.base.ply import load_ply
from jsgs.train import checkpoint as ckpt


@pytest.fixture(scope="module")
def stopped(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny CPU run stopped at step 2 of 4 (a checkpoint at 2, in the middle of the log's interval: its
    per-view sums are not empty), as jsgs writes it today."""
    root = tmp_path_factory.mktemp("older_ckpt")
    train_tiny_run(root, "--stop-at", "2", iterations=4, eval_at="4")
    return root / "run"


@pytest.fixture(scope="module")
def finished_today(stopped: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The stopped run resumed from its checkpoint as written today."""
    run = tmp_path_factory.mktemp("today") / "run"
    shutil.copytree(stopped, run)
    r = invoke(_resume_args(run))
    assert r.exit_code == 0, r.stderr
    assert _notes(r.stderr) == []
    return run


def _notes(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if ln.startswith("note: ") and "checkpoint fields" in ln]


def _resume_args(run: Path) -> list[str]:
    import json

    manifest = json.loads((run / "config.json").read_text())["manifest"]["path"]
    return ["train", manifest, "--out", str(run), "--resume", "--quiet"]


def _edit(run: Path, change: Callable[[dict[str, Any]], None]) -> Path:
    """The run's last checkpoint rewritten with ``change`` applied (as an earlier version wrote it)."""
    path = ckpt.list_checkpoints(run / "checkpoints")[-1][1]
    doc = torch.load(path, weights_only=True)
    change(doc)
    torch.save(doc, path)
    return path


def _before_per_view(doc: dict[str, Any]) -> None:
    """The log as the first version kept it: no per-view sums, no skipped counts."""
    assert doc["log"]["per_view"], "the checkpoint is inside the log's interval"
    del doc["log"]["per_view"], doc["log"]["skipped"]


def _per_view_of_loss_and_terms(doc: dict[str, Any]) -> None:
    """The log as the version with the first per-view sums kept it: each view's steps, loss and terms."""
    del doc["log"]["skipped"]
    views = doc["log"]["per_view"]
    doc["log"]["per_view"] = {k: {"steps": v["steps"], "loss": v["loss"], "terms": v["terms"]}
                              for k, v in views.items()}  # fmt: skip


def _view_steps(run: Path) -> int:
    import json

    evals = json.loads((run / "metrics.json").read_text())["evals"]
    return sum(v["steps"] for v in evals[-1]["train"]["per_view"].values())


@pytest.mark.parametrize(
    ("change", "fields", "view_steps"),
    [
        (_before_per_view, "log.per_view {}, log.skipped {}", 2),
        (_per_view_of_loss_and_terms, "log.skipped {}, log.per_view.*.stats {}, log.per_view.*.per_view {}, "
                                      "log.per_view.*.skipped {}", 4),
    ],
)  # fmt: skip
def test_an_earlier_checkpoint_resumes_to_the_same_gaussians(
    stopped: Path, finished_today: Path, tmp_path: Path, change: Callable[[dict[str, Any]], None],
    fields: str, view_steps: int,
) -> None:  # fmt: skip
    run = tmp_path / "run"
    shutil.copytree(stopped, run)
    path = _edit(run, change)
    r = invoke(_resume_args(run))
    assert r.exit_code == 0, r.stderr
    assert "complete: 4/4" in r.output
    assert _notes(r.stderr) == [
        f"note: {path} was written before some checkpoint fields existed; read with the values that do "
        f"what that version did: {fields}"
    ]
    mine, today = load_ply(run / "point_cloud.ply"), load_ply(finished_today / "point_cloud.ply")
    assert mine.keys() == today.keys()
    for k in today:
        np.testing.assert_array_equal(mine[k], today[k], err_msg=k)
    # the interval's per-view means: only the steps after the checkpoint where it kept none
    assert (_view_steps(run), _view_steps(finished_today)) == (view_steps, 4)
    r = invoke(["export", str(run), "--out", str(tmp_path / "m.ply")])  # reads point_cloud.ply
    assert r.exit_code == 0 and _notes(r.stderr) == [], r.stderr


def _drop(key: str) -> Callable[[dict[str, Any]], None]:
    def change(doc: dict[str, Any]) -> None:
        del doc[key]

    return change


def _drop_log_steps(doc: dict[str, Any]) -> None:
    del doc["log"]["steps"]


@pytest.mark.parametrize(
    ("change", "what"),
    [
        (_drop("rng"), "not a usable checkpoint (at rng: missing)"),
        (_drop("train_time_s"), "not a usable checkpoint (at train_time_s: missing)"),
        (_drop_log_steps, "not a usable checkpoint (at log: expected steps, loss, terms, stats)"),
        (_drop("format_version"), "checkpoint format version None is not supported"),
    ],
)
def test_a_checkpoint_lacking_what_no_version_lacked_is_refused_in_one_line(
    stopped: Path, tmp_path: Path, change: Callable[[dict[str, Any]], None], what: str
) -> None:
    run = tmp_path / "run"
    shutil.copytree(stopped, run)
    path = _edit(run, change)
    r = invoke(_resume_args(run))
    assert r.exit_code == 1 and "Traceback" not in r.output + r.stderr, r.stderr
    (line,) = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert line.startswith(f"error: {path}: {what}"), line
    assert not (run / "point_cloud.ply").exists()


def test_a_sharded_resume_of_a_checkpoint_without_shards_is_refused() -> None:
    """Several processes resuming a checkpoint without ``shards``/``rng_ranks`` (one process's, or several's
    before the Gaussians were sharded, when every process held them all): no sound split, one line."""
    from jsgs.train.distributed import World, split_checkpoint

    doc = {"splats": {"means": torch.zeros(4, 3)}, "optimizers": {}, "strategy": {}, "rng": {}}
    with pytest.raises(JsgsError, match=r"^ck.pt: lacks shards and rng_ranks .* 2 processes cannot resume"):
        split_checkpoint(doc, World(rank=0, size=2), "ck.pt")


def test_fields_of_today_fill_only_what_is_absent() -> None:
    log = {"steps": 1, "loss": 1.0, "terms": {}, "stats": {}, "skipped": {"fro": 1},
           "per_view": {"a": {"steps": 1, "loss": 1.0, "terms": {}}}}  # fmt: skip
    doc = {"log": log}
    assert ckpt.fields_of_today(doc) == [
        "log.per_view.*.stats {}", "log.per_view.*.per_view {}", "log.per_view.*.skipped {}"
    ]
    assert log["skipped"] == {"fro": 1}
    assert log["per_view"]["a"] == {"steps": 1, "loss": 1.0, "terms": {}, "stats": {}, "per_view": {},
                                    "skipped": {}}  # fmt: skip
    assert ckpt.fields_of_today(doc) == []
    assert ckpt.fields_of_today({"log": "x"}) == [] and ckpt.fields_of_today([]) == []
