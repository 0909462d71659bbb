"""Safe file writing and reading.

Writing: a crash or Ctrl-C never leaves a half-written file under the final name. Every file is first
written to a temporary file with an unpredictable name in the destination folder, created exclusively
(``mkstemp``: ``O_CREAT | O_EXCL``, so a link planted under any name is never followed), then renamed onto
the final name (``os.replace``: a link at the final name is replaced, never written through); a failure
removes the temporary file.

Reading a user's file: :func:`open_regular` refuses at once what is not a regular file (a FIFO would block
the open forever, a device would never end), with one line naming it.
"""

from __future__ import annotations

import json
import os
import re
import stat
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, BinaryIO


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(final: str | os.PathLike[str], what: str | None = None) -> Iterator[Path]:
    """Yield a temporary path ``.NAME.XXXXXXXX.part.SUFFIX`` in the same folder as ``final``; rename it onto
    ``final`` only on success. With ``what`` (for long writes that a kill may cut short, such as a video)
    the temporary file has a marker beside it, ``.NAME.XXXXXXXX.part`` + :data:`PART_MARKER`, naming its
    writer (:func:`writer_record`), made before the file and removed after it, so that what a killed writer
    left is recognised and removed by the next one (:func:`clear_file_leftovers`)."""
    from jsgs.base.errors import JsgsError

    final = Path(final)
    marker = None
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        if what is None:
            suffix = ".part" + final.suffix
            fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.", suffix=suffix, dir=final.parent)
        else:
            fd, tmp, marker = _marked_temp(final, what)
    except OSError as e:
        raise JsgsError(f"{final}: cannot write ({e.strerror or e})") from None
    try:
        # mkstemp creates 0600 files; give the result the permissions a plain open() would have.
        os.fchmod(fd, 0o666 & ~_umask())
    finally:
        os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, final)
    except OSError as e:
        # a full disk or a read-only file system shows up on the temporary file: name the file asked for
        raise JsgsError(f"{final}: cannot write ({e.strerror or e})") from None
    finally:
        if os.path.lexists(tmp_path):
            tmp_path.unlink()
        if marker is not None:
            marker.unlink(missing_ok=True)


def _marked_temp(final: Path, what: str) -> tuple[int, str, Path]:
    """The marker and the (open, empty) temporary file of :func:`atomic_path` with ``what``: the marker is
    made first (``mkstemp``) and holds the writer, then the file of the same name stem, also exclusively."""
    record = json.dumps(writer_record(what, final.name)) + "\n"
    for _ in range(100):
        fd, name = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".part" + PART_MARKER, dir=final.parent)
        marker = Path(name)
        try:
            with os.fdopen(fd, "w") as f:
                f.write(record)
            tmp = name[: -len(PART_MARKER)] + final.suffix
            flags = os.O_CREAT | os.O_EXCL | os.O_WRONLY | getattr(os, "O_CLOEXEC", 0)
            return os.open(tmp, flags, 0o600), tmp, marker
        except FileExistsError:  # an entry of that name that is not ours: take another name
            marker.unlink(missing_ok=True)
        except BaseException:
            marker.unlink(missing_ok=True)
            raise
    raise FileExistsError(f"no free temporary name beside {final.name}")


#: the marker inside a temporary folder of :func:`atomic_folder` (``.NAME.XXXXXXXX.part``, and the earlier
#: folder moved aside, ``.NAME.XXXXXXXX.old``), and beside a temporary file of :func:`atomic_path` with a
#: writer (``.NAME.XXXXXXXX.part`` + this name): the writer that made it (:func:`writer_record`, naming the
#: final name in ``for``), so that a leftover of a killed writer is known as ours
#: (:func:`clear_folder_leftovers`, :func:`clear_file_leftovers`)
PART_MARKER = ".jsgs-part.json"


@contextmanager
def atomic_folder(final: str | os.PathLike[str], what: str = "a jsgs command") -> Iterator[Path]:
    """Yield a new empty folder ``.NAME.XXXXXXXX.part`` beside ``final`` (same parent, so the renames stay on
    one file system); when the block succeeds it takes ``final``'s place: an existing ``final`` is first
    moved aside (``.NAME.XXXXXXXX.old``), put back if the rename fails, and removed only once the new folder
    is in place. When the block fails (an error, Ctrl-C) the temporary folder is removed and ``final`` is
    untouched. A link at ``final`` is replaced, never followed. The caller decides whether ``final`` may be
    replaced at all (only what the tool made). Both temporary folders hold :data:`PART_MARKER` naming their
    writer (``what``, its PID, host and start time) while they exist, so what a killed writer left is
    recognised and removed by the next writer (:func:`clear_folder_leftovers`); the marker leaves the new
    folder just before it is renamed onto ``final``."""
    import shutil

    from jsgs.base.errors import JsgsError

    final = Path(final)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".part", dir=final.parent))
    except OSError as e:
        raise JsgsError(f"{final}: cannot write ({e.strerror or e})") from None
    try:
        record = writer_record(what, final.name)
        write_json_atomic(work / PART_MARKER, record)
        os.chmod(work, 0o777 & ~_umask())  # mkdtemp makes 0700; give what mkdir would
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    try:
        yield work
        try:
            (work / PART_MARKER).unlink(missing_ok=True)
            _swap_in(work, final, record)
        except OSError as e:
            raise JsgsError(f"{final}: cannot replace it ({e.strerror or e})") from None
    finally:
        if os.path.lexists(work):
            shutil.rmtree(work, ignore_errors=True)


def _swap_in(work: Path, final: Path, record: dict[str, Any]) -> None:
    """Rename ``work`` onto ``final`` (see :func:`atomic_folder`); a folder moved aside holds ``record`` as
    its :data:`PART_MARKER` until it is gone."""
    if not os.path.lexists(final):
        os.rename(work, final)
        return
    folder = final.is_dir() and not final.is_symlink()
    if folder:  # a folder is renamed onto an empty folder, a file or link onto a file
        aside = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".old", dir=final.parent))
    else:
        fd, name = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".old", dir=final.parent)
        os.close(fd)
        aside = Path(name)
    try:
        os.replace(final, aside)
    except BaseException:
        aside.rmdir() if folder else aside.unlink()
        raise
    try:
        if folder:
            write_json_atomic(aside / PART_MARKER, record)
        os.rename(work, final)
    except BaseException:
        if folder:
            (aside / PART_MARKER).unlink(missing_ok=True)
        os.replace(aside, final)
        raise
    if folder:
        _remove_marked(aside)
    else:
        aside.unlink()


def _remove_marked(folder: Path) -> None:
    """Remove ``folder`` and what it holds, its :data:`PART_MARKER` last (a writer killed meanwhile leaves a
    folder that is still known as ours); links inside are removed, never followed."""
    import shutil

    for p in folder.iterdir():
        if p.name == PART_MARKER:
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
    (folder / PART_MARKER).unlink(missing_ok=True)
    folder.rmdir()


def clear_folder_leftovers(final: str | os.PathLike[str]) -> list[str]:
    """Deal with the temporary folders :func:`atomic_folder` left beside ``final`` (``.NAME.XXXXXXXX.part``
    and ``.NAME.XXXXXXXX.old``: a writer killed mid-write, SIGKILL or power loss) before writing ``final``
    again; returns one line for each, to print. Only a real folder holding our :data:`PART_MARKER` for
    ``final`` whose writer no longer runs (its PID is gone from this host, or belongs to a process that
    started at another time) is touched: a ``.part`` folder is removed, and so is an ``.old`` one when
    ``final`` exists (the swap had finished); an ``.old`` one without ``final`` (killed mid-swap) is put back
    as ``final``, so the earlier output is as it was. Anything else (no marker, a writer that still runs or
    runs on another host, a link) is left alone with a warning naming it."""
    final = Path(final)
    pattern = re.compile(rf"\.{re.escape(final.name)}\.[A-Za-z0-9_]+\.(part|old)")
    if not final.parent.is_dir():
        return []
    lines = []
    for p in sorted(final.parent.iterdir()):
        m = pattern.fullmatch(p.name)
        if m is None:
            continue
        marker = p / PART_MARKER
        read = load_writer(marker) if p.is_dir() and not p.is_symlink() else None
        who = _leftover_writer(p, final, marker, read, f"it holds no {PART_MARKER} of jsgs for it")
        lines.append(who if isinstance(who, str) else _clear_leftover(p, m[1], final, who))
    return lines


def _leftover_writer(
    shown: Path, final: Path, marker: Path, who: Writer | str | None, unmarked: str
) -> Writer | str:
    """The writer, no longer running, of the leftover ``shown`` beside ``final`` whose ``marker`` gave ``who``
    (:func:`load_writer`; None: not read), so it may be cleared; else the warning line saying why it is left
    alone: the marker is not a writer record of jsgs for ``final`` (``unmarked`` says so when there is no
    marker at all), or its writer still runs (or runs on another host)."""
    if not isinstance(who, Writer) or who.doc.get("for") != final.name:
        why = (
            f"its marker is not a writer record of jsgs ({who})"
            if isinstance(who, str) and os.path.lexists(marker)
            else unmarked
        )
        return (
            f"warning: {shown}: left beside {final.name} by an interrupted write, but {why}; left alone "
            "(remove it yourself once it is not needed)"
        )
    if not who.gone():
        return f"warning: {shown}: {who.what} ({who.where()}) is still writing it; left alone"
    return who


def _clear_leftover(p: Path, kind: str, final: Path, who: Writer) -> str:
    """Remove (or put back) one leftover of a writer that is gone (:func:`clear_folder_leftovers`)."""
    try:
        if kind == "old" and not os.path.lexists(final):
            (p / PART_MARKER).unlink()
            os.rename(p, final)
            return (
                f"note: {final}: put back from {p.name}, which {who.what} ({who.where()}, no longer running) "
                "had moved aside and not yet replaced"
            )
        _remove_marked(p)
    except OSError as e:
        return f"warning: {p}: could not remove it ({e.strerror or e}); left by {who.what} ({who.where()})"
    what = "unfinished output" if kind == "part" else "earlier output it was replacing"
    return f"note: removed {p}, the {what} of {who.what} ({who.where()}, no longer running)"


def clear_file_leftovers(final: str | os.PathLike[str]) -> list[str]:
    """Deal with the temporary files :func:`atomic_path` with a writer left beside ``final``
    (``.NAME.XXXXXXXX.part.SUFFIX`` and its marker ``.NAME.XXXXXXXX.part`` + :data:`PART_MARKER`: a writer
    killed mid-write) before writing ``final`` again; returns one line for each, to print. A temporary file
    is removed, its marker last, only when the marker names ``final`` and a writer that no longer runs on
    this host (as :func:`clear_folder_leftovers`) and the file is a regular file (not a link); a marker whose
    file is gone (killed just before or after the file's life) goes the same way. Anything else (no marker
    or an unreadable one, a writer that still runs or runs on another host, a link) is left alone with a
    warning naming it."""
    final = Path(final)
    if not final.parent.is_dir():
        return []
    ends = sorted({final.suffix, PART_MARKER}, key=len, reverse=True)  # a suffix "" matches last
    ending = "|".join(map(re.escape, ends))
    pattern = re.compile(rf"\.{re.escape(final.name)}\.([A-Za-z0-9_]+)\.part({ending})")
    stems = sorted({m[1] for p in final.parent.iterdir() if (m := pattern.fullmatch(p.name))})
    lines = []
    for stem in stems:
        base = final.parent / f".{final.name}.{stem}.part"
        tmp, marker = Path(f"{base}{final.suffix}"), Path(f"{base}{PART_MARKER}")
        has_tmp = os.path.lexists(tmp)
        shown = tmp if has_tmp else marker
        who = _leftover_writer(
            shown, final, marker, load_writer(marker), f"no marker of jsgs ({marker.name}) records its writer"
        )
        if isinstance(who, str):
            lines.append(who)
        elif has_tmp and (tmp.is_symlink() or not tmp.is_file()):
            lines.append(f"warning: {tmp}: is not a plain file, so {who.what} did not write it; left alone")
        else:
            try:
                tmp.unlink(missing_ok=True)
                marker.unlink()
            except OSError as e:
                lines.append(f"warning: {shown}: could not remove it ({e.strerror or e}); left by {who.what}")
                continue
            what = "the unfinished output" if has_tmp else "the marker"
            lines.append(f"note: removed {shown}, {what} of {who.what} ({who.where()}, no longer running)")
    return lines


def atomic_leftovers(folder: str | os.PathLike[str], final_name: str) -> list[Path]:
    """The temporary files :func:`atomic_path` left in ``folder`` for final names matching the regular
    expression ``final_name`` (a process killed mid-write leaves them; a writer that holds the folder's
    :class:`OutputLock` may remove them). Regular files only, never a link."""
    folder = Path(folder)
    pattern = re.compile(rf"\.(?:{final_name})\.[A-Za-z0-9_]+\.part(?:\.[A-Za-z0-9]+)?")
    if not folder.is_dir():
        return []
    found = (p for p in folder.iterdir() if pattern.fullmatch(p.name))
    return sorted(p for p in found if p.is_file() and not p.is_symlink())


def write_bytes_atomic(final: str | os.PathLike[str], data: bytes) -> None:
    with atomic_path(final) as tmp:
        tmp.write_bytes(data)


def write_json_atomic(final: str | os.PathLike[str], doc: Any, indent: int | None = 1) -> None:
    write_bytes_atomic(final, (json.dumps(doc, indent=indent) + "\n").encode())


def write_json_checked(final: str | os.PathLike[str], doc: Any, schema: str) -> None:
    """Check ``doc`` against ``jsgs/schemas/<schema>.schema.json`` (JsgsError, one line naming ``final``, and
    nothing written when it is not valid), then :func:`write_json_atomic` it to ``final``."""
    from jsgs.base.schema import validate

    validate(doc, schema, os.fspath(final))
    write_json_atomic(final, doc)


def write_with_atomic(final: str | os.PathLike[str], writer: Callable[[Path], None]) -> None:
    """Call ``writer(tmp_path)`` (e.g. ``img.save``) and move the result onto ``final``."""
    with atomic_path(final) as tmp:
        writer(tmp)


def open_log(path: str | os.PathLike[str]) -> BinaryIO:
    """A log file opened for writing from its start (a child process may write into it as it runs), created
    if absent; a link at ``path`` is refused (``O_NOFOLLOW``) rather than written through."""
    from jsgs.base.errors import JsgsError

    path = Path(path)
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags, 0o666)
    except OSError as e:
        if path.is_symlink():
            raise JsgsError(f"{path}: is a link; logs are written only to plain files") from None
        raise JsgsError(f"{path}: cannot write ({e.strerror or e})") from None
    return os.fdopen(fd, "wb")


_KINDS = (
    (stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
)  # fmt: skip


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def open_regular(path: str | os.PathLike[str], buffering: int = -1) -> BinaryIO:
    """``path`` opened for reading in binary mode, refused at once (JsgsError, one line) when it is not a
    regular file: the open does not wait for a FIFO's writer (``O_NONBLOCK``), and the check is made on the
    opened file (``fstat``), so nothing can be swapped in between. A missing or unreadable file raises the
    usual OSError (FileNotFoundError, PermissionError), which callers already turn into their own line."""
    from jsgs.base.errors import JsgsError

    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise JsgsError(f"{os.fspath(path)}: is {_kind(st.st_mode)}, not a regular file")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return os.fdopen(fd, "rb", buffering=buffering)


def read_regular_bytes(path: str | os.PathLike[str]) -> bytes:
    """The bytes of the regular file at ``path`` (see :func:`open_regular`)."""
    with open_regular(path) as f:
        return f.read()


def read_regular_text(path: str | os.PathLike[str], encoding: str = "utf-8") -> str:
    """The text of the regular file at ``path`` (see :func:`open_regular`); UnicodeDecodeError (a
    ValueError) when it is not ``encoding``."""
    return read_regular_bytes(path).decode(encoding)


def not_regular(path: str | os.PathLike[str]) -> str | None:
    """Why the entry at ``path`` cannot be read as a regular file, in words (``"is a FIFO (named pipe), not
    a regular file"``, ``"is a link to a missing file"``), found without opening it; None when it is a
    regular file or absent."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return "is a link to a missing file" if os.path.islink(path) else None
    except OSError as e:
        return f"cannot be read ({e.strerror or e})"
    return None if stat.S_ISREG(st.st_mode) else f"is {_kind(st.st_mode)}, not a regular file"


def refuse_non_regular(path: str | os.PathLike[str]) -> None:
    """JsgsError when ``path`` exists and is not a regular file (for readers that take a path and open it
    themselves, such as pycolmap); a missing file is left to the reader."""
    from jsgs.base.errors import JsgsError

    try:
        st = os.stat(path)
    except OSError:
        return
    if not stat.S_ISREG(st.st_mode):
        raise JsgsError(f"{os.fspath(path)}: is {_kind(st.st_mode)}, not a regular file")


def load_json_record(
    path: str | os.PathLike[str], schema: str, shown: str, link: str = "is a link"
) -> dict[str, Any] | str:
    """The small JSON record at ``path`` (a lock, a marker) when it is valid against
    ``jsgs/schemas/<schema>.schema.json``, else why it is not, in one line naming the file as ``shown``: a
    link (``link`` says so), missing, not a regular file (a FIFO is refused at once, never waited on),
    unreadable, empty (a writer killed between creating and filling it), not JSON, or not valid."""
    from jsgs.base.errors import JsgsError
    from jsgs.base.schema import validate

    if os.path.islink(path):
        return f"{shown}: {link}"
    if not os.path.lexists(path):
        return f"{shown}: is missing"
    if (why := not_regular(path)) is not None:
        return f"{shown}: {why}"
    try:
        text = read_regular_text(path)
        if not text.strip():
            return f"{shown}: is empty"
        doc = json.loads(text)
        validate(doc, schema, shown)
    except (ValueError, RecursionError):  # UnicodeDecodeError and json's errors are ValueErrors
        return f"{shown}: is not JSON"
    except OSError as e:
        return f"{shown}: cannot be read ({e.strerror or e})"
    except JsgsError as e:
        return str(e)
    return doc  # the schemas of these records take objects only


#: the ``format`` and ``format_version`` of a writer record (``jsgs/schemas/writer.schema.json``); a record
#: without ``format`` is the earlier form of the same record, read with the same meaning
WRITER_FORMAT = "jsgs-writer"
WRITER_VERSION = 1


def writer_record(what: str, target: str | None = None) -> dict[str, Any]:
    """Who writes: this process's PID, host name and start time (:func:`_start_time`), ``what`` it does and,
    in a marker, the final name ``target`` it writes (``for``), with the format and jsgs version; checked
    against ``jsgs/schemas/writer.schema.json``. The output lock and the markers of :data:`PART_MARKER` hold
    it, and :func:`load_writer` reads it back."""
    import socket

    import jsgs
    from jsgs.base.schema import validate

    doc: dict[str, Any] = {
        "format": WRITER_FORMAT,
        "format_version": WRITER_VERSION,
        "jsgs_version": jsgs.__version__,
    }
    if target is not None:
        doc["for"] = target
    doc.update(pid=os.getpid(), host=socket.gethostname(), start=_start_time(os.getpid()), what=what)
    validate(doc, "writer", "the writer record of this process")
    return doc


class Writer:
    """A valid :func:`writer_record` read back (:func:`load_writer`)."""

    def __init__(self, doc: dict[str, Any]) -> None:
        self.doc = doc
        self.pid: int = doc["pid"]
        self.what = " ".join(doc.get("what", "another process").split())  # one line
        start, host = doc.get("start"), doc.get("host")
        self.start = start if type(start) is int else None
        self.host: str | None = host  # None: recorded without it (this host)

    def elsewhere(self) -> bool:
        """Whether it runs (or ran) on another host, where its PID says nothing here."""
        import socket

        return self.host is not None and self.host != socket.gethostname()

    def gone(self) -> bool:
        """Whether it no longer runs: a PID of this host that is gone, or now belongs to another process."""
        return not self.elsewhere() and not _alive(self.pid, self.start)

    def where(self) -> str:
        return f"PID {self.pid} on host {self.host}" if self.elsewhere() else f"PID {self.pid}"


def load_writer(path: str | os.PathLike[str]) -> Writer | str:
    """The writer recorded in the lock or marker file at ``path``, or why there is none, in words naming the
    file (absent, a link or not a regular file, empty: a writer killed between creating and filling it, not
    JSON, or not valid against ``jsgs/schemas/writer.schema.json``). Such a file is not provably a jsgs
    writer's: callers leave it alone."""
    path = Path(path)
    doc = load_json_record(path, "writer", path.name)
    if isinstance(doc, str):
        return doc
    if type(doc["pid"]) is not int:  # the schema's integer takes 7.0
        return f"{path.name}: not a valid writer file: at pid: {doc['pid']!r} is not a whole number"
    return Writer(doc)


def read_writer(path: str | os.PathLike[str]) -> Writer | None:
    """The writer recorded at ``path`` (:func:`load_writer`), None when there is no valid one."""
    who = load_writer(path)
    return who if isinstance(who, Writer) else None


LOCK_NAME = ".jsgs.lock"


class OutputLock:
    """One writer per output folder: ``FOLDER/.jsgs.lock`` holds the writer (:func:`writer_record`: its PID,
    host, start time and what it is doing), created exclusively (``O_EXCL``) and removed by
    :meth:`release`. A second writer gets a one-line JsgsError naming the holder; a lock whose PID no longer
    runs on this machine (a killed writer) is taken over, and so is one whose PID now belongs to another
    process (the lock records its writer's start time where ``/proc`` gives it, so a PID reused after a
    crash does not keep the folder locked). A lock of another host is never taken over, nor one that is not a
    valid record (:func:`load_writer`: a JsgsError names it, and it is left in place)."""

    def __init__(self, folder: str | os.PathLike[str], what: str) -> None:
        from jsgs.base.errors import JsgsError

        self.path = Path(folder) / LOCK_NAME
        if self.path.parent.exists() and not self.path.parent.is_dir():
            raise JsgsError(f"{self.path.parent}: exists and is not a folder")
        # a folder made only to hold the lock goes again with it when the writer wrote nothing
        self.created = not self.path.parent.exists()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        record = json.dumps(writer_record(what)) + "\n"
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                w = load_writer(self.path)
                if isinstance(w, str):
                    if not os.path.lexists(self.path):
                        continue  # released meanwhile
                    raise JsgsError(
                        f"{self.path.parent}: its output lock is not a lock of jsgs ({w}), so it is left "
                        f"alone; remove {self.path} once no jsgs command writes into this folder"
                    ) from None
                if (w.elsewhere() or w.pid != os.getpid()) and not w.gone():
                    raise JsgsError(
                        f"{self.path.parent}: in use by {w.what} ({w.where()}); wait for it to end or "
                        f"stop it (a lock left by a killed writer is taken over: {self.path})"
                    ) from None
                self.path.unlink(missing_ok=True)  # stale: its writer is gone
                continue
            with os.fdopen(fd, "w") as f:
                f.write(record)
            return
        raise JsgsError(f"{self.path}: could not take the output lock (another writer keeps taking it)")

    def release(self) -> None:
        holder = read_writer(self.path)
        if holder is not None and holder.pid == os.getpid() and not holder.elsewhere():
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


def _start_time(pid: int) -> int | None:
    """When process ``pid`` started (clock ticks since boot, ``/proc/PID/stat`` field 22), or None where
    that cannot be read."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
        # the command name (field 2) may hold spaces and parentheses: count the fields after the last ')'
        return int(text.rpartition(")")[2].split()[19])
    except (OSError, ValueError, IndexError):
        return None


def _alive(pid: int, start: int | None = None) -> bool:
    """Whether ``pid`` runs, and is the process that started at ``start`` (when recorded and readable)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    now = _start_time(pid) if start is not None else None
    return now is None or now == start


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
