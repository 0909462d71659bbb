"""The manifest reader (``jsgs.base.manifest``): it imports no dataset library, every bad manifest
is one clear error, and its point check bypasses the schema validator; the schema is the shared one.
Writing manifests (``jsgstools manifest``, ``compress``) is tested in
``tests/test_jsgstools/test_manifest.py``."""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from jsgs.base.errors import JsgsError
from jsgs.base.manifest import load_manifest, validate_document

ROOT = Path(__file__).resolve().parents[3]


def test_reader_imports_no_dataset_libraries(compressed_scene: Path) -> None:
    code = (
        "import sys, jsgs.base.manifest as m; m.load_manifest(sys.argv[1]); "
        "bad = [k for k in ('pycolmap', 'cv2', 'PIL') if k in sys.modules]; assert not bad, bad"
    )
    r = subprocess.run(
        [sys.executable, "-c", code, str(compressed_scene / "manifest.json")],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr


# ----------------------------------------------------------------------------------------------------
# Bad manifests on read


def _mutate(doc: dict[str, Any], how: str) -> Any:
    d = copy.deepcopy(doc)
    if how == "format":
        d["format"] = "something-else"
    elif how == "missing split":
        del d["views"][0]["split"]
    elif how == "extra key":
        d["views"][0]["colour"] = 1
    elif how == "nan pose":
        d["views"][1]["t"][0] = float("nan")
    elif how == "not a rotation":
        d["views"][1]["R"][0][0] = 2.0
    elif how == "reflection":
        d["views"][1]["R"] = (-np.asarray(d["views"][1]["R"])).tolist()
    elif how == "duplicate names":
        d["views"][1]["name"] = d["views"][0]["name"]
    elif how == "point not a number":
        d["points"]["xyz"][3][1] = "1.0"
    elif how == "point infinite":
        d["points"]["xyz"][3][1] = float("inf")
    elif how == "point short":
        d["points"]["xyz"][3] = [1.0, 2.0]
    elif how == "count mismatch":
        d["points"]["count"] += 1
    elif how == "rgb out of range":
        d["points"]["rgb"][0][2] = 256
    elif how == "table shape":
        d["views"][1]["jpeg"]["luma_table"] = d["views"][1]["jpeg"]["luma_table"][:7]
    elif how == "negative focal":
        d["views"][1]["camera"]["fx"] = -1.0
    elif how == "no views":
        d["views"] = []
    elif how == "missing image":
        d["views"][2]["image"] = d["views"][2]["image"].replace("view_002", "nope")
    elif how == "missing reference":
        d["views"][2]["reference"] = d["views"][2]["reference"].replace("view_002", "nope")
    elif how == "not an object":
        d = [1, 2]
    else:
        raise AssertionError(how)
    return d


BAD = [
    "format",
    "missing split",
    "extra key",
    "nan pose",
    "not a rotation",
    "reflection",
    "duplicate names",
    "point not a number",
    "point infinite",
    "point short",
    "count mismatch",
    "rgb out of range",
    "table shape",
    "negative focal",
    "no views",
    "missing image",
    "missing reference",
    "not an object",
]


@pytest.mark.parametrize("how", BAD)
def test_bad_manifest_is_one_clear_error(compressed_scene: Path, tmp_path: Path, how: str) -> None:
    doc = json.loads((compressed_scene / "manifest.json").read_text())
    for v in doc["views"]:  # absolute paths (accepted as they are), so the copy can live in tmp_path
        v["image"] = str(compressed_scene / v["image"])
        v["reference"] = str(compressed_scene / v["reference"])
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    assert len(load_manifest(path).views) == 12  # the unmutated copy is fine
    path.write_text(json.dumps(_mutate(doc, how)))
    with pytest.raises(JsgsError) as e:
        load_manifest(path)
    msg = str(e.value)
    assert msg.startswith(f"{path}: ") and "\n" not in msg, msg


def test_unreadable_manifests(tmp_path: Path) -> None:
    with pytest.raises(JsgsError, match="nope.json: manifest not found"):
        load_manifest(tmp_path / "nope.json")
    (tmp_path / "a.json").write_text("{not json")
    with pytest.raises(JsgsError, match=r"a.json: not JSON: .* line 1, column 2"):
        load_manifest(tmp_path / "a.json")
    (tmp_path / "b.json").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(JsgsError, match="b.json: cannot read the manifest"):
        load_manifest(tmp_path / "b.json")


def test_many_points_bypass_the_schema_validator(
    compressed_scene: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """50k points are checked by the vectorised point check, never element by element by jsonschema (which
    takes seconds for that many): the schema validator sees empty point lists, and a bad last point is still
    found."""
    import jsgs.base.schema

    doc = json.loads((compressed_scene / "manifest.json").read_text())
    rng = np.random.default_rng(0)
    doc["points"] = {
        "count": 50_000,
        "xyz": rng.normal(size=(50_000, 3)).tolist(),
        "rgb": rng.integers(0, 256, (50_000, 3)).tolist(),
    }
    seen: list[int] = []
    real = jsgs.base.schema.validate

    def spy(d: Any, name: str, where: str) -> None:
        seen.append(len(d["points"]["xyz"]))
        real(d, name, where)

    monkeypatch.setattr(jsgs.base.schema, "validate", spy)
    validate_document(doc, "big.json")
    assert seen == [0]
    doc["points"]["xyz"][-1][2] = float("nan")
    with pytest.raises(JsgsError, match="big.json"):
        validate_document(doc, "big.json")


def test_schema_is_the_shared_one() -> None:
    from jsgs.base.schema import load_schema

    schema = load_schema("manifest")
    assert schema["properties"]["format"] == {"const": "jsgs-manifest"}
    assert os.path.isfile(ROOT / "jsgs" / "schemas" / "compress_record.schema.json")
