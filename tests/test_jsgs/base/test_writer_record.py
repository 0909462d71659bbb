"""The writer record (``jsgs/schemas/writer.schema.json``) held by the output lock and by the markers of
unfinished writes: written with its format and version, read back the same, the earlier record without them
read with the same meaning, and anything else left alone with one line (never removed, never taken over)."""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jsgs
from jsgs.base.errors import JsgsError
from jsgs.base.io import (
    LOCK_NAME,
    PART_MARKER,
    OutputLock,
    Writer,
    atomic_folder,
    atomic_path,
    clear_file_leftovers,
    clear_folder_leftovers,
    load_writer,
    writer_record,
)
from jsgs.base.schema import validate

DEAD = 2**22 + 12345  # above Linux's PID limit: no such process
HOST = socket.gethostname()
#: the record as jsgs wrote it before it had a format (a marker's; the lock's has no "for")
EARLIER = {"for": "out", "pid": DEAD, "host": HOST, "start": 1, "what": "jsgs render"}
CURRENT = {"format": "jsgs-writer", "format_version": 1, "jsgs_version": jsgs.__version__, **EARLIER}
INVALID = {
    "a later format version": json.dumps({**CURRENT, "format_version": 2}),
    "another format": json.dumps({**CURRENT, "format": "someone-else"}),
    "a format without its version": json.dumps({k: v for k, v in CURRENT.items() if k != "jsgs_version"}),
    "a version without a format": json.dumps({**EARLIER, "format_version": 1}),
    "an unknown field": json.dumps({**EARLIER, "note": "mine"}),
    "a PID as text": json.dumps({**EARLIER, "pid": str(DEAD)}),
    "a PID of 7.0": json.dumps({**EARLIER, "pid": 7.0}),
    "PID 0": json.dumps({**EARLIER, "pid": 0}),
    "a host that is no text": json.dumps({**EARLIER, "host": 5}),
    "a list": json.dumps([EARLIER]),
    "not JSON": '{"pid": ',
    "empty": "",
    "not UTF-8": b"\xff\xfe".decode("latin-1"),
}


def test_records_carry_their_format_and_read_back_the_same(tmp_path: Path) -> None:
    """The lock, a folder's marker and a file's marker: each a valid current record naming this process."""
    with OutputLock(tmp_path / "run", "jsgs train (into run)"):
        doc = json.loads((tmp_path / "run" / LOCK_NAME).read_text())
        who = load_writer(tmp_path / "run" / LOCK_NAME)
    assert isinstance(who, Writer) and who.doc == doc and "for" not in doc
    assert (who.pid, who.host, who.what, who.gone()) == (os.getpid(), HOST, "jsgs train (into run)", False)
    assert (doc["format"], doc["format_version"], doc["jsgs_version"]) == ("jsgs-writer", 1, jsgs.__version__)
    validate(doc, "writer", "lock")
    with atomic_folder(tmp_path / "frames", "jsgs render") as work:
        folder_marker = load_writer(work / PART_MARKER)
    with atomic_path(tmp_path / "out.mp4", "jsgs render") as tmp:
        file_marker = load_writer(tmp.with_name(tmp.name[: -len(".mp4")] + PART_MARKER))
    for who, target in ((folder_marker, "frames"), (file_marker, "out.mp4")):
        assert isinstance(who, Writer) and who.doc == writer_record("jsgs render", target), who
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "out.mp4"]  # markers gone, lock too


@pytest.mark.parametrize("record", [EARLIER, CURRENT], ids=["earlier", "current"])
def test_a_gone_writers_leftovers_and_lock_go_in_either_form(
    tmp_path: Path, record: dict[str, object]
) -> None:
    """A record without ``format`` means what the current one means: its killed writer's folder, file and
    lock are removed or taken over."""
    folder = tmp_path / ".out.aaaa1111.part"
    folder.mkdir()
    (folder / PART_MARKER).write_text(json.dumps(record))
    video = tmp_path / ".out.mp4.bbbb2222.part.mp4"
    video.write_bytes(b"half")
    marker = video.with_name(f".out.mp4.bbbb2222.part{PART_MARKER}")
    marker.write_text(json.dumps({**record, "for": "out.mp4"}))
    assert [s.split(",")[0] for s in clear_folder_leftovers(tmp_path / "out")] == [f"note: removed {folder}"]
    assert [s.split(",")[0] for s in clear_file_leftovers(tmp_path / "out.mp4")] == [f"note: removed {video}"]
    lock = {k: v for k, v in record.items() if k != "for"}
    (tmp_path / LOCK_NAME).write_text(json.dumps(lock))
    with OutputLock(tmp_path, "jsgs render"):
        assert load_writer(tmp_path / LOCK_NAME).pid == os.getpid()  # type: ignore[union-attr]
    assert sorted(tmp_path.iterdir()) == []


@pytest.mark.parametrize("text", INVALID.values(), ids=INVALID.keys())
def test_an_invalid_record_is_kept_with_one_line(tmp_path: Path, text: str) -> None:
    """A marker or lock that is no valid writer record is not provably ours: the folder, the file and its
    marker, and the lock stay as they are, with one line each naming them and the problem."""
    data = text.encode("latin-1")
    folder = tmp_path / ".out.aaaa1111.part"
    folder.mkdir()
    (folder / PART_MARKER).write_bytes(data)
    video = tmp_path / ".out.mp4.bbbb2222.part.mp4"
    video.write_bytes(b"half")
    video.with_name(f".out.mp4.bbbb2222.part{PART_MARKER}").write_bytes(data)
    (tmp_path / LOCK_NAME).write_bytes(data)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    lines = clear_folder_leftovers(tmp_path / "out") + clear_file_leftovers(tmp_path / "out.mp4")
    with pytest.raises(JsgsError, match="its output lock is not a lock of jsgs") as e:
        OutputLock(tmp_path, "jsgs render")
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
    assert [s.split(":")[:2] for s in lines] == [["warning", f" {folder}"], ["warning", f" {video}"]]
    assert all("its marker is not a writer record of jsgs (" in s for s in lines), lines
    assert all("\n" not in s for s in [*lines, str(e.value)])


ANY_JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=8), c, max_size=3),
    max_leaves=8,
)
FIELD = st.integers() | st.text(max_size=8) | st.none()
NEAR_RECORD = st.fixed_dictionaries({}, optional=dict.fromkeys(CURRENT, FIELD))


@settings(max_examples=150, deadline=None, derandomize=True, database=None)
@given(ANY_JSON | NEAR_RECORD)
def test_reading_never_raises(tmp_path_factory: pytest.TempPathFactory, doc: object) -> None:
    """Whatever JSON a marker holds, reading it gives a writer (usable) or a reason, never an exception."""
    path = tmp_path_factory.mktemp("m") / PART_MARKER
    path.write_text(json.dumps(doc))
    who = load_writer(path)
    if isinstance(who, Writer):
        validate(who.doc, "writer", "record")
        assert isinstance(who.gone(), bool) and who.where()
    else:
        assert isinstance(who, str) and who.startswith(PART_MARKER) and "\n" not in who
