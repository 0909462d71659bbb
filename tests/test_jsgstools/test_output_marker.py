"""The marker `OUT/.jsgstools.json` of the jsgstools output folders: written in its versioned form and valid
against jsgs/schemas/output_marker.schema.json, the earlier form (no `format`) read with the same meaning, and
a marker that does not validate never lets `--force` touch the folder."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

import pytest
from click.testing import CliRunner

import jsgs
from jsgs.base.errors import JsgsError
from jsgs.base.schema import validate
from jsgstools.cli import main as tools_main
from jsgstools.scene import MARKER, MARKER_FORMAT, MARKER_VERSION, load_marker, marker_record, read_marker
from jsgstools.synth import synth

EARLIER = {"tool": "synth", "jsgstools_version": "0.1.0", "created": "2026-01-02T03:04:05+00:00"}


def _synth(out: Path, force: bool = False) -> None:
    synth(out, views=2, size=(16, 12), force=force)


def _tree(root: Path) -> dict[str, bytes | str]:
    """Every entry under ``root`` with its bytes (a file) or what it is (anything else)."""
    tree: dict[str, bytes | str] = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        if p.is_symlink():
            tree[rel] = "link -> " + os.readlink(p)
        elif p.is_file():
            tree[rel] = p.read_bytes()
        else:
            tree[rel] = "folder" if p.is_dir() else "other"
    return tree


def test_marker_round_trip(tmp_path: Path) -> None:
    out = tmp_path / "out"
    _synth(out)
    doc = json.loads((out / MARKER).read_text())
    validate(doc, "output_marker", "test")  # also checked by the writer; the file on disk is what counts
    assert doc["format"] == MARKER_FORMAT == "jsgstools-output-marker"
    assert doc["format_version"] == MARKER_VERSION == 1
    assert doc["tool"] == "synth" and doc["jsgstools_version"] == jsgs.__version__
    assert load_marker(out) == doc and read_marker(out) == "synth"
    # the same tool's --force takes its own folder back
    (out / "images" / "stale.png").write_bytes(b"old")
    _synth(out, force=True)
    assert not (out / "images" / "stale.png").exists()
    assert load_marker(out)["format"] == MARKER_FORMAT  # type: ignore[index]


def test_marker_record_is_checked_when_written() -> None:
    assert marker_record("compress")["tool"] == "compress"
    with pytest.raises(JsgsError, match="not a valid output_marker file: at tool"):
        marker_record("Not A Tool")


def test_earlier_marker_without_format_means_the_same(tmp_path: Path) -> None:
    out = tmp_path / "out"
    _synth(out)
    (out / MARKER).write_text(json.dumps(EARLIER))
    assert load_marker(out) == EARLIER and read_marker(out) == "synth"
    _synth(out, force=True)  # accepted as synth's folder, and rewritten in the present form
    assert load_marker(out)["format"] == MARKER_FORMAT  # type: ignore[index]
    # an earlier marker of another tool is that tool's folder, as before
    (out / MARKER).write_text(json.dumps({**EARLIER, "tool": "compress"}))
    before = _tree(out)
    with pytest.raises(JsgsError, match="made by jsgstools compress"):
        _synth(out, force=True)
    assert _tree(out) == before


def _write(text: str) -> Callable[[Path], None]:
    return lambda p: p.write_text(text)


BAD_MARKERS: dict[str, tuple[Callable[[Path], None], str]] = {
    "empty": (_write(""), "is empty"),
    "not JSON": (_write('{"tool": "synth"'), "is not JSON"),
    "not an object": (_write('["synth"]'), "not a valid output_marker file"),
    "no tool": (_write(json.dumps({k: v for k, v in EARLIER.items() if k != "tool"})), "'tool' is a"),
    "a tool that is no name": (_write(json.dumps({**EARLIER, "tool": 7})), "at tool"),
    "a later version": (
        _write(json.dumps({"format": MARKER_FORMAT, "format_version": 2, **EARLIER})),
        "at format_version",
    ),
    "another format": (_write(json.dumps({"format": "x", "format_version": 1, **EARLIER})), "at format"),
    "format without version": (_write(json.dumps({"format": MARKER_FORMAT, **EARLIER})), "format_version"),
    "an unknown key": (_write(json.dumps({**EARLIER, "owner": "me"})), "owner"),
    "a folder": (lambda p: p.mkdir(), "is a folder, not a regular file"),
    "a link": (lambda p: p.symlink_to(p.parent / "images"), "is a link"),
}


@pytest.mark.parametrize("case", BAD_MARKERS)
def test_invalid_marker_is_refused_and_nothing_is_touched(tmp_path: Path, case: str) -> None:
    make, why = BAD_MARKERS[case]
    out = tmp_path / "out"
    _synth(out)
    (out / MARKER).unlink()
    make(out / MARKER)
    reason = load_marker(out)
    assert isinstance(reason, str) and reason.startswith(f"{out / MARKER}: ") and why in reason
    assert read_marker(out) is None
    before = _tree(out)
    with pytest.raises(JsgsError) as e:
        _synth(out, force=True)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{out / MARKER}: ") and why in msg
    assert "not provably a marker of jsgstools" in msg and "choose an empty or new folder" in msg
    assert _tree(out) == before


def test_invalid_marker_alone_is_not_overwritten(tmp_path: Path) -> None:
    """A folder holding only a marker counts as empty, but an invalid marker is not replaced either."""
    out = tmp_path / "out"
    out.mkdir()
    (out / MARKER).write_text("someone else's notes")
    with pytest.raises(JsgsError, match="is not JSON; not provably"):
        _synth(out)
    assert _tree(out) == {MARKER: b"someone else's notes"}


def test_invalid_marker_on_the_command_line(tmp_path: Path) -> None:
    out = tmp_path / "out"
    _synth(out)
    (out / MARKER).write_text(json.dumps({"format": MARKER_FORMAT, "format_version": 2, **EARLIER}))
    before = _tree(out)
    r = CliRunner().invoke(tools_main, ["synth", str(out), "--views", "2", "--size", "16x12", "--force"])
    assert r.exit_code != 0 and "Traceback" not in r.output
    lines = [line for line in r.output.splitlines() if line.strip()]
    assert len(lines) == 1 and str(out / MARKER) in lines[0] and "not provably" in lines[0], r.output
    assert _tree(out) == before
