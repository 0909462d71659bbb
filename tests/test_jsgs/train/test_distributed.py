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
from hypothesis import given, settings
from hypothesis import strategies as st

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
def test_torchrun_on_one_and_two_machines_trains_what_two_processes_do(scene: Path, tmp_path: Path) -> None:
    """torchrun's launches of ``-m jsgs.cli train`` on one machine (``--standalone --nproc-per-node 2``: what
    ``--processes 2`` / ``--gpus 2`` stand for) and on two (``--nnodes 2 --node-rank K``, one process each,
    both started here: LOCAL_RANK 0 on both, RANK 0 and 1) train the same model, bit for bit, as
    ``--processes 2``, and write the run once (rank 0)."""
    import socket

    cfg = _settings(tmp_path)
    common = ["--preset", "paper", "--config", str(cfg), "--method", "gsplat", "--iterations", "6",
              "--eval-at", "6", "--quiet"]  # fmt: skip

    def torchrun(out: str, *launch: str) -> list[str]:
        return [sys.executable, "-m", "torch.distributed.run", *launch, "-m", "jsgs.cli", "train", str(scene),
                "--out", str(tmp_path / out), *common]  # fmt: skip

    _ok(_train(scene, tmp_path / "local", *common[:-1], processes=2))
    one = subprocess.run(torchrun("one", "--standalone", "--nproc-per-node", "2"), env=_env(),
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert one.returncode == 0, one.stderr
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    launch = ["--nnodes", "2", "--nproc-per-node", "1", "--master-addr", "127.0.0.1", "--master-port"]
    nodes = [
        subprocess.Popen(torchrun("nodes", "--node-rank", str(k), *launch, str(port)), env=_env(),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
        for k in (0, 1)
    ]
    outs = [n.communicate(timeout=300) for n in nodes]
    assert [n.returncode for n in nodes] == [0, 0], outs
    runs = ("local", "one", "nodes")
    local, *others = (json.loads((tmp_path / d / "metrics.json").read_text()) for d in runs)
    assert local["world_size"] == 2
    assert all((m["world_size"], m["status"]) == (2, "complete") for m in others)
    assert _files(tmp_path / "one") == _files(tmp_path / "local") == _files(tmp_path / "nodes")
    ply = [(tmp_path / d / "point_cloud.ply").read_bytes() for d in runs]
    assert ply[0] == ply[1] == ply[2]


@pytest.mark.slow
def test_jsgs_on_two_processes_matches_one_process(tmp_path: Path) -> None:
    """JSGS on JPEG views (the torch exchange, the Gaussian Controller's gradients sent back to the owners)
    at equal views seen (2 x 20 steps against 40): the test PSNR within 1 dB of one process's, both having
    learnt more than that."""
    scene = make_scene(tmp_path / "jscene", n_views=6, jpeg_train=True)
    cfg = _settings(tmp_path)
    one, two = tmp_path / "one", tmp_path / "two"
    common = ["--preset", "paper", "--config", str(cfg), "--method", "jsgs"]
    _ok(_train(scene, one, *common, "--iterations", "40", "--eval-at", "4,40"))
    _ok(_train(scene, two, *common, "--iterations", "20", "--eval-at", "2,20", processes=2))
    m1 = json.loads((one / "metrics.json").read_text())
    m2 = json.loads((two / "metrics.json").read_text())
    assert json.loads((two / "config.json").read_text())["derived"]["exchange"] == "torch"
    (early1, psnr1), (early2, psnr2) = ((m["evals"][0]["psnr"], m["evals"][1]["psnr"]) for m in (m1, m2))
    assert psnr1 - early1 > 1.0 and psnr2 - early2 > 1.0, (early1, psnr1, early2, psnr2)
    assert abs(psnr1 - psnr2) < 1.0, (psnr1, psnr2)
    assert {"obs", "low", "mid", "fro"} <= set(m2["evals"][1]["train"]["terms"])


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
    """The mcmc preset (relocation, growth to the budget, noise) with JSGS on JPEG views (the Gaussian
    Controller's extra channels: the torch exchange): one global budget, split into the shards' shares, which
    each shard fills; every view's per-view terms are logged."""
    import torch

    from jsgs.train.checkpoint import list_checkpoints

    scene = make_scene(tmp_path / "jscene", n_views=6, jpeg_train=True)
    cfg = _settings(tmp_path, refine_start_iter=2, refine_every=3, cap_max=60)
    # gsplat's exchange asked for where it cannot render (the CPU's reference rasterizer, JSGS's extra
    # channels): the torch exchange, with a note that says why
    cfg.write_text(json.dumps({**json.loads(cfg.read_text()), "speed": {"exchange": "gsplat"}}))
    run = tmp_path / "run"
    r = _train(scene, run, "--method", "jsgs", "--config", str(cfg), "--iterations", "12", "--eval-at", "12",
               processes=2)  # fmt: skip
    _ok(r)
    note = (
        "note: speed.exchange gsplat: gsplat's distributed rasterisation cannot render this run's views (the "
        "torch backend); the processes exchange the Gaussians with torch"
    )
    assert r.stderr.count(note) == 1, r.stderr
    m = json.loads((run / "metrics.json").read_text())
    assert m["world_size"] == 2 and m["num_gaussians"] == 60
    assert json.loads((run / "config.json").read_text())["derived"]["exchange"] == "torch"
    (_, last), *_ = reversed(list_checkpoints(run / "checkpoints"))
    doc = torch.load(last, weights_only=True)
    assert doc["shards"] == [30, 30] and doc["splats"]["means"].shape[0] == 60
    terms = m["evals"][0]["train"]["terms"]
    assert {"obs", "low", "mid", "fro"} <= set(terms), terms  # the per-view terms of every view


def test_the_scene_sized_budget_is_one_budget_on_two_processes(tmp_path: Path) -> None:
    """The default budget (sized to the scene) on two processes: each process reads it from the same
    manifest, so the run records one budget (the scene's 102: 4 training views of 32x24 / 30) and its two
    shards grow to their equal shares of it and no further."""
    import torch

    from jsgs.train.budget import scene_budget
    from jsgs.train.checkpoint import list_checkpoints
    from jsgs.train.config import TrainConfig
    from jsgs.train.data import load_training_scene

    manifest = make_scene(tmp_path / "scene", n_views=6)
    expected = scene_budget(load_training_scene(manifest, TrainConfig(device="cpu"))).cap_max
    assert expected == 102
    cfg = _settings(tmp_path, refine_start_iter=1, refine_every=2)
    run = tmp_path / "run"
    r = _train(manifest, run, "--config", str(cfg), "--iterations", "16", "--eval-at", "16", processes=2)
    _ok(r)
    assert r.stderr.count("note: budget from the scene: strategy.cap_max = 102 ") == 1, r.stderr
    doc = json.loads((run / "config.json").read_text())
    assert doc["settings"]["strategy"]["cap_max"] == doc["derived"]["budget"]["cap_max"] == expected
    assert json.loads((run / "metrics.json").read_text())["num_gaussians"] == expected
    (_, last), *_ = reversed(list_checkpoints(run / "checkpoints"))
    assert torch.load(last, weights_only=True)["shards"] == [51, 51]


def test_setup_error_on_one_process_is_one_line(scene: Path, tmp_path: Path) -> None:
    """A bad RUN found by rank 0 stops both processes, with rank 0's one line."""
    out = tmp_path / "taken"
    out.mkdir()
    (out / "mine.txt").write_text("not a run")
    line = _one_error(_train(scene, out, "--iterations", "4", processes=2))
    assert "folder is not empty" in line
    assert _files(out) == ["mine.txt"]


@pytest.mark.slow
def test_fewer_initial_gaussians_than_processes_is_one_line(scene: Path, tmp_path: Path) -> None:
    """Four initial Gaussians (the fewest the initialisation takes) for five processes: every process stops
    at setup, with one line naming the manifest (a process without Gaussians could take part in neither
    exchange); nothing is written."""
    settings = tmp_path / "four_points.json"
    settings.write_text(json.dumps({"device": "cpu", "init": {"type": "random", "num_points": 4}}))
    out = tmp_path / "run"
    line = _one_error(_train(scene, out, "--config", str(settings), "--iterations", "4", processes=5))
    assert f"{scene}: 4 initial Gaussian(s) cannot be shared by 5 processes" in line, line
    assert "train on at most 4 process(es)" in line and not (out / "config.json").exists()


@pytest.mark.slow
def test_a_prune_of_every_gaussian_leaves_one_per_process(scene: Path, tmp_path: Path) -> None:
    """DefaultStrategy told to prune every Gaussian (prune_opa 0.999) on two processes: each shard keeps
    its most opaque one, and the run trains on, evaluates and writes its model with two Gaussians."""
    cfg = _settings(tmp_path, refine_start_iter=2, refine_every=2, prune_opa=0.999)
    out = tmp_path / "run"
    _ok(_train(scene, out, "--preset", "paper", "--config", str(cfg), "--iterations", "6", "--eval-at", "6",
               processes=2))  # fmt: skip
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "complete" and metrics["num_gaussians"] == 2
    assert metrics["evals"][0]["num_gaussians"] == 2


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
    """One of two processes, each owning every other Gaussian and rendering view ``rank`` from all of them
    (the torch exchange); rank 0 then renders both views alone with every Gaussian and compares: each
    shard's gradient is its rows of the two views' mean gradient, and DefaultStrategy's statistics are its
    rows of one process's."""
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
    cfg = TrainConfig.from_preset("paper", device="cpu")
    cfg.strategy.refine_scale2d_stop_iter = 100  # the radii statistic too
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    full = init_splats(torch.rand(31, 3, generator=g) - 0.5, torch.rand(31, 3, generator=g), cfg, 1.0,
                       torch.device("cpu"))  # fmt: skip
    rows = dd.shard_rows(31, world, "test")
    shard = torch.nn.ParameterDict({n: torch.nn.Parameter(full[n].data[rows].clone()) for n in PARAM_NAMES})
    cams = []
    for a in (0.3, 2.1):
        R, t = look_at(np.array([3 * np.cos(a), 3 * np.sin(a), 0.5]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
        vm = torch.eye(4)
        vm[:3, :3], vm[:3, 3] = torch.tensor(R, dtype=torch.float32), torch.tensor(t, dtype=torch.float32)
        cams.append(vm[None])
    K = torch.tensor([[[28.0, 0, 16], [0, 28.0, 12], [0, 0, 1]]])
    target = torch.rand(1, 24, 32, 3, generator=g)

    def one_view(splats: torch.nn.ParameterDict, strategy: Densifier, state: dict, i: int) -> None:
        r = render_view(splats, cams[i], K, 32, 24, 0, cfg, "torch")
        strategy.step_pre_backward(splats, {}, state, 0, r.info)
        (r.rgb - target).abs().mean().backward()
        strategy.gsplat._update_state(splats, state, r.info, packed=False)

    holder: dict = {}
    shared = Densifier(cfg.strategy)
    fold = dd.share_strategy_statistics(shared, world, lambda: holder["ex"].rows)
    state = shared.initialize_state(scene_scale=1.0)
    holder["ex"] = ex = dd.gather_gaussians(world, shard, PARAM_NAMES)
    assert ex.sizes == [16, 15] and ex.rows == ((0, 16) if rank == 0 else (16, 31))
    one_view(ex.params, shared, state, rank)
    params = [shard[n] for n in PARAM_NAMES]
    assert dd.reduce_gradients(world, params, True, ex)
    mine = {"grads": [p.grad for p in params], "state": {k: state[k] for k in ("grad2d", "count", "radii")}}
    parts = dd.gather_to_main(world, mine)
    if rank == 0:  # both views on one process, every Gaussian in the gathered order
        assert parts is not None
        order = torch.cat([torch.arange(0, 31, 2), torch.arange(1, 31, 2)])
        alone_splats = torch.nn.ParameterDict(
            {n: torch.nn.Parameter(full[n].data[order].clone()) for n in PARAM_NAMES}
        )
        alone = Densifier(cfg.strategy)
        ref = alone.initialize_state(scene_scale=1.0)
        grads = []
        for i in (0, 1):
            for p in alone_splats.values():
                p.grad = None
            one_view(alone_splats, alone, ref, i)
            grads.append([alone_splats[n].grad.clone() for n in PARAM_NAMES])
        for j, (name, g0, g1) in enumerate(zip(PARAM_NAMES, *grads, strict=True)):
            got = torch.cat([parts[0]["grads"][j], parts[1]["grads"][j]])
            assert torch.allclose(got, (g0 + g1) / 2, rtol=1e-5, atol=1e-8), name
        assert ref["count"].sum() > 0 and ref["grad2d"].sum() > 0
        for key in ("grad2d", "count", "radii"):
            got = torch.cat([parts[0]["state"][key], parts[1]["state"][key]])
            assert torch.allclose(got, ref[key], rtol=1e-5, atol=1e-9), key
    # the same step with the statistics in the gradients' reduce-scatter (as the trainer makes it): the
    # same gradients and statistics, bit for bit, from one reduce-scatter (the sums of this process's rows)
    # and the radii's MAX all-reduce; and the same again where gloo has no reduce-scatter (torch < 2.13:
    # an all-reduce of the same buffer, this process's block copied out)
    ops: list = []
    all_reduce, scatter = dist.all_reduce, dd._reduce_scatter_tensor
    native = getattr(dist, "reduce_scatter_single", None)
    for fallback in (False, True):
        holder["ex"] = ex = dd.gather_gaussians(world, shard, PARAM_NAMES)
        r = render_view(ex.params, cams[rank], K, 32, 24, 0, cfg, "torch")
        again = shared.initialize_state(scene_scale=1.0)
        shared.step_pre_backward(ex.params, {}, again, 0, r.info)
        (r.rgb - target).abs().mean().backward()
        assert fold(r.info, False, shared.gsplat.refine_stop_iter) is None  # the strategy reads none then
        ops.clear()
        dist.all_reduce = lambda t, op=dist.ReduceOp.SUM: ops.append(op) or all_reduce(t, op=op)
        dd._reduce_scatter_tensor = lambda out, t: ops.append("scatter") or scatter(out, t)
        if fallback:
            dist.reduce_scatter_single = None
        try:
            assert dd.reduce_gradients(world, params, True, ex, fold(r.info, False, 0))
            shared.gsplat._update_state(ex.params, again, r.info, packed=False)
        finally:
            dist.all_reduce, dd._reduce_scatter_tensor = all_reduce, scatter
            if native is not None:
                dist.reduce_scatter_single = native
        expected = ["scatter", dist.ReduceOp.SUM] if fallback or native is None else ["scatter"]
        assert ops == [*expected, dist.ReduceOp.MAX], (fallback, ops)
        assert all(torch.equal(p.grad, g) for p, g in zip(params, mine["grads"], strict=True))
        assert all(torch.equal(again[k], state[k]) for k in ("grad2d", "count", "radii"))
    # the same step with the step's SH degree (0) given to the exchange, as the trainer gives it: shN's 45
    # values per Gaussian stay home both ways (14 of 59 gathered and reduced, with the rendered flag) and
    # every gradient is the same, bit for bit (shN's: zeros, as the render reads none of it)
    moved: list = []
    gather_tensor = dd._all_gather_tensor
    dd._all_gather_tensor = lambda out, t: moved.append(t.numel()) or gather_tensor(out, t)
    dd._reduce_scatter_tensor = lambda out, t: moved.append(t.numel()) or scatter(out, t)
    try:
        holder["ex"] = ex = dd.gather_gaussians(world, shard, PARAM_NAMES, ex.sizes, sh_degree=0)
        one_view(ex.params, Densifier(cfg.strategy), shared.initialize_state(scene_scale=1.0), rank)
        assert dd.reduce_gradients(world, params, True, ex)
    finally:
        dd._all_gather_tensor, dd._reduce_scatter_tensor = gather_tensor, scatter
    assert ex.params["shN"].shape == (31, 0, 3)
    assert params[PARAM_NAMES.index("shN")].grad.shape == (16 - rank, 15, 3)
    assert moved == [16 * 14, 2 * 16 * (14 + 1)], moved
    assert all(torch.equal(p.grad, g) for p, g in zip(params, mine["grads"], strict=True))
    # a step where only rank 0's view rendered keeps the gradients everywhere; one where none did, none
    for rendered, anywhere in ((rank == 0, True), (False, False)):
        ex = dd.gather_gaussians(world, shard, PARAM_NAMES)
        if rendered:
            ex.params["means"].sum().backward()
        for p in params:
            p.grad = None
        assert dd.reduce_gradients(world, params, rendered, ex) is anywhere
        assert all((p.grad is not None) is anywhere for p in params)
    # the step's values: one all-gather of a tensor; a layout not seen before sent once as an object, a row
    # longer than the capacity gathered again, longer, on both processes
    sent: list = []
    object_gather = dd.gather
    dd.gather = lambda w, obj: sent.append(obj) or object_gather(w, obj)  # type: ignore[assignment]
    values = dd.StepGather(world, capacity=4)
    lay = ("a",) if rank == 0 else ("b", "c")
    for n in (3, 3, 6 * rank + 1):
        got = values(lay, [float(rank)], torch.arange(float(n)) + 10 * rank)
        assert got[rank] == (lay, [float(rank), *(torch.arange(float(n)) + 10 * rank).tolist()])
        assert got[1 - rank][0] == (("a",) if rank == 1 else ("b", "c"))
    assert sent == [lay] and values.capacity == 8 and values.table == [("a",), ("b", "c")]
    assert got[0][1] == [0.0, 0.0] and got[1][1] == [1.0, *range(10, 17)]
    dd.gather = object_gather  # type: ignore[assignment]
    # the step's values in the gradients' reduce-scatter instead (its flag column; the shards of 16 and 15
    # rows padded to hold both rows): the same gradients bit for bit, each process's row delivered to both,
    # exactly, whether or not the views rendered
    host = [0.1 * (rank + 1), 1.0 / 3.0, float(2**40 + rank)]
    sent_values = torch.tensor([float(rank), -2.5, float("nan")])
    # (a row longer than the capacity asks for the all-gather, and the capacity grows on both processes)
    ex = dd.gather_gaussians(world, shard, PARAM_NAMES)
    assert not dd.reduce_gradients(world, params, False, ex, rider=values.rider(lay, host, sent_values))
    assert values.unpack(ex.riders.tolist()) is None and values.rider_capacity == 3 * 3 + 3
    for rendered, anywhere in ((True, True), (False, False)):
        ex = dd.gather_gaussians(world, shard, PARAM_NAMES)
        for p in params:
            p.grad = None
        if rendered:
            one_view(ex.params, Densifier(cfg.strategy), shared.initialize_state(scene_scale=1.0), rank)
        rider = values.rider(lay, host, sent_values)
        assert rider.dtype == torch.float32 and rider.numel() == 3 + values.rider_capacity
        assert dd.reduce_gradients(world, params, rendered, ex, rider=rider) is anywhere
        if rendered:
            assert all(torch.equal(p.grad, g) for p, g in zip(params, mine["grads"], strict=True))
        rows = values.unpack(ex.riders.tolist())
        assert rows is not None and [r[0] for r in rows] == [("a",), ("b", "c")]
        for r, (_, row) in enumerate(rows):
            assert row[:3] == [0.1 * (r + 1), 1.0 / 3.0, float(2**40 + r)], row
            assert row[3:5] == [float(r), -2.5] and row[5] != row[5] and len(row) == 6, row
    # equal shards of 40 rows, more than the rows need (1 + 2 x 15): no padding, the same buffer's size and
    # gradients as without them
    big = torch.nn.ParameterDict(
        {n: torch.nn.Parameter(torch.cat([shard[n].data] * 3)[:40].clone()) for n in PARAM_NAMES}
    )
    grads, moved = [], []
    dd._reduce_scatter_tensor = lambda out, t: moved.append(t.numel()) or scatter(out, t)
    for rider in (None, values.rider(lay, host, sent_values)):
        ex = dd.gather_gaussians(world, big, PARAM_NAMES)
        for p in big.values():
            p.grad = None
        one_view(ex.params, Densifier(cfg.strategy), shared.initialize_state(scene_scale=1.0), rank)
        assert dd.reduce_gradients(world, [big[n] for n in PARAM_NAMES], True, ex, rider=rider)
        grads.append([big[n].grad for n in PARAM_NAMES])
    dd._reduce_scatter_tensor = scatter
    assert moved == [2 * 40 * (59 + 1)] * 2, moved
    assert all(torch.equal(a, b) for a, b in zip(*grads, strict=True))
    rows = values.unpack(ex.riders.tolist())
    assert rows is not None and [row[3:5] for _, row in rows] == [[0.0, -2.5], [1.0, -2.5]], rows
    # both processes leave together, then skip the interpreter's teardown: with gloo's threads alive a
    # process aborts there now and then ("terminate called without an active exception": 3 in 45 runs on 2
    # cores, with or without destroy_process_group; none in 25 runs that leave this way)
    dist.barrier()
    os._exit(0)


def test_sharded_gradients_and_statistics_reduce_to_their_owners(tmp_path: Path) -> None:
    """Two processes, each owning half of the Gaussians and rendering one view from all of them: the
    gradients and DefaultStrategy's running statistics that reach each owner are its rows of one process's
    after both views (the mean gradient; sums, counts, max radii)."""
    import torch.multiprocessing as mp

    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    mp.spawn(_reductions_worker, args=(str(tmp_path / "store"),), nprocs=2, join=True)


#: every collective of torch.distributed a step could make, by name
_COLLECTIVES = (
    "all_gather", "all_gather_into_tensor", "all_gather_single", "all_gather_object", "all_reduce",
    "reduce_scatter", "reduce_scatter_tensor", "reduce_scatter_single", "broadcast", "broadcast_object_list",
    "barrier", "gather", "gather_object", "scatter", "all_to_all", "all_to_all_single",
)  # fmt: skip


def _counted_steps(trainer: Any, steps: int, calls: list, check: Any) -> list[Any]:
    """``steps`` steps of ``trainer``, each step's collectives (name, dtype of its tensor) and host reads
    (``Tensor.tolist`` / ``Tensor.item`` called by the trainer and jsgs.train.distributed: the step's own;
    the reference rasterizer's, the optimizer's and the view sampler's, of CPU tensors on a GPU too, are
    left out) appended to ``calls`` as a list; the
    steps' results (``check()`` after each step, not counted)."""
    import torch
    import torch.distributed as dist

    own = {name: getattr(dist, name) for name in _COLLECTIVES if hasattr(dist, name)}
    reads = {name: getattr(torch.Tensor, name) for name in ("tolist", "item")}

    def collective(name: str) -> Any:
        def call(*args: Any, **kwargs: Any) -> Any:
            tensor = next((a for a in args if isinstance(a, torch.Tensor)), None)
            calls[-1].append((name, getattr(tensor, "dtype", None)))
            return own[name](*args, **kwargs)

        return call

    def read(name: str) -> Any:
        def call(self: Any, *args: Any) -> Any:
            if Path(sys._getframe(1).f_code.co_filename).name in ("trainer.py", "distributed.py"):
                calls[-1].append((name, "host read"))
            return reads[name](self, *args)

        return call

    results = []
    for step in range(steps):
        calls.append([])
        for name in own:
            setattr(dist, name, collective(name))
        for name in reads:
            setattr(torch.Tensor, name, read(name))
        try:
            results.append(trainer.step(step))
        finally:
            for name, fn in own.items():
                setattr(dist, name, fn)
            for name, fn in reads.items():
                setattr(torch.Tensor, name, fn)
        check()
    return results


def _collectives_worker(rank: int, port: int, root: str) -> None:
    """One of two processes training on the torch exchange (the CPU), once with each strategy, every
    collective and host read of each step recorded; then again with the step's values in an all-gather of
    their own, which trains the same model and logs the same values, bit for bit."""
    import torch
    import torch.distributed as dist

    from jsgs.train.config import TrainConfig
    from jsgs.train.model import PARAM_NAMES
    from jsgs.train.trainer import Trainer, TrainingDiverged

    torch.set_num_threads(1)
    os.environ.update(RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE="2", MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))  # fmt: skip
    manifest = Path(root) / "scene" / "manifest.json"
    refine = {3, 6, 9}  # refine_start_iter 2, refine_every 3: the steps after which counts may change
    for strategy in ({"type": "default", "grow_grad2d": 1e-9}, {"type": "mcmc", "cap_max": 400}):
        runs = []
        for fold in (True, False):
            cfg = TrainConfig.from_preset("paper", device="cpu", method="gsplat", iterations=10, eval_at=[])
            for key, value in {**strategy, "refine_start_iter": 2, "refine_every": 3}.items():
                setattr(cfg.strategy, key, value)
            trainer = Trainer(manifest, Path(root) / f"{strategy['type']}{fold}", cfg, log=lambda s: None)
            trainer.setup()
            trainer.fold_step_values = fold
            assert trainer.exchange == "torch"
            calls: list = []
            held: list = []

            def check(trainer: Any = trainer, held: list = held, kind: str = strategy["type"]) -> None:
                everyone: list[Any] = [None, None]  # every process holds every shard's size
                dist.all_gather_object(everyone, int(trainer.splats["means"].shape[0]))
                assert trainer.sizes == everyone, (kind, trainer.sizes, everyone)
                held.append(everyone)

            runs.append((trainer, _counted_steps(trainer, 10, calls, check)))
            if trainer.lock is not None:
                trainer.lock.release()
            if not fold:
                continue
            for step, made in enumerate(calls[1:], start=1):
                # every step: the parameters' all-gather, then the gradients' reduce-scatter, which brings
                # every process's logged values (read on the host once); a step of the refinement schedule
                # then gathers the shard sizes (int64, read on the host)
                expected = [("all_gather_single", torch.float32), ("reduce_scatter_single", torch.float32),
                            ("tolist", "host read")]  # fmt: skip
                if step in refine:
                    expected += [("all_gather_single", torch.int64), ("tolist", "host read")]
                assert made == expected, (strategy, step, made)
        (one, one_results), (two, two_results) = runs
        assert one_results == two_results, strategy  # every view's logged values, bit for bit
        assert one.acc.state() == two.acc.state(), strategy
        assert all(torch.equal(one.splats[n], two.splats[n]) for n in PARAM_NAMES), strategy
        # the refinement changed the shards' sizes, after refinement steps only
        changed = {s for s in range(1, 10) if held[s] != held[s - 1]}
        assert changed and changed <= refine, (strategy, held)
        # a parameter that is NaN on rank 1 alone stops both processes after the same step, by the values
        # the reduce-scatter brought
        if rank == 1:
            with torch.no_grad():
                one.splats["opacities"][0] = float("nan")
        with pytest.raises(TrainingDiverged, match="iteration 10: parameter 'opacities'"):
            one.step(10)
        dist.barrier()
    dist.barrier()
    os._exit(0)  # (as _reductions_worker)


def test_a_steps_collectives_and_host_reads(scene: Path, tmp_path: Path) -> None:
    """The torch exchange on two processes (DefaultStrategy growing, MCMCStrategy adding): an ordinary step
    makes two collectives, the parameters' all-gather and the gradients' reduce-scatter, which also brings
    every process's logged values, read on the host once; a refinement step adds the all-gather of the
    shard sizes and its read, after the strategy, and every process then holds every shard's size. The
    same runs with the logged values in an all-gather of their own train and log the same, bit for bit."""
    import socket

    import torch.multiprocessing as mp

    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    (tmp_path / "scene").symlink_to(scene.parent)
    mp.spawn(_collectives_worker, args=(port, str(tmp_path)), nprocs=2, join=True)



def _rider_worker(rank: int, store: str, backend: str) -> None:
    """One of two processes (gloo on the CPU, or NCCL with a GPU each): every process's step values ride in
    the gradients' reduce-scatter, its device values including NaN, infinities, -0.0 and float32's largest,
    and arrive at every process as sent (-0.0 as 0.0: a sum with the other processes' zeros); the gradients
    are the mean of both processes'."""
    import math

    import torch
    import torch.distributed as dist

    from jsgs.train import distributed as dd
    from jsgs.train.config import TrainConfig
    from jsgs.train.model import PARAM_NAMES, init_splats

    torch.set_num_threads(1)
    device = torch.device(f"cuda:{rank}" if backend == "nccl" else "cpu")
    if device.type == "cuda":
        torch.cuda.set_device(device)
    dist.init_process_group(backend, init_method=f"file://{store}", rank=rank, world_size=2)
    world = dd.World(rank, 2, rank)
    cfg = TrainConfig.from_preset("paper", device=device.type)
    g = torch.Generator().manual_seed(1)
    full = init_splats(torch.rand(31, 3, generator=g) - 0.5, torch.rand(31, 3, generator=g), cfg, 1.0, device)
    rows = dd.shard_rows(31, world, "test")
    shard = torch.nn.ParameterDict({n: torch.nn.Parameter(full[n].data[rows].clone()) for n in PARAM_NAMES})
    params = [shard[n] for n in PARAM_NAMES]
    gathers = dd.StepGather(world)
    lay = ("a",) if rank == 0 else ("b", "c")
    host = [0.1 * (rank + 1), 1.0 / 3.0, float(2**40 + rank)]
    sent = [float(rank), -2.5, math.nan, math.inf, -math.inf, -0.0, 3.4028234663852886e38, 1e-30]
    values = torch.tensor(sent, device=device)
    gathers(lay, host, values)  # the layouts' first step: the all-gather, which registers them
    ex = dd.gather_gaussians(world, shard, PARAM_NAMES)
    for p in ex.params.values():
        p.grad = torch.full_like(p, float(rank + 1))
    assert dd.reduce_gradients(world, params, True, ex, rider=gathers.rider(lay, host, values))
    assert all(torch.equal(p.grad, torch.full_like(p, 1.5)) for p in params)
    got = gathers.unpack(ex.riders.tolist())
    assert got is not None and [lay for lay, _ in got] == [("a",), ("b", "c")]
    for r, (_, row) in enumerate(got):
        expected = [0.1 * (r + 1), 1.0 / 3.0, float(2**40 + r), float(r), -2.5]
        assert row[:5] == expected and math.isnan(row[5]), (r, row)
        assert row[6:] == [math.inf, -math.inf, 0.0, 3.4028234663852886e38, torch.tensor(1e-30).item()], row
    dist.barrier()
    os._exit(0)  # (as _reductions_worker)


@pytest.mark.parametrize("backend", ["gloo", pytest.param("nccl", marks=pytest.mark.gpu)])
def test_step_values_ride_the_reduce_scatter_exactly(tmp_path: Path, backend: str) -> None:
    """The values of a step that ride in the gradients' reduce-scatter reach every process exactly, NaN and
    infinities included (so a non-finite value on one process stops every process), on gloo and on NCCL
    (two GPUs; its sums are the GPU's)."""
    import torch
    import torch.multiprocessing as mp

    if backend == "nccl" and torch.cuda.device_count() < 2:
        pytest.skip("needs two GPUs")
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    mp.spawn(_rider_worker, args=(str(tmp_path / "store"), backend), nprocs=2, join=True)

@settings(max_examples=300, deadline=None)
@given(
    st.floats(allow_nan=False, allow_infinity=False, min_value=-1e30, max_value=1e30)
    | st.floats(min_value=2.0**-74, max_value=2.0**-70)
    | st.sampled_from([2.0**-74, -(2.0**-74), 3.4028234663852886e38, -3.4028234663852886e38])
)
def test_a_host_value_rides_as_three_float32_exactly(x: float) -> None:
    """A float64 host value (a loss weight, a Gaussian count) as the three float32 a rider row carries:
    their sum is the value, bit for bit, and each is 0 or a normal float32, for 0 and every magnitude from
    2**-74 to float32's largest (as StepGather.rider's docstring and docs/performance.md say; smaller values
    may not: those rows ask for the all-gather, below)."""
    import torch

    from jsgs.train import distributed as dd

    pieces = dd._three_float32(x)
    assert all(float(torch.tensor(p, dtype=torch.float32)) == p for p in pieces)
    if x == 0.0 or abs(x) >= 2.0**-74:
        assert sum(pieces) == x
        assert all(p == 0.0 or abs(p) >= dd._FLOAT32_NORMAL for p in pieces)


def test_a_rider_row_that_cannot_ride_asks_for_the_all_gather() -> None:
    """A rider row (:meth:`StepGather.rider`) of a layout not in the table, of a host value three normal
    float32 do not hold (NaN, beyond float32's range, a piece below float32's normal range, which a GPU's
    sum may flush to zero) or longer than the capacity asks for the all-gather: unpack gives None, and the
    capacity grows to the longest row asked for; rows that ride unpack to what the all-gather gives."""
    import math

    import torch

    from jsgs.train import distributed as dd

    gathers = [dd.StepGather(dd.World(r, 2, r), capacity=8) for r in (0, 1)]
    for g in gathers:
        g.layouts, g.table = {"a": 0}, ["a"]
    values = torch.tensor([1.5, float("inf")])
    assert gathers[0].rider("new", [1.0], values)[:2].tolist() == [-1.0, 5.0]
    for host in ([math.nan], [1e300], [1e-40], [3e-24], [1.0, 2.0, 3.0]):
        row = gathers[0].rider("a", host, values)
        assert row[0] == -1.0 and row.numel() == 3 + 8, host
    riders = [g.rider("a", [0.1, 7.0], values).tolist() for g in gathers]
    assert [r[:3] for r in riders] == [[0.0, 2.0, 2.0]] * 2
    assert gathers[1].unpack(riders) == [("a", [0.1, 7.0, 1.5, math.inf])] * 2
    too_long = gathers[0].rider("a", [1.0, 2.0, 3.0], values).tolist()
    for g in gathers:
        assert g.unpack([riders[0], too_long]) is None and g.rider_capacity == 11


def test_held_shard_sizes_are_checked_against_the_shard() -> None:
    """gather_gaussians with the sizes a process holds: its own entry must be its shard's row count (a size
    held past a change of the shard is an internal error, never a silently misaligned exchange)."""
    import torch

    from jsgs.train import distributed as dd

    shard = torch.nn.ParameterDict({"means": torch.nn.Parameter(torch.zeros(2, 3))})
    ex = dd.gather_gaussians(dd.World(), shard, ["means"], [2])
    assert ex.sizes == [2] and ex.rows == (0, 2)
    with pytest.raises(RuntimeError, match="shard sizes"):
        dd.gather_gaussians(dd.World(), shard, ["means"], [3])


def test_gsplat_exchange_statistics_add_camera_by_camera() -> None:
    """gsplat's exchange hands the owner its Gaussians' projection for every process's camera ([C, N, ...]
    in one ``info``): DefaultStrategy's statistics from it are those of the cameras added one view at a
    time, as on one process (the largest radii too, where one call's duplicate indices would keep either)."""
    import torch

    from jsgs.train import distributed as dd
    from jsgs.train.config import TrainConfig
    from jsgs.train.strategy import Densifier

    cfg = TrainConfig.from_preset("paper", device="cpu")
    cfg.strategy.refine_scale2d_stop_iter = 100
    g = torch.Generator().manual_seed(3)
    n = 40
    radii = (torch.rand(3, n, 2, generator=g) * 9).int()
    radii[0, :5] = 0
    means2d = torch.zeros(3, n, 2, requires_grad=True)
    means2d.grad = torch.randn(3, n, 2, generator=g)
    params = {"means": torch.zeros(n, 3)}
    info = {"width": 64, "height": 48, "n_cameras": 1, "radii": radii, "gaussian_ids": None,
            "means2d": means2d}  # fmt: skip
    shared = Densifier(cfg.strategy)
    dd.per_camera_statistics(shared, dd.World(0, 3, 0))
    state = shared.initialize_state(scene_scale=1.0)
    shared.gsplat._update_state(params, state, info, packed=False)
    alone = Densifier(cfg.strategy)
    ref = alone.initialize_state(scene_scale=1.0)
    for c in range(3):
        view = torch.zeros(1, n, 2, requires_grad=True)
        view.grad = means2d.grad[c : c + 1].clone()
        one = {**info, "radii": radii[c : c + 1], "means2d": view}
        alone.gsplat._update_state(params, ref, one, packed=False)
    assert ref["count"].max() == 3 and ref["radii"].sum() > 0
    for key in ("grad2d", "count", "radii"):
        assert torch.allclose(state[key], ref[key]), key


def test_torch_exchange_by_default_and_gsplats_where_asked_and_it_renders() -> None:
    """Every method takes the torch exchange unless ``speed.exchange: gsplat`` asks for gsplat's distributed
    rasterisation, which it gets where that renders every training view (gsplat backend, one image size,
    no distortion, no extra channels, no absgrad: it projects every process's camera with the calling
    process's image size); elsewhere the torch exchange, and the reason the run's note gives."""
    from types import SimpleNamespace

    import torch

    from jsgs.train import distributed as dd
    from jsgs.train.config import TrainConfig
    from jsgs.train.trainer import Trainer

    cfg = TrainConfig.from_preset("paper", device="cpu")

    def trainer(sizes: list[tuple[int, int]], backend: str, world: int, extra: bool, **view: object) -> Any:
        views = [SimpleNamespace(width=w, height=h, distortion=view.get("distortion")) for w, h in sizes]
        hook = SimpleNamespace(renders_extra=lambda: extra)
        t = SimpleNamespace(world=dd.World(0, world, 0), backend=backend, hook=hook, train_views=views)
        t._gsplat_cannot = lambda c: Trainer._gsplat_cannot(t, c)  # type: ignore[arg-type]
        return t

    def kind(sizes: list[tuple[int, int]], backend: str = "gsplat", world: int = 2, extra: bool = False,
             **view: object) -> tuple[str, str | None]:  # fmt: skip
        t = trainer(sizes, backend, world, extra, **view)
        return Trainer._exchange_kind(t, cfg), Trainer._gsplat_cannot(t, cfg)  # type: ignore[arg-type]

    assert cfg.speed.exchange == "torch"
    assert kind([(64, 48), (64, 48)]) == ("torch", None)  # gsplat's could render, the default is torch
    assert kind([(64, 48)], world=1)[0] == "none"
    cfg.speed.exchange = "gsplat"
    assert kind([(64, 48), (64, 48)]) == ("gsplat", None)
    sizes = "2 image sizes (it projects every process's camera at one size)"
    assert kind([(64, 48), (48, 64)]) == ("torch", sizes)
    assert kind([(64, 48)], backend="torch") == ("torch", "the torch backend")
    assert kind([(64, 48)], distortion=torch.zeros(4)) == ("torch", "lens distortion")
    assert kind([(64, 48)], extra=True) == ("torch", "the method renders extra channels")
    assert kind([(64, 48)], world=1)[0] == "none"
    cfg.strategy.absgrad = True
    assert kind([(64, 48)]) == ("torch", "strategy.absgrad")


def test_checkpoint_shards_merge_and_split_back() -> None:
    """A checkpoint gathered from two shards has one process's layout (rows concatenated by rank) and gives
    each process back exactly its rows, Adam moments, statistics and generators; row counts that do not
    fit are one line."""
    import torch

    from jsgs.base.errors import JsgsError
    from jsgs.train import distributed as dd

    def part(n: int, seed: int) -> dict[str, Any]:
        g = torch.Generator().manual_seed(seed)
        moments = {"step": torch.tensor(3.0), "exp_avg": torch.randn(n, 3, generator=g),
                   "exp_avg_sq": torch.rand(n, 3, generator=g)}  # fmt: skip
        return {
            "splats": {"means": torch.randn(n, 3, generator=g)},
            "optimizers": {"means": {"state": {0: moments}, "param_groups": [{"lr": 0.1}]}},
            "strategy": {"grad2d": torch.rand(n, generator=g), "count": torch.rand(n, generator=g),
                         "radii": None, "scene_scale": 1.5},  # fmt: skip
            "rng": {"torch": torch.tensor([seed], dtype=torch.uint8)},
        }

    parts = [part(4, 0), part(3, 1)]
    doc = dd.merge_shards(parts)
    assert doc["shards"] == [4, 3] and doc["splats"]["means"].shape == (7, 3)
    assert doc["rng"] is parts[0]["rng"] and doc["strategy"]["scene_scale"] == 1.5
    for rank, p in enumerate(parts):
        back = dd.split_checkpoint(doc, dd.World(rank, 2, rank), "ck.pt")
        assert torch.equal(back["splats"]["means"], p["splats"]["means"])
        moments, want = back["optimizers"]["means"]["state"][0], p["optimizers"]["means"]["state"][0]
        for m in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(moments[m], want[m])
        assert torch.equal(back["strategy"]["grad2d"], p["strategy"]["grad2d"])
        assert back["strategy"]["radii"] is None and back["rng"] is p["rng"]
    with pytest.raises(JsgsError, match=r"ck\.pt: .*shards"):
        dd.split_checkpoint({**doc, "shards": [4, 4]}, dd.World(0, 2, 0), "ck.pt")
    with pytest.raises(JsgsError, match=r"ck\.pt: .*shards: .* at least one each \(7 in the file\)"):
        dd.split_checkpoint({**doc, "shards": [7, 0]}, dd.World(0, 2, 0), "ck.pt")  # an empty shard
    with pytest.raises(JsgsError, match="3 processes"):
        dd.split_checkpoint(doc, dd.World(0, 3, 0), "ck.pt")


def test_a_signal_to_any_process_stops_all_after_the_step() -> None:
    from jsgs.train import distributed as dd

    assert dd.stop_request([None, None]) is None
    assert dd.stop_request([None, "SIGTERM", "SIGINT"]) == "SIGTERM to rank 1"


def test_budget_shares_sum_to_the_budget() -> None:
    """The budget's shares sum to it; the initial Gaussians' shards fit in them, at least one Gaussian each,
    and fewer Gaussians than processes is one line."""
    import torch

    from jsgs.base.errors import JsgsError
    from jsgs.train import distributed as dd

    for cap in (0, 1, 2, 59, 60, 61, 1_000_000):
        for size in (1, 2, 3, 8):
            shares = [dd.shard_cap(cap, dd.World(r, size, r)) for r in range(size)]
            assert sum(shares) == cap and max(shares) - min(shares) <= 1
            if cap < size:
                for r in range(size):
                    with pytest.raises(JsgsError) as e:
                        dd.shard_rows(cap, dd.World(r, size, r), "scene/manifest.json")
                    assert str(e.value) == (
                        f"scene/manifest.json: {cap} initial Gaussian(s) cannot be shared by {size} "
                        f"processes (each needs at least one); train on at most {cap} process(es), or start "
                        "from more points"
                    )
                continue
            rows = [dd.shard_rows(cap, dd.World(r, size, r), "test") for r in range(size)]
            assert all(1 <= len(n) <= s for n, s in zip(rows, shares, strict=True))
            assert sorted(torch.cat(rows).tolist()) == list(range(cap))


def test_pruning_never_empties_a_shard() -> None:
    """DefaultStrategy's pruning on several processes: a prune of every Gaussian of the shard keeps the most
    opaque one, with its Adam moments and statistics; any other prune is gsplat's own, row for row."""
    import gsplat.strategy.default as gsd
    import torch

    from jsgs.train import distributed as dd
    from jsgs.train.config import TrainConfig
    from jsgs.train.strategy import Densifier

    def shard(opacities: list[float]) -> tuple[torch.nn.ParameterDict, dict[str, Any]]:
        n = len(opacities)
        params = torch.nn.ParameterDict({
            "means": torch.nn.Parameter(torch.arange(3.0 * n).reshape(n, 3)),
            "scales": torch.nn.Parameter(torch.full((n, 3), -3.0)),
            "opacities": torch.nn.Parameter(torch.logit(torch.tensor(opacities))),
        })  # fmt: skip
        optimizers = {k: torch.optim.Adam([p], lr=0.1) for k, p in params.items()}
        for p in params.values():
            p.sum().backward()
        for o in optimizers.values():
            o.step()
        return params, optimizers

    cfg = TrainConfig.from_preset("paper", device="cpu").strategy
    for opacities in ([0.001, 0.004, 0.002], [0.001, 0.5, 0.002, 0.9], [0.3, 0.6]):
        got, want = Densifier(cfg), Densifier(cfg)
        dd.keep_a_gaussian_per_shard(got, dd.World(0, 2, 0))
        results = []
        for strategy in (got, want):
            params, optimizers = shard(opacities)
            state = strategy.initialize_state(scene_scale=1.0)
            state["grad2d"], state["count"] = torch.arange(len(opacities)) + 1.0, torch.ones(len(opacities))
            before = params["means"].data.clone()
            strategy.gsplat._prune_gs(params, optimizers, state, 100)
            results.append((params, optimizers["means"].state_dict()["state"][0]["exp_avg"], state["grad2d"]))
        assert gsd.remove.__module__ == "gsplat.strategy.ops"  # the patch lasts one call
        (params, moments, grad2d), (ref, ref_moments, ref_grad2d) = results
        if all(o < cfg.prune_opa for o in opacities):  # gsplat would prune them all: the most opaque stays
            assert ref["means"].shape[0] == 0 and params["means"].shape[0] == 1
            assert torch.equal(params["means"].data, before[1:2])
            assert moments.shape == (1, 3) and grad2d.tolist() == [2.0]
        else:
            assert torch.equal(params["means"].data, ref["means"].data) and params["means"].shape[0] > 0
            assert torch.equal(moments, ref_moments) and torch.equal(grad2d, ref_grad2d)
    one = Densifier(cfg)  # one process: gsplat's strategy untouched
    dd.keep_a_gaussian_per_shard(one, dd.World(0, 1, 0))
    assert "_prune_gs" not in vars(one.gsplat)


def test_the_shard_prune_removes_what_gsplat_removes() -> None:
    """The per-shard prune finds its rows with gsplat's own rule (opacity, and after reset_every the 3D
    scale, before refine_scale2d_stop_iter the screen radius): on random shards it removes the rows, moments
    and statistics gsplat's DefaultStrategy removes, leaves gsplat's modules as they are, and keeps the
    model's tensors untouched while it looks."""
    import dataclasses

    import gsplat.strategy.default as gsd
    import gsplat.strategy.ops as ops
    import torch

    from jsgs.train import distributed as dd
    from jsgs.train.config import TrainConfig
    from jsgs.train.strategy import Densifier

    base = TrainConfig.from_preset("paper", device="cpu").strategy
    cfg = dataclasses.replace(base, refine_scale2d_stop_iter=4000, prune_opa=0.3)
    n, counts = 64, {}
    for step in (100, 3500, 4500):  # one shard, pruned at three steps
        g = torch.Generator().manual_seed(0)
        opacities, scales = torch.randn(n, 1, generator=g), torch.randn(n, 3, generator=g) - 3.0
        radii = torch.rand(n, generator=g) * 0.2
        results = []
        for wrap in (True, False):
            strategy = Densifier(cfg)
            if wrap:
                dd.keep_a_gaussian_per_shard(strategy, dd.World(0, 2, 0))
            params = torch.nn.ParameterDict({
                "means": torch.nn.Parameter(torch.arange(3.0 * n).reshape(n, 3)),
                "scales": torch.nn.Parameter(scales.clone()),
                "opacities": torch.nn.Parameter(opacities.clone()),
            })  # fmt: skip
            optimizers = {k: torch.optim.Adam([p], lr=0.1) for k, p in params.items()}
            sum(p.sum() for p in params.values()).backward()
            for o in optimizers.values():
                o.step()
            state = strategy.initialize_state(scene_scale=1.0)
            state.update(grad2d=torch.arange(n) + 1.0, count=torch.ones(n), radii=radii.clone())
            if wrap:
                own = gsd.DefaultStrategy._prune_gs.__get__(strategy.gsplat)
                mask = dd._prune_mask(own, params, state, step)
                assert params["means"].shape[0] == n and state["radii"].shape == (n,)
                assert "jsgs_row" not in state
            count = strategy.gsplat._prune_gs(params, optimizers, state, step)
            moments = optimizers["opacities"].state_dict()["state"][0]["exp_avg"]
            rows = torch.round(params["means"].detach()[:, 0] / 3).long()  # Adam moved them by 0.1
            results.append((count, rows, moments, state["grad2d"], state["radii"]))
        (count, rows, *rest), (want_count, want_rows, *want_rest) = results
        assert count == want_count == int(mask.sum()) and 0 < count < n
        assert torch.equal(rows, want_rows) and torch.equal(rows, torch.where(~mask)[0])
        assert all(torch.equal(a, b) for a, b in zip(rest, want_rest, strict=True))
        counts[step] = count
        assert gsd.remove is ops.remove
    assert counts[100] < counts[4500] < counts[3500]  # opacity; and 3D scale; and screen radius


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


def test_a_crashed_process_is_named_by_its_error() -> None:
    """The launcher's line for a process that died without its own ``error:`` line is the error its output
    tells (a C++ exception's ``what()``, a traceback's exception), not a stack frame."""
    from jsgs.train.launch import crash_line

    abort = [
        "terminate called after throwing an instance of 'c10::Error'",
        "  what():  CUDA error: an illegal memory access was encountered",
        "CUDA kernel errors might be asynchronously reported at some other API call, so the stacktrace below "
        "might be incorrect.",
        "For debugging consider passing CUDA_LAUNCH_BLOCKING=1",
        "Compile with `TORCH_USE_CUDA_DSA` to enable device-side assertions.",
        "",
        "Exception raised from c10_cuda_check_implementation at /pytorch/c10/cuda/CUDAException.cpp:42",
        "frame #0: c10::Error::Error(c10::SourceLocation, std::string) + 0x98 (0x7f in libc10.so)",
        "frame #4: <unknown function> + 0x129ecc (0x7f in /lib/x86_64-linux-gnu/libc.so.6)",
    ]
    assert crash_line(abort) == "CUDA error: an illegal memory access was encountered"
    traceback = [
        "Traceback (most recent call last):",
        '  File "x.py", line 3, in <module>',
        "    raise ValueError('boom')",
        "torch.OutOfMemoryError: CUDA out of memory. Tried to allocate 2.00 GiB",
        "For debugging consider passing CUDA_LAUNCH_BLOCKING=1",
        "frame #1: <unknown function> + 0x129ecc (0x7f in /lib/x86_64-linux-gnu/libc.so.6)",
    ]
    assert crash_line(traceback) == "torch.OutOfMemoryError: CUDA out of memory. Tried to allocate 2.00 GiB"
    assert crash_line(["Segmentation fault", "frame #2: <unknown function> + 0x1 (0x7f in x.so)"]) == (
        "Segmentation fault"
    )
    assert crash_line([]) is None


def test_gpus_without_gpus_is_one_line(tmp_path: Path) -> None:
    import torch
    from click.testing import CliRunner

    from jsgs.cli import main

    if torch.cuda.device_count() >= 64:
        pytest.skip("a machine with 64 GPUs")
    args = ["train", str(tmp_path / "m.json"), "--out", str(tmp_path / "r"), "--gpus", "64"]
    r = CliRunner().invoke(main, args)
    assert "GPU(s)" in _one_error((r.exit_code, r.output))


def _gsplat_ops_in_torch() -> None:
    """gsplat 1.5.3's ``rasterization`` on the CPU: its CUDA ops replaced by gsplat's own torch versions
    (``gsplat.cuda._torch_impl``; the non-packed, pinhole, classic layout jsgs uses), and jsgs's gsplat
    backend let through on CPU tensors; its gather of the shards' sizes (``all_gather_int32``, CUDA only)
    made with gloo. The rest of ``rasterization``, its ``distributed=True`` path included (the cameras'
    all-gather, the owner's SH colours, the all-to-alls and their backward), is gsplat's own, on gloo."""
    import gsplat.rendering as gr
    import torch
    from gsplat.cuda import _torch_impl as ti

    import jsgs.render.backend as jb

    def projection(means: Any, covars: Any, quats: Any, scales: Any, viewmats: Any, Ks: Any, width: int,
                   height: int, eps2d: float = 0.3, packed: bool = False, near_plane: float = 0.01,
                   far_plane: float = 1e10, radius_clip: float = 0.0, calc_compensations: bool = False,
                   camera_model: str = "pinhole", **_: Any) -> Any:  # fmt: skip
        assert not packed and radius_clip == 0.0 and covars is None
        covars, _ = ti._quat_scale_to_covar_preci(quats, scales, compute_preci=False, triu=False)
        return ti._fully_fused_projection(
            means, covars, viewmats, Ks, width, height, eps2d, near_plane, far_plane, calc_compensations,
            camera_model,
        )  # fmt: skip

    def isect_tiles(means2d: Any, radii: Any, depths: Any, tile_size: int, tile_width: int,
                    tile_height: int, packed: bool = False, **_: Any) -> Any:  # fmt: skip
        assert not packed
        return ti._isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height)

    def rasterize_to_pixels(means2d: Any, conics: Any, colors: Any, opacities: Any, width: int, height: int,
                            tile_size: int, isect_offsets: Any, flatten_ids: Any, backgrounds: Any = None,
                            packed: bool = False, absgrad: bool = False) -> Any:  # fmt: skip
        """Each tile's Gaussians front to back (isect_tiles' order), alpha = min(0.999, o·exp(-σ)) where
        at least 1/255, over the background (``_torch_impl``'s own needs a CUDA op and nerfacc)."""
        assert not packed and not absgrad
        I, N = means2d.shape[:2]
        ends = torch.cat([isect_offsets.flatten()[1:], torch.tensor([len(flatten_ids)])]).tolist()
        starts = isect_offsets.flatten().tolist()
        ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
        pix = torch.stack([xs, ys], -1).float() + 0.5
        img = means2d.new_zeros(I, height, width, colors.shape[-1])
        trans = means2d.new_ones(I, height, width, 1)
        th, tw = isect_offsets.shape[1:]
        for k, (a, b) in enumerate(zip(starts, ends, strict=True)):
            if a == b:
                continue
            i, ty, tx = k // (th * tw), (k // tw) % th, k % tw
            rows = slice(ty * tile_size, (ty + 1) * tile_size)
            cols = slice(tx * tile_size, (tx + 1) * tile_size)
            ids = flatten_ids[a:b].long() % N
            d = pix[rows, cols][:, :, None, :] - means2d[i, ids]  # [h, w, K, 2]
            c = conics[i, ids]
            dx, dy = d[..., 0], d[..., 1]
            sigma = 0.5 * (c[:, 0] * dx**2 + c[:, 2] * dy**2) + c[:, 1] * dx * dy
            alpha = torch.clamp_max(opacities[i, ids] * torch.exp(-sigma), 0.999)
            alpha = torch.where((sigma >= 0) & (alpha >= 1 / 255), alpha, torch.zeros_like(alpha))
            t = torch.cumprod(torch.cat([torch.ones_like(alpha[..., :1]), 1 - alpha], -1), -1)
            img[i, rows, cols] = ((alpha * t[..., :-1])[..., None] * colors[i, ids]).sum(-2)
            trans[i, rows, cols] = t[..., -1:]
        if backgrounds is not None:
            img = img + trans * backgrounds[:, None, None, :]
        return img, 1 - trans

    def spherical_harmonics(degree: int, dirs: Any, coeffs: Any, masks: Any = None) -> Any:
        colors = ti._spherical_harmonics(degree, dirs, coeffs)
        return colors if masks is None else colors * masks[..., None]  # unseen: 0, as the kernel leaves them

    def all_gather_int32(world_size: int, value: int, device: Any = None) -> list[int]:
        import torch.distributed as dist

        out = [torch.zeros(1, dtype=torch.int32) for _ in range(world_size)]
        dist.all_gather(out, torch.tensor([value], dtype=torch.int32))
        return [int(t.item()) for t in out]

    gr.all_gather_int32 = all_gather_int32
    gr.fully_fused_projection = projection
    gr.isect_tiles = isect_tiles
    gr.isect_offset_encode = ti._isect_offset_encode
    gr.rasterize_to_pixels = rasterize_to_pixels
    gr.spherical_harmonics = spherical_harmonics
    jb.resolve_backend = lambda backend, device: backend


def _gsplat_exchange_worker(rank: int, store: str, cuda: bool) -> None:
    """One of two processes (GPUs with NCCL, or the CPU with gloo and :func:`_gsplat_ops_in_torch`), each
    owning every other Gaussian and rendering view ``rank`` through gsplat's ``distributed=True``
    rasterisation (non-packed), colours of SH degree 3; rank 0 then renders both views alone (every Gaussian
    in the shards' order) and compares the gradients and DefaultStrategy's statistics each owner received."""
    import numpy as np
    import torch
    import torch.distributed as dist
    from _train_scene import look_at

    from jsgs.train import distributed as dd
    from jsgs.train.config import TrainConfig
    from jsgs.train.model import PARAM_NAMES, init_splats
    from jsgs.train.render_view import render_view
    from jsgs.train.strategy import Densifier

    if cuda:
        torch.cuda.set_device(rank)
        device = torch.device("cuda", rank)
    else:
        _gsplat_ops_in_torch()
        device = torch.device("cpu")
    backend = "nccl" if cuda else "gloo"
    dist.init_process_group(backend, init_method=f"file://{store}", rank=rank, world_size=2)
    world = dd.World(rank, 2, rank)
    cfg = TrainConfig.from_preset("paper", device=device.type)
    cfg.strategy.refine_scale2d_stop_iter = 100
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    n = 301 if cuda else 300  # shards of unequal sizes, where the all-to-all allows them (gloo's does not)
    points, colors = torch.rand(n, 3, generator=g) - 0.5, torch.rand(n, 3, generator=g)
    full = init_splats(points, colors, cfg, 1.0, device)
    # view-dependent colours (SH degree 3), which the owner evaluates along each process's camera's directions
    full["shN"].data.copy_(0.3 * torch.randn(full["shN"].shape, generator=g).to(device))
    rows = dd.shard_rows(n, world, "test").to(device)
    shard = torch.nn.ParameterDict({n: torch.nn.Parameter(full[n].data[rows].clone()) for n in PARAM_NAMES})
    cams = []
    for a in (0.3, 2.1):
        R, t = look_at(np.array([3 * np.cos(a), 3 * np.sin(a), 0.5]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
        vm = torch.eye(4)
        vm[:3, :3], vm[:3, 3] = torch.tensor(R, dtype=torch.float32), torch.tensor(t, dtype=torch.float32)
        cams.append(vm[None].to(device))
    K = torch.tensor([[[56.0, 0, 32], [0, 56.0, 24], [0, 0, 1]]], device=device)
    target = torch.rand(1, 48, 64, 3, generator=g).to(device)

    def one_view(splats: Any, strategy: Densifier, state: dict, i: int, spread: bool) -> None:
        r = render_view(splats, cams[i], K, 64, 48, cfg.render.sh_degree, cfg, "gsplat", distributed=spread)
        if spread:  # the owner's projection, for both processes' cameras
            assert r.info["means2d"].shape == (2, splats["means"].shape[0], 2)
        strategy.step_pre_backward(splats, {}, state, 0, r.info)
        (r.rgb - target).abs().mean().backward()
        strategy.gsplat._update_state(splats, state, r.info, packed=False)

    shared = Densifier(cfg.strategy)
    dd.per_camera_statistics(shared, world)
    state = shared.initialize_state(scene_scale=1.0)
    cfg.render.packed = True  # refused by gsplat's distributed path: the render is non-packed anyway
    one_view(shard, shared, state, rank, True)
    cfg.render.packed = False
    params = [shard[n] for n in PARAM_NAMES]
    assert dd.reduce_gradients(world, params, True) is True
    mine = {"grads": [p.grad for p in params], "state": {k: state[k] for k in ("grad2d", "count", "radii")}}
    parts = dd.gather_to_main(world, mine)
    if rank == 0:
        assert parts is not None
        order = torch.cat([torch.arange(0, n, 2), torch.arange(1, n, 2)]).to(device)
        alone_splats = torch.nn.ParameterDict(
            {n: torch.nn.Parameter(full[n].data[order].clone()) for n in PARAM_NAMES}
        )
        alone = Densifier(cfg.strategy)
        ref = alone.initialize_state(scene_scale=1.0)
        grads = []
        for i in (0, 1):
            for p in alone_splats.values():
                p.grad = None
            one_view(alone_splats, alone, ref, i, False)
            grads.append([alone_splats[n].grad.clone().cpu() for n in PARAM_NAMES])
        for j, (name, g0, g1) in enumerate(zip(PARAM_NAMES, *grads, strict=True)):
            got = torch.cat([parts[0]["grads"][j], parts[1]["grads"][j]])
            assert torch.allclose(got, (g0 + g1) / 2, rtol=1e-3, atol=1e-7), name
        assert ref["count"].sum() > 0
        for key in ("grad2d", "count", "radii"):
            got = torch.cat([parts[0]["state"][key], parts[1]["state"][key]])
            assert torch.allclose(got, ref[key].cpu(), rtol=1e-3, atol=1e-7), key
    dist.barrier()
    if cuda:
        dist.destroy_process_group()
    else:  # gloo: see _reductions_worker
        os._exit(0)


@pytest.mark.gpu
def test_gsplat_exchange_sends_gradients_and_statistics_to_their_owners(tmp_path: Path) -> None:
    """Two GPUs, gsplat's ``rasterization(..., distributed=True)``: the gradients and
    DefaultStrategy's statistics each shard receives are its rows of one GPU's after both views."""
    import torch
    import torch.multiprocessing as mp

    if torch.cuda.device_count() < 2:
        pytest.skip("needs two GPUs")
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    mp.spawn(_gsplat_exchange_worker, args=(str(tmp_path / "store"), True), nprocs=2, join=True)


def test_gsplat_exchange_on_the_cpu_sends_gradients_and_statistics_to_their_owners(tmp_path: Path) -> None:
    """The same on the CPU: gsplat's ``distributed=True`` path itself (the owner's projection and SH
    colours for every process's camera, the all-to-alls and their backward) over gloo, with gsplat's torch
    versions of its CUDA ops: each shard's gradients and statistics are its rows of one process's."""
    import torch.multiprocessing as mp

    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    mp.spawn(_gsplat_exchange_worker, args=(str(tmp_path / "store"), False), nprocs=2, join=True)


@pytest.mark.gpu
def test_two_gpus_train_with_gsplats_exchange(scene: Path, tmp_path: Path) -> None:
    """`jsgs train --gpus 2` with the gsplat baseline on gsplat's exchange (``speed.exchange: gsplat``), one
    run folder, and the test PSNR within 0.2 dB of the torch exchange's (the default) on the same two GPUs
    at the same 200 steps (the same views in the same order, the same rasterizer, gradients that agree: the
    test above), both having learnt more than 1 dB; the SH degree rises every 50 steps, so view-dependent
    colours (evaluated on each Gaussian's owner for every process's camera) are trained too. JSGS asking
    for gsplat's exchange takes the torch exchange (the Gaussian Controller's extra channels).

    Not compared with one GPU at equal views seen: on this scene, 400 steps against 2 x 200, the batch of two
    views lands 2.0 dB lower with either exchange (gsplat's on GPUs, the torch exchange on the CPU), where
    the PSNR still climbs about 3 dB per 100 steps (docs/performance.md)."""
    import torch

    if torch.cuda.device_count() < 2:
        pytest.skip("needs two GPUs")
    settings: dict[str, Any] = {
        "eval": {"fps_passes": 1, "fps_warmup": 0},
        "render": {"sh_degree_interval": 50},
    }
    cfg, cfg_torch = tmp_path / "cuda.json", tmp_path / "cuda_torch.json"
    cfg.write_text(json.dumps({**settings, "speed": {"exchange": "gsplat"}}))
    cfg_torch.write_text(json.dumps(settings))  # the default exchange: torch
    two, torch_two, jsgs_two = tmp_path / "two", tmp_path / "torch", tmp_path / "jsgs"
    common = ["--preset", "paper", "--device", "cuda", "--gpus", "2"]
    steps = ["--iterations", "200", "--eval-at", "20,200"]
    _ok(_train(scene, two, *common, "--config", str(cfg), *steps))
    _ok(_train(scene, torch_two, *common, "--config", str(cfg_torch), *steps))
    jsgs_args = ["--config", str(cfg), "--iterations", "20", "--eval-at", "20", "--method", "jsgs"]
    _ok(_train(scene, jsgs_two, *common, *jsgs_args))
    m2 = json.loads((two / "metrics.json").read_text())
    c2 = json.loads((two / "config.json").read_text())
    assert (m2["world_size"], c2["derived"]["exchange"]) == (2, "gsplat")
    assert json.loads((torch_two / "config.json").read_text())["derived"]["exchange"] == "torch"
    assert json.loads((jsgs_two / "config.json").read_text())["derived"]["exchange"] == "torch"
    mt = json.loads((torch_two / "metrics.json").read_text())
    (early_g, psnr_g), (early_t, psnr_t) = ((m["evals"][0]["psnr"], m["evals"][1]["psnr"]) for m in (m2, mt))
    assert psnr_g - early_g > 1.0 and psnr_t - early_t > 1.0, (early_g, psnr_g, early_t, psnr_t)
    assert abs(psnr_g - psnr_t) < 0.2, (psnr_g, psnr_t)
