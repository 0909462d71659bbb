"""One scene on two processes (jsgs.train.distributed, jsgs train --processes): gloo and the reference
rasterizer on the CPU, the tiny synthetic scene. Each test starts the run as a user does (the CLI, which
starts the processes) and checks what lands in the run folder."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from _train_scene import make_scene

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_scene(tmp_path_factory.mktemp("scene"), n_views=9)


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    return env


def _settings(tmp: Path, **strategy: Any) -> Path:
    """A fast settings file: one timed FPS pass, no refinement unless ``strategy`` asks for it."""
    doc = {
        "device": "cpu",
        "eval": {"fps_passes": 1, "fps_warmup": 0},
        "strategy": {"refine_start_iter": 10_000, **strategy},
    }
    path = tmp / f"settings_{len(list(tmp.glob('settings_*')))}.json"
    path.write_text(json.dumps(doc))
    return path


def _train(manifest: Path, out: Path, *args: str, processes: int = 1) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "jsgs.cli", "train", str(manifest), "--out", str(out), "--quiet", *args]
    if "--method" not in args and "--resume" not in args:
        cmd += ["--method", "gsplat"]
    if processes > 1:
        cmd += ["--processes", str(processes)]
    return subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=300)


def _ok(r: subprocess.CompletedProcess[str]) -> None:
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr, r.stderr


def _files(run: Path) -> list[str]:
    return sorted(str(p.relative_to(run)) for p in run.rglob("*"))


def _one_error(r: subprocess.CompletedProcess[str] | tuple[int, str]) -> str:
    code, err = (r.returncode, r.stderr) if isinstance(r, subprocess.CompletedProcess) else r
    assert code != 0, err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, err
    return lines[0]


@pytest.mark.slow
def test_two_processes_write_one_run_and_match_one_process(scene: Path, tmp_path: Path) -> None:
    """Equal views seen (2 x 20 steps against 40): one run folder written once, world_size recorded, the
    evaluation made once, and the test PSNR within 1 dB of one process's."""
    cfg = _settings(tmp_path)
    one, two = tmp_path / "one", tmp_path / "two"
    common = ["--preset", "paper", "--config", str(cfg)]
    _ok(_train(scene, one, *common, "--iterations", "40", "--eval-at", "4,40"))
    r = _train(scene, two, *common, "--iterations", "20", "--eval-at", "2,20", processes=2)
    _ok(r)
    assert r.stdout.count("complete:") == 1  # one summary: only rank 0 reports
    m1 = json.loads((one / "metrics.json").read_text())
    m2 = json.loads((two / "metrics.json").read_text())
    c2 = json.loads((two / "config.json").read_text())
    assert (m1["world_size"], m2["world_size"], c2["derived"]["world_size"]) == (1, 2, 2)
    assert m2["status"] == "complete" and len(m2["evals"]) == 2
    # every view the two processes rendered is in rank 0's log: 2 per step
    assert m2["evals"][1]["train"]["steps"] == 36
    assert sum(v["steps"] for v in m2["evals"][1]["train"]["per_view"].values()) == 36
    # the same files as one process writes (no second copy, no leftover lock or partial file)
    rename = {"step_000040": "step_000020", "step_000004": "step_000002"}
    expected = []
    for f in _files(one):
        for a, b in rename.items():
            f = f.replace(a, b)
        expected.append(f)
    assert _files(two) == sorted(expected)
    (early1, psnr1), (early2, psnr2) = ((m["evals"][0]["psnr"], m["evals"][1]["psnr"]) for m in (m1, m2))
    # both learnt more than the tolerance after 4 views, and end within it of each other
    assert psnr1 - early1 > 1.0 and psnr2 - early2 > 1.0, (early1, psnr1, early2, psnr2)
    assert abs(psnr1 - psnr2) < 1.0, (psnr1, psnr2)


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="finds the processes through /proc")
def test_sigterm_to_one_process_stops_all_and_resume_is_exact(scene: Path, tmp_path: Path) -> None:
    """SIGTERM to rank 1 alone: every process stops after the same step with rank 0's checkpoint (one error
    line); resumed, the run ends bit for bit where an uninterrupted one does (DefaultStrategy refining on
    the shared statistics); resuming it on one process is refused with one line."""
    cfg = _settings(tmp_path, refine_start_iter=3, refine_every=4, refine_stop_iter=13, grow_grad2d=0.0001)
    full, part = tmp_path / "full", tmp_path / "part"
    common = ["--preset", "paper", "--config", str(cfg), "--iterations", "120", "--eval-at", ""]
    _ok(_train(scene, full, *common, processes=2))
    cmd = [sys.executable, "-m", "jsgs.cli", "train", str(scene), "--out", str(part), "--quiet", *common,
           "--method", "gsplat", "--processes", "2"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    try:
        ranks = _ranks_once_set_up(proc, part)
        time.sleep(0.2)  # past the signal handlers' installation
        os.kill(ranks[1], signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    line = _one_error((proc.returncode, err))
    assert "interrupted by SIGTERM to rank 1" in line, line
    m = json.loads((part / "metrics.json").read_text())
    assert m["status"] == "stopped" and 0 < m["step"] < 120, m["step"]
    line = _one_error(_train(scene, part, "--resume"))
    assert "2 process(es)" in line and "now 1" in line
    _ok(_train(scene, part, "--resume", processes=2))
    assert (part / "point_cloud.ply").read_bytes() == (full / "point_cloud.ply").read_bytes()
    # the refinement ran (the statistics shared by the processes made every one of them grow alike)
    m = json.loads((full / "metrics.json").read_text())
    c = json.loads((full / "config.json").read_text())
    assert m["num_gaussians"] > c["derived"]["initial_gaussians"]


def test_mcmc_and_jsgs_on_two_processes(tmp_path: Path) -> None:
    """The mcmc preset (relocation, growth to the budget, noise: one global budget) with JSGS on JPEG views:
    the processes stay identical (checked at every checkpoint) and the budget is the run's, not a
    process's."""
    scene = make_scene(tmp_path / "jscene", n_views=6, jpeg_train=True)
    cfg = _settings(tmp_path, refine_start_iter=2, refine_every=3, cap_max=60)
    run = tmp_path / "run"
    r = _train(scene, run, "--method", "jsgs", "--config", str(cfg), "--iterations", "12", "--eval-at", "12",
               processes=2)  # fmt: skip
    _ok(r)
    m = json.loads((run / "metrics.json").read_text())
    assert m["world_size"] == 2 and m["num_gaussians"] == 60
    terms = m["evals"][0]["train"]["terms"]
    assert {"obs", "low", "mid", "fro"} <= set(terms), terms  # the per-view terms of every view


def test_setup_error_on_one_process_is_one_line(scene: Path, tmp_path: Path) -> None:
    """A bad RUN found by rank 0 stops both processes, with rank 0's one line."""
    out = tmp_path / "taken"
    out.mkdir()
    (out / "mine.txt").write_text("not a run")
    line = _one_error(_train(scene, out, "--iterations", "4", processes=2))
    assert "folder is not empty" in line
    assert _files(out) == ["mine.txt"]


def _children(pid: int) -> list[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(x) for x in path.read_text().split()] if path.exists() else []


def _rank_of(pid: int) -> int | None:
    try:
        env = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    except OSError:
        return None
    for item in env:
        if item.startswith(b"RANK="):
            return int(item[5:])
    return None


def _ranks_once_set_up(proc: subprocess.Popen[str], out: Path) -> dict[int | None, int]:
    """The launcher's processes by rank, once config.json shows that every one has set up."""
    deadline = time.monotonic() + 120
    while not (out / "config.json").exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.05)
    ranks = {_rank_of(c): c for c in _children(proc.pid)}
    assert set(ranks) == {0, 1}, ranks
    return ranks


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="finds the processes through /proc")
def test_a_failing_process_stops_every_process_with_one_line(scene: Path, tmp_path: Path) -> None:
    """Rank 1 killed in the middle of training: rank 0 stops too (its next collective fails), the launcher
    reports one line and no process is left."""
    cfg = _settings(tmp_path)
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "jsgs.cli", "train", str(scene), "--out", str(out), "--quiet", "--config",
           str(cfg), "--method", "gsplat", "--iterations", "100000", "--eval-at", "",
           "--processes", "2"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    try:
        ranks = _ranks_once_set_up(proc, out)
        time.sleep(1.0)
        os.kill(ranks[1], signal.SIGKILL)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    line = _one_error((proc.returncode, err))
    assert "rank 1" in line, line
    for pid in ranks.values():
        assert not Path(f"/proc/{pid}").exists() or "zombie" in Path(f"/proc/{pid}/status").read_text()
    assert not (out / ".jsgs.lock").exists()


def _reductions_worker(rank: int, store: str) -> None:
    """One of two processes: renders view ``rank`` and reduces; rank 0 then does both views alone and
    compares (the averaged gradients and DefaultStrategy's shared statistics against one process's)."""
    import numpy as np
    import torch
    import torch.distributed as dist
    from _train_scene import look_at

    from jsgs.train import distributed as dd
    from jsgs.train.config import TrainConfig
    from jsgs.train.model import PARAM_NAMES, init_splats
    from jsgs.train.render_view import render_view
    from jsgs.train.strategy import Densifier

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=2)
    world = dd.World(rank, 2, rank)
    cfg = TrainConfig(device="cpu")
    cfg.strategy.refine_scale2d_stop_iter = 100  # the radii statistic too
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    splats = init_splats(torch.rand(30, 3, generator=g) - 0.5, torch.rand(30, 3, generator=g), cfg, 1.0,
                         torch.device("cpu"))  # fmt: skip
    cams = []
    for a in (0.3, 2.1):
        R, t = look_at(np.array([3 * np.cos(a), 3 * np.sin(a), 0.5]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
        vm = torch.eye(4)
        vm[:3, :3], vm[:3, 3] = torch.tensor(R, dtype=torch.float32), torch.tensor(t, dtype=torch.float32)
        cams.append(vm[None])
    K = torch.tensor([[[28.0, 0, 16], [0, 28.0, 12], [0, 0, 1]]])
    target = torch.rand(1, 24, 32, 3, generator=g)

    def one_view(strategy: Densifier, state: dict, i: int) -> None:
        r = render_view(splats, cams[i], K, 32, 24, 0, cfg, "torch")
        strategy.step_pre_backward(splats, {}, state, 0, r.info)
        (r.rgb - target).abs().mean().backward()
        strategy.gsplat._update_state(splats, state, r.info, packed=False)

    shared = Densifier(cfg.strategy)
    dd.share_strategy_statistics(shared, world)
    state = shared.initialize_state(scene_scale=1.0)
    one_view(shared, state, rank)
    params = [splats[n] for n in PARAM_NAMES]
    flags = dd.average_gradients(world, params, True, "SIGINT" if rank == 1 else None)
    assert (flags.rendered, flags.stop) == (2, "SIGINT to rank 1")
    averaged = [p.grad.clone() for p in params]
    if rank == 0:  # the same two views on one process
        alone = Densifier(cfg.strategy)
        ref = alone.initialize_state(scene_scale=1.0)
        grads = []
        for i in (0, 1):
            for p in params:
                p.grad = None
            one_view(alone, ref, i)
            grads.append([p.grad.clone() for p in params])
        for name, a, g0, g1 in zip(PARAM_NAMES, averaged, *grads, strict=True):
            assert torch.allclose(a, (g0 + g1) / 2, rtol=1e-5, atol=1e-8), name
        assert ref["count"].sum() > 0 and ref["grad2d"].sum() > 0
        for key in ("grad2d", "count", "radii"):
            assert torch.allclose(state[key], ref[key], rtol=1e-5, atol=1e-9), key
    # both processes leave together: a rank that tears gloo down while its peer still works aborts
    dist.barrier()
    dist.destroy_process_group()


def test_gradients_and_strategy_statistics_reduce_as_one_process(tmp_path: Path) -> None:
    """Two processes, one view each: the averaged gradients are the mean of the two views' gradients, and
    DefaultStrategy's running statistics equal one process's after both views (sums, counts, max radii)."""
    import torch.multiprocessing as mp

    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    mp.spawn(_reductions_worker, args=(str(tmp_path / "store"),), nprocs=2, join=True)


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--gpus", "2", "--processes", "2"], "exclude each other"),
        (["--gpus", "2", "--device", "cpu"], "use --processes"),
        (["--processes", "0"], "at least 1"),
    ],
)
def test_launch_options_refused_in_one_line(tmp_path: Path, args: list[str], expected: str) -> None:
    from click.testing import CliRunner

    from jsgs.cli import main

    r = CliRunner().invoke(main, ["train", str(tmp_path / "m.json"), "--out", str(tmp_path / "run"), *args])
    line = _one_error((r.exit_code, r.output))
    assert expected in line, line
    assert not (tmp_path / "run").exists()


def test_gpus_without_gpus_is_one_line(tmp_path: Path) -> None:
    import torch
    from click.testing import CliRunner

    from jsgs.cli import main

    if torch.cuda.device_count() >= 64:
        pytest.skip("a machine with 64 GPUs")
    args = ["train", str(tmp_path / "m.json"), "--out", str(tmp_path / "r"), "--gpus", "64"]
    r = CliRunner().invoke(main, args)
    assert "GPU(s)" in _one_error((r.exit_code, r.output))
