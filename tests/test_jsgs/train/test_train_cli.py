"""``jsgs train`` on the command line: a short run end to end, and one-line errors (exit 1, no traceback) for
bad or mismatched manifests and refused operations."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from _train_scene import edit_manifest, make_scene
from click.testing import CliRunner

from jsgs.cli import main

FAST = {"eval": {"fps_passes": 1, "fps_warmup": 0}, "strategy": {"refine_start_iter": 10_000}}


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_scene(tmp_path_factory.mktemp("cli_scene"))


@pytest.fixture()
def fast_config(tmp_path: Path) -> Path:
    p = tmp_path / "fast.json"
    p.write_text(json.dumps(FAST))
    return p


def run(*args: str) -> Any:
    return CliRunner().invoke(main, ["train", *args], catch_exceptions=False)


def one_line_error(result: Any, pattern: str) -> None:
    assert result.exit_code == 1, (result.exit_code, result.output, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert "Traceback" not in result.output + result.stderr
    import re

    assert re.search(pattern, lines[0]), lines[0]


def test_cli_trains_and_resumes(scene: Path, tmp_path: Path, fast_config: Path) -> None:
    out = tmp_path / "run"
    base = [str(scene), "--out", str(out), "--device", "cpu", "--config", str(fast_config), "--quiet"]
    r = run(*base, "--iterations", "4", "--eval-at", "2,4", "--stop-at", "2", "--seed", "3")
    assert r.exit_code == 0, r.output + r.stderr
    assert "stopped: 2/4 steps" in r.output
    conf = json.loads((out / "config.json").read_text())
    assert conf["settings"]["seed"] == 3 and conf["settings"]["eval_at"] == [2, 4]
    assert conf["command"].startswith("jsgs train ") and "--stop-at 2" in conf["command"]
    # resuming with the run's own settings (flags repeated identically are accepted); the manifest named by
    # the folder that holds it
    assert scene.name == "manifest.json"
    r = run(str(scene.parent), "--out", str(out), "--resume", "--quiet", "--iterations", "4")
    assert r.exit_code == 0, r.output + r.stderr
    assert json.loads((out / "config.json").read_text())["manifest"]["path"] == str(scene.resolve())
    assert "complete: 4/4 steps" in r.output and "PSNR" in r.output
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "complete" and [e["step"] for e in m["evals"]] == [2, 4]
    # a flag that would change the run is refused on resume
    one_line_error(
        run(str(scene), "--out", str(out), "--resume", "--seed", "4"),
        r"differs: seed \(3 in the run, 4 now\)",
    )
    one_line_error(run(*base, "--iterations", "4"), "folder is not empty; pass --resume")
    one_line_error(run(*base, "--resume", "--force"), "exclude each other")
    # --force with a manifest that fails its checks leaves the earlier run untouched
    one_line_error(run(str(tmp_path / "missing.json"), *base[1:], "--force"), "manifest not found")
    assert (out / "metrics.json").exists() and (out / "checkpoints").is_dir()
    # --force starts over; the default schedule is cut at --iterations
    r = run(*base, "--iterations", "3", "--force")
    assert r.exit_code == 0, r.output + r.stderr
    assert json.loads((out / "config.json").read_text())["settings"]["eval_at"] == [3]


def test_cli_reproduces_from_run_config(scene: Path, tmp_path: Path, fast_config: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    common = ["--device", "cpu", "--quiet"]
    r = run(str(scene), "--out", str(a), "--config", str(fast_config), "--iterations", "3", *common)
    assert r.exit_code == 0, r.stderr
    r = run(str(scene), "--out", str(b), "--config", str(a / "config.json"), *common)
    assert r.exit_code == 0, r.stderr
    ma, mb = (json.loads((d / "metrics.json").read_text()) for d in (a, b))
    assert ma["evals"][-1]["psnr"] == mb["evals"][-1]["psnr"]
    assert ma["evals"][-1]["views"] == mb["evals"][-1]["views"]


def _copy(scene: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "scene"
    shutil.copytree(scene.parent, dst)
    return dst / scene.name


def _set_view(i: int, key: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def f(doc: dict[str, Any]) -> None:
        doc["views"][i][key] = value

    return f


def _set_cam(i: int, key: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def f(doc: dict[str, Any]) -> None:
        doc["views"][i]["camera"][key] = value

    return f


def _all_split(split: str) -> Callable[[dict[str, Any]], None]:
    def f(doc: dict[str, Any]) -> None:
        for v in doc["views"]:
            v["split"] = split

    return f


def _no_points(doc: dict[str, Any]) -> None:
    doc["points"] = {"count": 0, "xyz": [], "rgb": []}


def _jpeg_test_view(doc: dict[str, Any]) -> None:
    from _train_scene import jpeg_state

    doc["views"][0]["jpeg"] = jpeg_state(50)  # view 0 is a test view with no reference


BAD: list[tuple[str, Callable[[dict[str, Any]], None] | None, str]] = [
    ("distorted", _set_cam(1, "distortion", {"model": "OPENCV_FISHEYE", "params": [0.02, 0.0, 0.0, 0.0]}),
     r"view 'view_001.png': camera has lens distortion \(OPENCV_FISHEYE\)"),
    ("size", _set_cam(1, "width", 40), r"is 32x24 but its camera is 40x24 \(the trainer never resamples"),
    ("missing image", _set_view(2, "image", "images/nope.png"), r"image images/nope.png not found"),
    ("not a rotation", _set_view(1, "R", [[1, 0, 0], [0, 1, 0], [0, 0, 2]]), "not a rotation matrix"),
    ("schema", _set_view(1, "split", "val"), r"not a valid manifest file: at views/1/split"),
    ("no train", _all_split("test"),
     r"no training views: all \d+ view\(s\) have split 'test'; jsgs train needs at least one \(jsgstools "
     r"manifest --test-every 0 makes every view a training view; 2 or more keeps some test views\)$"),
    ("no points", _no_points, "0 points: SfM initialisation needs more than 3"),
]  # fmt: skip


def test_distorted_cameras_train_on_their_own_grid(scene: Path, tmp_path: Path) -> None:
    """SIMPLE_RADIAL views train with the reference rasterizer (no resampling) and the loss falls."""
    import json

    manifest = _copy(scene, tmp_path / "d")

    def radial(doc: dict[str, Any]) -> None:
        for v in doc["views"]:
            v["camera"]["distortion"] = {"model": "SIMPLE_RADIAL", "params": [0.03]}

    edit_manifest(manifest, radial)
    r = run(str(manifest), "--out", str(tmp_path / "rd"), "--device", "cpu", "--iterations", "30",
            "--eval-at", "10,30", "--preset", "paper", "--quiet")  # fmt: skip
    assert r.exit_code == 0, r.output
    evals = json.loads((tmp_path / "rd" / "metrics.json").read_text())["evals"]
    assert evals[1]["train"]["loss"] < evals[0]["train"]["loss"]


def test_jpeg_test_views_and_no_test_views_train(scene: Path, tmp_path: Path) -> None:
    """A test view with no lossless copy is evaluated against its JPEG and says so; a manifest without test
    views trains without evaluations; scene.require_lossless_reference refuses the first in one line."""
    import json

    manifest = _copy(scene, tmp_path / "a")
    edit_manifest(manifest, _jpeg_test_view)
    r = run(str(manifest), "--out", str(tmp_path / "ra"), "--device", "cpu", "--iterations", "2", "--eval-at",
            "2", "--quiet")  # fmt: skip
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "ra" / "metrics.json").read_text())
    assert doc["reference"] == "mixed" and len(doc["evals"]) == 1 and "against their JPEGs" in r.output
    strict = tmp_path / "strict.json"
    strict.write_text(json.dumps({"scene": {"require_lossless_reference": True}}))
    r = run(str(manifest), "--out", str(tmp_path / "rs"), "--device", "cpu", "--iterations", "2", "--config",
            str(strict), "--quiet")  # fmt: skip
    one_line_error(r, "test view 'view_000.png' has only a JPEG image and no lossless")
    manifest = _copy(scene, tmp_path / "b")
    edit_manifest(manifest, _all_split("train"))
    r = run(str(manifest), "--out", str(tmp_path / "rb"), "--device", "cpu", "--iterations", "2", "--eval-at",
            "2", "--quiet")  # fmt: skip
    assert r.exit_code == 0 and "no test views" in r.output, r.output
    doc = json.loads((tmp_path / "rb" / "metrics.json").read_text())
    assert doc["reference"] == "none" and doc["evals"] == [] and doc["status"] == "complete"


@pytest.mark.parametrize("edit,pattern", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_cli_bad_manifests_fail_in_one_line(
    scene: Path, tmp_path: Path, edit: Callable[[dict[str, Any]], None], pattern: str
) -> None:
    manifest = _copy(scene, tmp_path)
    edit_manifest(manifest, edit)
    r = run(str(manifest), "--out", str(tmp_path / "run"), "--device", "cpu", "--iterations", "2", "--quiet")
    one_line_error(r, pattern)


def test_cli_other_one_line_errors(scene: Path, tmp_path: Path) -> None:
    out = str(tmp_path / "run")
    one_line_error(run(str(tmp_path / "none.json"), "--out", out), "manifest not found")
    (tmp_path / "photos").mkdir()
    one_line_error(
        run(str(tmp_path / "photos"), "--out", out),
        r"photos: neither a manifest nor a COLMAP scene; for a folder of photos run `jsgstools sfm ",
    )
    (tmp_path / "colmap" / "sparse").mkdir(parents=True)
    one_line_error(
        run(str(tmp_path / "colmap"), "--out", out),
        r"colmap: a folder without manifest.json; write one with `jsgstools manifest ",
    )
    notjson = tmp_path / "m.json"
    notjson.write_text("{")
    one_line_error(run(str(notjson), "--out", out), "not JSON")
    one_line_error(run(str(scene), "--out", out, "--eval-at", "a,b"), "--eval-at: expected comma-separated")
    one_line_error(
        run(str(scene), "--out", out, "--iterations", "5", "--eval-at", "9"), "eval_at steps must lie"
    )
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"optim": {"means_lrr": 1}}))
    one_line_error(run(str(scene), "--out", out, "--config", str(cfg)), "unknown setting optim.means_lrr")
    one_line_error(run(str(scene), "--out", out, "--method", "nope", "--iterations", "1", "--device", "cpu"),
                   "unknown method 'nope'")  # fmt: skip
    one_line_error(run(str(scene), "--out", str(tmp_path / "x"), "--resume"), "nothing to resume")


def test_checkpoints_rotate_and_the_setting_is_recorded(scene: Path, tmp_path: Path) -> None:
    """checkpoint_keep K keeps the newest K checkpoints (0: all), is recorded in config.json, and a
    config.json written before the setting existed still resumes, keeping every checkpoint as jsgs then
    did."""
    from jsgs.train import checkpoint as ckpt

    for keep, expected in ((2, [8, 10]), (0, [2, 4, 6, 8, 10])):
        cfg = tmp_path / f"keep{keep}.json"
        cfg.write_text(json.dumps({**FAST, "checkpoint_every": 2, "checkpoint_keep": keep}))
        out = tmp_path / f"run{keep}"
        r = run(str(scene), "--out", str(out), "--device", "cpu", "--config", str(cfg), "--iterations", "10",
                "--eval-at", "10", "--quiet")  # fmt: skip
        assert r.exit_code == 0, r.output + r.stderr
        assert [s for s, _ in ckpt.list_checkpoints(out / "checkpoints")] == expected
        assert json.loads((out / "config.json").read_text())["settings"]["checkpoint_keep"] == keep
    # a run stopped at 8 whose config.json and checkpoints predate checkpoint_keep
    cfg = tmp_path / "old.json"
    cfg.write_text(json.dumps({**FAST, "checkpoint_every": 2}))
    out = tmp_path / "old"
    r = run(str(scene), "--out", str(out), "--device", "cpu", "--config", str(cfg), "--iterations", "10",
            "--eval-at", "10", "--stop-at", "8", "--quiet")  # fmt: skip
    assert r.exit_code == 0, r.output + r.stderr
    conf = json.loads((out / "config.json").read_text())
    del conf["settings"]["checkpoint_keep"]
    (out / "config.json").write_text(json.dumps(conf))
    import torch

    for _, p in ckpt.list_checkpoints(out / "checkpoints"):
        doc = torch.load(p, weights_only=True)
        del doc["settings"]["checkpoint_keep"]
        torch.save(doc, p)
    r = run(str(scene), "--out", str(out), "--resume", "--quiet")
    assert r.exit_code == 0, r.output + r.stderr
    assert "complete: 10/10" in r.output and "checkpoint_keep 0" in r.stderr
    # step 2 went while the run kept 3; resumed as an earlier version's run none goes (3 would keep 6-10)
    assert [s for s, _ in ckpt.list_checkpoints(out / "checkpoints")] == [4, 6, 8, 10]


def test_what_a_killed_run_leaves_is_cleaned_up(scene: Path, tmp_path: Path, fast_config: Path) -> None:
    """Half-written (0-byte) temporaries of checkpoints, metrics.json and renders and the lock of a writer
    that no longer runs: --resume removes the temporaries and takes the lock over; a folder holding only such
    leftovers counts as empty for a new run."""
    from jsgs.base.io import LOCK_NAME

    out = tmp_path / "run"
    base = [str(scene), "--out", str(out), "--device", "cpu", "--config", str(fast_config), "--quiet"]
    r = run(*base, "--iterations", "4", "--eval-at", "2,4", "--stop-at", "2")
    assert r.exit_code == 0, r.output + r.stderr
    dead = json.dumps({"pid": 2**22 + 4321, "what": "jsgs train (killed)"})
    leftovers = [out / "checkpoints" / ".step_000003.pt.k1ll3d_x.part.pt",
                 out / ".metrics.json.abc_1234.part.json",
                 out / "renders" / "step_000002" / ".view_000.png.zz9_zz9z.part.png"]  # fmt: skip
    for p in leftovers:
        p.write_bytes(b"")
    (out / LOCK_NAME).write_text(dead)
    mine = out / "checkpoints" / "notes.txt"  # not ours: stays
    mine.write_text("mine")
    r = run(str(scene), "--out", str(out), "--resume", "--quiet")
    assert r.exit_code == 0, r.output + r.stderr
    assert "removed 3 half-written file(s)" in r.stderr and "complete: 4/4" in r.output
    assert not any(p.exists() for p in leftovers) and not (out / LOCK_NAME).exists()
    assert mine.read_text() == "mine"
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    (fresh / ".config.json.q1w2e3r4.part.json").write_bytes(b"")
    (fresh / LOCK_NAME).write_text(dead)
    r = run(str(scene), "--out", str(fresh), "--device", "cpu", "--config", str(fast_config), "--iterations",
            "2", "--quiet")  # fmt: skip
    assert r.exit_code == 0, r.output + r.stderr
    assert not [p for p in fresh.iterdir() if ".part" in p.name or p.name == LOCK_NAME]
