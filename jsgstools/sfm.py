"""``jsgstools sfm PHOTOS --out SCENE``: a COLMAP model for a folder of photos, with pycolmap (SIFT features,
exhaustive or sequential matching, incremental mapping), without touching the photos' bytes.

- The photos are copied (or hard-linked with ``link``) into ``SCENE/images`` byte for byte: a JPEG keeps its
  own quantization tables, EXIF and 8×8 grid, which is what JSGS reads.
- One shared camera when every photo has the same size (``single_camera`` None), else one per photo; the
  camera model is the user's (default SIMPLE_PINHOLE: the trainer renders pinhole cameras).
- The largest model is kept as ``SCENE/sparse/0``; ``SCENE/sfm.json`` (``jsgs/schemas/sfm.schema.json``)
  records the settings, each stage's time, every model found and the photos left unregistered.
"""

from __future__ import annotations

import datetime
import os
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from jsgs.base.errors import JsgsError

from .scene import IMAGE_EXTENSIONS, prepare_output_dir, removes_partial_output, write_model_atomic

OWNED = ("images", "sparse", "database.db", "sfm.json")
MATCHERS = ("exhaustive", "sequential")
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def list_photos(folder: Path) -> list[Path]:
    """The image files directly in ``folder`` (known extensions, any case), sorted by name."""
    if not folder.is_dir():
        raise JsgsError(f"{folder}: not a folder of photos")
    photos = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    if len(photos) < 2:
        raise JsgsError(f"{folder}: {len(photos)} photo(s) found; structure from motion needs at least two")
    return photos


def _sizes(photos: list[Path]) -> set[tuple[int, int]]:
    from PIL import Image

    out = set()
    from jsgs.base.io import open_regular

    for p in photos:
        try:
            with open_regular(p) as f, Image.open(f) as im:
                out.add(im.size)
        except (OSError, ValueError) as e:
            raise JsgsError(f"{p}: cannot read image ({e})") from None
    return out


@removes_partial_output
def sfm(
    photos_dir: str | Path,
    out: str | Path,
    *,
    matcher: str = "exhaustive",
    camera_model: str = "SIMPLE_PINHOLE",
    single_camera: bool | None = None,
    max_image_size: int = 1600,
    max_features: int = 1024,
    threads: int = -1,
    link: bool = False,
    force: bool = False,
    seed: int = 0,
    say: Callable[[str], None] | None = None,
    command: str | None = None,
) -> dict[str, Any]:
    """Run the whole reconstruction into ``out`` (see the module docstring); returns the sfm.json record."""
    import pycolmap

    import jsgs
    from jsgs.base.io import OutputLock, write_json_atomic
    from jsgs.base.schema import validate

    say = say or (lambda s: print(s, file=sys.stderr, flush=True))
    photos_dir, out = Path(photos_dir), Path(out)
    _check_options(matcher, camera_model, max_image_size, max_features)
    pycolmap.logging.minloglevel = 2  # COLMAP's own per-image log lines; our progress line per stage instead
    photos = list_photos(photos_dir)
    sizes = _sizes(photos)
    single = len(sizes) == 1 if single_camera is None else single_camera
    threads = threads if threads > 0 else (os.cpu_count() or 1)
    with OutputLock(out, f"jsgstools sfm (into {out})"):
        prepare_output_dir(out, force, OWNED, protect=photos_dir, tool="sfm")
        images = out / "images"
        images.mkdir()
        for p in photos:  # byte for byte: the photos' JPEG state is what JSGS reads
            (os.link if link else shutil.copyfile)(p, images / p.name)
        db = out / "database.db"
        times: dict[str, float] = {}

        times["features"] = _extract_features(db, images, camera_model, single, max_image_size, max_features,
                                              threads)  # fmt: skip
        say(f"sfm: features of {len(photos)} photos ({times['features']:.1f} s)")
        times["matching"] = _match_features(db, matcher, threads)
        say(f"sfm: {matcher} matching ({times['matching']:.1f} s)")
        t0 = time.perf_counter()
        models = _incremental_mapping(db, images, out / ".sfm_models", threads, seed)
        times["mapping"] = time.perf_counter() - t0
        if not models:
            raise JsgsError(f"{photos_dir}: no model could be built from these photos (too few matches)")
        ranked = sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True)
        best = ranked[0]
        write_model_atomic(best, out / "sparse" / "0")
        registered = sorted(str(im.name) for im in best.images.values() if im.has_pose)
        left_out = sorted(set(p.name for p in photos) - set(registered))
        say(f"sfm: mapping ({times['mapping']:.1f} s): {len(registered)} of {len(photos)} photos registered"
            + (f", {len(ranked) - 1} smaller model(s) dropped" if len(ranked) > 1 else ""))  # fmt: skip
        record = {
            "format": "jsgs-sfm",
            "format_version": 1,
            "jsgstools_version": jsgs.__version__,
            "pycolmap_version": str(pycolmap.__version__),
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "command": command,
            "settings": {
                "photos": str(photos_dir), "matcher": matcher, "camera_model": camera_model,
                "single_camera": single, "max_image_size": max_image_size, "max_features": max_features,
                "threads": threads, "link": link, "seed": seed,
            },  # fmt: skip
            "seconds": {k: round(v, 3) for k, v in times.items()},
            "photos": len(photos),
            "registered": len(registered),
            "unregistered": left_out,
            "models": [{"images": r.num_reg_images(), "points3D": r.num_points3D()} for r in ranked],
            "points3D": best.num_points3D(),
        }
        validate(record, "sfm", str(out / "sfm.json"))
        write_json_atomic(out / "sfm.json", record)
    return record


def _check_options(matcher: str, camera_model: str, max_image_size: int, max_features: int) -> None:
    """JsgsError (one line, naming the option) for a matcher, camera model or size not allowed."""
    if matcher not in MATCHERS:
        raise JsgsError(f"--matcher {matcher!r}: choose {', '.join(MATCHERS)}")
    if camera_model not in CAMERA_MODELS:
        raise JsgsError(f"--camera-model {camera_model!r}: choose {', '.join(CAMERA_MODELS)}")
    if max_image_size < 64 or max_features < 64:
        raise JsgsError("--max-image-size and --max-features must be at least 64")


def _extract_features(
    db: Path, images: Path, camera_model: str, single: bool, max_image_size: int, max_features: int,
    threads: int,
) -> float:  # fmt: skip
    """SIFT features of every photo into the database (one shared camera when ``single``); seconds taken."""
    import pycolmap

    t0 = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = max_image_size
    extraction.num_threads = threads
    extraction.sift.max_num_features = max_features
    mode = pycolmap.CameraMode.SINGLE if single else pycolmap.CameraMode.PER_IMAGE
    pycolmap.extract_features(db, images, camera_mode=mode, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)  # fmt: skip
    return time.perf_counter() - t0


def _match_features(db: Path, matcher: str, threads: int) -> float:
    """Match the features, every pair (exhaustive) or neighbours in name order (sequential); seconds taken."""
    import pycolmap

    t0 = time.perf_counter()
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pycolmap.match_sequential(db, matching_options=matching, device=pycolmap.Device.cpu)
    return time.perf_counter() - t0


def _incremental_mapping(db: Path, images: Path, work: Path, threads: int, seed: int) -> Any:
    """pycolmap's incremental mapping: every model it finds (its scratch folder ``work`` removed after)."""
    import pycolmap

    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = threads
    opts.random_seed = seed
    if work.exists():
        shutil.rmtree(work)
    work.mkdir()
    try:
        return pycolmap.incremental_mapping(db, images, work, options=opts)
    finally:
        shutil.rmtree(work, ignore_errors=True)
