"""The worker pool: each training run is a ``jsgs train`` subprocess (a crash or an out-of-memory stays in
its run), ``jobs_per_gpu`` of them at a time on each GPU (``CUDA_VISIBLE_DEVICES`` pins one GPU per
process), or ``jobs`` at a time on the CPU. Finished runs are skipped; a failed run is recorded with the tail
of its log and the others go on."""

from __future__ import annotations

import json
import os
import queue
import subprocess
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from jsgs.base.io import die_with_parent, open_log
from jsgs.bench import plan as plan_mod
from jsgs.bench.plan import Run

TAIL_CHARS = 4000


def run_state(run: Run) -> tuple[str, dict[str, Any] | None]:
    """``("complete", metrics)`` when RUN/metrics.json says complete at the requested final step with an
    evaluation there; ``("resumable", metrics)`` when it stopped, was interrupted or failed (an error such
    as a full disk; resuming continues from the last checkpoint and writes what was missing) with a
    checkpoint; else ``("todo", metrics or None)`` (also for a run without a folder yet: a budget not
    resolved)."""
    if not run.out:
        return "todo", None
    path = Path(run.out) / "metrics.json"
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return "todo", None
    evals = doc.get("evals") or []
    if (
        doc.get("status") == "complete"
        and doc.get("step") == run.iterations
        and doc.get("iterations") == run.iterations
        and evals
        and evals[-1].get("step") == run.iterations
        and [e.get("step") for e in evals] == run.eval_at
    ):
        return "complete", doc
    ckpts = Path(run.out) / "checkpoints"
    if (
        doc.get("status") in ("running", "stopped", "failed")
        and doc.get("iterations") == run.iterations
        and ckpts.is_dir()
        and any(ckpts.glob("*.pt"))
    ):
        return "resumable", doc
    return "todo", doc


def skipped_record(run: Run) -> dict[str, Any] | None:
    """The bench.json record of a run already complete at the requested step (None: it is not)."""
    if run_state(run)[0] != "complete":
        return None
    return {"id": run.id, "status": "skipped", "reason": "complete at the requested step"}


def detect_slots(device: str, jobs_per_gpu: int) -> list[str | None]:
    """One entry per concurrent worker: the GPU index it pins (``CUDA_VISIBLE_DEVICES``), or None (CPU)."""
    if device == "cuda":
        # A bench given CUDA_VISIBLE_DEVICES=1,2 must pin its workers to GPUs 1 and 2, not to 0 and 1.
        visible = os.environ.get("CUDA_VISIBLE_DEVICES")
        if visible is not None and visible.strip():
            gpus = [g.strip() for g in visible.split(",") if g.strip()]
        else:
            import torch

            gpus = [str(g) for g in range(torch.cuda.device_count())]
        return [g for g in gpus for _ in range(jobs_per_gpu)]
    return [None] * jobs_per_gpu


def like_runs(run: Run) -> str:
    """The runs whose wall times foretell ``run``'s: the same scene, ``--method`` and length (a gsplat run
    trained past its recipe, ``--gsplat-steps``, is not timed by the recipe-length ones)."""
    return f"{run.scene}/{run.train_method}/{run.iterations}"


def expected_seconds(run: Run, finished: dict[str, list[float]]) -> float | None:
    """The median wall time of the like runs (:func:`like_runs`) finished so far (None: none finished yet),
    used to start no run that the --time-limit would cut short."""
    times = sorted(finished.get(like_runs(run), []))
    return times[len(times) // 2] if times else None


def _tail(path: Path, n: int = TAIL_CHARS) -> str:
    try:
        data = path.read_bytes()
    except OSError:
        return ""
    return data[-n:].decode("utf-8", "replace")


def run_one(
    run: Run,
    gpu: str | None,
    device: str,
    config: str | None,
    env_extra: dict[str, str],
    deadline: float | None = None,
) -> dict[str, Any]:
    """Run (or resume) one training in a subprocess; returns its record for bench.json."""
    state, _ = run_state(run)
    resume = state == "resumable"
    argv = plan_mod.train_argv(run, device, config, resume)
    env = {**os.environ, **env_extra}
    if gpu is not None:
        env["CUDA_VISIBLE_DEVICES"] = gpu
    elif device == "cpu":
        env["CUDA_VISIBLE_DEVICES"] = ""
    log = Path(run.log)
    log.parent.mkdir(parents=True, exist_ok=True)
    Path(run.out).parent.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    with open_log(log) as f:
        f.write(("$ " + " ".join(argv) + "\n").encode())
        f.flush()
        timed_out = False
        try:
            # a training dies with the bench (SIGTERM: it stops after its step with a checkpoint)
            proc = subprocess.Popen(
                argv, stdout=f, stderr=subprocess.STDOUT, env=env, preexec_fn=die_with_parent
            )
            try:
                rc = proc.wait(timeout=None if deadline is None else max(1.0, deadline - time.time()))
            except subprocess.TimeoutExpired:  # --time-limit: stop it; it resumes from its last checkpoint
                timed_out = True
                proc.terminate()
                try:
                    rc = proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    rc = proc.wait()
        except OSError as e:  # could not start at all
            f.write(f"could not start: {e}\n".encode())
            rc = -1
    seconds = time.time() - t0
    state, doc = run_state(run)
    rec: dict[str, Any] = {
        "id": run.id, "gpu": gpu, "resumed": resume, "returncode": rc, "seconds": round(seconds, 3),
        "log": str(log),
    }  # fmt: skip
    if rc == 0 and state == "complete":
        rec["status"] = "complete"
    else:
        rec["status"] = "failed"
        why = f"exit code {rc}"
        if rc == 0:
            why = f"exit code 0 but metrics.json is not complete at step {run.iterations}"
        if timed_out:
            why = "stopped at the bench's --time-limit (rerun to resume it from its last checkpoint)"
        if doc is not None and doc.get("status") in ("diverged", "failed"):
            why = f"{doc['status']}: {doc.get('error')}"
        rec["error"] = why
        rec["stderr_tail"] = _tail(log)
    return rec


def run_pool(
    runs: list[Run],
    slots: list[str | None],
    device: str,
    config: str | None,
    env_extra: dict[str, str] | None = None,
    progress: bool = True,
    on_done: Callable[[dict[str, Any]], None] | None = None,
    deadline: float | None = None,
) -> dict[str, dict[str, Any]]:
    """Run every unfinished run of ``runs`` on the worker ``slots``; returns ``{run id: record}`` for all
    of them (``status`` complete / skipped / failed)."""
    from tqdm import tqdm

    records: dict[str, dict[str, Any]] = {}
    todo: list[Run] = []
    for r in runs:
        done = skipped_record(r)
        if done is not None:
            records[r.id] = done
        else:
            todo.append(r)
    # The longer JSGS runs go first so the short baselines fill the gaps at the end (and before a deadline).
    todo.sort(key=lambda r: r.train_method != "jsgs")
    finished: dict[str, list[float]] = {}
    if not slots:
        slots = [None]
    free: queue.Queue[str | None] = queue.Queue()
    for s in slots:
        free.put(s)
    lock = threading.Lock()
    bar = tqdm(
        total=len(runs), initial=len(runs) - len(todo), desc="bench", unit="run", disable=not progress,
        dynamic_ncols=True,
    )  # fmt: skip
    counts = {"failed": 0, "skipped": len(runs) - len(todo), "done": 0}

    def work(run: Run) -> None:
        slot = free.get()
        try:
            with lock:
                need = expected_seconds(run, finished)
            if deadline is not None and time.time() >= deadline:
                rec = {"id": run.id, "status": "failed", "error": "not started: --time-limit reached",
                       "stderr_tail": ""}  # fmt: skip
            elif deadline is not None and need is not None and time.time() + need > deadline:
                why = f"not started: like runs took {need:.0f} s, more than the --time-limit leaves"
                rec = {"id": run.id, "status": "failed", "stderr_tail": "", "error": why}
            else:
                rec = run_one(run, slot, device, config, env_extra or {}, deadline)
        except Exception as e:  # a bug in the harness must not stop the other runs either
            rec = {"id": run.id, "status": "failed", "error": f"harness error: {e!r}", "stderr_tail": ""}
        finally:
            free.put(slot)
        with lock:
            records[run.id] = rec
            if rec["status"] == "complete" and not rec.get("resumed"):
                finished.setdefault(like_runs(run), []).append(rec["seconds"])
            counts["failed" if rec["status"] == "failed" else "done"] += 1
            bar.set_postfix(counts, refresh=False)
            bar.update(1)
            if rec["status"] == "failed":
                bar.write(f"failed: {run.id}: {rec.get('error')} (log: {rec.get('log')})")
            if on_done is not None:
                on_done(rec)

    with ThreadPoolExecutor(max_workers=len(slots)) as ex:
        list(ex.map(work, todo))
    bar.close()
    return {r.id: records[r.id] for r in runs}
