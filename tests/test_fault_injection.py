"""Fault injection across the command line: every bad input, hand-edited file and signal below must give a
non-zero exit, exactly one ``error:`` line (validate: its problem lines and one error line), no traceback, no
half-written file, no orphaned process, and no change to the source scene."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from jsgs.cli import main as jsgs_main
from jsgstools.cli import main as tools_main


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _half_written(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if ".part" in p.name] if root.exists() else []


def _check_one_line(output: str, code: int) -> None:
    assert code != 0, output
    assert "Traceback" not in output, output
    errors = [ln for ln in output.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1, output


def _first(scene: Path, sub: str) -> Path:
    return sorted((scene / sub).iterdir())[0]


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: max(1, path.stat().st_size // 2)])


# (name, how to break a copy of the scene, the command given that copy and a fresh output path)
Breaker = Callable[[Path], None]
SCENE_CASES: list[tuple[str, Breaker, list[str]]] = [
    ("truncated cameras.bin", lambda s: _truncate(s / "sparse/0/cameras.bin"), ["validate"]),
    ("truncated images.bin", lambda s: _truncate(s / "sparse/0/images.bin"), ["manifest"]),
    ("truncated points3D.bin", lambda s: _truncate(s / "sparse/0/points3D.bin"), ["compress"]),
    ("truncated PNG", lambda s: _truncate(_first(s, "images")), ["validate"]),
    ("truncated PNG", lambda s: _truncate(_first(s, "images")), ["compress"]),
    ("not an image", lambda s: _first(s, "images").write_bytes(b"hello"), ["manifest"]),
    ("no images folder", lambda s: shutil.rmtree(s / "images"), ["compress"]),
]


def _command(kind: str, scene: Path, out: Path) -> list[str]:
    if kind == "validate":
        return ["validate", str(scene)]
    if kind == "manifest":
        return ["manifest", str(scene), "--out", str(out / "manifest.json")]
    return ["compress", str(scene), "--out", str(out), "--schedule", "uniform", "--jobs", "1"]


@pytest.mark.parametrize(("name", "breaker", "kind"), [(n, b, k[0]) for n, b, k in SCENE_CASES])
def test_bad_scenes(synth_scene: Path, tmp_path: Path, name: str, breaker: Breaker, kind: str) -> None:
    scene = tmp_path / "scene"
    shutil.copytree(synth_scene, scene)
    breaker(scene)
    before = _tree(scene)
    out = tmp_path / "out"
    r = CliRunner().invoke(tools_main, _command(kind, scene, out))
    _check_one_line(r.output, r.exit_code)
    assert _tree(scene) == before, name
    assert not (out / "manifest.json").exists() and not _half_written(out)


def test_force_never_deletes_what_the_tool_did_not_make(synth_scene: Path, tmp_path: Path) -> None:
    other = tmp_path / "other_scene"
    shutil.copytree(synth_scene, other)
    (other / ".jsgstools.json").unlink()  # a COLMAP scene of the user's, not a synth output
    before = _tree(other)
    for args in (
        ["compress", str(synth_scene), "--out", str(other), "--schedule", "uniform", "--force"],
        ["synth", str(other), "--views", "2", "--size", "16x12", "--force"],
        ["manifest", str(synth_scene), "--out", str(_first(other, "images")), "--force"],
    ):
        r = CliRunner().invoke(tools_main, args)
        _check_one_line(r.output, r.exit_code)
        assert _tree(other) == before, args


@pytest.mark.parametrize(
    ("settings", "needle"),
    [({"optim": {"beta1": 5}}, "optim.beta1"), ({"optim": {"means_lr": -1}}, "optim.means_lr"),
     ({"render": {"near_plane": -1}}, "render.near_plane"),
     ({"strategy": {"cap_max": 0}}, "strategy.cap_max"),
     ({"iterations": "ten"}, "iterations"), ({"no_such_key": 1}, "no_such_key")],
)  # fmt: skip
def test_bad_settings_are_refused_before_anything_runs(
    compressed_scene: Path, tmp_path: Path, settings: dict[str, object], needle: str
) -> None:
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps(settings))
    run = tmp_path / "run"
    args = ["train", str(compressed_scene / "manifest.json"), "--out", str(run), "--config", str(cfg),
            "--device", "cpu", "--quiet"]  # fmt: skip
    r = CliRunner().invoke(jsgs_main, args)
    _check_one_line(r.output, r.exit_code)
    assert needle in r.output and not run.exists()


@pytest.mark.parametrize(
    ("args", "needle"),
    [(["compress", "{scene}", "--out", "{out}", "--schedule", "uniform", "--test-every", "1"],
      "--test-every"),
     (["compress", "{scene}", "--out", "{out}", "--schedule", "nope"], "schedule"),
     (["inspect-dqt", "{scene}/images"], "")],
)  # fmt: skip
def test_bad_tool_options(synth_scene: Path, tmp_path: Path, args: list[str], needle: str) -> None:
    argv = [a.format(scene=synth_scene, out=tmp_path / "out") for a in args]
    r = CliRunner().invoke(tools_main, argv)
    assert r.exit_code != 0 and "Traceback" not in r.output and needle in r.output, r.output


def test_bench_time_limit_must_be_positive(synth_scene: Path, tmp_path: Path) -> None:
    args = ["bench", str(synth_scene), "--out", str(tmp_path / "b"), "--time-limit", "-1", "--device", "cpu"]
    r = CliRunner().invoke(jsgs_main, args)
    _check_one_line(r.output, r.exit_code)
    assert "--time-limit" in r.output


def test_a_16_bit_scene_trains_on_its_values(synth_scene: Path, tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    shutil.copytree(synth_scene, scene)
    img = _first(scene, "images")
    grey = np.asarray(Image.open(img).convert("L")).astype(np.uint16)
    Image.fromarray(grey * 257).save(img)
    r = CliRunner().invoke(tools_main, ["manifest", str(scene), "--out", str(tmp_path / "m.json")])
    assert r.exit_code == 0, r.output
    from jsgs.train.data import load_image

    t = load_image(img, grey.shape[1], grey.shape[0], "image")
    assert (t.numpy() == grey.astype(np.uint8)[..., None]).all()


# ---------------------------------------------------------------------------------------------------------
# signals: one line, exit 143, no stack dump, no orphaned worker, no half-written file


def _wait_for(pred: Callable[[], bool], timeout: float) -> bool:
    end = time.time() + timeout
    while time.time() < end:
        if pred():
            return True
        time.sleep(0.05)
    return False


def _processes_naming(needle: str) -> list[int]:
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if needle.encode() in (d / "cmdline").read_bytes():
                    pids.append(int(d.name))
            except OSError:
                pass
    return pids


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc to find orphaned processes")
@pytest.mark.parametrize("tool", ["synth", "compress"])
def test_sigterm_is_one_line_and_leaves_nothing_running(synth_scene: Path, tmp_path: Path, tool: str) -> None:
    out = tmp_path / f"out_{tool}_sigterm"
    if tool == "synth":
        args = ["synth", str(out), "--views", "64", "--size", "320x240"]
        started = lambda: (out / "images").is_dir()  # noqa: E731
    else:
        src = tmp_path / "big"
        from jsgstools.synth import synth

        synth(src, views=48, size=(320, 240))
        args = ["compress", str(src), "--out", str(out), "--schedule", "uniform", "--jobs", "2"]
        started = lambda: (out / "reference").is_dir()  # noqa: E731
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.Popen([sys.executable, "-m", "jsgstools.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env)  # fmt: skip
    assert _wait_for(started, 60), "the command did not start writing"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    text = err.decode()
    assert proc.returncode == 143, text
    assert text.strip() == "error: terminated (SIGTERM)", text
    assert _wait_for(lambda: not _processes_naming(str(out)), 10), "orphaned processes remain"
    assert not _half_written(out)
    assert not (out / "manifest.json").exists()
