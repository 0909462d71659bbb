"""``jsgs train --gpus N`` / ``--processes N``: start the N processes of one run on this machine, as
``torchrun --standalone --nproc-per-node N`` would, and stop them all when one fails.

Each process runs ``python -m jsgs.cli train ...`` (the same command without the launch option) with
torchrun's environment variables (``RANK``, ``LOCAL_RANK``, ``WORLD_SIZE``, ``LOCAL_WORLD_SIZE``,
``MASTER_ADDR``, ``MASTER_PORT``); :mod:`jsgs.train.distributed` does the rest. Rank 0's standard output and
its notes and progress on standard error pass through; the other processes' output is kept in memory and
shown only when one of them is the process that failed. When a process ends with an error, the others are
given :data:`GRACE_S` seconds to notice (their next collective fails) and are then killed; the launcher
prints exactly one ``error:`` line: the first failing process's own message (not the "another process
stopped" of the ones that followed it) and exits non-zero.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque

from jsgs.base.errors import JsgsError

#: the first words of the message of a process that stopped because another one did
#: (:class:`jsgs.train.distributed.PeerStopped`): the launcher shows the other process's message instead
PEER_PREFIX = "another process of the run stopped"
GRACE_S = 10.0
_KEEP_LINES = 200


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class _Rank:
    def __init__(self, rank: int, proc: subprocess.Popen[str], forward: bool) -> None:
        self.rank = rank
        self.proc = proc
        self.lines: deque[str] = deque(maxlen=_KEEP_LINES)
        self.errors: list[str] = []
        self.forward = forward
        self.ended_at: float | None = None
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            line = line.rstrip("\n")
            if line.startswith("error:"):
                self.errors.append(line)
                continue
            self.lines.append(line)
            if self.forward:
                print(line, file=sys.stderr, flush=True)

    def message(self) -> str | None:
        """This process's one-line error without ``error:``, or the error its last lines tell
        (:func:`crash_line`)."""
        self.thread.join(timeout=5.0)
        if self.errors:
            return self.errors[-1].removeprefix("error:").strip()
        return crash_line(list(self.lines))


#: lines of a crash report that name no error: C++ stack frames and CUDA's advice
_NOISE = re.compile(
    r"^(frame #\d+:|Exception raised from |CUDA kernel errors might be |For debugging consider |"
    r"Compile with `TORCH_USE_CUDA_DSA`|Search for `cudaErrorIllegalAddress`|\[rank\d+\]:\[W)"
)
#: a Python exception's last line ("RuntimeError: ...", "torch.OutOfMemoryError: ...")
_PY_ERROR = re.compile(r"^([A-Za-z_][\w.]*(Error|Exception|Interrupt|Exit))(: |$)")


def crash_line(lines: list[str]) -> str | None:
    """The error a process's last output lines tell: the message of an uncaught C++ exception
    (``what():  ...``), else a Python traceback's last exception line, else the last line that is not a
    C++ stack frame or CUDA's debugging advice; None when it wrote nothing."""
    text = [ln.strip() for ln in lines if ln.strip()]
    whats = [ln.split("what():", 1)[1].strip() for ln in text if "what():" in ln]
    if whats and whats[-1]:
        return whats[-1]
    errors = [ln for ln in text if _PY_ERROR.match(ln)]
    if errors:
        return errors[-1]
    kept = [ln for ln in text if not _NOISE.match(ln)]
    if kept:
        return kept[-1]
    return text[-1] if text else None


def _pick_error(failed: list[_Rank]) -> str:
    """The message to show: the earliest-ending process whose message is its own (not a peer's stop)."""
    failed = sorted(failed, key=lambda r: (r.ended_at or 0.0, r.rank))
    own = [(r, m) for r in failed if (m := r.message()) is not None and not m.startswith(PEER_PREFIX)]
    if own:
        r, m = own[0]
        return m if r.rank == 0 else f"rank {r.rank}: {m}"
    r = failed[0]
    m = r.message()
    return m if m else f"rank {r.rank} of the run exited with status {r.proc.returncode}"


def launch(args: list[str], processes: int, gpus: bool) -> int:
    """Run ``jsgs train ARGS`` on ``processes`` processes (one GPU each with ``gpus``); returns the exit
    status to end with (0, or that of the failed run after its one error line)."""
    if processes < 1:
        raise JsgsError(f"--{'gpus' if gpus else 'processes'}: expected at least 1 (got {processes})")
    if os.environ.get("WORLD_SIZE") not in (None, "", "1"):
        raise JsgsError(
            "--gpus/--processes start the processes themselves; under torchrun (WORLD_SIZE is set) leave the "
            "option out"
        )
    if gpus:
        import torch

        have = torch.cuda.device_count()
        if have < processes:
            raise JsgsError(f"--gpus {processes}: this machine has {have} GPU(s)")
    port = free_port()
    ranks: list[_Rank] = []
    base = {k: v for k, v in os.environ.items() if k not in ("RANK", "LOCAL_RANK", "WORLD_SIZE")}
    # as torchrun: the machine's cores shared between the processes rather than each taking all of them
    base.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // processes)))
    for rank in range(processes):
        env = {
            **base,
            "RANK": str(rank),
            "LOCAL_RANK": str(rank),
            "WORLD_SIZE": str(processes),
            "LOCAL_WORLD_SIZE": str(processes),
            "MASTER_ADDR": "127.0.0.1",
            "MASTER_PORT": str(port),
        }
        proc = subprocess.Popen(
            [sys.executable, "-m", "jsgs.cli", "train", *args],
            env=env,
            stdout=None if rank == 0 else subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            bufsize=1,
        )
        ranks.append(_Rank(rank, proc, forward=rank == 0))
    return _supervise(ranks)


def _supervise(ranks: list[_Rank]) -> int:
    first_failure: float | None = None
    killed = False
    try:
        while True:
            now = time.monotonic()
            for r in ranks:
                if r.ended_at is None and r.proc.poll() is not None:
                    r.ended_at = now
                    if r.proc.returncode != 0 and first_failure is None:
                        first_failure = now
            running = [r for r in ranks if r.ended_at is None]
            if not running:
                break
            if first_failure is not None and now - first_failure > GRACE_S and not killed:
                for r in running:
                    r.proc.kill()
                killed = True
            time.sleep(0.05)
    except KeyboardInterrupt:
        # the terminal's Ctrl-C reached every process: each stops after its step with a checkpoint (rank 0
        # writes it); wait for them, then report as they do
        for r in ranks:
            try:
                r.proc.wait()
            except KeyboardInterrupt:
                r.proc.send_signal(signal.SIGKILL)
    failed = [r for r in ranks if r.proc.returncode != 0]
    for r in ranks:
        r.thread.join(timeout=5.0)
    if not failed:
        return 0
    print(f"error: {_pick_error(failed)}", file=sys.stderr, flush=True)
    code = ranks[0].proc.returncode or failed[0].proc.returncode
    return code if code > 0 else 1


def launch_command(command: str, gpus: int | None, processes: int | None, device: str | None) -> int:
    """``jsgs train ... --gpus N`` (or ``--processes N``) as typed (``command``, canonical form): the same
    command without the option on N processes (:func:`launch`); one process runs in this one."""
    import shlex

    if gpus is not None and processes is not None:
        raise JsgsError("--gpus and --processes exclude each other")
    n = gpus if gpus is not None else processes
    assert n is not None
    name = "--gpus" if gpus is not None else "--processes"
    if n < 1:
        raise JsgsError(f"{name}: expected at least 1 (got {n})")
    if gpus is not None and device == "cpu":
        raise JsgsError("--gpus trains on GPUs; with --device cpu use --processes")
    words = shlex.split(command)[2:]  # without "jsgs train"
    args: list[str] = []
    skip = False
    for w in words:
        if skip:
            skip = False
            continue
        if w in ("--gpus", "--processes"):
            skip = True
            continue
        args.append(w)
    if gpus is not None and device is None:
        args += ["--device", "cuda"]
    return launch(args, n, gpus=gpus is not None)
