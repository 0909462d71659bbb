"""Fault injection for what the commands write and what they read: no command writes through a link it did
not make (a planted link at the old fixed temporary name, a link at the output's own name), export and
render never replace a run's own files, a failed command removes what it wrote (a full disk simulated with
RLIMIT_FSIZE), render streams its frames and refuses sizes and rates it cannot use, a broken model gives
one line instead of a black video or a traceback, and a FIFO named like an input is refused at once."""

from __future__ import annotations

import contextlib
import json
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from _train_scene import train_tiny_run
from click.testing import CliRunner

from jsgs.cli import main as jsgs_main
from jsgstools.cli import main as tools_main

ROOT = Path(__file__).resolve().parents[1]


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _one_line(output: str, code: int) -> str:
    assert code != 0, output
    assert "Traceback" not in output, output
    errors = [ln for ln in output.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1, output
    return errors[0]


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("writes")
    train_tiny_run(root, iterations=3, eval_at="3")
    return root / "run"


def _rewrite_ply(run: Path, change: str) -> None:
    """Rewrite RUN/point_cloud.ply byte for byte in the 3DGS layout with one defect (save_ply would refuse
    to write it)."""
    from jsgs.base.ply import ply_header, read_ply_vertices

    path = run / "point_cloud.ply"
    v = read_ply_vertices(path)
    names = list(v.dtype.names or ())
    t = np.stack([v[n] for n in names], axis=1).astype("<f4")
    if change == "nan rows":
        t[:3, names.index("x")] = np.nan
    elif change == "all nan":
        t[:, names.index("y")] = np.nan
    elif change == "zero quaternions":
        for i in range(4):
            t[:, names.index(f"rot_{i}")] = 0.0
    elif change == "no gaussians":
        t = t[:0]
    elif change == "transparent rows":
        t[:5, names.index("opacity")] = -10.0  # sigmoid 4.5e-5: below ply-compressed's 1/255
    path.write_bytes(ply_header(t.shape[0], (t.shape[1] - 17) // 3) + t.tobytes())


# ---------------------------------------------------------------------------------------------------------
# links


def test_render_never_writes_through_a_planted_link(run: Path, tmp_path: Path) -> None:
    import imageio.v2 as iio

    victim = tmp_path / "elsewhere" / "victim.txt"
    victim.parent.mkdir()
    victim.write_bytes(b"not yours")
    out = tmp_path / "out"
    out.mkdir()
    # the fixed temporary name render used to write through, and names like the new temporary files
    for name in (".v.part.mp4", ".v.mp4.part.mp4", ".v.mp4.cameras.json.part.json"):
        (out / name).symlink_to(victim)
    args = ["render", str(run), "--out", str(out / "v.mp4"), "--frames", "2", "--device", "cpu"]
    r = CliRunner().invoke(jsgs_main, args)
    assert r.exit_code == 0, r.output
    assert victim.read_bytes() == b"not yours"
    assert (out / "v.mp4").is_file() and not (out / "v.mp4").is_symlink()
    assert iio.get_reader(out / "v.mp4").count_frames() == 2
    # a link at the output's own name: refused without --force, replaced (never followed) with it
    (out / "w.mp4").symlink_to(victim)
    args = ["render", str(run), "--out", str(out / "w.mp4"), "--frames", "2", "--device", "cpu"]
    r = CliRunner().invoke(jsgs_main, args)
    assert "exists (use --force" in _one_line(r.output, r.exit_code)
    r = CliRunner().invoke(jsgs_main, [*args, "--force"])
    assert r.exit_code == 0, r.output
    assert victim.read_bytes() == b"not yours" and not (out / "w.mp4").is_symlink()
    left = sorted(p.name for p in out.iterdir() if ".part" in p.name)
    assert left == [".v.mp4.cameras.json.part.json", ".v.mp4.part.mp4", ".v.part.mp4"]  # only the planted


def test_atomic_writes_replace_links_and_leave_nothing_on_failure(tmp_path: Path) -> None:
    from jsgs.base.errors import JsgsError
    from jsgs.base.io import open_log, write_bytes_atomic, write_with_atomic
    from jsgs.bench.results import write_csv

    victim = tmp_path / "victim"
    victim.write_bytes(b"keep")
    (tmp_path / "results.csv.tmp").symlink_to(victim)  # the bench's old fixed temporary name
    write_csv([{"id": "a"}], tmp_path / "results.csv")
    (tmp_path / "f.bin").symlink_to(victim)
    write_bytes_atomic(tmp_path / "f.bin", b"new")
    assert victim.read_bytes() == b"keep" and (tmp_path / "f.bin").read_bytes() == b"new"
    assert not (tmp_path / "f.bin").is_symlink() and (tmp_path / "results.csv").read_text().endswith(",a\n")

    def fail(p: Path) -> None:
        p.write_bytes(b"half")
        raise OSError(28, "No space left on device")

    with pytest.raises(JsgsError, match="g.bin: cannot write"):
        write_with_atomic(tmp_path / "g.bin", fail)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".g.bin")]
    (tmp_path / "train.log").symlink_to(victim)
    with pytest.raises(JsgsError, match="is a link"):
        open_log(tmp_path / "train.log")
    assert victim.read_bytes() == b"keep"


# ---------------------------------------------------------------------------------------------------------
# a run's own files


def test_export_and_render_never_replace_the_run_files(run: Path) -> None:
    before = _tree(run)
    for args, needle in (
        (["export", str(run), "--out", str(run / "config.json"), "--force"], "run's own config.json"),
        (["export", str(run), "--out", str(run / "point_cloud_colmap.ply"), "--force"], "point_cloud_colmap"),
        (["export", str(run), "--out", str(run / "metrics"), "--force"], "run's own metrics.json"),  # record
        (["export", str(run), "--out", str(run / "checkpoints" / "x.ply"), "--force"], "checkpoints"),
        (["render", str(run), "--out", str(run), "--force", "--device", "cpu"], "is or contains the run"),
        (["render", str(run), "--out", str(run / "renders"), "--force", "--device", "cpu"], "renders"),
    ):
        r = CliRunner().invoke(jsgs_main, args)
        assert needle in _one_line(r.output, r.exit_code), args
    assert _tree(run) == before


# ---------------------------------------------------------------------------------------------------------
# broken models


@pytest.mark.parametrize("change", ["nan rows", "all nan", "zero quaternions", "no gaussians"])
def test_broken_models_are_refused_in_one_line(run: Path, tmp_path: Path, change: str) -> None:
    broken = tmp_path / "run"
    shutil.copytree(run, broken)
    _rewrite_ply(broken, change)
    for args in (
        ["export", str(broken), "--out", str(tmp_path / "x.ply")],
        ["export", str(broken), "--out", str(tmp_path / "x.splat"), "--format", "splat"],
        ["render", str(broken), "--out", str(tmp_path / "x.mp4"), "--frames", "2", "--device", "cpu"],
        ["view", str(broken), "--device", "cpu", "--port", "18089"],  # refused before any server starts
    ):
        r = CliRunner().invoke(jsgs_main, args)
        line = _one_line(r.output, r.exit_code)
        assert "point_cloud.ply" in line, line
        assert ("no Gaussians" if change == "no gaussians" else "the model is damaged") in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # nothing written


def test_export_records_the_rows_it_writes(run: Path, tmp_path: Path) -> None:
    from jsgs.base.ply import read_ply_vertices

    faint = tmp_path / "run"
    shutil.copytree(run, faint)
    _rewrite_ply(faint, "transparent rows")
    n = len(read_ply_vertices(faint / "point_cloud.ply"))
    for fmt, kept in (("ply", n), ("splat", n), ("ply-compressed", n - 5)):
        out = tmp_path / f"x.{fmt}"
        r = CliRunner().invoke(jsgs_main, ["export", str(faint), "--out", str(out), "--format", fmt])
        assert r.exit_code == 0, r.output
        rec = json.loads((tmp_path / f"x.{fmt}.json").read_text())
        data = out.read_bytes()
        in_file = len(data) // 32 if fmt == "splat" else int(re.search(rb"element vertex (\d+)", data)[1])
        assert rec["gaussians"] == in_file == kept and rec["dropped"] == n - kept
        assert f"{kept} Gaussians" in r.output and (("5 nearly transparent" in r.output) == (kept < n))


# ---------------------------------------------------------------------------------------------------------
# bounded resources


@pytest.mark.parametrize(
    ("option", "needle"),
    [(["--size", "100000x100000"], "at most 8192 pixels a side"), (["--fps", "nan"], "--fps nan"),
     (["--fps", "inf"], "--fps inf"), (["--fps", "-1"], "--fps -1"), (["--fps", "1e9"], "--fps 1e+09")],
)  # fmt: skip
def test_render_refuses_sizes_and_rates_up_front(tmp_path: Path, option: list[str], needle: str) -> None:
    # RUN does not even exist: the settings are checked before anything is read
    args = ["render", str(tmp_path / "no_run"), "--out", str(tmp_path / "v.mp4"), *option, "--device", "cpu"]
    r = CliRunner().invoke(jsgs_main, args)
    assert needle in _one_line(r.output, r.exit_code)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("cameras", "size", "needle"),
    [(100_001, (32, 24), "100001 cameras; render draws at most 100,000"),
     (2, (100_000, 24), "100000x24 is larger than jsgs render draws")],
)  # fmt: skip
def test_render_refuses_camera_path_files_beyond_the_limits(
    run: Path, tmp_path: Path, cameras: int, size: tuple[int, int], needle: str
) -> None:
    from jsgs.apps.camera_path import CameraPath

    K = np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])
    doc = CameraPath(np.repeat(np.eye(4)[None], 2, 0), K, *size, "interpolate").to_json(30.0)
    if cameras > 2:
        doc["camtoworld"] = [0] * cameras  # counted before anything else is read of them
    path = tmp_path / "path.json"
    path.write_text(json.dumps(doc))
    args = ["render", str(run), "--out", str(tmp_path / "v.mp4"), "--path", str(path), "--device", "cpu"]
    r = CliRunner().invoke(jsgs_main, args)
    assert needle in _one_line(r.output, r.exit_code)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["path.json"]


def test_render_streams_frames_to_the_encoder(
    run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import imageio.v2 as iio

    import jsgs.apps.viewer

    events: list[str] = []
    render_rgb, get_writer = jsgs.apps.viewer.render_rgb, iio.get_writer

    def rendering(*a: object, **k: object) -> np.ndarray:
        events.append("render")
        return render_rgb(*a, **k)  # type: ignore[arg-type]

    def writer(*a: object, **k: object) -> object:
        w = get_writer(*a, **k)  # type: ignore[arg-type]
        append = w.append_data

        def appending(img: np.ndarray) -> None:
            events.append("encode")
            append(img)

        w.append_data = appending
        return w

    monkeypatch.setattr(jsgs.apps.viewer, "render_rgb", rendering)
    monkeypatch.setattr(iio, "get_writer", writer)
    args = ["render", str(run), "--out", str(tmp_path / "v.mp4"), "--frames", "5", "--device", "cpu"]
    r = CliRunner().invoke(jsgs_main, args)
    assert r.exit_code == 0, r.output
    assert events == ["render", "encode"] * 5  # each frame encoded before the next is drawn


def _fs_limit(limit: int) -> None:
    # a write past the limit fails with EFBIG, as one on a full disk fails with ENOSPC
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))


@pytest.mark.skipif(not hasattr(resource, "RLIMIT_FSIZE"), reason="needs RLIMIT_FSIZE")
def test_compress_that_fails_on_a_full_disk_leaves_nothing(synth_scene: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    before = _tree(synth_scene)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    argv = [sys.executable, "-m", "jsgstools.cli", "compress", str(synth_scene), "--out", str(out),
            "--schedule", "uniform", "--jobs", "1"]  # fmt: skip
    r = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=300,
                       preexec_fn=lambda: _fs_limit(4000))  # fmt: skip
    assert "cannot write (File too large)" in _one_line(r.stderr, r.returncode)
    assert not out.exists()  # neither the marker, the lock, nor a half-made dataset
    assert _tree(synth_scene) == before


# ---------------------------------------------------------------------------------------------------------
# inputs that are not regular files


@pytest.fixture
def fifo(tmp_path: Path) -> Iterator[Path]:
    """A FIFO; a background thread opens its write end whenever a reader waits on it and closes it again,
    so a reader that opens it blocks only briefly and then sees an empty file (the test fails on the
    message, never hangs)."""
    path = tmp_path / "pipe"
    path.mkdir()
    path = path / "named.jpg"
    os.mkfifo(path)
    stop = threading.Event()

    def unblock() -> None:
        while not stop.wait(0.05):
            try:
                os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))
            except OSError:
                pass  # no reader waiting

    t = threading.Thread(target=unblock, daemon=True)
    t.start()
    yield path
    stop.set()
    t.join()


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_inspect_dqt_refuses_a_fifo_and_reports_the_other_files(tmp_path: Path, fifo: Path) -> None:
    from PIL import Image

    rgb = np.random.default_rng(0).integers(0, 256, (16, 16, 3), dtype=np.uint8)
    a, c = tmp_path / "a.jpg", tmp_path / "c.jpg"
    Image.fromarray(rgb).save(a, quality=80)
    Image.fromarray(rgb).save(c, quality=60)
    for extra in ([], ["--analyze"]):
        r = CliRunner().invoke(tools_main, ["inspect-dqt", *extra, str(a), str(fifo), str(c)])
        line = _one_line(r.output, r.exit_code)
        assert line == f"error: {fifo}: is a FIFO (named pipe), not a regular file"
        rows = [ln.split()[0] for ln in r.output.splitlines() if ln.endswith(".jpg") or ".jpg " in ln]
        assert str(a) in rows and str(c) in rows, r.output


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_other_readers_refuse_a_fifo(run: Path, tmp_path: Path, fifo: Path) -> None:
    manifest = json.loads((run / "config.json").read_text())["manifest"]["path"]
    for args in (
        ["train", str(fifo), "--out", str(tmp_path / "r"), "--device", "cpu"],
        ["train", manifest, "--config", str(fifo), "--out", str(tmp_path / "r"), "--device", "cpu"],
        ["render", str(run), "--out", str(tmp_path / "v.mp4"), "--path", str(fifo), "--device", "cpu"],
    ):
        r = CliRunner().invoke(jsgs_main, args)
        line = _one_line(r.output, r.exit_code)
        assert line == f"error: {fifo}: is a FIFO (named pipe), not a regular file"
    assert not (tmp_path / "r" / "config.json").exists() and not (tmp_path / "v.mp4").exists()
    # a newer "checkpoint" that is a FIFO (through a link: the same open) stops --resume in one line
    resumed = tmp_path / "resumed"
    shutil.copytree(run, resumed)
    (resumed / "checkpoints" / "step_999999.pt").symlink_to(fifo)
    args = ["train", manifest, "--out", str(resumed), "--resume", "--device", "cpu"]
    r = CliRunner().invoke(jsgs_main, args)
    assert "step_999999.pt: is a FIFO (named pipe)" in _one_line(r.output, r.exit_code)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_a_fifo_among_a_scenes_images_is_named(synth_scene: Path, tmp_path: Path, fifo: Path) -> None:
    scene = tmp_path / "scene"
    shutil.copytree(synth_scene, scene)
    image = sorted((scene / "images").iterdir())[0]
    image.unlink()
    image.symlink_to(fifo)
    for args in (["validate", str(scene)], ["manifest", str(scene), "--out", str(tmp_path / "m.json")]):
        r = CliRunner().invoke(tools_main, args)
        assert f"{image}: is a FIFO (named pipe)" in r.output and r.exit_code != 0, r.output
        assert "Traceback" not in r.output
    assert not (tmp_path / "m.json").exists()


def test_every_entry_the_trainer_writes_is_protected() -> None:
    from jsgs.base.io import LOCK_NAME
    from jsgs.base.run_files import RUN_OWNED
    from jsgs.train.trainer import RUN_ENTRIES

    assert set(RUN_ENTRIES) | {LOCK_NAME, "viewer_cameras.json"} <= set(RUN_OWNED)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_force_never_waits_on_a_fifo_named_like_an_earlier_output(
    run: Path, synth_scene: Path, tmp_path: Path
) -> None:
    """--force reads the earlier output to see whether the tool made it: a FIFO there is refused at once."""
    out, again = tmp_path / "out", tmp_path / "again"
    out.mkdir()
    (out / "x").write_text("")
    again.mkdir()
    manifest = json.loads((run / "config.json").read_text())["manifest"]["path"]
    fifos = (tmp_path / "m.json", out / ".jsgstools.json", again / "config.json")
    for p in fifos:
        os.mkfifo(p)  # nobody writes them: a reader that opened one would wait forever
    cases = (
        (tools_main, ["manifest", str(synth_scene), "--out", str(tmp_path / "m.json"), "--force"],
         "is not a jsgs manifest"),
        (tools_main, ["downscale", str(synth_scene), "--out", str(out), "--force"],
         f"{out / '.jsgstools.json'}: is a FIFO (named pipe), not a regular file; not provably a marker"),
        (jsgs_main, ["train", manifest, "--out", str(again), "--force", "--device", "cpu"],
         "this folder holds none"),
        (jsgs_main, ["export", str(again), "--out", str(tmp_path / "x.ply")],
         f"{again / 'config.json'}: is a FIFO (named pipe), not a regular file"),
    )  # fmt: skip
    results: list[object] = []

    def invoke() -> None:
        results.extend(CliRunner().invoke(cli, args) for cli, args, _ in cases)

    t = threading.Thread(target=invoke, daemon=True)
    t.start()
    t.join(120)  # the commands take seconds; a reader waiting on a FIFO never returns
    if t.is_alive():
        for p in fifos:  # let the waiting reader go before failing
            with contextlib.suppress(OSError):
                os.close(os.open(p, os.O_WRONLY | os.O_NONBLOCK))
        t.join(30)
        pytest.fail(f"a command waited on a FIFO (after {len(results)} of {len(cases)} commands)")
    for r, (_, _, needle) in zip(results, cases, strict=True):
        assert needle in _one_line(r.output, r.exit_code), r.output  # type: ignore[attr-defined]
