"""``jsgstools compress``: a mixed-quality JPEG dataset from a clean scene, as in the paper's setup.

Rules (all recorded in ``DIR/compress.json`` and in the manifest's ``producer.settings``):

- **Split.** Registered views sorted by image name (Python string order); view ``i`` is a test view when ``i %
  test_every == 0`` (the 1st, 9th, 17th, ... with the default 8: one in eight, 7:1). Test views are never
  compressed.
- **Levels.** Qualities 10, 20, ..., 90. Weights per level (ascending quality): uniform 1 each; gaussian
  ``exp(-x^2/2)`` at ``x = linspace(-2, 2, 9)`` (q=10 at x=-2); descending 1, 2, ..., 9 (9 for q=90 down to 1
  for q=10); fixed: every training view at ``--quality``; clean: training views stay lossless (PNG).
- **Counts** (largest remainder, exact): level k gets ``floor(n * w_k / sum(w))``; the views left over go one
  each to the levels with the largest fractional parts ``n * w_k / sum(w) - floor(...)``; ties go to the
  higher quality. Arithmetic is exact (rationals; gaussian weights are taken as their exact float values), so
  the counts always sum to the number of training views and symmetric gaussian levels tie exactly. (Like any
  largest-remainder rule it is not monotone in n: gaussian gives q20 one view at n=8 and none at n=9.)
- **Assignment.** The list of qualities (ascending, each repeated by its count) is shuffled with
  ``numpy.random.default_rng(seed).permutation`` and dealt to the training views in sorted-name order.
- **Encoding.** Pillow (libjpeg), ``quality=q``, baseline, ``optimize=False``, chroma subsampling 4:2:0 by
  default (``--subsampling 444|422|420``), no metadata; RGB input (other modes are converted; alpha dropped).
- **Geometry.** The COLMAP cameras are scaled to the image files (one downscale factor for the scene,
  detected; intrinsics times file size / camera size). Distorted cameras (SIMPLE_RADIAL, RADIAL, OPENCV,
  FULL_OPENCV) are undistorted to PINHOLE with OpenCV *before* compression, keeping the image size and
  principal point and zooming the focal length by the smallest factor that leaves no black border
  (:func:`jsgstools.scene.undistorted_camera`; Lanczos-4 resampling). The references are the same undistorted
  images, losslessly. Pinhole scenes are not resampled at all.

Output: ``DIR/images/<stem>.jpg`` (train views; ``.png`` for test views, and for train views under ``clean``,
so that DIR is itself a complete COLMAP scene), ``DIR/reference/<stem>.png`` (lossless reference of every
view), ``DIR/sparse/0/`` (binary model: PINHOLE cameras as used, poses unchanged, image names = the new files,
keypoints moved with the undistortion, points3D and tracks kept), ``DIR/compress.json`` and, written last (its
presence marks a complete run), ``DIR/manifest.json``. Every file is written atomically.
"""

from __future__ import annotations

import io
import os
import shlex
from collections.abc import Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from jsgs import __version__
from jsgs.base.errors import JsgsError
from jsgs.base.io import write_bytes_atomic
from jsgs.base.schema import validate as schema_validate
from jsgs.jpeg.tables import CHROMA_SAMPLINGS

from .scene import (
    LOSSLESS_FORMATS,
    ColmapCamera,
    ColmapScene,
    image_stem,
    prepare_output_dir,
    removes_partial_output,
    undistorted_camera,
    view_camera,
)

QUALITIES: tuple[int, ...] = tuple(range(10, 100, 10))
SCHEDULES = ("uniform", "gaussian", "descending", "fixed", "clean")
#: --subsampling value ("420" for "4:2:0") -> (name, Pillow's ``subsampling`` argument), what Pillow writes
SUBSAMPLING = {
    name.replace(":", ""): (name, s.pillow) for name, s in CHROMA_SAMPLINGS.items() if s.pillow is not None
}
#: What ``compress`` writes into DIR (and removes first with --force).
OWNED = ("images", "reference", "sparse", "compress.json", "manifest.json")

SPLIT_RULE = (
    "registered views sorted by image name; view i is test when i % test_every == 0; test views are "
    "never compressed"
)
COUNT_RULE = (
    "largest remainder on n * w / sum(w), exact arithmetic; leftover views go to the largest fractional "
    "parts; ties go to the higher quality"
)
ASSIGN_RULE = (
    "qualities ascending, each repeated by its count, shuffled by numpy.random.default_rng(seed)."
    "permutation, dealt to the train views in sorted-name order"
)


# ----------------------------------------------------------------------------------------------------
# Schedule arithmetic (pure; tested exhaustively)


def schedule_weights(schedule: str) -> list[Fraction]:
    """Weights of the nine levels ``QUALITIES`` (ascending quality) of a mixed schedule, as exact
    rationals."""
    if schedule == "uniform":
        return [Fraction(1)] * 9
    if schedule == "gaussian":
        return [Fraction(float(np.exp(-x * x / 2))) for x in np.linspace(-2.0, 2.0, 9)]
    if schedule == "descending":
        return [Fraction(k) for k in range(1, 10)]  # q=10 -> 1, ..., q=90 -> 9
    raise JsgsError(f"--schedule {schedule!r}: not a mixed schedule (uniform, gaussian, descending)")


def largest_remainder(weights: Sequence[Fraction | int | float], n: int) -> list[int]:
    """Split ``n`` items over levels in proportion to ``weights`` (exact): floors of the quotas, then one more
    to each of the ``n - sum(floors)`` levels with the largest fractional parts; among equal fractional parts
    the later level (the higher quality) wins."""
    if n < 0:
        raise ValueError("n must be >= 0")
    w = [Fraction(x) for x in weights]
    if any(x < 0 for x in w) or sum(w) <= 0:
        raise ValueError("weights must be >= 0 with a positive sum")
    total = sum(w)
    quotas = [Fraction(n) * x / total for x in w]
    counts = [q.numerator // q.denominator for q in quotas]
    left = n - sum(counts)
    order = sorted(range(len(w)), key=lambda k: (-(quotas[k] - counts[k]), -k))
    for k in order[:left]:
        counts[k] += 1
    return counts


def split_names(names: Sequence[str], test_every: int) -> dict[str, str]:
    """name -> "train" | "test" (see SPLIT_RULE)."""
    if test_every < 1:
        raise JsgsError(f"--test-every {test_every}: must be at least 1")
    if test_every == 1 and names:
        raise JsgsError(
            f"--test-every 1: every one of the {len(names)} views would be a test view and none left to "
            "train on"
        )
    return {name: ("test" if i % test_every == 0 else "train") for i, name in enumerate(sorted(names))}


@dataclass(frozen=True)
class CompressionPlan:
    """Which view gets what. ``quality[name]`` is None for lossless (test views; train views under clean)."""

    schedule: str
    split: dict[str, str]
    quality: dict[str, int | None]
    counts: dict[int, int]  # quality -> number of train views (empty for clean)
    weights: list[float]  # per level of QUALITIES (empty for clean)


def plan(
    names: Sequence[str], schedule: str, quality: int | None = None, seed: int = 0, test_every: int = 8
) -> CompressionPlan:
    """The split, the per-level counts and the seeded assignment, without touching any file."""
    if schedule not in SCHEDULES:
        raise JsgsError(f"--schedule {schedule!r}: choose one of {', '.join(SCHEDULES)}")
    if schedule == "fixed":
        if quality is None:
            raise JsgsError("--schedule fixed needs --quality Q")
        if not 1 <= quality <= 100:
            raise JsgsError(f"--quality {quality}: must be within 1..100")
    elif quality is not None:
        raise JsgsError(f"--quality applies to --schedule fixed only (got --schedule {schedule})")
    if len(set(names)) != len(names):
        raise JsgsError("duplicate image names")
    split = split_names(names, test_every)
    train = [n for n in sorted(names) if split[n] == "train"]
    q_of: dict[str, int | None] = {n: None for n in names}
    if schedule == "clean":
        return CompressionPlan(schedule, split, q_of, {}, [])
    if schedule == "fixed":
        assert quality is not None
        counts = {quality: len(train)}
        weights: list[float] = []
    else:
        w = schedule_weights(schedule)
        counts = dict(zip(QUALITIES, largest_remainder(w, len(train)), strict=True))
        weights = [float(x) for x in w]
    pool = np.array([q for q in sorted(counts) for _ in range(counts[q])], dtype=np.int64)
    dealt = np.random.default_rng(seed).permutation(pool)
    for name, q in zip(train, dealt, strict=True):
        q_of[name] = int(q)
    return CompressionPlan(schedule, split, q_of, counts, weights)


# ----------------------------------------------------------------------------------------------------
# Encoding (runs in worker processes)


@dataclass(frozen=True)
class Task:
    name: str  # model image name in the source
    src: str  # source image file
    camera: ColmapCamera  # the source camera scaled to the file (may be distorted)
    pinhole: ColmapCamera  # the output camera (PINHOLE, same size)
    reference: str  # output reference PNG
    image: str  # output observed image (.jpg, or .png when quality is None)
    quality: int | None
    subsampling: int  # Pillow's value
    recompress: int | None = None  # save the JPEG once more at this quality (decoded first)


def _png_bytes(arr: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(arr, "RGB").save(buf, format="PNG", compress_level=3)  # 1 % larger than 6, 40 % faster
    return buf.getvalue()


def jpeg_bytes(arr: np.ndarray, quality: int, subsampling: int) -> bytes:
    """Baseline JPEG of ``arr`` ((H, W, 3) uint8 RGB) through Pillow/libjpeg at IJG ``quality``."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(arr, "RGB").save(
        buf, format="JPEG", quality=quality, subsampling=subsampling, optimize=False, progressive=False
    )
    return buf.getvalue()


def check_recompress(recompress: int | None) -> None:
    """``--recompress``: None or an IJG quality (JsgsError, one line, otherwise)."""
    if recompress is not None and not 1 <= recompress <= 100:
        raise JsgsError(f"--recompress {recompress}: must be an IJG quality in 1..100")


def observed_jpeg(arr: np.ndarray, quality: int, subsampling: int, recompress: int | None = None) -> bytes:
    """The observed file of a view: :func:`jpeg_bytes` at ``quality``; with ``recompress``, that file decoded
    and saved once more at IJG quality ``recompress`` (what an app does to a photo: the header then holds
    only the second tables)."""
    data = jpeg_bytes(arr, quality, subsampling)
    if recompress is None:
        return data
    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        again = np.asarray(im.convert("RGB"))
    return jpeg_bytes(again, recompress, subsampling)


def load_rgb(path: str | Path) -> np.ndarray:
    """(H, W, 3) uint8 (:func:`jsgs.base.images.read_rgb8`: grey and palette expanded, 16-bit by value, alpha
    dropped; a file that cannot be decoded is a one-line JsgsError)."""
    from jsgs.base.images import read_rgb8

    return read_rgb8(path)


def run_task(task: Task) -> dict[str, Any]:
    """Read, undistort (when the camera is distorted), write the reference and the observed image."""
    try:
        import cv2

        cv2.setNumThreads(1)  # one view per process already uses every core
    except ImportError:  # pragma: no cover
        pass
    from .scene import undistort_image

    arr = load_rgb(task.src)
    if (arr.shape[1], arr.shape[0]) != (task.camera.width, task.camera.height):
        raise JsgsError(f"{task.src}: {arr.shape[1]}x{arr.shape[0]} is not camera {task.camera.describe()}")
    if not task.camera.is_pinhole:
        arr = undistort_image(arr, task.camera, task.pinhole)
    ref = _png_bytes(arr)
    write_bytes_atomic(task.reference, ref)
    data = ref
    if task.quality is not None:
        data = observed_jpeg(arr, task.quality, task.subsampling, task.recompress)
    write_bytes_atomic(task.image, data)
    return {"name": task.name, "bytes": len(data), "reference_bytes": len(ref)}


def _run_all(tasks: list[Task], jobs: int, progress: bool) -> list[dict[str, Any]]:
    from tqdm import tqdm

    bar = tqdm(total=len(tasks), desc="compress", unit="view", disable=not progress)
    results: list[dict[str, Any]] = []
    try:
        if jobs <= 1 or len(tasks) <= 1:
            for t in tasks:
                results.append(run_task(t))
                bar.update()
            return results
        import multiprocessing

        # spawn: workers start clean (no inherited OpenCV thread pools or pycolmap state from the parent).
        ctx = multiprocessing.get_context("spawn")
        from jsgs.base.io import die_with_parent

        with ProcessPoolExecutor(
            max_workers=min(jobs, len(tasks)), mp_context=ctx, initializer=die_with_parent
        ) as pool:
            futures: list[Future[dict[str, Any]]] = [pool.submit(run_task, t) for t in tasks]
            pending = set(futures)
            try:
                while pending:
                    # one view at a time: the bar advances per finished view; an error stops the rest
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for f in done:
                        results.append(f.result())  # re-raises a worker's error
                        bar.update()
            except BaseException:
                for f in pending:
                    f.cancel()
                raise
        return results
    finally:
        bar.close()


# ----------------------------------------------------------------------------------------------------
# The command


@dataclass(frozen=True)
class CompressResult:
    out: Path
    record: dict[str, Any]
    manifest: dict[str, Any]


def _camera_doc(cam: ColmapCamera) -> dict[str, Any]:
    return {
        "camera_id": cam.camera_id,
        "model": cam.model,
        "width": cam.width,
        "height": cam.height,
        "params": list(cam.params),
    }


def _output_model(
    scene: Any, out_names: dict[str, str], cams_in: dict[int, ColmapCamera], cams_out: dict[int, ColmapCamera]
) -> Any:
    """A new pycolmap model: PINHOLE cameras ``cams_out``, the registered images renamed to ``out_names`` with
    keypoints moved to the output pixel grid, points3D with their tracks (observations of dropped, unposed
    images removed)."""
    import pycolmap

    from .scene import undistort_points

    src = scene.reconstruction
    new = pycolmap.Reconstruction()
    for cid, cam in sorted(cams_out.items()):
        pc = pycolmap.Camera.create_from_model_name(cid, "PINHOLE", 1.0, cam.width, cam.height)
        pc.params = list(cam.params)
        new.add_camera_with_trivial_rig(pc)
    kept = set()
    for v in scene.views:
        im = src.images[v.image_id]
        kp = np.array([p.xy for p in im.points2D], dtype=np.float64).reshape(-1, 2)
        if len(kp):
            cin = cams_in[v.camera_id]
            orig = scene.cameras[v.camera_id]
            kp = kp * np.array([cin.width / orig.width, cin.height / orig.height])
            kp = undistort_points(kp, cin, cams_out[v.camera_id])
        ni = pycolmap.Image(name=out_names[v.name], keypoints=kp, camera_id=v.camera_id, image_id=v.image_id)
        new.add_image_with_trivial_frame(ni, im.cam_from_world())
        kept.add(v.image_id)
    for pid in sorted(src.points3D):
        p = src.points3D[pid]
        q = pycolmap.Point3D()
        q.xyz = p.xyz
        q.color = p.color
        q.error = p.error
        q.track = pycolmap.Track([e for e in p.track.elements if e.image_id in kept])
        new.add_point3D_with_id(pid, q)
    # Reprojection errors are in pixels: recompute them on the new pixel grid where a track allows it, and
    # keep the source's value for points without observations (LLFF), which COLMAP would reset to 0.
    new.update_point_3d_errors()
    for pid, p in src.points3D.items():
        if new.points3D[pid].track.length() == 0:
            new.points3D[pid].error = p.error
    return new


@removes_partial_output
def compress(
    scene_dir: str | Path,
    out: str | Path,
    schedule: str,
    quality: int | None = None,
    seed: int = 0,
    test_every: int = 8,
    subsampling: str = "420",
    force: bool = False,
    jobs: int | None = None,
    progress: bool = False,
    command: str | None = None,
    recompress: int | None = None,
    analyze: bool = False,
) -> CompressResult:
    """Build the dataset described in the module docstring from ``scene_dir`` into ``out``. ``recompress``:
    every JPEG training view is decoded and saved once more at that quality (its header then says
    ``recompress`` while its pixels went through both: a photo saved twice). ``analyze``: the manifest
    records each JPEG view's compression analysis (``jsgstools manifest --analyze``)."""
    check_recompress(recompress)
    from . import manifest_writer as manifest_mod
    from .scene import write_model_atomic
    from .validate import require_valid

    scene_dir, out = Path(scene_dir), Path(out)
    _check_options(subsampling, jobs, test_every)
    report = require_valid(scene_dir)
    scene = report.scene
    assert scene is not None
    _require_lossless(scene)
    the_plan = plan([v.name for v in scene.views], schedule, quality, seed, test_every)
    out_names = _output_names(scene, the_plan)
    cams_in, cams_out, zoom = _cameras(scene)

    prepare_output_dir(out, force, OWNED, protect=scene_dir, tool="compress")
    ss_name, ss_pil = SUBSAMPLING[subsampling]
    tasks = _tasks(scene, out, the_plan, out_names, cams_in, cams_out, ss_pil, recompress)
    results = {r["name"]: r for r in _run_all(tasks, jobs or os.cpu_count() or 1, progress)}

    write_model_atomic(_output_model(scene, out_names, cams_in, cams_out), out / "sparse" / "0")

    downscale = None if report.downscale in (None, 1.0) else report.downscale
    command = command or _command_line(
        scene_dir, out, schedule, quality, seed, test_every, subsampling, recompress
    )
    settings = {
        "schedule": schedule,
        "quality": quality,
        "seed": seed,
        "test_every": test_every,
        "subsampling": ss_name,
        **schedule_settings(the_plan, schedule, quality, ss_name),
        "split_rule": SPLIT_RULE,
        "count_rule": COUNT_RULE,
        "assignment_rule": ASSIGN_RULE,
        "downscale": downscale,
        "undistorted": any(not c.is_pinhole for c in cams_in.values()),
        "recompress": recompress,
    }
    record: dict[str, Any] = {
        "format": "jsgs-compress-record",
        "format_version": 1,
        "producer": {"tool": "jsgstools compress", "version": __version__, "command": command},
        "source": {
            "scene": str(scene_dir),
            "name": scene.name,
            "model": str(scene.model_dir.relative_to(scene_dir)),
            "model_format": scene.model_format,
            "downscale": downscale,
        },
        "settings": settings,
        "cameras": _camera_records(scene, cams_in, cams_out, zoom),
        "views": _view_records(scene, the_plan, out_names, results),
    }
    schema_validate(record, "compress_record", str(out / "compress.json"))
    write_bytes_atomic(out / "compress.json", manifest_mod.dumps(record).encode())

    producer = {
        "tool": "jsgstools compress",
        "version": __version__,
        "command": command,
        "settings": {
            **settings,
            "per_view_quality": {out_names[v.name]: the_plan.quality[v.name] for v in scene.views},
        },
    }
    doc = manifest_mod.build_manifest(out, out / "manifest.json", producer=producer, analyze=analyze)
    manifest_mod.write_manifest(doc, out / "manifest.json")
    return CompressResult(out, record, doc)


def _command_line(
    scene_dir: Path, out: Path, schedule: str, quality: int | None, seed: int, test_every: int,
    subsampling: str, recompress: int | None,
) -> str:  # fmt: skip
    """The ``jsgstools compress`` command line that makes the dataset, recorded when none is given."""
    return (
        f"jsgstools compress {shlex.quote(str(scene_dir))} --out {shlex.quote(str(out))} "
        f"--schedule {schedule}"
        + (f" --quality {quality}" if quality is not None else "")
        + f" --seed {seed} --test-every {test_every} --subsampling {subsampling}"
        + (f" --recompress {recompress}" if recompress is not None else "")
    )


def _check_options(subsampling: str, jobs: int | None, test_every: int) -> None:
    """JsgsError (one line, naming the option) for a subsampling, job count or test spacing not allowed."""
    if subsampling not in SUBSAMPLING:
        raise JsgsError(f"--subsampling {subsampling!r}: choose one of {', '.join(SUBSAMPLING)}")
    if jobs is not None and jobs < 1:
        raise JsgsError(f"--jobs {jobs}: must be at least 1")
    if test_every < 1:
        raise JsgsError(f"--test-every {test_every}: must be at least 1")


def _require_lossless(scene: ColmapScene) -> None:
    """JsgsError naming the first source image that is not lossless (and how many more there are)."""
    lossy = [v for v in scene.views if v.format not in LOSSLESS_FORMATS]
    if lossy:
        raise JsgsError(
            f"{lossy[0].path}: compress needs lossless source images, this one is {lossy[0].format}"
            + (f" (and {len(lossy) - 1} more)" if len(lossy) > 1 else "")
        )


def _output_names(scene: ColmapScene, the_plan: CompressionPlan) -> dict[str, str]:
    """source name -> output name: the stem of the model name, .jpg for encoded views, .png for lossless
    ones (JsgsError when two would be one file)."""
    out_names: dict[str, str] = {}
    for v in scene.views:
        ext = ".png" if the_plan.quality[v.name] is None else ".jpg"
        out_names[v.name] = image_stem(v.name) + ext
    stems: dict[str, list[str]] = {}
    for v in scene.views:
        stems.setdefault(image_stem(v.name).lower(), []).append(v.name)
    clash = [names for names in stems.values() if len(names) > 1]
    if clash:
        raise JsgsError(
            f"{scene.model_dir}: images {' and '.join(map(repr, clash[0]))} would be written to the "
            "same output file (names differ only by extension or case)"
        )
    return out_names


def _cameras(
    scene: ColmapScene,
) -> tuple[dict[int, ColmapCamera], dict[int, ColmapCamera], dict[int, float]]:
    """The cameras of the registered views: scaled to the files (in), then undistorted to PINHOLE (out),
    and the zoom of each undistortion; by camera id."""
    cams_in: dict[int, ColmapCamera] = {}
    cams_out: dict[int, ColmapCamera] = {}
    zoom: dict[int, float] = {}
    for v in scene.views:
        if v.camera_id not in cams_in:
            cam = view_camera(scene, v)
            cams_in[v.camera_id] = cam
            cams_out[v.camera_id], zoom[v.camera_id] = undistorted_camera(cam)
    return cams_in, cams_out, zoom


def _tasks(
    scene: ColmapScene, out: Path, the_plan: CompressionPlan, out_names: dict[str, str],
    cams_in: dict[int, ColmapCamera], cams_out: dict[int, ColmapCamera], subsampling: int,
    recompress: int | None,
) -> list[Task]:  # fmt: skip
    """One :class:`Task` per registered view: its source, cameras, output files and quality."""
    return [
        Task(
            name=v.name,
            src=str(v.path),
            camera=cams_in[v.camera_id],
            pinhole=cams_out[v.camera_id],
            reference=str(out / "reference" / (image_stem(v.name) + ".png")),
            image=str(out / "images" / out_names[v.name]),
            quality=the_plan.quality[v.name],
            subsampling=subsampling,
            recompress=recompress,
        )
        for v in scene.views
    ]


def _camera_records(
    scene: ColmapScene, cams_in: dict[int, ColmapCamera], cams_out: dict[int, ColmapCamera],
    zoom: dict[int, float],
) -> list[dict[str, Any]]:  # fmt: skip
    """compress.json's ``cameras``: each camera as in the source, scaled and output."""
    return [
        {
            "camera_id": cid,
            "source": _camera_doc(scene.cameras[cid]),
            "scaled": _camera_doc(cams_in[cid]),
            "output": _camera_doc(cams_out[cid]),
            "undistorted": not cams_in[cid].is_pinhole,
            "zoom": zoom[cid],
        }
        for cid in sorted(cams_out)
    ]


def _view_records(
    scene: ColmapScene, the_plan: CompressionPlan, out_names: dict[str, str],
    results: dict[str, dict[str, Any]],
) -> list[dict[str, Any]]:  # fmt: skip
    """compress.json's ``views``: each view's names, split, quality, files and size in bytes."""
    return [
        {
            "name": out_names[v.name],
            "source_name": v.name,
            "split": the_plan.split[v.name],
            "quality": the_plan.quality[v.name],
            "image": f"images/{out_names[v.name]}",
            "reference": f"reference/{image_stem(v.name)}.png",
            "bytes": results[v.name]["bytes"],
        }
        for v in scene.views
    ]


def schedule_settings(
    the_plan: CompressionPlan, schedule: str, quality: int | None, ss_name: str
) -> dict[str, Any]:
    """What a dataset records of its quality schedule and encoder (shared by ``compress`` and ``derive``,
    whose JPEGs are the same)."""
    return {
        "qualities": list(QUALITIES)
        if schedule not in ("fixed", "clean")
        else ([quality] if schedule == "fixed" else []),
        "weights": the_plan.weights,
        "counts": {str(q): c for q, c in sorted(the_plan.counts.items())},
        "encoder": f"Pillow {_pillow_version()} (libjpeg), baseline, optimize=False, subsampling {ss_name}",
    }


def _pillow_version() -> str:
    import PIL

    return str(PIL.__version__)
