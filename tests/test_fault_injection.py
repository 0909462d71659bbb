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


# ---------------------------------------------------------------------------------------------------------
# training state: checkpoints, resume, the JPEG files, a model that turns non-finite

FAST_TRAIN = ["--device", "cpu", "--quiet", "--preset", "paper", "--method", "gsplat"]


@pytest.fixture(scope="module")
def stopped_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(the manifest of a tiny scene, a run on it stopped after 2 of 4 steps with a checkpoint)."""
    from _train_scene import make_scene

    from jsgs.train.config import TrainConfig
    from jsgs.train.trainer import train

    root = tmp_path_factory.mktemp("stopped")
    manifest = make_scene(root / "scene")
    cfg = TrainConfig.from_preset("paper", method="gsplat", iterations=4, eval_at=[4], device="cpu")
    cfg.eval.fps_passes, cfg.eval.fps_warmup = 1, 0
    train(manifest, root / "run", cfg, stop_at=2, progress=False, log=lambda s: None)
    return manifest, root / "run"


def _ckpt_edit(fn: Callable[[dict], None]) -> Callable[[Path], None]:
    def edit(run: Path) -> None:
        import torch

        path = run / "checkpoints" / "step_000002.pt"
        doc = torch.load(path, weights_only=True)
        fn(doc)
        torch.save(doc, path)

    return edit


def _config_edit(fn: Callable[[dict], None]) -> Callable[[Path], None]:
    def edit(run: Path) -> None:
        doc = json.loads((run / "config.json").read_text())
        fn(doc)
        (run / "config.json").write_text(json.dumps(doc))

    return edit


def _nan_means(d: dict) -> None:
    d["splats"]["means"][0, 0] = float("nan")


def _rename(run: Path) -> None:
    (run / "checkpoints" / "step_000002.pt").rename(run / "checkpoints" / "step_000003.pt")


RESUME_CASES: list[tuple[str, Callable[[Path], None], str]] = [
    ("NaN parameter", _ckpt_edit(_nan_means),
     r"step_000002.pt: not a usable checkpoint \(at splats.means: non-finite"),
    ("missing key", _ckpt_edit(lambda d: d.pop("rng")),
     r"step_000002.pt: not a usable checkpoint \(at rng: missing"),
    ("wrong shape", _ckpt_edit(lambda d: d["splats"].update(quats=d["splats"]["quats"][:, :3])),
     r"at splats.quats: shape \(\d+, 3\), expected \(N, 4\)"),
    ("wrong dtype", _ckpt_edit(lambda d: d["splats"].update(means=d["splats"]["means"].double())),
     "at splats.means: dtype float64, expected float32"),
    ("negative step", _ckpt_edit(lambda d: d.update(step=-1)), "at step: -1 is not a non-negative integer"),
    ("Inf Adam state",
     _ckpt_edit(lambda d: d["optimizers"]["sh0"]["state"][0]["exp_avg"].fill_(float("inf"))),
     r"at optimizers.sh0.state\[0\].exp_avg: non-finite"),
    ("renamed", _rename, "at step: 2 but the file is named for step 3"),
    ("another scene", _ckpt_edit(lambda d: d.update(manifest_sha256="0" * 64)),
     "written for another manifest than the one .*config.json names"),
    ("config.json edited", _config_edit(lambda d: d["settings"].update(seed=7)),
     r"written with other settings than .*config.json .*: seed \(7 in config.json, 42 in the checkpoint\)"),
    ("iterations below the step", _config_edit(lambda d: d["settings"].update(iterations=1, eval_at=[1])),
     r"other settings .*: eval_at \(\[1\] in config.json, \[4\] in the checkpoint\)"),
    ("truncated", lambda run: _truncate(run / "checkpoints" / "step_000002.pt"),
     "step_000002.pt: not a readable checkpoint"),
]  # fmt: skip


@pytest.mark.parametrize(("name", "edit", "needle"), RESUME_CASES, ids=[c[0] for c in RESUME_CASES])
def test_resume_uses_only_a_checkpoint_it_can_check(
    stopped_run: tuple[Path, Path], tmp_path: Path, name: str, edit: Callable[[Path], None], needle: str
) -> None:
    import re

    manifest, run = stopped_run
    mine = tmp_path / "run"
    shutil.copytree(run, mine)
    edit(mine)
    before = _tree(mine)
    r = CliRunner().invoke(jsgs_main, ["train", str(manifest), "--out", str(mine), "--resume", "--quiet"])
    _check_one_line(r.output, r.exit_code)
    assert re.search(needle, r.output), r.output
    assert _tree(mine) == before, "a refused resume changes nothing"


def test_resume_with_fewer_iterations_than_done_is_one_line(stopped_run: tuple[Path, Path]) -> None:
    manifest, run = stopped_run
    args = ["train", str(manifest), "--out", str(run), "--resume", "--iterations", "1", "--eval-at", "1"]
    r = CliRunner().invoke(jsgs_main, args)
    _check_one_line(r.output, r.exit_code)
    assert "differs: eval_at" in r.output or "differs: iterations" in r.output


def test_a_jpeg_saved_again_after_its_manifest_is_named(compressed_scene: Path, tmp_path: Path) -> None:
    """The manifest records each JPEG's header digest; a file saved again with other tables is refused by
    name before training. A manifest without digests (an older one) trains, with a note saying so."""
    scene = tmp_path / "data"
    shutil.copytree(compressed_scene, scene)
    doc = json.loads((scene / "manifest.json").read_text())
    view = next(v for v in doc["views"] if v["jpeg"] is not None and v["split"] == "train")
    assert len(view["jpeg"]["header_sha256"]) == 64
    jpeg = scene / view["image"]
    Image.open(jpeg).convert("RGB").save(jpeg, quality=view["jpeg"]["quality"] % 97 + 2)
    args = ["train", str(scene), "--iterations", "1", "--eval-at", "", *FAST_TRAIN]
    r = CliRunner().invoke(jsgs_main, [*args, "--out", str(tmp_path / "run")])
    _check_one_line(r.output, r.exit_code)
    assert f"{jpeg}: changed since" in r.output and "write the manifest again" in r.output, r.output
    for v in doc["views"]:
        if v["jpeg"] is not None:
            del v["jpeg"]["header_sha256"]
    (scene / "manifest.json").write_text(json.dumps(doc))
    r = CliRunner().invoke(jsgs_main, [*args, "--out", str(tmp_path / "old")])
    assert r.exit_code == 0, r.output
    assert "have no header digest in the manifest" in r.output


def test_a_model_that_turns_non_finite_stops_with_one_line(tmp_path: Path) -> None:
    """A view's pose at 1e308: the reader refuses it, or training stops at the first non-finite parameter;
    either way one line, and never a run that says complete without its model."""
    from _train_scene import edit_manifest, make_scene

    manifest = make_scene(tmp_path / "scene")
    edit_manifest(manifest, lambda d: d["views"][1].update(t=[1e308, 0.0, 0.0]))
    run = tmp_path / "run"
    r = CliRunner().invoke(jsgs_main, ["train", str(manifest), "--out", str(run), "--iterations", "4",
                                       "--eval-at", "2,4", *FAST_TRAIN])  # fmt: skip
    _check_one_line(r.output, r.exit_code)
    assert not (run / "point_cloud.ply").exists()
    if (run / "metrics.json").exists():
        m = json.loads((run / "metrics.json").read_text())
        assert m["status"] == "diverged" and "became non-finite" in m["error"], m


# ---------------------------------------------------------------------------------------------------------
# numbers that enter through a file or the command line: finite and in range where read, one line


def _manifest_case(compressed_scene: Path, tmp_path: Path, edit: Callable[[dict], None] | str) -> Path:
    """A copy of the compressed scene's manifest (beside its files) with ``edit`` applied, or replaced by the
    text ``edit``."""
    data = tmp_path / "data"
    shutil.copytree(compressed_scene, data)
    path = data / "manifest.json"
    if isinstance(edit, str):
        path.write_text(edit)
    else:
        doc = json.loads(path.read_text())
        edit(doc)
        path.write_text(json.dumps(doc))
    return path


def _coincident(doc: dict) -> None:
    for v in doc["views"]:  # every camera centre at (1, 2, 3): t = -R c
        v["t"] = (-np.asarray(v["R"]) @ np.array([1.0, 2.0, 3.0])).tolist()


def _narrow(doc: dict) -> None:
    doc["views"][0]["camera"].update(width=8, cx=4.0)


def _set(path: str, value: object) -> Callable[[dict], None]:
    def edit(doc: dict) -> None:
        *keys, last = path.split("/")
        node = doc
        for k in keys:
            node = node[int(k)] if isinstance(node, list) else node[k]
        node[int(last) if isinstance(node, list) else last] = value

    return edit


DEEP = "[" * 100_000 + "]" * 100_000


@pytest.mark.parametrize(
    ("edit", "needle"),
    [(_coincident, "one position"), (_set("points/xyz/0", [1e308, 0, 0]), "points/xyz/0"),
     (_set("views/0/t", [1e308, 0, 0]), "views/0/t"), (_set("views/0/camera/fx", 1e308), "camera/fx"),
     (_set("views/0/camera/fy", 1e-300), "camera/fy"), (_set("views/0/camera/width", 10**12), "width"),
     (_set("scene/seed", 2**70), "64 bits"), (_narrow, "SSIM window"), (DEEP, "nested deeper"),
     ('{"format": "jsgs-manifest", "format_version": NaN}', "not a finite number"),
     ('{"format": ' + "1" * 5000 + "}", "4300 digits")],
    ids=["coincident cameras", "point at 1e308", "pose at 1e308", "focal 1e308", "focal 1e-300",
         "width 1e12", "seed beyond 64 bits", "narrower than SSIM", "nested 100000 deep", "NaN literal",
         "5000-digit integer"],
)  # fmt: skip
def test_hostile_manifests_get_one_line(
    compressed_scene: Path, tmp_path: Path, edit: Callable[[dict], None] | str, needle: str
) -> None:
    manifest = _manifest_case(compressed_scene, tmp_path, edit)
    run = tmp_path / "run"
    args = ["train", str(manifest), "--out", str(run), "--iterations", "2", "--device", "cpu", "--quiet"]
    r = CliRunner().invoke(jsgs_main, args)
    _check_one_line(r.output, r.exit_code)
    assert needle in r.output and str(manifest) in r.output, r.output
    assert not (run / "point_cloud.ply").exists() and not (run / "metrics.json").exists()


def test_degenerate_geometry_is_handled_where_it_can_be(compressed_scene: Path, tmp_path: Path) -> None:
    """A point absurdly far from the cameras is left out (with a note), and coincident cameras train in the
    manifest's own units when the world is not normalised."""
    def far_and_coincident(doc: dict) -> None:
        doc["points"]["xyz"][0] = [1e9, 0.0, 0.0]
        _coincident(doc)

    manifest = _manifest_case(compressed_scene, tmp_path, far_and_coincident)
    cfg = tmp_path / "cfg.json"
    # a fixed budget above the points, so that every point kept starts as a Gaussian
    cfg.write_text(json.dumps({"scene": {"normalize_world": False}, "strategy": {"cap_max": 300_000}}))
    run = tmp_path / "run"
    args = ["train", str(manifest), "--out", str(run), "--iterations", "1", "--eval-at", "", "--config",
            str(cfg), "--device", "cpu", "--quiet"]  # fmt: skip
    r = CliRunner().invoke(jsgs_main, args)
    assert r.exit_code == 0, r.output
    derived = json.loads((run / "config.json").read_text())["derived"]
    n = len(json.loads(manifest.read_text())["points"]["xyz"])
    assert derived["initial_gaussians"] == n - 1
    notes = " ".join(derived["notes"])
    assert "1 of" in notes and "left out" in notes and "one position" in notes, notes


@pytest.mark.parametrize(
    ("text", "needle"),
    [('{"scene": {"global_scale": 1e300}}', "scene.global_scale"),
     ('{"optim": {"means_lr": 1e300}}', "optim.means_lr"),
     ('{"seed": 1180591620717411303424}', "64 bits"), ('{"seed": 9223372036854775808}', "seed"),
     ('{"init": {"scale": NaN}}', "not a finite number"), ('{"loss": {"ssim_lambda": 1e400}}', "finite"),
     (DEEP, "nested deeper"), ('{"method": "jsgs", "method_options": {"lambda_obs": 1e300}}', "lambda_obs")],
)  # fmt: skip
def test_hostile_settings_files_get_one_line(compressed_scene: Path, tmp_path: Path, text: str,
                                             needle: str) -> None:  # fmt: skip
    cfg = tmp_path / "cfg.json"
    cfg.write_text(text)
    run = tmp_path / "run"
    args = ["train", str(compressed_scene / "manifest.json"), "--out", str(run), "--config", str(cfg),
            "--device", "cpu", "--quiet"]  # fmt: skip
    r = CliRunner().invoke(jsgs_main, args)
    _check_one_line(r.output, r.exit_code)
    assert needle in r.output and str(cfg) in r.output and not run.exists(), r.output


@pytest.mark.parametrize(
    ("main", "args", "needle"),
    [("jsgs", ["train", "{data}", "--out", "{out}", "--seed", str(2**70)], "seed must be <="),
     ("jsgs", ["train", "{data}", "--out", "{out}", "--iterations", str(10**30)], "iterations must be <="),
     ("jsgs", ["train", "{data}", "--out", "{out}", "--viewer", "70000"], "--viewer"),
     ("jsgs", ["train", "{data}", "--out", "{out}", "--processes", str(10**20)], "--processes"),
     ("jsgs", ["render", "{out}", "--out", "{out}/v.mp4", "--fps", "nan"], "--fps"),
     ("jsgs", ["render", "{out}", "--out", "{out}/v.mp4", "--fps", "inf"], "--fps"),
     ("jsgs", ["view", "{out}", "--port", "70000"], "--port"),
     ("jsgs", ["bench", "{data}", "--out", "{out}", "--time-limit", "inf"], "--time-limit"),
     ("jsgs", ["bench", "{data}", "--out", "{out}", "--jobs-per-gpu", str(10**30)], "--jobs-per-gpu"),
     ("tools", ["synth", "{out}", "--size", "8x2000"], "SSIM"),
     ("tools", ["synth", "{out}", "--seed", "-1"], "--seed"),
     ("tools", ["compress", "{scene}", "--out", "{out}", "--schedule", "uniform", "--seed", str(2**64)],
      "--seed"),
     ("tools", ["compress", "{scene}", "--out", "{out}", "--schedule", "uniform", "--jobs", str(10**30)],
      "--jobs"),
     ("tools", ["manifest", "{scene}", "--out", "{out}/m.json", "--test-every", str(2**64)], "--test-every"),
     ("tools", ["sfm", "{scene}", "--out", "{out}", "--max-image-size", str(10**30)], "--max-image-size"),
     ("tools", ["sfm", "{scene}", "--out", "{out}", "--seed", str(2**40)], "--seed")],
)  # fmt: skip
def test_command_line_numbers_are_checked_before_anything_runs(
    synth_scene: Path, compressed_scene: Path, tmp_path: Path, main: str, args: list[str], needle: str
) -> None:
    out = tmp_path / "out"
    argv = [a.format(data=compressed_scene, scene=synth_scene, out=out) for a in args]
    r = CliRunner().invoke(jsgs_main if main == "jsgs" else tools_main, argv)
    assert r.exit_code != 0 and "Traceback" not in r.output and needle in r.output, r.output
    assert not out.exists() or not any(out.iterdir()), list(out.iterdir())


def _bad_colmap_point(scene: Path) -> None:
    import struct

    path = scene / "sparse/0/points3D.bin"
    data = bytearray(path.read_bytes())
    struct.pack_into("<3d", data, 16, 1e308, 0.0, 0.0)  # the first point's xyz, after the count and its id
    path.write_bytes(bytes(data))


def _colmap_poses(scene: Path, centre: Callable[[int, np.ndarray], object]) -> None:
    """Move the camera of the k-th image (by id) from its centre c to ``centre(k, c)`` (rotation kept)."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(scene / "sparse/0"))
    for k, iid in enumerate(sorted(rec.images)):
        frame = rec.frames[rec.images[iid].frame_id]
        pose = frame.rig_from_world
        R = pose.rotation.matrix()
        c = -R.T @ np.asarray(pose.translation)
        frame.rig_from_world = pycolmap.Rigid3d(pose.rotation, -R @ np.asarray(centre(k, c), dtype=float))
    rec.write_binary(str(scene / "sparse/0"))


@pytest.mark.parametrize(
    ("breaker", "needle"),
    [(_bad_colmap_point, "beyond ±1e+12"),
     (lambda s: _colmap_poses(s, lambda k, c: [1e308, 0, 0] if k == 0 else c), "beyond ±1e+12")],
    ids=["point at 1e308", "camera at 1e308"],
)  # fmt: skip
def test_colmap_numbers_out_of_range_get_one_line(synth_scene: Path, tmp_path: Path, breaker: Breaker,
                                                  needle: str) -> None:  # fmt: skip
    scene = tmp_path / "scene"
    shutil.copytree(synth_scene, scene)
    breaker(scene)
    for args in (["validate", str(scene)], ["manifest", str(scene), "--out", str(tmp_path / "m.json")]):
        r = CliRunner().invoke(tools_main, args)
        _check_one_line(r.output, r.exit_code)
        assert needle in r.output, r.output
    assert not (tmp_path / "m.json").exists()


def test_coincident_colmap_cameras_are_named_by_validate(synth_scene: Path, tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    shutil.copytree(synth_scene, scene)
    _colmap_poses(scene, lambda k, c: [1.0, 2.0, 3.0])
    r = CliRunner().invoke(tools_main, ["validate", str(scene)])
    assert r.exit_code == 0 and "cameras are at one position" in r.output, r.output


def _one_view_scene(synth_scene: Path, scene: Path) -> None:
    """``synth_scene`` copied to ``scene`` with only its first registered view."""
    import pycolmap

    shutil.copytree(synth_scene, scene)
    rec = pycolmap.Reconstruction(str(scene / "sparse/0"))
    for iid in sorted(rec.images)[1:]:
        (scene / "images" / rec.images[iid].name).unlink()
        rec.deregister_frame(rec.images[iid].frame_id)
    rec.write_binary(str(scene / "sparse/0"))


def test_a_single_camera_is_named_by_validate_manifest_and_train(
    synth_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One registered camera: validate and manifest warn that jsgs train refuses it (no camera distance for
    the world's normalisation) and, with the default split, that no view trains; jsgs train says either in
    one line, and trains with scene.normalize_world false."""
    scene = tmp_path / "scene"
    _one_view_scene(synth_scene, scene)
    lone = "warning: scene/sparse/0: only one camera: jsgs train refuses the scene unless scene.normalize"
    no_train = "no training views: with test every 8, all 1 view(s) are test views; jsgs train needs at least"
    monkeypatch.chdir(tmp_path)  # the messages name the scene as given
    r = CliRunner().invoke(tools_main, ["validate", "scene"])
    assert r.exit_code == 0 and lone in r.output and f"scene/sparse/0: {no_train}" in r.output, r.output
    r = CliRunner().invoke(tools_main, ["validate", "scene", "--test-every", "0"])
    assert r.exit_code == 0 and lone in r.output and "no training views" not in r.output, r.output
    for every, name in (("8", "m8.json"), ("0", "m0.json")):
        r = CliRunner().invoke(tools_main, ["manifest", "scene", "--out", name, "--test-every", every])
        assert r.exit_code == 0 and lone in r.output, r.output
        assert (f"warning: {name}: {no_train}" in r.output) == (every == "8"), r.output
    train = ["train", "--iterations", "2", "--eval-at", "2", "--device", "cpu", "--quiet"]
    for name, needle in (("m8.json", f"error: m8.json: {no_train} one (jsgstools manifest --test-every 0 "
                                     "makes every view a training view)\n"),
                         ("m0.json", "error: m0.json: only one camera (")):  # fmt: skip
        r = CliRunner().invoke(jsgs_main, [*train, name, "--out", f"run_{name}"])
        _check_one_line(r.output, r.exit_code)
        assert needle in r.output, r.output
    assert "set scene.normalize_world to false to train in the manifest's own units" in r.output
    Path("flat.json").write_text(json.dumps({"scene": {"normalize_world": False}}))
    r = CliRunner().invoke(jsgs_main, [*train, "m0.json", "--out", "run", "--config", "flat.json"])
    assert r.exit_code == 0 and "note: only one camera: camera extent 0 replaced by 1" in r.output, r.output


def test_no_training_view_advice_fits_the_scene(
    synth_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One view, so the split leaves no training view: for a COLMAP scene the warning suggests
    --test-every 0 (which then trains); for a scene jsgstools compress made, whose compress.json fixes the
    split (--test-every 0 is refused there), it names the record and says to compress a source with more
    views. With several views and --test-every 1, a larger spacing is suggested too."""
    from jsgstools.compress import compress
    from jsgstools.validate import split_warning

    monkeypatch.chdir(tmp_path)  # the messages name the scenes as given
    _one_view_scene(synth_scene, tmp_path / "scene")
    compress(Path("scene"), Path("data"), "gaussian", seed=0, jobs=1)
    plain = "no training views: with test every 8, all 1 view(s) are test views; jsgs train needs at least "
    fixed = (
        "no training views: data/compress.json (test every 8) makes all 1 view(s) test views and fixes the "
        "split of a compressed scene; jsgs train needs at least one (compress a source with more views)"
    )
    r = CliRunner().invoke(tools_main, ["validate", "scene"])
    advice = "one (jsgstools manifest --test-every 0 makes every view a training view)"
    assert f"warning: scene/sparse/0: {plain}{advice}\n" in r.output, r.output
    r = CliRunner().invoke(tools_main, ["validate", "data", "--test-every", "0"])
    (line,) = (ln for ln in r.output.splitlines() if "no training views" in ln)
    assert line.endswith(fixed) and "--test-every" not in line, r.output
    r = CliRunner().invoke(tools_main, ["manifest", "data", "--out", "m.json"])
    assert r.exit_code == 0 and f"warning: m.json: {fixed}\n" in r.output, r.output
    r = CliRunner().invoke(tools_main, ["manifest", "data", "--out", "m0.json", "--test-every", "0"])
    assert r.exit_code != 0 and "its split cannot be changed to 0" in r.output, r.output
    assert split_warning("m.json", 5, 0, 1) == (
        "m.json: no training views: with test every 1, all 5 view(s) are test views; jsgs train needs at "
        "least one (jsgstools manifest --test-every 0 makes every view a training view; 2 or more keeps some "
        "test views)"
    )
    # jsgs train refuses such a manifest with the same line: the record's advice for a compressed scene (its
    # own manifest and one jsgstools manifest wrote), the spacing's for a COLMAP scene
    train = ["train", "--iterations", "2", "--eval-at", "2", "--device", "cpu", "--quiet"]
    r = CliRunner().invoke(tools_main, ["manifest", "scene", "--out", "plain.json"])
    assert r.exit_code == 0, r.output
    for name in ("m.json", "data/manifest.json", "plain.json"):
        r = CliRunner().invoke(jsgs_main, [*train, name, "--out", f"run_{Path(name).stem}"])
        _check_one_line(r.output, r.exit_code)
        expected = f"error: {name}: {plain}{advice}" if name == "plain.json" else f"error: {name}: {fixed}"
        assert f"{expected}\n" in r.output, r.output


# PLY files: a model that cannot be rendered gets one line from every reader (export, render, view)


def _fake_run(root: Path, table: np.ndarray | None = None, header: bytes | None = None) -> Path:
    from jsgs.base.ply import ply_header
    from jsgs.train.config import RUN_CONFIG_FORMAT, RUN_CONFIG_VERSION, TrainConfig, to_dict

    run = root / "run"
    run.mkdir()
    derived = {"device": "cpu", "backend": "torch", "scene_scale": 1.0, "normalization": np.eye(4).tolist(),
               "num_train_views": 1, "num_test_views": 0, "initial_gaussians": 1}  # fmt: skip
    config = {"format": RUN_CONFIG_FORMAT, "format_version": RUN_CONFIG_VERSION, "command": "",
              "versions": {"jsgs": "0", "torch": "0", "gsplat": None, "python": "3"},
              "manifest": {"path": str(root / "manifest.json"), "sha256": "0"},
              "settings": to_dict(TrainConfig()), "derived": derived}  # fmt: skip
    (run / "config.json").write_text(json.dumps(config))  # a run's config.json: export reads it whole
    n = 0 if table is None else len(table)
    body = b"" if table is None else table.astype("<f4").tobytes()
    (run / "point_cloud.ply").write_bytes((header or ply_header(n, 0)) + body)
    return run


def _gaussians(n: int) -> np.ndarray:
    t = np.random.default_rng(0).normal(size=(n, 17)).astype(np.float32)
    t[:, 13:17] = [1.0, 0.0, 0.0, 0.0]  # rot_0..rot_3
    return t


def _with(row: int, col: int | slice, value: float) -> np.ndarray:
    t = _gaussians(4)
    t[row, col] = value
    return t


@pytest.mark.parametrize(
    ("table", "header", "needle"),
    [(_with(2, 0, np.nan), None, "non-finite values (in means"),
     (_with(1, 9, np.inf), None, "non-finite values (in opacities_logit"),
     (_with(3, slice(13, 17), 0.0), None, "zero rotation quaternion"), (_with(0, 1, 1e30), None, "beyond"),
     (None, None, "no Gaussians"),
     (_gaussians(2), b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n"
      b"property float x\nend_header\n", "unusable properties")],
    ids=["NaN", "Inf", "zero quaternion", "centre at 1e30", "empty", "property named twice"],
)  # fmt: skip
def test_broken_models_get_one_line_on_export(tmp_path: Path, table: np.ndarray | None, header: bytes | None,
                                              needle: str) -> None:  # fmt: skip
    run = _fake_run(tmp_path, table, header)
    out = tmp_path / "model.ply"
    r = CliRunner().invoke(jsgs_main, ["export", str(run), "--out", str(out)])
    _check_one_line(r.output, r.exit_code)
    assert needle in r.output and "point_cloud.ply" in r.output, r.output
    assert not out.exists()


@pytest.mark.parametrize("command", ["export", "render", "view"])
def test_a_run_config_nested_deep_gets_one_line(tmp_path: Path, command: str) -> None:
    run = _fake_run(tmp_path, _gaussians(3))
    (run / "config.json").write_text(DEEP)
    args = {"export": ["export", str(run), "--out", str(tmp_path / "m.ply")],
            "render": ["render", str(run), "--out", str(tmp_path / "v.mp4")],
            "view": ["view", str(run)]}[command]  # fmt: skip
    r = CliRunner().invoke(jsgs_main, args)
    _check_one_line(r.output, r.exit_code)
    assert "config.json" in r.output and ("nested deeper" in r.output or "recursion" in r.output), r.output
