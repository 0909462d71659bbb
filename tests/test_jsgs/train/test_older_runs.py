"""A run's config.json written by an earlier version (before ``speed``, ``checkpoint_keep``, the MCMC
strategy, ... existed) is read with the values that do what that version did, with one note naming them:
every committed config.json under docs/results reads, keeping what it records; ``jsgs render`` / ``export``
and ``--resume`` work on a run whose files lack ``speed``; a missing setting whose earlier value is not known
is refused in one line; a file written today must still hold every section."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pytest
from _train_scene import invoke_afresh as invoke
from _train_scene import train_tiny_run

from jsgs.base.errors import JsgsError

ROOT = Path(__file__).resolve().parents[3]
COMMITTED = sorted((ROOT / "docs" / "results").glob("**/config.json"))


def _flat(doc: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``doc``'s settings as dotted keys (method_options whole)."""
    out: dict[str, Any] = {}
    for k, v in doc.items():
        if isinstance(v, dict) and k != "method_options":
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def test_every_committed_run_config_reads_as_recorded(capsys: pytest.CaptureFixture[str]) -> None:
    """Each config.json under docs/results (written from 21 Nov on, several lacking ``speed``) reads; every
    value it records is the value read (``speed.exchange: auto`` as ``gsplat``), and the note names exactly
    the settings it lacks, each with the value read."""
    from jsgs.train import config
    from jsgs.train.config import config_from_document, current_values, to_dict

    config._said.clear()  # the notes are said once per process: other tests read some of these files
    assert len(COMMITTED) >= 100
    lacking = 0
    for path in COMMITTED:
        doc = json.loads(path.read_text())
        cfg = config_from_document(doc, path)
        read = _flat(to_dict(cfg))
        recorded = _flat(current_values(doc["settings"]))
        assert {k: read[k] for k in recorded} == recorded, path
        missing = sorted(set(read) - set(recorded))
        err = capsys.readouterr().err
        if missing:
            lacking += 1
            (line,) = err.strip().splitlines()
            assert line.startswith(f"note: {path} was written before some settings existed"), line
            named = line.split(": ", 2)[2].split(", ")
            assert sorted(n.split(" ")[0] for n in named) == missing, path
            assert all(json.loads(n.split(" ", 1)[1]) == read[n.split(" ")[0]] for n in named), line
        else:
            assert err == "", path
    assert lacking >= 80  # the paper_protocol and weight_sweep runs, and others


def test_what_older_files_get() -> None:
    """The values older files get: what jsgs did before each setting (all checkpoints kept, the torch SSIM,
    DefaultStrategy with its fixed budget, gsplat's exchange as a recorded ``auto``), a renamed key read
    under today's name; a setting every version recorded is not guessed (one line naming file and key)."""
    from jsgs.train.config import TrainConfig, recorded_settings, to_dict

    old = to_dict(TrainConfig.from_preset("paper"))
    for key in ("speed", "checkpoint_keep"):
        del old[key]
    for key in ("type", "cap_max", "cap_max_auto", "noise_lr", "min_opacity"):
        del old["strategy"][key]
    cfg = recorded_settings(old, "old/config.json")
    assert (cfg.speed.ssim_kernel, cfg.speed.exchange, cfg.checkpoint_keep) == ("torch", "gsplat", 0)
    assert (cfg.strategy.type, cfg.strategy.cap_max_auto) == ("default", False)
    renamed = {**old, "loss": {**old["loss"], "ssim_kernel": "cuda"}}
    assert recorded_settings(renamed, "old/config.json").speed.ssim_kernel == "cuda"
    jsgs = {**old, "method": "jsgs", "method_options": {"gc_kernel": "torch", "cuda_graph": False}}
    opts = recorded_settings(jsgs, "old/config.json").method_options
    assert opts == {"speed": {"gc_kernel": "torch", "cuda_graph": False}}
    del old["render"]["sh_degree"]
    with pytest.raises(JsgsError, match=r"^old/config.json: lacks the setting render.sh_degree, which chan"):
        recorded_settings(old, "old/config.json")


@pytest.fixture(scope="module")
def stopped(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny CPU run stopped at step 2 of 4 (a checkpoint at 2), as jsgs writes it today."""
    root = tmp_path_factory.mktemp("older")
    train_tiny_run(root, "--stop-at", "2", iterations=4, eval_at="2,4")
    return root / "run"


def _without_speed(run: Path, checkpoints: bool) -> dict[str, Any]:
    """Remove ``speed`` from RUN/config.json (and, with ``checkpoints``, from its checkpoints' settings), as
    a run trained before the section existed has it; the config.json document as it was."""
    import torch

    from jsgs.train import checkpoint as ckpt

    doc = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**doc, "settings": {
        k: v for k, v in doc["settings"].items() if k != "speed"}}))  # fmt: skip
    for _, p in ckpt.list_checkpoints(run / "checkpoints") if checkpoints else []:
        state = torch.load(p, weights_only=True)
        del state["settings"]["speed"]
        torch.save(state, p)
    return doc


def _notes(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if ln.startswith("note: ") and "before some settings" in ln]


def test_a_run_without_speed_resumes_renders_and_exports(stopped: Path, tmp_path: Path) -> None:
    """A run whose config.json and checkpoints lack ``speed``: --resume finishes it, render and export read
    it, each with one note naming what was assumed; the strict schema still refuses such a file as new."""
    from jsgs.base.schema import validate
    from jsgs.train.config import _all_names, config_schema

    run = tmp_path / "run"
    shutil.copytree(stopped, run)
    doc = _without_speed(run, checkpoints=True)
    validate(doc, "config", "today")  # written today: every section
    assert config_schema()["properties"]["settings"]["allOf"][1]["required"] == _all_names()
    assert {"speed", "checkpoint_keep"} <= set(_all_names())
    with pytest.raises(JsgsError, match="'speed' is a required property"):
        validate(json.loads((run / "config.json").read_text()), "config", "old")
    resume = ["train", doc["manifest"]["path"], "--out", str(run), "--resume", "--quiet"]
    r = invoke(resume)
    assert r.exit_code == 0, r.stderr
    assert "complete: 4/4" in r.output
    (note,) = _notes(r.stderr)
    assert note.endswith('speed.ssim_kernel "torch", speed.exchange "gsplat"'), note
    r = invoke(["export", str(run), "--out", str(tmp_path / "m.ply")])
    assert r.exit_code == 0, r.stderr
    assert len(_notes(r.stderr)) == 1 and (tmp_path / "m.ply").stat().st_size > 0
    args = ["render", str(run), "--out", str(tmp_path / "v.mp4"), "--frames", "2", "--device", "cpu"]
    r = invoke(args)
    assert r.exit_code == 0, r.stderr
    assert len(_notes(r.stderr)) == 1 and (tmp_path / "v.mp4").stat().st_size > 0


def test_a_config_without_speed_beside_a_checkpoint_with_it_is_refused(stopped: Path, tmp_path: Path) -> None:
    """config.json lacking ``speed`` beside a checkpoint written with it (edited after the checkpoint): the
    earlier version's values differ from the checkpoint's, so --resume refuses in one line naming both."""
    run = tmp_path / "run"
    shutil.copytree(stopped, run)
    doc = _without_speed(run, checkpoints=False)
    resume = ["train", doc["manifest"]["path"], "--out", str(run), "--resume", "--quiet"]
    r = invoke(resume)
    assert r.exit_code == 1 and "Traceback" not in r.output
    (line,) = [ln for ln in r.stderr.splitlines() if ln.startswith("error: ")]
    assert "written with other settings than" in line, line
    assert "speed.exchange ('gsplat' in config.json" in line, line


def test_a_new_run_takes_an_older_runs_config(tmp_path: Path) -> None:
    """``jsgs train --config OLD_RUN/config.json``: the older run's settings whole, with what it lacks as
    that version did it."""
    from jsgs.train.config import command_settings

    old = ROOT / "docs" / "results" / "weight_sweep" / "base0_obs1" / "config.json"
    assert "speed" not in json.loads(old.read_text())["settings"]
    cfg = command_settings(config_file=old)
    assert (cfg.strategy.type, cfg.speed.ssim_kernel, cfg.checkpoint_keep, cfg.iterations) == (
        "default", "torch", 0, 10_000)  # fmt: skip
