"""``jsgs render``: camera paths (interpolation through the key cameras, orbits looking at the focus point),
a video readable by imageio with the requested frames, PNG frames, the path JSON rendered again to the same
frames, the test views beside their references, saved viewer cameras as key frames, one-line errors."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from _train_scene import edit_manifest, train_tiny_run
from click.testing import CliRunner
from PIL import Image

from jsgs.apps.camera_path import focus_point, interpolate, look_at, orbit, scaled_K


def _ring(n: int) -> np.ndarray:
    c2w = []
    for k in range(n):
        a = 0.3 * k
        pos = np.array([4 * math.cos(a), 0.5, 4 * math.sin(a)])
        c2w.append(look_at(pos, np.zeros(3), np.array([0.0, 1.0, 0.0])))
    return np.stack(c2w)


def test_interpolation_passes_through_the_key_cameras() -> None:
    keys = _ring(4)
    path = interpolate(keys, 7)  # 3 segments, 2 frames each: keys at frames 0, 2, 4, 6
    for i, k in zip((0, 2, 4, 6), keys, strict=True):
        assert np.allclose(path[i], k, atol=1e-9)
    for c in path:  # proper rotations
        assert np.allclose(c[:3, :3] @ c[:3, :3].T, np.eye(3), atol=1e-9) and np.linalg.det(c[:3, :3]) > 0


def test_orbits_look_at_the_focus_point() -> None:
    keys = _ring(6)
    f = focus_point(keys)
    assert np.allclose(f, 0.0, atol=1e-6)  # every camera looks at the origin
    for kind in ("spiral", "ellipse"):
        path = orbit(keys, 10, kind)
        for c in path:
            d = f - c[:3, 3]
            assert np.allclose(c[:3, 2], d / np.linalg.norm(d), atol=1e-9)
        assert len({tuple(np.round(c[:3, 3], 6)) for c in path}) == 10  # it moves


def test_orbits_refuse_cameras_that_look_all_around() -> None:
    """Four cameras on a ring looking inward: the mean viewing direction is exactly zero, so the average
    camera has no direction; one line instead of numpy's divide warning and a path of NaN."""
    import warnings

    from jsgs.base.errors import JsgsError

    ring = np.stack([look_at(np.array(p, float), np.zeros(3), np.array([0.0, 1.0, 0.0]))
                     for p in ([4, 0, 0], [0, 0, 4], [-4, 0, 0], [0, 0, -4])])  # fmt: skip
    assert not ring[:, :3, 2].sum(axis=0).any()
    for kind in ("spiral", "ellipse"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(JsgsError, match=f"--path {kind}: the training cameras look all around"):
                orbit(ring, 5, kind)
    assert np.isfinite(interpolate(ring, 5)).all()  # the other path still works


def test_scaled_intrinsics_keep_the_field_of_view() -> None:
    K = np.array([[30.0, 0, 16.0], [0, 30.0, 12.0], [0, 0, 1]])
    K2 = scaled_K(K, 32, 24, 64, 48)
    assert np.allclose(K2, [[60, 0, 32], [0, 60, 24], [0, 0, 1]])


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:

    root = tmp_path_factory.mktemp("render")
    train_tiny_run(root)
    return root / "run"


def test_video_frames_and_path_round_trip(run: Path, tmp_path: Path) -> None:
    import imageio.v2 as iio

    from jsgs.base.schema import validate
    from jsgs.cli import main

    video = tmp_path / "spiral.mp4"
    args = ["render", str(run), "--out", str(video), "--path", "spiral", "--frames", "6", "--fps", "12",
            "--size", "33x25", "--device", "cpu"]  # fmt: skip
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    reader = iio.get_reader(video)
    assert reader.count_frames() == 6 and reader.get_meta_data()["fps"] == 12
    assert reader.get_data(0).shape == (26, 34, 3)  # padded to even sizes for H.264
    cams = json.loads((tmp_path / "spiral.mp4.cameras.json").read_text())
    validate(cams, "camera_path", "cameras")
    assert cams["kind"] == "spiral" and len(cams["camtoworld"]) == 6
    assert (cams["width"], cams["height"]) == (33, 25)
    # the same path as PNG frames, twice: from the generator and from its JSON
    a, b = tmp_path / "a", tmp_path / "b"
    r = CliRunner().invoke(main, ["render", str(run), "--out", str(a), "--path", "spiral", "--frames", "6",
                                  "--size", "33x25", "--device", "cpu"])  # fmt: skip
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["render", str(run), "--out", str(b), "--path", str(a / "cameras.json"),
                                  "--device", "cpu"])  # fmt: skip
    assert r.exit_code == 0, r.output
    fa, fb = sorted(a.glob("frame_*.png")), sorted(b.glob("frame_*.png"))
    assert len(fa) == len(fb) == 6
    for x, y in zip(fa, fb, strict=True):
        assert (np.asarray(Image.open(x)) == np.asarray(Image.open(y))).all()
    assert np.asarray(Image.open(fa[0])).std() > 1  # something drawn


def test_test_views_beside_references_and_viewer_cameras(run: Path, tmp_path: Path) -> None:
    from jsgs.apps.viewer import load_run_model, save_camera
    from jsgs.base.rotations import matrix_to_quat
    from jsgs.cli import main

    r = CliRunner().invoke(main, ["render", str(run), "--out", str(tmp_path / "t"), "--path", "test",
                                  "--device", "cpu"])  # fmt: skip
    assert r.exit_code == 0, r.output
    frames = sorted((tmp_path / "t").glob("frame_*.png"))
    model = load_run_model(run, "cpu")
    assert len(frames) == len(model.scene.test_views)
    assert Image.open(frames[0]).size == (64, 24)  # render | reference
    for v in model.scene.train_views[:2]:
        save_camera(model, v.camtoworld[:3, 3], matrix_to_quat(v.camtoworld[:3, :3]), 0.9, 4 / 3)
    args = ["render", str(run), "--out", str(tmp_path / "v"), "--path", str(run / "viewer_cameras.json"),
            "--frames", "3", "--device", "cpu"]  # fmt: skip
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    assert len(list((tmp_path / "v").glob("frame_*.png"))) == 3


def test_render_errors_are_one_line(run: Path, tmp_path: Path) -> None:
    from jsgs.apps.camera_path import CameraPath
    from jsgs.cli import main

    K = np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])
    doc = CameraPath(np.repeat(np.eye(4)[None], 2, 0), K, 32, 24, "interpolate").to_json(30.0)
    doc["camtoworld"][1][3] = [0.0, 0.0, 0.0, 0.0]  # not invertible
    (tmp_path / "flat.json").write_text(json.dumps(doc))
    for args, needle in (
        (["--out", str(tmp_path / "x.mp4"), "--path", str(tmp_path / "flat.json")],
         "flat.json: camtoworld/1: not a camera pose (its last row is not 0 0 0 1)"),  # fmt: skip
        (["--out", str(tmp_path / "x.mp4"), "--size", "big"], "--size 'big'"),
        (["--out", str(tmp_path / "x.txt")], "give a video"),
        (["--out", str(tmp_path / "x.mp4"), "--path", str(tmp_path / "none.json")], "no such file"),
        (["--out", str(tmp_path / "x.mp4"), "--fps", "0"], "--fps 0"),
    ):
        r = CliRunner().invoke(main, ["render", str(run), *args, "--device", "cpu"])
        assert r.exit_code == 1 and needle in r.output and r.output.count("\n") == 1, r.output


@pytest.mark.parametrize("recorded", ["trained", "edited"])
def test_a_manifest_edited_to_have_no_training_views_is_one_line(
    run: Path, tmp_path: Path, recorded: str
) -> None:
    """Only an edit after training leaves a run's manifest without training views; reading the run refuses
    it (the scene's own check, naming the manifest). When the manifest's sha256 is no longer the one
    config.json recorded, the line says it changed since training and keeps that reason; when config.json
    records the edited manifest's sha256, the scene's line is unchanged."""
    import hashlib

    from jsgs.cli import main

    config = json.loads((run / "config.json").read_text())
    scene = shutil.copytree(Path(config["manifest"]["path"]).parent, tmp_path / "scene")
    copy = shutil.copytree(run, tmp_path / "run")
    manifest = scene / "manifest.json"
    config["manifest"]["path"] = str(manifest)
    edit_manifest(manifest, lambda d: [v.update(split="test") for v in d["views"]])
    if recorded == "edited":
        config["manifest"]["sha256"] = hashlib.sha256(manifest.read_bytes()).hexdigest()
    else:
        assert config["manifest"]["sha256"] != hashlib.sha256(manifest.read_bytes()).hexdigest()
    (copy / "config.json").write_text(json.dumps(config))
    r = CliRunner().invoke(main, ["render", str(copy), "--out", str(tmp_path / "x.mp4"), "--device", "cpu"])
    assert r.exit_code == 1 and r.output.count("\n") == 1, r.output
    reason = "no training views: "
    if recorded == "trained":
        prefix = f"error: {manifest}: changed since {copy} was trained (sha256 differs from config.json's); "
        assert r.output.startswith(prefix + reason), r.output
    else:
        assert r.output.startswith(f"error: {manifest}: {reason}"), r.output
        assert "changed since" not in r.output, r.output
    assert "jsgs train needs at least one" in r.output, r.output
    assert not (tmp_path / "x.mp4").exists()


def _siblings(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.parent.iterdir() if p.name.startswith(f".{folder.name}."))


def test_force_keeps_the_earlier_frames_until_the_new_ones_are_complete(
    run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import jsgs.apps.viewer
    from jsgs.apps.render_video import render_run

    out = tmp_path / "frames"
    render_run(run, out, "spiral", 3, device="cpu", progress=False)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert sorted(before) == ["cameras.json", "frame_00000.png", "frame_00001.png", "frame_00002.png"]
    render_rgb, calls = jsgs.apps.viewer.render_rgb, []

    def interrupted(*a: object, **k: object) -> np.ndarray:
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return render_rgb(*a, **k)  # type: ignore[arg-type]

    monkeypatch.setattr(jsgs.apps.viewer, "render_rgb", interrupted)
    with pytest.raises(KeyboardInterrupt):  # Ctrl-C in the middle of a --force render
        render_run(run, out, "ellipse", 2, size=(30, 20), device="cpu", progress=False, force=True)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before and _siblings(out) == []
    monkeypatch.setattr(jsgs.apps.viewer, "render_rgb", render_rgb)
    render_run(run, out, "ellipse", 2, size=(30, 20), device="cpu", progress=False, force=True)
    assert sorted(p.name for p in out.iterdir()) == ["cameras.json", "frame_00000.png", "frame_00001.png"]
    assert json.loads((out / "cameras.json").read_text())["kind"] == "ellipse" and _siblings(out) == []
    assert Image.open(out / "frame_00001.png").size == (30, 20)  # the new frames, not the earlier 32x24


def test_force_replaces_only_a_folder_of_frames_render_made(run: Path, tmp_path: Path) -> None:
    from jsgs.cli import main

    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "frame_00000.png").write_bytes(b"mine")
    mixed, bare, link = tmp_path / "mixed", tmp_path / "bare", tmp_path / "link"
    args = ["render", str(run), "--out", str(mixed), "--frames", "2", "--device", "cpu"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    (mixed / "notes.txt").write_text("keep")
    bare.mkdir()
    (bare / "frame_00000.png").write_bytes(b"not a render")  # frames from elsewhere, no cameras.json
    shutil.copy(mixed / "cameras.json", victim / "cameras.json")
    link.symlink_to(victim, target_is_directory=True)
    for out, needle in ((mixed, "holds notes.txt, which jsgs render does not write"),
                        (bare, "has no cameras.json of jsgs render"), (link, "is a link")):  # fmt: skip
        args = ["render", str(run), "--out", str(out), "--frames", "2", "--force", "--device", "cpu"]
        r = CliRunner().invoke(main, args)
        assert r.exit_code == 1 and r.output.count("\n") == 1 and needle in r.output, r.output
        assert "--force replaces only a folder of frames that jsgs render made" in r.output
    assert (mixed / "notes.txt").read_text() == "keep" and len(list(mixed.glob("frame_*.png"))) == 2
    assert (bare / "frame_00000.png").read_bytes() == b"not a render"
    assert (victim / "frame_00000.png").read_bytes() == b"mine" and link.is_symlink()


def test_atomic_folder_swaps_in_only_a_finished_folder(tmp_path: Path) -> None:
    from jsgs.base.io import atomic_folder

    final = tmp_path / "out"
    final.mkdir()
    (final / "old").write_text("old")
    with pytest.raises(RuntimeError), atomic_folder(final) as work:
        (work / "new").write_text("half")
        raise RuntimeError("disk error")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"] and (final / "old").read_text() == "old"
    with atomic_folder(final) as work:
        (work / "new").write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert [p.name for p in final.iterdir()] == ["new"]
    target = tmp_path / "target"
    target.mkdir()
    (target / "t").write_text("t")
    link = tmp_path / "link"
    link.symlink_to(target, target_is_directory=True)
    with atomic_folder(link) as work:
        (work / "new").write_text("new")
    assert not link.is_symlink() and (link / "new").exists() and (target / "t").read_text() == "t"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "out", "target"]


def test_frames_into_an_empty_folder_or_a_link_to_one(run: Path, tmp_path: Path) -> None:
    from jsgs.apps.render_video import render_run

    empty, target, link = tmp_path / "empty", tmp_path / "target", tmp_path / "link"
    empty.mkdir()
    target.mkdir()
    link.symlink_to(target, target_is_directory=True)
    for out in (empty, link):
        render_run(run, out, "spiral", 2, device="cpu", progress=False)
    want = ["cameras.json", "frame_00000.png", "frame_00001.png"]
    assert sorted(p.name for p in empty.iterdir()) == want and not empty.is_symlink()
    assert link.is_symlink() and sorted(p.name for p in target.iterdir()) == want
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "link", "target"]


def _killed_inside(writer: str, write: str, out: Path) -> None:
    """A process that enters ``jsgs.base.io``'s ``writer`` (atomic_folder or atomic_path) for ``out`` as
    jsgs render, runs ``write`` on what it yields (``work``) and kills itself with SIGKILL inside it."""
    import signal
    import subprocess
    import sys

    code = (
        f"import os, signal, sys\nfrom jsgs.base.io import {writer}\n"
        f"with {writer}(sys.argv[1], 'jsgs render') as work:\n"
        f"    {write}\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    assert subprocess.run([sys.executable, "-c", code, str(out)]).returncode == -signal.SIGKILL


def _plant(folder: Path, marker: dict[str, object] | None, content: str = "frame") -> Path:
    from jsgs.base.io import PART_MARKER

    folder.mkdir()
    (folder / "frame_00000.png").write_text(content)
    if marker is not None:
        (folder / PART_MARKER).write_text(json.dumps(marker))
    return folder


def test_leftovers_of_a_killed_render_are_removed_only_when_ours_and_gone(tmp_path: Path) -> None:
    """Beside ``frames``: a ``.part`` folder whose writer is gone (removed), one whose writer runs, one of
    another host, one without our marker, one whose marker names another folder, a link to a marked folder
    (all left alone, one warning each); an ``.old`` folder of a gone writer is removed while ``frames``
    exists, and put back as ``frames`` when a swap was cut short."""
    import os
    import socket

    from jsgs.base.io import PART_MARKER, _start_time, clear_folder_leftovers

    host = socket.gethostname()
    dead = {"for": "frames", "pid": 2**22 + 12345, "host": host, "start": 1, "what": "jsgs render"}
    live = {**dead, "pid": os.getppid(), "start": _start_time(os.getppid())}
    final = tmp_path / "frames"
    gone = _plant(tmp_path / ".frames.aaaa1111.part", dead)
    running = _plant(tmp_path / ".frames.bbbb2222.part", live)
    remote = _plant(tmp_path / ".frames.cccc3333.part", {**dead, "host": host + "-elsewhere"})
    bare = _plant(tmp_path / ".frames.dddd4444.part", None)
    other = _plant(tmp_path / ".frames.eeee5555.part", {**dead, "for": "other"})
    target = _plant(tmp_path / "target", dead, "keep")
    link = tmp_path / ".frames.ffff6666.part"
    link.symlink_to(target, target_is_directory=True)
    old = _plant(tmp_path / ".frames.gggg7777.old", dead, "earlier")
    unrelated = _plant(tmp_path / ".framesx.hhhh8888.part", dead)  # another output's
    lines = clear_folder_leftovers(final)
    assert len(lines) == 7 and all("\n" not in s for s in lines), lines
    assert not gone.exists() and not old.exists()
    assert sorted(p.name for p in final.iterdir()) == ["frame_00000.png"]  # no frames: the .old came back
    assert (final / "frame_00000.png").read_text() == "earlier"
    assert [s.split(",")[0] for s in lines if s.startswith("note")] == [
        f"note: removed {gone}", f"note: {final}: put back from {old.name}"]  # fmt: skip
    for kept in (running, remote, bare, other):
        assert (kept / "frame_00000.png").read_text() == "frame"
        assert sum(str(kept) in s and s.startswith("warning: ") for s in lines) == 1, (kept, lines)
    assert link.is_symlink() and (target / "frame_00000.png").read_text() == "keep"
    assert (target / PART_MARKER).exists() and unrelated.exists()
    assert f"(PID {os.getppid()}) is still writing it" in next(s for s in lines if str(running) in s)
    assert f"on host {host}-elsewhere" in next(s for s in lines if str(remote) in s)
    assert "holds no .jsgs-part.json" in next(s for s in lines if str(bare) in s)
    # once frames exists, an .old folder of a gone writer is the output a finished swap was removing
    old = _plant(tmp_path / ".frames.iiii9999.old", dead)
    lines = clear_folder_leftovers(final)
    assert not old.exists() and (final / "frame_00000.png").read_text() == "earlier"
    assert [s for s in lines if not s.startswith("warning: ")] == [
        f"note: removed {old}, the earlier output it was replacing of jsgs render (PID {2**22 + 12345}, no "
        "longer running)"]  # fmt: skip


def test_render_removes_what_a_killed_render_left(run: Path, tmp_path: Path) -> None:
    """A process killed (SIGKILL) inside atomic_folder leaves its marked ``.part`` folder; the next jsgs
    render into the same folder removes it with a note and warns about an unmarked one, which it keeps."""

    from jsgs.base.io import PART_MARKER
    from jsgs.cli import main

    out = tmp_path / "frames"
    _killed_inside("atomic_folder", "(work / 'frame_00000.png').write_bytes(b'half')", out)
    (killed,) = _siblings(out)
    assert json.loads((tmp_path / killed / PART_MARKER).read_text())["what"] == "jsgs render"
    stranger = _plant(tmp_path / ".frames.zzzz0000.part", None, "someone's")
    r = CliRunner().invoke(main, ["render", str(run), "--out", str(out), "--frames", "2", "--device", "cpu"])
    assert r.exit_code == 0, r.output
    assert f"note: removed {tmp_path / killed}, the unfinished output of jsgs render (PID " in r.output
    assert f"warning: {stranger}: left beside frames" in r.output
    assert _siblings(out) == [stranger.name] and (stranger / "frame_00000.png").read_text() == "someone's"
    assert sorted(p.name for p in out.iterdir()) == ["cameras.json", "frame_00000.png", "frame_00001.png"]


def _plant_video(folder: Path, stem: str, marker: dict[str, object] | None, video: bool = True) -> Path:
    """A leftover temporary video ``.out.mp4.STEM.part.mp4`` (when ``video``) and its marker (when given)."""
    from jsgs.base.io import PART_MARKER

    tmp = folder / f".out.mp4.{stem}.part.mp4"
    if video:
        tmp.write_bytes(b"half a video")
    if marker is not None:
        (folder / f".out.mp4.{stem}.part{PART_MARKER}").write_text(json.dumps(marker))
    return tmp


def test_video_leftovers_are_removed_only_when_ours_and_gone(tmp_path: Path) -> None:
    """Beside ``out.mp4``: a temporary video whose marker names a writer that is gone (removed with its
    marker), a marker alone of a gone writer (removed); one whose writer runs, one of another host, one
    without a marker, one with a marker cut short, one whose marker names another output, a link with a
    gone writer's marker (all left alone, one warning each); another output's leftover is not looked at."""
    import os
    import socket

    from jsgs.base.io import PART_MARKER, _start_time, clear_file_leftovers

    host = socket.gethostname()
    dead = {"for": "out.mp4", "pid": 2**22 + 12345, "host": host, "start": 1, "what": "jsgs render"}
    live = {**dead, "pid": os.getppid(), "start": _start_time(os.getppid())}
    final = tmp_path / "out.mp4"
    gone = _plant_video(tmp_path, "aaaa1111", dead)
    lone = _plant_video(tmp_path, "bbbb2222", dead, video=False)
    running = _plant_video(tmp_path, "cccc3333", live)
    remote = _plant_video(tmp_path, "dddd4444", {**dead, "host": host + "-elsewhere"})
    bare = _plant_video(tmp_path, "eeee5555", None)
    cut = _plant_video(tmp_path, "ffff6666", None)
    cut.with_name(f".out.mp4.ffff6666.part{PART_MARKER}").write_text("")  # killed before its record
    other = _plant_video(tmp_path, "gggg7777", {**dead, "for": "other.mp4"})
    target = tmp_path / "target.mp4"
    target.write_bytes(b"keep")
    link = _plant_video(tmp_path, "hhhh8888", dead, video=False)
    link.symlink_to(target)
    unrelated = tmp_path / ".outx.mp4.iiii9999.part.mp4"
    unrelated.write_bytes(b"another output's")
    before = sorted(p.name for p in tmp_path.iterdir())
    lines = clear_file_leftovers(final)
    assert len(lines) == 8 and all("\n" not in s for s in lines), lines
    kept = (running, remote, bare, cut, other)
    removed = [gone.name, gone.name[: -len(".mp4")] + PART_MARKER, lone.name[: -len(".mp4")] + PART_MARKER]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(set(before) - set(removed))
    assert [s.split(",")[0] for s in lines if s.startswith("note")] == [
        f"note: removed {gone}", f"note: removed {tmp_path / removed[2]}"]  # fmt: skip
    assert "the unfinished output of jsgs render (PID" in lines[0]
    for p in kept:
        assert p.read_bytes() == b"half a video"
        assert sum(str(p) in s and s.startswith("warning: ") for s in lines) == 1, (p, lines)
    assert link.is_symlink() and target.read_bytes() == b"keep" and unrelated.exists()
    assert f"warning: {link}: is not a plain file" in " ".join(lines)
    assert f"(PID {os.getppid()}) is still writing it" in next(s for s in lines if str(running) in s)
    assert f"on host {host}-elsewhere" in next(s for s in lines if str(remote) in s)
    assert "records its writer; left alone" in next(s for s in lines if str(bare) in s)


def test_render_removes_what_a_killed_video_render_left(run: Path, tmp_path: Path) -> None:
    """A process killed (SIGKILL) while writing a video leaves the temporary video and its marker; the next
    jsgs render to the same file removes both with a note and warns about an unmarked one, which it keeps."""

    import imageio.v2 as iio

    from jsgs.base.io import PART_MARKER
    from jsgs.cli import main

    out = tmp_path / "out.mp4"
    _killed_inside("atomic_path", "work.write_bytes(b'half')", out)
    marker, video = _siblings(out)  # ".out.mp4.X.part.jsgs-part.json" sorts first
    assert video.endswith(".part.mp4") and marker == video[: -len(".mp4")] + PART_MARKER
    assert json.loads((tmp_path / marker).read_text())["what"] == "jsgs render"
    stranger = _plant_video(tmp_path, "zzzz0000", None)
    r = CliRunner().invoke(main, ["render", str(run), "--out", str(out), "--frames", "2", "--device", "cpu"])
    assert r.exit_code == 0, r.output
    assert f"note: removed {tmp_path / video}, the unfinished output of jsgs render (PID " in r.output
    assert f"warning: {stranger}: left beside out.mp4" in r.output
    assert _siblings(out) == [stranger.name] and stranger.read_bytes() == b"half a video"
    assert iio.get_reader(out).count_frames() == 2


def test_a_lock_of_another_host_is_never_taken_over(tmp_path: Path) -> None:
    """The output lock holds the same writer record as atomic_folder's marker: a PID recorded on another
    host says nothing here, so that lock is refused (naming the host) where a dead PID of this host's is
    taken over."""
    import socket

    from jsgs.base.errors import JsgsError
    from jsgs.base.io import LOCK_NAME, OutputLock

    dead = {"pid": 2**22 + 12345, "what": "jsgs train (into run)", "host": socket.gethostname() + "-b"}
    (tmp_path / LOCK_NAME).write_text(json.dumps(dead))
    with pytest.raises(JsgsError, match=rf"in use by jsgs train \(into run\) \(PID {dead['pid']} on host "):
        OutputLock(tmp_path, "jsgs render")
    (tmp_path / LOCK_NAME).write_text(json.dumps({**dead, "host": socket.gethostname()}))
    with OutputLock(tmp_path, "jsgs render"):
        assert json.loads((tmp_path / LOCK_NAME).read_text())["what"] == "jsgs render"
    assert not (tmp_path / LOCK_NAME).exists()


@pytest.mark.parametrize("killed_in", ["the removal of the earlier folder", "the swap"])
def test_a_swap_killed_midway_leaves_a_marked_earlier_folder(tmp_path: Path, killed_in: str) -> None:
    """A process killed (SIGKILL) while atomic_folder replaces an earlier folder: killed while removing the
    earlier folder, that folder is left marked and the next writer removes it (the new one is in place);
    killed between moving it aside and renaming the new one in, it is put back, and the new folder (its
    marker already gone: it is about to become ``frames``) is kept with a warning."""
    import signal
    import subprocess
    import sys

    from jsgs.base.io import clear_folder_leftovers

    final = tmp_path / "frames"
    final.mkdir()
    (final / "frame_00000.png").write_text("earlier")
    step = "_remove_marked" if killed_in.startswith("the removal") else "write_json_atomic"
    code = (
        "import os, signal, sys\nimport jsgs.base.io as io\nown = io." + step + "\n"
        "def kill(p, *a):\n"
        "    if p.name.endswith('.old') or p.parent.name.endswith('.old'):\n"
        "        if io.write_json_atomic is kill: own(p, *a)\n"
        "        os.kill(os.getpid(), signal.SIGKILL)\n"
        "    return own(p, *a)\n"
        "io." + step + " = kill\n"
        "with io.atomic_folder(sys.argv[1], 'jsgs render') as work:\n"
        "    (work / 'frame_00000.png').write_text('new')\n"
    )
    assert subprocess.run([sys.executable, "-c", code, str(final)]).returncode == -signal.SIGKILL
    (left,) = (p for p in tmp_path.iterdir() if p.name.endswith(".old"))
    new = [p for p in tmp_path.iterdir() if p.name.endswith(".part")]
    lines = clear_folder_leftovers(final)
    assert not left.exists() and sorted(s.split(" ")[0] for s in lines) == ["note:"] + ["warning:"] * len(new)
    assert [p.name for p in final.iterdir()] == ["frame_00000.png"]
    if killed_in.startswith("the removal"):
        assert (final / "frame_00000.png").read_text() == "new" and not new
    else:
        assert (final / "frame_00000.png").read_text() == "earlier" and len(new) == 1
        assert (new[0] / "frame_00000.png").read_text() == "new"
        assert any(s.startswith(f"warning: {new[0]}: ") for s in lines), lines
