"""``derive``: a mixed-quality JPEG dataset made from a *clean* dataset with Pillow only (no pycolmap/OpenCV).

A dataset made by ``jsgstools compress SCENE --out BASE --schedule clean`` holds, per view, the lossless
(undistorted) reference ``BASE/reference/<stem>.png`` and, in ``BASE/manifest.json``, the PINHOLE cameras,
poses and points3D that every other schedule of the same scene shares. :func:`derive` encodes the train views
of another schedule from those references exactly as ``compress`` would (same split, same counts, same seeded
assignment — :func:`jsgstools.compress.plan` — and the same encoder call,
:func:`jsgstools.compress.observed_jpeg`), so its JPEG files are byte-identical to ``compress``'s. Only
``OUT/images/<stem>.jpg`` and ``OUT/manifest.json`` are written: test views (and the train views under
``clean``) and every ``reference`` point at the base's reference PNGs by relative path, so one base per scene
serves every schedule and seed.

This module imports neither pycolmap nor OpenCV (``jsgstools.compress`` and ``jsgstools.manifest_writer``
import them only inside the functions that need them), so it runs on a machine with torch and Pillow alone.
"""

from __future__ import annotations

import json
import os
import shlex
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from jsgs import __version__
from jsgs.base.errors import JsgsError
from jsgs.base.io import write_bytes_atomic
from jsgs.base.limits import parse_json

from .compress import (
    SUBSAMPLING,
    CompressionPlan,
    check_recompress,
    load_rgb,
    observed_jpeg,
    plan,
    schedule_settings,
)
from .scene import image_stem, prepare_output_dir, removes_partial_output

#: What ``derive`` writes into OUT (and removes first with ``force``).
OWNED = ("images", "manifest.json")


def _rel(path: Path, base: Path) -> str:
    return Path(os.path.relpath(os.path.abspath(path), os.path.abspath(base))).as_posix()


def read_base(base_manifest: str | Path) -> tuple[dict[str, Any], dict[str, str]]:
    """The base manifest (validated; a clean, pinhole dataset whose every view has its reference file) and
    view name -> source image name (from ``compress.json`` beside it when present, else the view name)."""
    from jsgs.base.manifest import validate_document

    path = Path(base_manifest)
    if path.is_dir():
        path = path / "manifest.json"
    from jsgs.base.io import read_regular_text

    try:
        text = read_regular_text(path)
    except OSError as e:
        raise JsgsError(f"{path}: cannot read the base manifest ({e.strerror or e})") from None
    doc = parse_json(text, path, "a JSON file")
    validate_document(doc, str(path))
    schedule = doc["scene"]["schedule"]
    if schedule != "clean":
        raise JsgsError(
            f"{path}: not a clean dataset (schedule {schedule!r}); derive needs one made by "
            "`jsgstools compress SCENE --out BASE --schedule clean`"
        )
    root = path.parent
    for v in doc["views"]:
        cam = v["camera"]
        if cam["model"] != "PINHOLE" or cam["distortion"] is not None:
            raise JsgsError(f"{path}: view {v['name']!r} has a {cam['model']} camera with distortion; "
                            "the base must be compress's undistorted PINHOLE output")  # fmt: skip
        if v["reference"] is None:
            raise JsgsError(f"{path}: view {v['name']!r} has no lossless reference")
        ref = root / v["reference"]
        if not ref.is_file():
            raise JsgsError(f"{ref}: reference file of view {v['name']!r} is missing")
    source_names = {v["name"]: v["name"] for v in doc["views"]}
    rec_path = root / "compress.json"
    if rec_path.is_file():
        try:
            rec = json.loads(rec_path.read_text())
            names = {r["name"]: r["source_name"] for r in rec["views"] if r["name"] in source_names}
            source_names.update(names)
        except (OSError, ValueError, KeyError, TypeError, RecursionError) as e:
            raise JsgsError(f"{rec_path}: unreadable compress record ({e})") from None
    return doc, source_names


@removes_partial_output
def derive(
    base_manifest: str | Path,
    out: str | Path,
    schedule: str,
    quality: int | None = None,
    seed: int = 0,
    subsampling: str = "420",
    force: bool = False,
    jobs: int | None = None,
    command: str | None = None,
    recompress: int | None = None,
    analyze: bool = False,
) -> dict[str, Any]:
    """Write ``out/images/<stem>.jpg`` (train views) and ``out/manifest.json`` from the clean dataset whose
    manifest is ``base_manifest``; returns the manifest document. See the module docstring. ``recompress``
    and ``analyze`` as in :func:`jsgstools.compress.compress` (a photo saved twice; the manifest records
    each JPEG view's compression analysis)."""
    from . import manifest_writer as manifest_mod

    if subsampling not in SUBSAMPLING:
        raise JsgsError(f"--subsampling {subsampling!r}: choose one of {', '.join(SUBSAMPLING)}")
    if jobs is not None and jobs < 1:
        raise JsgsError(f"--jobs {jobs}: must be at least 1")
    check_recompress(recompress)
    base_path = Path(base_manifest)
    if base_path.is_dir():
        base_path = base_path / "manifest.json"
    out = Path(out)
    base, source_names = read_base(base_path)
    base_root = base_path.parent
    test_every = int(base["scene"]["test_every"])
    by_source = _views_by_source(base_path, base["views"], source_names)
    # The same split/counts/assignment as compress (validates schedule and quality too).
    the_plan = plan(list(by_source), schedule, quality, seed, test_every)
    _check_split(base_path, by_source, the_plan, test_every)

    prepare_output_dir(out, force, OWNED, protect=base_root, tool="derive")
    ss_name, ss_pil = SUBSAMPLING[subsampling]
    sizes = _encode_views(by_source, the_plan, base_root, out, ss_pil, recompress, jobs)
    mviews, per_view_quality = _manifest_views(by_source, the_plan, base_root, out, analyze)

    command = command or (
        f"jsgstools.derive {shlex.quote(str(base_path))} --out {shlex.quote(str(out))} --schedule {schedule}"
        + (f" --quality {quality}" if quality is not None else "")
        + f" --seed {seed} --subsampling {subsampling}"
        + (f" --recompress {recompress}" if recompress is not None else "")
        + (" --analyze" if analyze else "")
    )
    settings = {
        "derive": True,
        "base": str(base_path),
        "base_relative": _rel(base_path, out),
        "base_producer": base["producer"].get("command"),
        "schedule": schedule,
        "quality": quality,
        "seed": seed,
        "test_every": test_every,
        "subsampling": ss_name,
        "recompress": recompress,
        **schedule_settings(the_plan, schedule, quality, ss_name),
        "source": "the base's lossless reference PNGs; compress's split, counts, assignment and encoding",
        "bytes": {f"{image_stem(by_source[s]['name'])}.jpg": n for s, n in sorted(sizes.items())},
        "per_view_quality": per_view_quality,
    }
    doc = {
        "format": "jsgs-manifest",
        "format_version": 1,
        "producer": {
            "tool": "jsgstools derive",
            "version": __version__,
            "command": command,
            "settings": settings,
        },  # fmt: skip
        "scene": {
            **base["scene"],
            "schedule": schedule,
            "quality": quality,
            "seed": seed,
            "subsampling": ss_name,
        },  # fmt: skip
        "views": mviews,
        "points": base["points"],
    }
    manifest_mod.write_manifest(doc, out / "manifest.json")  # validated, atomic, written last
    return doc


def _views_by_source(
    base_path: Path, views: list[dict[str, Any]], source_names: dict[str, str]
) -> dict[str, dict[str, Any]]:
    """The base's views by their source image name (JsgsError when two share one)."""
    by_source = {source_names[v["name"]]: v for v in views}
    if len(by_source) != len(views):
        raise JsgsError(f"{base_path}: two views share a source image name")
    return by_source


def _check_split(
    base_path: Path, by_source: dict[str, dict[str, Any]], the_plan: CompressionPlan, test_every: int
) -> None:
    """JsgsError when a base view's split is not the one compress's split rule gives it."""
    for src, v in by_source.items():
        if the_plan.split[src] != v["split"]:
            raise JsgsError(f"{base_path}: view {v['name']!r} is {v['split']} in the base but "
                            f"{the_plan.split[src]} by the split rule (test every {test_every})")  # fmt: skip


def _encode_views(
    by_source: dict[str, dict[str, Any]], the_plan: CompressionPlan, base_root: Path, out: Path,
    subsampling: int, recompress: int | None, jobs: int | None,
) -> dict[str, int]:  # fmt: skip
    """Encode each JPEG view's reference into ``out/images/<stem>.jpg`` on a thread pool; source name ->
    bytes written."""

    def encode(src: str) -> tuple[str, int]:
        v = by_source[src]
        q = the_plan.quality[src]
        assert q is not None
        ref = base_root / v["reference"]
        arr = load_rgb(ref)
        cam = v["camera"]
        if (arr.shape[1], arr.shape[0]) != (cam["width"], cam["height"]):
            size = f"{arr.shape[1]}x{arr.shape[0]}"
            raise JsgsError(f"{ref}: {size} is not its camera's {cam['width']}x{cam['height']}")
        data = observed_jpeg(arr, q, subsampling, recompress)
        write_bytes_atomic(out / "images" / f"{image_stem(v['name'])}.jpg", data)
        return src, len(data)

    encoded = [s for s in by_source if the_plan.quality[s] is not None]
    workers = min(jobs or os.cpu_count() or 1, max(1, len(encoded)))
    with ThreadPoolExecutor(max_workers=workers) as ex:  # Pillow releases the GIL while encoding
        return dict(ex.map(encode, encoded))


def _manifest_views(
    by_source: dict[str, dict[str, Any]], the_plan: CompressionPlan, base_root: Path, out: Path,
    analyze: bool,
) -> tuple[list[dict[str, Any]], dict[str, int | None]]:  # fmt: skip
    """The manifest's views (a lossless one reads the base's reference; a JPEG one its new file and its
    header's state) and each view's quality by its name."""
    from . import manifest_writer as manifest_mod

    mviews: list[dict[str, Any]] = []
    per_view_quality: dict[str, int | None] = {}
    for src, v in by_source.items():
        q = the_plan.quality[src]
        ref_rel = _rel(base_root / v["reference"], out)
        if q is None:
            name, image, jpeg = f"{image_stem(v['name'])}.png", ref_rel, None
        else:
            name = f"{image_stem(v['name'])}.jpg"
            image = f"images/{name}"
            jpeg = manifest_mod.jpeg_file_state(out / image, analyze)
        per_view_quality[name] = q
        mviews.append({"name": name, "image": image, "split": v["split"], "camera": v["camera"],
                       "R": v["R"], "t": v["t"], "jpeg": jpeg, "reference": ref_rel})  # fmt: skip
    return mviews, per_view_quality


def restore_clean_images(dataset: str | Path) -> int:
    """A clean dataset carried without ``images/`` (only ``manifest.json``, ``compress.json`` and
    ``reference/``): put back each lossless ``images/<stem>.png`` as a copy of its reference (``compress``
    writes both from the same bytes). Returns the number of files restored; a missing reference is an
    error."""
    root = Path(dataset)
    doc, _ = read_base(root / "manifest.json")
    n = 0
    for v in doc["views"]:
        img = root / v["image"]
        if v["jpeg"] is None and not img.is_file():
            write_bytes_atomic(img, (root / v["reference"]).read_bytes())
            n += 1
    return n
