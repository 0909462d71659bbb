"""``jsgstools manifest``: write the training manifest (jsgs/schemas/manifest.schema.json) of a scene.

Works for a scene made by ``compress`` (its ``compress.json`` supplies the split, schedule, seed and the rest
of the provenance) and for a user's own collection (JPEG or lossless images with their COLMAP cameras), where
the split is every ``test_every``-th view by sorted image name and distortion is recorded as found, not
removed.

Per view: the image path relative to the manifest's folder, the split, the camera scaled to the image file
(COLMAP pixel convention, distortion parameters as COLMAP orders them), world-to-camera R and t (OpenCV axes:
``x_cam = R @ x_world + t``), the JPEG state read from the file header by :mod:`jsgstools.dqt` with the
digest of that header (``header_sha256`` and its ``header_digest_scheme``; null for lossless images) and the
lossless reference ``SCENE/reference/<stem>.png`` when it exists. Per scene: points3D (xyz, RGB 0..255) and
provenance. The document is validated against the schema before it is written
(atomically).
"""

from __future__ import annotations

import json
import os
import shlex
from collections.abc import Callable
from pathlib import Path
from typing import Any

from jsgs import __version__
from jsgs.base.errors import JsgsError
from jsgs.base.io import write_bytes_atomic
from jsgs.base.limits import read_json
from jsgs.base.schema import validate as schema_validate

from .scene import JPEG_FORMATS, ColmapScene, ColmapView, image_stem, view_camera

RECORD = "compress.json"


def dumps(doc: Any, indent: int = 1) -> str:
    """JSON text with every list of plain values on one line (a point, a table row, a rotation row) and
    everything else indented: readable, and about a third of the size of fully indented JSON."""

    def enc(x: Any, level: int) -> str:
        pad, inner = " " * (indent * level), " " * (indent * (level + 1))
        if isinstance(x, dict) and x:
            items = [f"{inner}{json.dumps(str(k))}: {enc(v, level + 1)}" for k, v in x.items()]
            return "{\n" + ",\n".join(items) + "\n" + pad + "}"
        if isinstance(x, list) and x and any(isinstance(v, (dict, list)) for v in x):
            return "[\n" + ",\n".join(inner + enc(v, level + 1) for v in x) + "\n" + pad + "]"
        return json.dumps(x)

    return enc(doc, 0) + "\n"


def _rel(path: Path, base: Path) -> str:
    return Path(os.path.relpath(os.path.abspath(path), os.path.abspath(base))).as_posix()


def read_record(scene_dir: Path) -> dict[str, Any] | None:
    """``scene_dir/compress.json`` (validated), or None when the scene was not made by ``compress``."""

    path = scene_dir / RECORD
    if not path.is_file():
        return None
    doc = read_json(path, "a compress record")
    schema_validate(doc, "compress_record", str(path))
    return doc


def camera_doc(scene: ColmapScene, view: ColmapView) -> dict[str, Any]:
    """The manifest's camera object for ``view``: its camera scaled to the image file."""
    cam = view_camera(scene, view)
    fx, fy = cam.focal
    cx, cy = cam.principal_point
    dist = cam.distortion
    return {
        "model": cam.model,
        "width": cam.width,
        "height": cam.height,
        "fx": fx,
        "fy": fy,
        "cx": cx,
        "cy": cy,
        "distortion": None if cam.is_pinhole and not dist else {"model": cam.model, "params": list(dist)},
    }


def jpeg_state(view: ColmapView, analyze: bool = False) -> dict[str, Any] | None:
    """The manifest's ``jpeg`` object from the file header, or None for a lossless file; with ``analyze``,
    also what the pixels say about its compression history (``analysis``: :mod:`jsgstools.dqt.analysis`)."""
    if view.format not in JPEG_FORMATS:
        return None
    assert view.path is not None
    return jpeg_file_state(view.path, analyze)


def jpeg_file_state(path: str | Path, analyze: bool = False) -> dict[str, Any]:
    """The manifest's ``jpeg`` object of the JPEG file ``path`` (:func:`jpeg_state`), with the digest of its
    header (:mod:`jsgs.jpeg.header_digest`) by which the trainer tells a file changed since."""
    from jsgs.jpeg.header_digest import SCHEME, header_digest
    from jsgstools.dqt import read_header

    state = read_header(path).manifest_state()
    state["header_sha256"] = header_digest(path, SCHEME)
    state["header_digest_scheme"] = SCHEME
    if analyze:
        from jsgstools.dqt.analysis import analyze_file

        state["analysis"] = analyze_file(path).to_json()
    return state


def build_manifest(
    scene_dir: str | Path,
    out: str | Path,
    *,
    test_every: int | None = None,
    producer: dict[str, Any] | None = None,
    command: str | None = None,
    say: Callable[[str], None] | None = None,
    analyze: bool = False,
) -> dict[str, Any]:
    """The manifest document for ``scene_dir``, with paths relative to ``out``'s folder (nothing is written).

    ``test_every``: None = the compress record's value, or 8 for a scene without one; a value that contradicts
    the record is an error (the split of a compressed scene is fixed: its test views were not compressed).
    ``producer``: given by ``compress``; otherwise this tool's own."""
    from .validate import orientation_warning, require_valid, split_warning, world_warning

    scene_dir, out = Path(scene_dir), Path(out)
    record = read_record(scene_dir)
    # Any camera model is recorded with its parameters, so unsupported models do not block a manifest.
    report = require_valid(scene_dir, allow=("camera_model",))
    scene = report.scene
    assert scene is not None
    for w in (orientation_warning(scene), world_warning(scene)):
        if say is not None and w is not None:
            say(w)
    base = out.parent
    test_every, split = _split(scene_dir, scene, record, test_every)
    n_train = sum(s == "train" for s in split.values())
    fixed_by = None if record is None else str(scene_dir / RECORD)
    if say is not None and (w := split_warning(str(out), len(scene.views), n_train, test_every, fixed_by)):
        say(w)
    views = [_view_doc(scene, v, scene_dir, base, split[v.name], analyze) for v in scene.views]
    if record is not None:
        scene_info = _recorded_scene_info(record, test_every)
    else:
        ds = report.downscale
        scene_info = {
            "name": scene.name,
            "source": str(scene_dir),
            "schedule": None,
            "quality": None,
            "seed": None,
            "test_every": test_every,
            "subsampling": None,
            "downscale": None if ds in (None, 1.0) else ds,
            "undistorted": False,
        }
    if producer is None:
        producer = _own_producer(scene_dir, out, record, test_every, command)

    return {
        "format": "jsgs-manifest",
        "format_version": 1,
        "producer": producer,
        "scene": scene_info,
        "views": views,
        "points": {
            "count": int(len(scene.points_xyz)),
            "xyz": scene.points_xyz.tolist(),
            "rgb": scene.points_rgb.astype(int).tolist(),
        },
    }


def _split(
    scene_dir: Path, scene: ColmapScene, record: dict[str, Any] | None, test_every: int | None
) -> tuple[int, dict[str, str]]:
    """The test spacing and each view's split: the compress record's (JsgsError when ``test_every``
    contradicts it or a view is not in it), else every ``test_every``-th view by sorted name (8 when None)."""
    if record is not None:
        rec_every = int(record["settings"]["test_every"])
        if test_every is not None and test_every != rec_every:
            raise JsgsError(
                f"{scene_dir / RECORD}: the scene was compressed with --test-every {rec_every}; "
                f"its split cannot be changed to {test_every}"
            )
        split = {v["name"]: v["split"] for v in record["views"]}
        missing = sorted(v.name for v in scene.views if v.name not in split)
        if missing:
            raise JsgsError(f"{scene_dir / RECORD}: image {missing[0]!r} of the model is not in the record")
        return rec_every, split
    test_every = 8 if test_every is None else test_every
    if test_every < 0:
        raise JsgsError(f"--test-every {test_every}: must be 0 (no test views) or at least 1")
    split = {
        v.name: ("test" if test_every and i % test_every == 0 else "train") for i, v in enumerate(scene.views)
    }
    return test_every, split


def _view_doc(
    scene: ColmapScene, v: ColmapView, scene_dir: Path, base: Path, split: str, analyze: bool
) -> dict[str, Any]:
    """A view of the manifest, its paths relative to ``base`` (the manifest's folder)."""
    assert v.path is not None
    ref = scene_dir / "reference" / (image_stem(v.name) + ".png")
    return {
        "name": v.name,
        "image": _rel(v.path, base),
        "split": split,
        "camera": camera_doc(scene, v),
        "R": v.R.tolist(),
        "t": v.t.tolist(),
        "jpeg": jpeg_state(v, analyze),
        "reference": _rel(ref, base) if ref.is_file() else None,
    }


def _recorded_scene_info(record: dict[str, Any], test_every: int) -> dict[str, Any]:
    """The manifest's ``scene`` of a dataset made by compress, from its record."""
    st = record["settings"]
    return {
        "name": record["source"]["name"],
        "source": record["source"]["scene"],
        "schedule": st["schedule"],
        "quality": st["quality"],
        "seed": st["seed"],
        "test_every": test_every,
        "subsampling": st["subsampling"],
        "downscale": st["downscale"],
        "undistorted": st["undistorted"],
    }


def _own_producer(
    scene_dir: Path, out: Path, record: dict[str, Any] | None, test_every: int, command: str | None
) -> dict[str, Any]:
    """The manifest's ``producer`` when this tool makes it (with the compress record's settings, if any)."""
    cmd = command or (
        f"jsgstools manifest {shlex.quote(str(scene_dir))} --out {shlex.quote(str(out))} "
        f"--test-every {test_every}"
    )
    settings: dict[str, Any] = {
        "test_every": test_every,
        "split_rule": "the compress record's split"
        if record
        else "registered views sorted by image name; view i is test when i % test_every == 0",
    }
    if record is not None:
        settings["compress"] = {
            "command": record["producer"]["command"],
            **record["settings"],
            "per_view_quality": {v["name"]: v["quality"] for v in record["views"]},
        }
    return {
        "tool": "jsgstools manifest",
        "version": __version__,
        "command": cmd,
        "settings": settings,
    }


def write_manifest(doc: dict[str, Any], out: str | Path) -> None:
    """Validate ``doc`` (the schema and the checks of :func:`jsgs.base.manifest.validate_document`), then
    write it atomically."""
    from jsgs.base.manifest import validate_document

    validate_document(doc, str(out))
    write_bytes_atomic(out, dumps(doc).encode())


def _is_manifest(path: Path) -> bool:
    """Whether ``path`` holds a manifest this tool wrote (a JSON object with ``format`` jsgs-manifest)."""
    from jsgs.base.io import read_regular_bytes

    try:
        if path.stat().st_size > 512 * 2**20:
            return False
        doc = json.loads(read_regular_bytes(path))  # a FIFO is refused at once, never waited on
    except (OSError, ValueError, RecursionError, JsgsError):
        return False
    return isinstance(doc, dict) and doc.get("format") == "jsgs-manifest"


def manifest(
    scene_dir: str | Path,
    out: str | Path,
    test_every: int | None = None,
    force: bool = False,
    command: str | None = None,
    say: Callable[[str], None] | None = None,
    analyze: bool = False,
) -> dict[str, Any]:
    """Build and write the manifest of ``scene_dir`` to ``out``; refuses to replace a file unless
    ``force``."""
    out = Path(out)
    if out.is_dir():
        raise JsgsError(f"{out}: is a folder; give the manifest's file name (e.g. {out / 'manifest.json'})")
    if out.exists() and not force:
        raise JsgsError(f"{out}: exists (use --force to replace it)")
    if out.exists() and not _is_manifest(out):
        raise JsgsError(f"{out}: is not a jsgs manifest; --force replaces only a manifest (choose another)")
    doc = build_manifest(scene_dir, out, test_every=test_every, command=command, say=say, analyze=analyze)
    write_manifest(doc, out)
    return doc
