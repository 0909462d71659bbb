"""Property tests over the readers of what enters the tools (``docs/robustness.md``): the manifest (down to
the trainer's scene: normalisation, scene scale), the run settings, and PLY models. Random JSON, random values
put anywhere in a valid document and random byte mutations give either a valid result or one JsgsError line
naming the file or setting: never another exception, never a non-finite result, never a hang (every
example's time is bounded by the deadline). The JPEG header parser has its own fuzzing
(``tests/test_jsgstools/dqt/test_dqt_fuzz.py``).

Deterministic (derandomized); ``JSGS_PROPERTY_EXAMPLES`` (default 50 per test) sets the size of a run.
"""

from __future__ import annotations

import functools
import json
import math
import os
import shutil
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from jsgs.base.errors import JsgsError

EXAMPLES = int(os.environ.get("JSGS_PROPERTY_EXAMPLES", "50"))
PROPERTY = settings(
    max_examples=EXAMPLES,
    deadline=timedelta(seconds=20),  # a hang fails the example; a busy CI machine does not
    derandomize=True,
    database=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

SCALARS = (
    st.none()
    | st.booleans()
    | st.integers()
    | st.integers(-(2**70), 2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.sampled_from([0, -1, 1e-300, 1e300, 1e308, 2**63, -(2**63) - 1, 65536, 0.5])
    | st.text(max_size=6)
)
JSON = st.recursive(
    SCALARS,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=12,
)


def _one_line(err: JsgsError, where: str) -> None:
    text = str(err)
    assert "\n" not in text and where in text and len(text) < 600, text


@functools.cache
def _manifest_paths(text: str) -> tuple[list[tuple[Any, ...]], list[tuple[Any, ...]]]:
    """(every place, every coordinate: camera translations and points) in the manifest ``text``."""
    doc = json.loads(text)
    paths = _paths(doc)
    geometry = [p for p in paths if _is_number(doc, p) and (p[:2] == ("points", "xyz") or p[2:3] == ("t",))]
    return paths, geometry


def _paths(doc: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every place in ``doc`` (the root excluded): keys of objects and indices of arrays, recursively."""
    out: list[tuple[Any, ...]] = []
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    for k, v in items:
        out.append((*prefix, k))
        out += _paths(v, (*prefix, k))
    return out


def _replace(doc: Any, path: tuple[Any, ...], value: Any, delete: bool) -> Any:
    doc = json.loads(json.dumps(doc))
    node = doc
    for k in path[:-1]:
        node = node[k]
    if delete and isinstance(node, dict):
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return doc


@st.composite
def byte_mutants(draw: st.DrawFn, data: bytes) -> bytes:
    """``data`` with 1-4 flipped, set, inserted or deleted bytes, or cut short."""
    out = bytearray(data)
    for _ in range(draw(st.integers(1, 4))):
        if not out:
            break
        i = draw(st.integers(0, len(out) - 1))
        kind = draw(st.sampled_from(["flip", "set", "insert", "delete", "cut"]))
        if kind == "flip":
            out[i] ^= 1 << draw(st.integers(0, 7))
        elif kind == "set":
            out[i] = draw(st.sampled_from(b'0.9e-[]{}",:NI \x00\xff'))
        elif kind == "insert":
            out[i:i] = draw(st.sampled_from([b"[", b"]", b"9" * 30, b"e999", b"NaN", b"-", b",", b"\x00"]))
        elif kind == "delete":
            del out[i : i + draw(st.integers(1, 8))]
        else:
            del out[i:]
    return bytes(out)


# ---------------------------------------------------------------------------------------------------------
# the manifest, read by the trainer as far as its scene (normalisation and scene scale included)


@pytest.fixture(scope="module")
def small_dataset(compressed_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """A copy of the compressed scene whose manifest keeps 4 views and 40 points (small documents: fast
    examples)."""
    root = tmp_path_factory.mktemp("properties") / "data"
    shutil.copytree(compressed_scene, root)
    doc = json.loads((root / "manifest.json").read_text())
    doc["views"] = doc["views"][:4]
    doc["points"] = {"count": 40, "xyz": doc["points"]["xyz"][:40], "rgb": doc["points"]["rgb"][:40]}
    return root, doc


def _read_scene(root: Path, text: str | bytes) -> None:
    """The property for one manifest text: the trainer's scene, finite, or one JsgsError line naming it."""
    from jsgs.train.config import TrainConfig
    from jsgs.train.data import load_training_scene

    path = root / "manifest.json"
    path.write_bytes(text.encode("utf-8", "surrogatepass") if isinstance(text, str) else text)
    try:
        scene = load_training_scene(path, TrainConfig.from_preset("paper"))
    except JsgsError as e:
        _one_line(e, str(path))
        event("refused")
        return
    event("read")
    assert np.isfinite(scene.points).all() and np.isfinite(scene.transform).all()
    assert math.isfinite(scene.scene_scale) and scene.scene_scale > 0
    assert all(np.isfinite(v.viewmat).all() and np.isfinite(v.K).all() for v in scene.views)


@PROPERTY
@given(data=st.data())
def test_manifest_with_any_value_anywhere(small_dataset: tuple[Path, dict], data: st.DataObject) -> None:
    root, base = small_dataset
    path = data.draw(st.sampled_from(_manifest_paths(json.dumps(base))[0]))
    doc = _replace(base, path, data.draw(JSON), delete=data.draw(st.booleans()))
    _read_scene(root, json.dumps(doc))


@PROPERTY
@given(data=st.data())
def test_manifest_numbers_scaled_anywhere(small_dataset: tuple[Path, dict], data: st.DataObject) -> None:
    """Coordinates made huge, tiny, zero or negative (degenerate geometry: far points, cameras together)."""
    root, base = small_dataset
    numeric = _manifest_paths(json.dumps(base))[1]
    doc = base
    for _ in range(data.draw(st.integers(1, 6))):
        path = data.draw(st.sampled_from(numeric))
        factor = data.draw(st.sampled_from([0.0, -1.0, 1e-12, 1e6, 1e12, 1e100, 1e300]))
        doc = _replace(doc, path, _get(doc, path) * factor, delete=False)
    if data.draw(st.booleans()):  # every camera at one place
        centre = np.array(data.draw(st.sampled_from([[0.0, 0.0, 0.0], [0.5, -1.0, 2.0]])))
        doc = json.loads(json.dumps(doc))
        for v in doc["views"]:
            v["t"] = (-np.asarray(v["R"]) @ centre).tolist()
    _read_scene(root, json.dumps(doc))


def _get(doc: Any, path: tuple[Any, ...]) -> Any:
    for k in path:
        doc = doc[k]
    return doc


def _is_number(doc: Any, path: tuple[Any, ...]) -> bool:
    v = _get(doc, path)
    return isinstance(v, (int, float)) and not isinstance(v, bool)


@PROPERTY
@given(data=st.data())
def test_manifest_byte_mutations(small_dataset: tuple[Path, dict], data: st.DataObject) -> None:
    root, base = small_dataset
    _read_scene(root, data.draw(byte_mutants(json.dumps(base).encode())))


@PROPERTY
@given(doc=JSON)
def test_manifest_any_json(small_dataset: tuple[Path, dict], doc: Any) -> None:
    _read_scene(small_dataset[0], json.dumps(doc))


# ---------------------------------------------------------------------------------------------------------
# settings files (--config) and what the command line gives the same reader


def _settings_paths() -> list[tuple[str, ...]]:
    import dataclasses

    from jsgs.train.config import TrainConfig

    out: list[tuple[str, ...]] = []
    for f in dataclasses.fields(TrainConfig):
        value = getattr(TrainConfig.from_preset("paper"), f.name)
        if dataclasses.is_dataclass(value):
            out += [(f.name, g.name) for g in dataclasses.fields(value)]
        else:
            out.append((f.name,))
    return out


SETTINGS_PATHS = _settings_paths()


def _read_settings(path: Path, text: str | bytes) -> None:
    from jsgs.train.config import load_config_file

    path.write_bytes(text.encode("utf-8", "surrogatepass") if isinstance(text, str) else text)
    try:
        cfg = load_config_file(path)
    except JsgsError as e:
        _one_line(e, str(path))
        event("refused")
        return
    event("read")
    cfg.check(str(path))
    from jsgs.train.config import to_dict

    json.dumps(to_dict(cfg), allow_nan=False)  # every number finite


@PROPERTY
@given(data=st.data())
def test_settings_with_any_value_for_any_key(tmp_path_factory: pytest.TempPathFactory,
                                             data: st.DataObject) -> None:  # fmt: skip
    doc: dict[str, Any] = {}
    for _ in range(data.draw(st.integers(1, 3))):
        keys = data.draw(st.sampled_from(SETTINGS_PATHS))
        value = data.draw(JSON | st.sampled_from([{"method": "jsgs"}, "jsgs", [3000, 7000]]))
        node = doc
        for k in keys[:-1]:
            node = node.setdefault(k, {})
        node[keys[-1]] = value
    if data.draw(st.booleans()):
        doc["method"] = "jsgs"
        doc["method_options"] = data.draw(st.dictionaries(st.sampled_from(
            ["lambda_obs", "tau_s", "jpeg_mode", "speed", "base_noise_ref", "tables"]), JSON, max_size=3))
    _read_settings(tmp_path_factory.getbasetemp() / "settings.json", json.dumps(doc))


@PROPERTY
@given(data=st.data())
def test_settings_any_json_and_byte_mutations(tmp_path_factory: pytest.TempPathFactory,
                                              data: st.DataObject) -> None:  # fmt: skip
    base = json.dumps({"iterations": 30000, "optim": {"means_lr": 0.00016}, "scene": {"global_scale": 1.0},
                       "seed": 7, "eval_at": [7000, 30000]}).encode()  # fmt: skip
    text = data.draw(st.one_of(JSON.map(json.dumps), byte_mutants(base)))
    _read_settings(tmp_path_factory.getbasetemp() / "settings.json", text)


# ---------------------------------------------------------------------------------------------------------
# PLY models (jsgs export / render / view read them with jsgs.base.ply.load_ply)


def _ply_bytes() -> bytes:
    from jsgs.base.ply import ply_header

    t = np.random.default_rng(0).normal(size=(3, 6 + 3 + 9 + 1 + 3 + 4)).astype("<f4")
    return ply_header(3, 3) + t.tobytes()


PLY = _ply_bytes()
HEADER_LINES = [b"property float x", b"property list uchar int x", b"element vertex 99999999999",
                b"element vertex 0", b"element face 2", b"format ascii 1.0", b"property double x",
                b"property uchar opacity", b"comment \xff\xfe", b"end_header", b""]  # fmt: skip


@st.composite
def ply_mutants(draw: st.DrawFn) -> bytes:
    data = PLY
    end = data.index(b"end_header\n")
    if draw(st.booleans()):  # a header line replaced, inserted or dropped
        lines = data[:end].split(b"\n")
        i = draw(st.integers(1, len(lines) - 1))
        kind = draw(st.sampled_from(["replace", "insert", "drop"]))
        if kind == "replace":
            lines[i] = draw(st.sampled_from(HEADER_LINES))
        elif kind == "insert":
            lines.insert(i, draw(st.sampled_from(HEADER_LINES)))
        else:
            del lines[i]
        data = b"\n".join(lines) + data[end:]
    if draw(st.booleans()):  # a value of the body set to something a model cannot hold
        body = bytearray(data[data.index(b"end_header\n") + 11 :])
        if len(body) >= 4:
            at = 4 * draw(st.integers(0, len(body) // 4 - 1))
            value = draw(st.sampled_from([math.nan, math.inf, -math.inf, 1e30, 0.0, -1e38]))
            body[at : at + 4] = np.float32(value).tobytes()
        data = data[: data.index(b"end_header\n") + 11] + bytes(body)
    return draw(byte_mutants(data)) if draw(st.booleans()) else data


@PROPERTY
@given(data=ply_mutants())
def test_ply_mutations(tmp_path_factory: pytest.TempPathFactory, data: bytes) -> None:
    from jsgs.base.ply import load_ply

    path = tmp_path_factory.getbasetemp() / "model.ply"
    path.write_bytes(data)
    try:
        arrays = load_ply(path)
    except JsgsError as e:
        _one_line(e, str(path))
        event("refused")
        return
    event("read")
    n = len(arrays["means"])
    assert n > 0 and all(np.isfinite(a).all() and len(a) == n for a in arrays.values())
    assert (np.abs(arrays["quats"].astype(np.float64)).sum(axis=1) > 0).all()  # float32 squares overflow
