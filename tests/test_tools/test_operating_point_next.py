"""tools/campaigns/operating_point_next.sh on the CPU, with a stand-in for scripts/gpu_run.sh that fakes each
bench (no training): the lanes start each pinned bench once its carried data has come, take the queued jobs
in order where their estimates fit before the stop, and every call brings back one archive with each bench's
files; a job name the script does not know stops it with one line."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
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
    """A repository holding only the script, two carried folders (cup and fern; flower and mouse) and the
    environment that points the script's folders, scenes and stand-in into tmp_path."""
    repo = tmp_path / "repo"
    (repo / "tools" / "campaigns").mkdir(parents=True)
    shutil.copy(ROOT / SCRIPT, repo / SCRIPT)
    for carry, scenes in (("c1", ("cup", "fern")), ("c2", ("flower", "mouse"))):
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
    queue = "ac_cup b_fern b_mouse300 c_fern_s0"
    p1 = _phase(repo, env, "1", STOP_AT="600", EST_PCT="1", OVERHEAD="1", QUEUE=queue)
    assert p1.returncode == 0, p1.stderr
    time.sleep(0.5)
    # flower and mouse come with the second call: no lane starts them before
    assert not any("SCENES=flower" in c or "SCENES=mouse" in c for c in _calls(env).values())
    p2 = _phase(repo, env, "2", WAIT="60", QUEUE=queue)
    assert p2.returncode == 0, p2.stderr
    calls = _calls(env)
    pinned = [f"a_{s}_s{i}" for s in ("cup", "fern", "flower", "mouse") for i in (0, 1)]
    assert sorted(calls) == sorted([*pinned, *queue.split()])
    gpu = {"a_cup_s0": "0", "a_fern_s0": "0", "a_cup_s1": "1", "a_fern_s1": "1", "a_flower_s0": "2",
           "a_mouse_s0": "2", "a_flower_s1": "3", "a_mouse_s1": "3"}  # fmt: skip
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
    p1 = _phase(repo, env, "1", STOP_AT="300", OVERHEAD="10", LANES="0:", QUEUE="c_cup_s0 b_fern")
    assert p1.returncode == 0, p1.stderr
    p3 = _phase(repo, env, "3", WAIT="60")
    assert p3.returncode == 0, p3.stderr
    # the cup's uniform and descending runs need about 1,070 s; fern's one run about 200
    assert sorted(_calls(env)) == ["b_fern"]
    status = _archive(env, "3")["status.txt"].decode()
    assert "lanes done: 1 of 1" in status and "queue left: c_cup_s0 \n" in status


def test_an_unknown_job_stops_it_with_one_line(campaign: tuple[Path, dict[str, str]]) -> None:
    repo, env = campaign
    p = _phase(repo, env, "1", QUEUE="b_fern d_fern")
    assert p.returncode == 2
    assert p.stderr.strip().splitlines() == ["error: job d_fern: not one of a_*, ac_*, b_*, c_*"]
    assert not Path(env["SRC"]).exists()
