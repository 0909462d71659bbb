"""Atomic file writing: a crash or Ctrl-C never leaves a half-written file under the final name."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(final: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path in the same folder as ``final``; rename it onto ``final`` only on success."""
    from jsgs.errors import JsgsError

    final = Path(final)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".part" + final.suffix, dir=final.parent)
    except OSError as e:
        raise JsgsError(f"{final}: cannot write ({e.strerror or e})") from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # mkstemp creates 0600 files; give the result the permissions a plain open() would have.
        os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, final)
    except OSError as e:
        # a full disk or a read-only file system shows up on the temporary file: name the file asked for
        raise JsgsError(f"{final}: cannot write ({e.strerror or e})") from None
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_bytes_atomic(final: str | os.PathLike[str], data: bytes) -> None:
    with atomic_path(final) as tmp:
        tmp.write_bytes(data)


def write_json_atomic(final: str | os.PathLike[str], doc: Any, indent: int | None = 1) -> None:
    write_bytes_atomic(final, (json.dumps(doc, indent=indent) + "\n").encode())


def write_with_atomic(final: str | os.PathLike[str], writer: Callable[[Path], None]) -> None:
    """Call ``writer(tmp_path)`` (e.g. ``img.save``) and move the result onto ``final``."""
    with atomic_path(final) as tmp:
        writer(tmp)


LOCK_NAME = ".jsgs.lock"


class OutputLock:
    """One writer per output folder: ``FOLDER/.jsgs.lock`` holds the writer's PID and what it is doing,
    created exclusively (``O_EXCL``) and removed by :meth:`release`. A second writer gets a one-line
    JsgsError naming the holder; a lock whose PID no longer runs on this machine (a killed writer) is taken
    over."""

    def __init__(self, folder: str | os.PathLike[str], what: str) -> None:
        from jsgs.errors import JsgsError

        self.path = Path(folder) / LOCK_NAME
        if self.path.parent.exists() and not self.path.parent.is_dir():
            raise JsgsError(f"{self.path.parent}: exists and is not a folder")
        # a folder made only to hold the lock goes again with it when the writer wrote nothing
        self.created = not self.path.parent.exists()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        record = json.dumps({"pid": os.getpid(), "what": what}) + "\n"
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                holder = _lock_holder(self.path)
                if holder is not None and holder[0] != os.getpid() and _alive(holder[0]):
                    raise JsgsError(
                        f"{self.path.parent}: in use by {holder[1]} (PID {holder[0]}); wait for it to end or "
                        f"stop it (a lock left by a killed writer is taken over: {self.path})"
                    ) from None
                self.path.unlink(missing_ok=True)  # stale: its writer is gone
                continue
            with os.fdopen(fd, "w") as f:
                f.write(record)
            return
        raise JsgsError(f"{self.path}: could not take the output lock (another writer keeps taking it)")

    def release(self) -> None:
        holder = _lock_holder(self.path)
        if holder is not None and holder[0] == os.getpid():
            self.path.unlink(missing_ok=True)
            if self.created:
                try:
                    self.path.parent.rmdir()  # only when empty: the writer failed before writing anything
                except OSError:
                    pass

    def __enter__(self) -> OutputLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _lock_holder(path: Path) -> tuple[int, str] | None:
    try:
        doc = json.loads(path.read_text())
        return int(doc["pid"]), str(doc.get("what", "another process"))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def die_with_parent() -> None:
    """In a child process (``preexec_fn``, a pool's ``initializer``): ask Linux to send it SIGTERM when its
    parent dies, however the parent died (SIGKILL included), so no worker outlives the command that started
    it. A no-op where ``prctl`` is not available."""
    import ctypes
    import signal
    import sys

    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
    except OSError:
        return
    pr_set_pdeathsig = 1
    libc.prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)
