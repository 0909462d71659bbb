"""``write_json_checked``: a report is written only when it is valid against its schema; an invalid one
raises one line naming the file and leaves what was there untouched (no new file, no leftover part)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from jsgs.base.errors import JsgsError
from jsgs.base.io import write_json_checked, writer_record


def test_a_valid_document_is_written_as_json(tmp_path: Path) -> None:
    doc = writer_record("testing")
    out = tmp_path / "record.json"
    write_json_checked(out, doc, "writer")
    assert json.loads(out.read_text()) == doc
    assert sorted(p.name for p in tmp_path.iterdir()) == ["record.json"]


def test_an_invalid_document_writes_nothing(tmp_path: Path) -> None:
    out = tmp_path / "record.json"
    out.write_text("kept\n")
    bad = {**writer_record("testing"), "pid": "not a number"}
    with pytest.raises(JsgsError) as e:
        write_json_checked(out, bad, "writer")
    line = str(e.value)
    assert "\n" not in line
    assert line.startswith(f"{out}: not a valid writer file: at pid:")
    assert out.read_text() == "kept\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["record.json"]
