"""tools/campaigns/operating_point_next.sh on the CPU, with a stand-in for scripts/gpu_run.sh that fakes each
bench (no training): the lanes start each pinned bench once its carried data has come, take the queued jobs
in order where their estimates fit before the stop, and every call brings back one archive with each bench's
files; a job name the script does not know, a first carry without the LPIPS weights and a later call that
finds no lanes (a fresh machine) stop it with one line; a carry that did not come is said and skipped, and a
scene already there is kept. Slow: the same with real benches (40 steps on tiny
synthetic scenes), gathered into a report (PHASE=gather), a bench cut before its report included."""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tarfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = "tools/campaigns/operating_point_next.sh"
pytestmark = pytest.mark.skipif(
    any(shutil.which(t) is None for t in ("bash", "tar", "flock", "setsid", "timeout")),
    reason="needs bash, tar, flock, setsid and timeout",
)

# Logs the settings operating_point.sh would get, then writes what a finished bench leaves (one run).
STUB = """echo "GPU=$CUDA_VISIBLE_DEVICES PART=${PART:-} SCENES=${SCENES:-} SEEDS=${SEEDS:-} \\
SCHEDULES=${SCHEDULES:-} RULE_BUDGETS=${RULE_BUDGETS:-} JOBS=${JOBS:-} GSPLAT_STEPS=${GSPLAT_STEPS:-} \\
OUT_DIR=${OUT_DIR:-} :: $*" >> "$CALLS"
[ "$1" = true ] && exit 0
r=$OUT_DIR/runs/$SCENES/x/jsgs/mcmc-auto/s0
mkdir -p "$r" && echo '{"status": "complete"}' > "$r/metrics.json" && echo '{}' > "$r/config.json"
echo scene > "$OUT_DIR/results.csv"
sleep 0.2
"""


@pytest.fixture
def campaign(tmp_path: Path) -> Iterator[tuple[Path, dict[str, str]]]:
    """A repository holding only the script, two carried folders (cup and mouse; fern and flower) and the
    environment that points the script's folders, scenes and stand-in into tmp_path."""
    repo = tmp_path / "repo"
    (repo / "tools" / "campaigns").mkdir(parents=True)
    shutil.copy(ROOT / SCRIPT, repo / SCRIPT)
    for carry, scenes in (("c1", ("cup", "mouse")), ("c2", ("fern", "flower"))):
        for s in scenes:
            base = tmp_path / carry / "bench" / "data" / s / "clean_s0"
            base.mkdir(parents=True)
            (base / "manifest.json").write_text("{}")
    (tmp_path / "c1" / "alexnet_features.pth").write_text("weights")
    (tmp_path / "stub.sh").write_text(STUB)
    folders = {"SRC": "src", "DATA": "data", "LOGS": "logs", "BENCHES": "b", "GPU_RUN": "stub.sh",
               "CALLS": "calls.log", "CARRY1": "c1", "CARRY2": "c2", "OUT": "out"}  # fmt: skip
    env = {**os.environ, **{k: str(tmp_path / v) for k, v in folders.items()}}
    env.update(FLOWER="flower", FERN="fern", CUP="cup", MOUSE="mouse", POLL="0.1")
    (tmp_path / "out").mkdir()
    yield repo, env
    # the lanes run in their own sessions: end any that a failed test left
    pids = tmp_path / "logs" / "lane_pids"
    for pid in pids.read_text().split() if pids.exists() else []:
        try:
            os.killpg(int(pid), signal.SIGTERM)
        except (ProcessLookupError, PermissionError):
            pass


def _phase(repo: Path, env: dict[str, str], phase: str, **extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["bash", SCRIPT], cwd=repo, env={**env, "PHASE": phase, **extra}, capture_output=True, text=True,
        timeout=120,
    )  # fmt: skip


def _calls(env: dict[str, str]) -> dict[str, str]:
    """The bench calls by job (the last part of OUT_DIR): their settings."""
    calls = Path(env["CALLS"]).read_text().splitlines() if Path(env["CALLS"]).exists() else []
    out: dict[str, str] = {}
    for line in calls:
        m = re.search(r"OUT_DIR=\S*/(\w+) :: bash tools/campaigns/operating_point.sh$", line)
        if m:
            assert m.group(1) not in out, f"{m.group(1)} started twice"
            out[m.group(1)] = line
    return out


def _archive(env: dict[str, str], phase: str) -> dict[str, bytes]:
    with tarfile.open(Path(env["OUT"]) / f"opn_{phase}.tgz") as t:
        return {m.name.removeprefix("./"): t.extractfile(m).read() for m in t.getmembers() if m.isfile()}  # type: ignore[union-attr]


def test_lanes_run_every_pinned_and_queued_job_once(campaign: tuple[Path, dict[str, str]]) -> None:
    repo, env = campaign
    queue = "ac_cup b_fern b_mouse300 c_fern_s0 a_fern_s1"
    p1 = _phase(repo, env, "1", STOP_AT="600", EST_PCT="1", OVERHEAD="1", QUEUE=queue)
    assert p1.returncode == 0, p1.stderr
    time.sleep(0.5)
    # fern comes with the second call: no lane starts a job of it before
    assert not any("SCENES=fern" in c for c in _calls(env).values())
    p2 = _phase(repo, env, "2", WAIT="60", QUEUE=queue)
    assert p2.returncode == 0, p2.stderr
    calls = _calls(env)
    pinned = [f"a_{s}_s{i}" for s in ("cup", "mouse") for i in (0, 1)]
    assert sorted(calls) == sorted([*pinned, *queue.split()])
    gpu = {"a_cup_s0": "0", "a_cup_s1": "1", "a_mouse_s0": "2", "a_mouse_s1": "3"}
    for job, g in gpu.items():
        assert calls[job].startswith(f"GPU={g} PART=time SCENES={job.split('_')[1]} SEEDS={job[-1]} ")
        assert "GSPLAT_STEPS=1.5" in calls[job]
    assert "SCHEDULES=gaussian,clean " in calls["a_fern_s1"] and "JOBS=3" in calls["a_fern_s1"]
    assert "SCHEDULES=gaussian " in calls["a_cup_s1"] and "JOBS=2" in calls["a_cup_s1"]
    assert "PART=time SCENES=cup SEEDS=0,1 SCHEDULES=clean " in calls["ac_cup"]
    assert "PART=rule SCENES=mouse SEEDS=1 " in calls["b_mouse300"]
    assert "RULE_BUDGETS=300k " in calls["b_mouse300"] and "JOBS=1 " in calls["b_mouse300"]
    assert "PART=rule SCENES=fern SEEDS=1 " in calls["b_fern"] and "JOBS=1 " in calls["b_fern"]
    assert "SCHEDULES=uniform,descending " in calls["c_fern_s0"] and "JOBS=4 " in calls["c_fern_s0"]
    files = _archive(env, "2")
    assert "lanes done: 4 of 4" in files["status.txt"].decode()
    assert "queue left: \n" in files["status.txt"].decode()
    assert all(f"bench_{j}.tar" in files for j in calls)
    assert "lane 3 done" in files["lanes.log"].decode()


def test_a_queued_job_that_does_not_fit_stays_queued(campaign: tuple[Path, dict[str, str]]) -> None:
    repo, env = campaign
    p1 = _phase(repo, env, "1", STOP_AT="400", OVERHEAD="10", LANES="0:", QUEUE="c_cup_s0 b_mouse100")
    assert p1.returncode == 0, p1.stderr
    p3 = _phase(repo, env, "3", WAIT="60")
    assert p3.returncode == 0, p3.stderr
    # the cup's uniform and descending runs need about 1,070 s; the mouse's one run about 290
    assert sorted(_calls(env)) == ["b_mouse100"]
    status = _archive(env, "3")["status.txt"].decode()
    assert "lanes done: 1 of 1" in status and "queue left: c_cup_s0 \n" in status


def test_a_carry_that_did_not_come_is_said_and_a_scene_already_there_kept(
    campaign: tuple[Path, dict[str, str]],
) -> None:
    repo, env = campaign
    p1 = _phase(repo, env, "1", STOP_AT="300", LANES="0:", QUEUE="c_cup_s0")
    assert p1.returncode == 0, p1.stderr
    missing = str(Path(env["CARRY2"]).parent / "not_carried")
    p2 = _phase(repo, env, "2", WAIT="5", CARRY2=missing)
    assert p2.returncode == 0, p2.stderr
    assert f"carry {missing}: not on this machine (not carried): no data this call" in p2.stdout.splitlines()
    # the first carry again: its scenes are here already and stay as they came
    p2 = _phase(repo, env, "2", WAIT="5", CARRY2=env["CARRY1"])
    assert p2.returncode == 0, p2.stderr
    data = Path(env["DATA"]) / "bench" / "data"
    assert sorted(p.name for p in data.iterdir()) == ["cup", "mouse"]
    assert sorted(p.name for p in (data / "cup").iterdir()) == [".ready", "clean_s0"]


def test_an_unknown_job_stops_it_with_one_line(campaign: tuple[Path, dict[str, str]]) -> None:
    repo, env = campaign
    p = _phase(repo, env, "1", QUEUE="b_fern d_fern")
    assert p.returncode == 2
    assert p.stderr.strip().splitlines() == ["error: job d_fern: not one of a_*, ac_*, b_*, c_*"]
    assert not Path(env["SRC"]).exists()


def test_a_call_on_a_fresh_machine_or_without_weights_stops_with_one_line(
    campaign: tuple[Path, dict[str, str]],
) -> None:
    repo, env = campaign
    p = _phase(repo, env, "2", WAIT="1")
    assert p.returncode == 3
    assert p.stderr.strip().splitlines() == [
        f"error: no lanes on this machine ({env['LOGS']}/lanes_n): the machine of PHASE=1 went back (more "
        "than 30 s idle?) and this call got a fresh one; start again with PHASE=1"
    ]
    (Path(env["CARRY1"]) / "alexnet_features.pth").unlink()
    p = _phase(repo, env, "1")
    assert p.returncode == 2 and not Path(env["SRC"]).exists()
    assert (
        p.stderr.strip()
        == f"error: {env['CARRY1']}/alexnet_features.pth: no LPIPS weights in the first carry"
    )


def _cut(archive: Path, job: str) -> None:
    """``archive`` as a call would have sent it had it ended while ``job``'s bench was still training: its
    report gone, its gsplat run's metrics.json still running."""
    with tarfile.open(archive) as t:
        members = {m.name: t.extractfile(m).read() for m in t.getmembers() if m.isfile()}  # type: ignore[union-attr]
    with tarfile.open(fileobj=io.BytesIO(members[f"./bench_{job}.tar"])) as b:
        files = {m.name: b.extractfile(m).read() for m in b.getmembers() if m.isfile()}  # type: ignore[union-attr]
    files = {k: v for k, v in files.items() if k.startswith("runs/")}
    for k in [k for k in files if "/gsplat/" in k and k.endswith("metrics.json")]:
        doc = json.loads(files[k])
        files[k] = json.dumps({**doc, "status": "running"}).encode()
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as b:
        for k, v in files.items():
            info = tarfile.TarInfo(k)
            info.size = len(v)
            b.addfile(info, io.BytesIO(v))
    members[f"./bench_{job}.tar"] = buf.getvalue()
    with tarfile.open(archive, "w:gz") as t:
        for k, v in members.items():
            info = tarfile.TarInfo(k)
            info.size = len(v)
            t.addfile(info, io.BytesIO(v))


@pytest.mark.slow
@pytest.mark.needs_data
def test_a_tiny_campaign_trains_and_gathers_into_a_report(tmp_path: Path) -> None:
    """PHASE 1 and 3 with real benches (40 steps, two 48x36 synthetic scenes, one lane each and a queued fixed
    budget), then PHASE=gather on the last archive with one bench cut before its report: the folder has the
    equal-time table, the auto budget, and each run's settings with the rule and JSGS's gc_every."""
    from jsgs.base.schema import validate
    from jsgstools.compress import compress
    from jsgstools.synth import synth

    weights = ROOT.parent / "shared" / "lpips" / "alexnet_features.pth"
    if not weights.is_file():
        pytest.skip(f"needs {weights}")
    repo = tmp_path / "repo"
    (repo / "tools").mkdir(parents=True)
    for d in ("jsgs", "jsgstools", "tools/results"):
        (repo / d).symlink_to(ROOT / d)
    shutil.copytree(ROOT / "tools" / "campaigns", repo / "tools" / "campaigns")
    for i, s in enumerate(("cup", "fern")):
        synth(tmp_path / "scenes" / s, views=8, size=(48, 36), seed=i, point_density=0.3)
        base = tmp_path / "c1" / "bench" / "data" / s / "clean_s0"
        compress(tmp_path / "scenes" / s, base, "clean", seed=0, jobs=1)
        shutil.rmtree(base / "images"), shutil.rmtree(base / "sparse")
    shutil.copy(weights, tmp_path / "c1" / "alexnet_features.pth")
    (tmp_path / "c2").mkdir()
    py = tmp_path / "venv" / "bin" / "python3"
    py.parent.mkdir(parents=True)
    py.write_text(f'#!/bin/sh\nexec {sys.executable} "$@"\n')
    py.chmod(0o755)
    (tmp_path / "gpu_run.sh").write_text(
        f'export PATH={py.parent}:$PATH PYTHONPATH=$PWD OMP_NUM_THREADS=1 JSGS_LPIPS_DOWNLOAD=0\nexec "$@"\n'
    )
    folders = {"SRC": "src", "DATA": "data", "LOGS": "logs", "BENCHES": "b", "GPU_RUN": "gpu_run.sh",
               "CARRY1": "c1", "CARRY2": "c2", "SCENE_DIR": "scenes", "VENV": "venv"}  # fmt: skip
    env = {**os.environ, **{k: str(tmp_path / v) for k, v in folders.items()}, "POLL": "0.2"}
    env.update(CUP="cup", FERN="fern", ITERS="40", EVAL_AT="20,40", EST_PCT="1", OVERHEAD="5", STOP_AT="500")
    env.update(LANES="0:a_cup_s0 1:a_fern_s1", QUEUE="b_fern", PYTHONPATH=str(ROOT))
    for phase, wait in (("1", "0"), ("3", "400")):
        (tmp_path / f"out{phase}").mkdir()
        p = _phase(repo, {**env, "OUT": str(tmp_path / f"out{phase}")}, phase, WAIT=wait)
        assert p.returncode == 0, p.stdout + p.stderr
    files = _archive({"OUT": str(tmp_path / "out3")}, "3")
    status = files["status.txt"].decode()
    assert "lanes done: 2 of 2" in status and "a_cup_s0: 2 runs complete, 2 started" in status, status
    # each bench's test renders at its first and last evaluation, small (tools/results/thumbs.py)
    thumbs = sorted(k for k in files if k.startswith("thumbs/a_fern_s1/") and k.endswith(".jpg"))
    steps: dict[str, set[str]] = {}
    for k in thumbs:
        steps.setdefault("/".join(k.split("/")[2:7]), set()).add(k.split("/")[7])
    assert steps == {  # gsplat on the JPEGs trains 1.5 x 40 steps: its last evaluation is at 60
        "fern/gaussian/gsplat/mcmc-auto/s1": {"step_000020", "step_000060"},
        "fern/gaussian/jsgs/mcmc-auto/s1": {"step_000020", "step_000040"},
        "fern/clean/gsplat/mcmc-auto/s1": {"step_000020", "step_000040"},
    }, thumbs
    assert "a_fern_s1: 3 runs complete" in status and "b_fern: 1 runs complete" in status, status
    archive = tmp_path / "out3" / "opn_3.tgz"
    _cut(archive, "a_cup_s0")
    target = tmp_path / "auto30"
    p = _phase(repo, env, "gather", ARCHIVE=str(archive), GATHER=str(tmp_path / "g"), TARGET=str(target))
    assert p.returncode == 0, p.stdout + p.stderr
    assert "a_cup_s0: no results.csv (the calls ended before its report): collected from its runs" in p.stdout
    report = (target / "report.md").read_text()
    assert "## Equal training time" in report and "the rule's choice at 30 training pixels" in report
    assert (
        "| cup | gaussian | auto | jsgs | 0 | 40 |" in report
    )  # compared with the cut gsplat run's evaluations
    assert "| fern | gaussian | auto | jsgs | 1 | 40 |" in report
    assert "gc_every 4 in 3 (budgets 100,000, auto)" in report
    rows = (target / "results.csv").read_text().splitlines()
    assert rows[0].startswith("scene,schedule,method,seed,strategy,budget,step,")
    assert {r.split(",")[5] for r in rows[1:]} == {"auto", "100000"}
    configs = json.loads((target / "configs.json").read_text())
    validate(configs, "configs", "configs.json")  # real runs' settings, versions and auto budgets
    assert configs["cup/gaussian/jsgs/mcmc-auto/s0"]["settings"]["method_options"]["gc_every"] == 4
    assert configs["fern/clean/gsplat/mcmc-auto/s1"]["derived"]["budget"]["pixels_per_gaussian"] == 30
