"""``jsgstools validate``: check that a COLMAP scene can be used, and list every problem.

Problems (each one line, naming the file; any problem means exit code 1):

- no COLMAP model in ``sparse/0/`` or ``sparse/`` (binary or text), or a model pycolmap cannot read;
- no ``images/`` folder; a registered image whose file is missing (exact name, or the only same-stem file),
  unreadable, or in a format other than JPEG, PNG, BMP, PPM;
- an image whose size matches its camera at no single scale factor, or at a factor other than the scene's
  (see :func:`jsgstools.scene.detect_downscale`); a camera shared by images of different sizes;
- a camera model other than the pinhole ones (SIMPLE_PINHOLE, PINHOLE) and the distorted ones ``compress`` can
  undistort (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV); non-finite or non-positive intrinsics;
- a non-finite pose or one beyond ``jsgs.base.limits.MAX_COORDINATE``; an image name used twice; no registered
  image; no points3D, or points that are not finite or lie beyond that limit;
- with ``decode`` (the ``validate`` command), an image that cannot be decoded (truncated, over the pixel
  limit: :mod:`jsgs.base.images`), as compress and the trainer would find it; an unreadable ``compress.json``.

Warnings (reported, exit code still 0): distorted cameras — ``compress`` undistorts a clean scene before
encoding, ``manifest`` records the distortion as is, and the trainer renders SIMPLE_RADIAL, RADIAL and OPENCV
views on the photos' own grid;
images in the model without a pose (ignored by every tool); a camera that sees none of the points3D; image
files the model does not use (photos SfM could not register); other models under ``sparse/``; all cameras at
one position, or whose up directions cancel out, or most of which sit at their common focus point
(:func:`jsgs.base.world.normalization_refusal`; the trainer then needs ``scene.normalize_world`` false).
"""

from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from jsgs.base.camera import DISTORTION_MODELS
from jsgs.base.errors import JsgsError
from jsgs.base.limits import MAX_COORDINATE
from jsgs.base.world import coincidence, normalization_refusal

from .scene import (
    JPEG_FORMATS,
    LOSSLESS_FORMATS,
    PINHOLE_MODELS,
    UNDISTORTABLE_MODELS,
    ColmapScene,
    ColmapView,
    detect_downscale,
    finite,
    fmt_factor,
    load_colmap_scene,
)

#: Problem kinds. ``manifest`` accepts scenes whose only problems are of kind ``camera_model`` (it records any
#: model with its parameters); ``compress`` accepts none.
KINDS = ("model", "images", "image", "size", "camera", "camera_model", "pose", "names", "points", "record")


@dataclass(frozen=True)
class Problem:
    kind: str
    message: str  # "<file or item>: <what is wrong>"


@dataclass
class ValidationReport:
    root: Path
    scene: ColmapScene | None
    problems: list[Problem] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    downscale: float | None = None

    @property
    def ok(self) -> bool:
        return not self.problems

    def blocking(self, allow: tuple[str, ...] = ()) -> list[Problem]:
        return [p for p in self.problems if p.kind not in allow]

    def summary_rows(self, test_every: int = 8) -> list[tuple[str, str]]:
        """(field, value) rows of the summary table."""
        s = self.scene
        if s is None:
            return [("scene", str(self.root))]
        models = Counter(c.model for c in s.cameras.values())
        sizes = Counter(v.size for v in s.views if v.size is not None)
        formats = Counter(v.format for v in s.views if v.format is not None)
        cam_sizes = Counter((c.width, c.height) for c in s.cameras.values())
        n = len(s.views)
        n_test = len(range(0, n, test_every)) if test_every > 0 else 0
        tests = [v for i, v in enumerate(s.views) if test_every > 0 and i % test_every == 0]
        jpeg_tests = sum(1 for v in tests if v.format in JPEG_FORMATS)
        rows = [
            ("scene", str(self.root)),
            ("model", f"{s.rel(s.model_dir)}/ ({s.model_format})"),
            (
                "cameras",
                f"{len(s.cameras)} (" + ", ".join(f"{k} x{v}" for k, v in sorted(models.items())) + ")",
            ),
            ("camera size", ", ".join(f"{w}x{h}" for (w, h), _ in sorted(cam_sizes.items()))),
            (
                "images",
                f"{n} registered, {sum(v.path is not None for v in s.views)} found in "
                f"{s.rel(s.images_dir)}/ ("
                + ", ".join(f"{k} x{v}" for k, v in sorted(formats.items()))
                + ")",
            ),
            ("image size", ", ".join(f"{w}x{h} x{c}" for (w, h), c in sorted(sizes.items()))),
            (
                "downscale",
                fmt_factor(self.downscale)
                + ("" if self.downscale in (None, 1.0) else " (intrinsics are scaled by 1/factor)"),
            ),
            ("points3D", str(len(s.points_xyz))),
            (
                "split",
                f"every {test_every}th view by sorted name is test (index % {test_every} == 0): "
                f"{n - n_test} train / {n_test} test"
                if test_every > 0
                else f"--test-every 0: all {n} views train, no test views (no evaluation)",
            ),
        ]
        if jpeg_tests and not (s.root / "compress.json").is_file():
            rows.append((
                "reference",
                f"{jpeg_tests} of {n_test} test views are JPEGs with no lossless copy: the trainer evaluates "
                "them against their JPEG (metrics.json reference jpeg)",
            ))  # fmt: skip
        record = s.root / "compress.json"
        if record.is_file():
            try:
                import json

                rec = json.loads(record.read_text())
                st = rec["settings"]
                n_train = sum(v["split"] == "train" for v in rec["views"])
                rows[-1] = (
                    "split",
                    f"from compress.json (test every {st['test_every']}): {n_train} train / "
                    f"{len(rec['views']) - n_train} test; schedule {st['schedule']}, seed "
                    f"{st['seed']}",
                )
            except (OSError, ValueError, KeyError, TypeError, RecursionError):
                rows.append(("compress.json", "unreadable (listed as a problem)"))
        return rows

    def format_summary(self, test_every: int = 8) -> str:
        rows = self.summary_rows(test_every)
        width = max(len(k) for k, _ in rows)
        return "\n".join(f"{k.ljust(width)}  {v}" for k, v in rows)


def _double_compression_warnings(scene: ColmapScene) -> list[str]:
    from jsgstools.dqt.analysis import analyze_file

    out = []
    for v in scene.views:
        if v.path is None or v.format not in JPEG_FORMATS or v.read_error is not None:
            continue
        try:
            a = analyze_file(v.path)
        except JsgsError:
            continue  # a JPEG the analysis cannot read (CMYK, 12-bit): reported by the other checks
        if a.double_compressed:
            out.append(
                f"{scene.rel(v.path)}: compressed twice (an earlier quality of about {a.primary_quality}; "
                f"confidence {a.confidence:.2f}): its header understates the damage (method_options.tables "
                "effective uses the earlier tables)"
            )
    return out


def orientation_warning(scene: ColmapScene) -> str | None:
    """One line about the photos whose EXIF Orientation is not 1 (None when there are none)."""
    turned = [v for v in scene.views if v.orientation != 1]
    if not turned:
        return None
    eg = ", ".join(f"{v.name} ({v.orientation})" for v in turned[:5]) + (" ..." if len(turned) > 5 else "")
    return (
        f"{len(turned)} photo(s) with an EXIF Orientation other than 1: {eg}; every tool uses the stored "
        "pixels as COLMAP does (the tag is ignored), so the model must have been made from them as stored"
    )


def _in_range(t: np.ndarray) -> bool:
    """A translation that is finite and within ±MAX_COORDINATE (a pose the checks below can compute with)."""
    return bool((np.abs(t) <= MAX_COORDINATE).all())


def _points_seen(scene: ColmapScene) -> list[tuple[object, int]]:
    """(view, number of points3D in front of its camera and inside its image), pinhole projection with the
    model's intrinsics (distortion ignored: a count, not a measurement)."""
    xyz = scene.points_xyz
    out: list[tuple[object, int]] = []
    if len(xyz) == 0:
        return out
    for v in scene.views:
        cam = scene.cameras.get(v.camera_id)
        if cam is None or not (finite(v.R) and _in_range(v.t)):
            continue
        pc = xyz @ v.R.T + v.t
        z = pc[:, 2]
        front = z > 1e-9
        K = cam.K
        u = K[0, 0] * pc[front, 0] / z[front] + K[0, 2]
        w = K[1, 1] * pc[front, 1] / z[front] + K[1, 2]
        inside = (u >= 0) & (u <= cam.width) & (w >= 0) & (w <= cam.height)
        out.append((v, int(inside.sum())))
    return out


def _decode_error(path: Path) -> str | None:
    """The one-line message of an image that cannot be decoded, else None."""
    from jsgs.base.images import read_rgb8

    try:
        read_rgb8(path)
    except JsgsError as e:
        return str(e)
    return None


def validate_scene(
    root: str | Path, decode: bool = False, analyze: bool = False, test_every: int | None = None
) -> ValidationReport:
    """Load ``root`` and check everything listed in the module docstring. Never raises for a bad scene.
    ``decode``: also decode every registered image (:func:`jsgs.base.images.read_rgb8`, what ``compress`` and
    the trainer do), so a truncated file or one over the pixel limit is reported here first. ``analyze``:
    warn about JPEG views compressed twice (:mod:`jsgstools.dqt.analysis`). ``test_every``: warn when that
    split would leave no training view."""
    root = Path(root)
    report = ValidationReport(root=root, scene=None)
    try:
        scene = load_colmap_scene(root)
    except JsgsError as e:
        report.problems.append(Problem("model", str(e)))
        return report
    report.scene = scene
    _check_cameras(scene, report)
    _check_names(scene, report)
    _check_views(scene, report, decode)
    _check_sizes(scene, report)
    _check_record(scene, report)
    if (w := orientation_warning(scene)) is not None:
        report.warnings.append(w)
    if analyze:
        report.warnings += _double_compression_warnings(scene)
    report.warnings += _left_out_warnings(scene)
    if (w := world_warning(scene)) is not None:
        report.warnings.append(w)
    if test_every is not None and (w := _split_warning(scene, test_every)) is not None:
        report.warnings.append(w)
    _check_points(scene, report)
    return report


def _check_cameras(scene: ColmapScene, report: ValidationReport) -> None:
    """Camera models: a distorted one compress can undistort is a warning, any other non-pinhole one a
    problem. (Size, finite positive focals, principal point and distortion are checked when the model is
    read: jsgstools.colmap_check; a model failing them is a "model" problem.)"""
    for cid, cam in sorted(scene.cameras.items()):
        where = f"{scene.rel(scene.model_dir)}: camera {cid}"
        if cam.model in UNDISTORTABLE_MODELS:
            jpeg_only = (
                "a JPEG-only scene trains as it is, on the photos' own grid"
                if cam.model in DISTORTION_MODELS
                else "a JPEG-only scene cannot train with it (the trainer renders "
                f"{', '.join(DISTORTION_MODELS)}): model the camera as OPENCV "
                "(jsgstools sfm --camera-model OPENCV)"
            )
            report.warnings.append(
                f"{where}: {cam.model} with distortion {list(cam.distortion)}: compress undistorts it to "
                f"PINHOLE before encoding; {jpeg_only}"
            )
        elif cam.model not in PINHOLE_MODELS:
            report.problems.append(
                Problem(
                    "camera_model",
                    f"{where}: camera model {cam.model} is not supported (supported: "
                    f"{', '.join(PINHOLE_MODELS)}; undistorted by compress: "
                    f"{', '.join(UNDISTORTABLE_MODELS)})",
                )
            )


def _check_names(scene: ColmapScene, report: ValidationReport) -> None:
    """Image names used twice, images without a pose (a warning), no registered image."""
    for name, ids in sorted(scene.duplicate_names.items()):
        report.problems.append(
            Problem(
                "names",
                f"{scene.rel(scene.model_dir)}: image name {name!r} is used by "
                f"{len(ids)} images (ids {', '.join(map(str, ids))})",
            )
        )
    if scene.unregistered:
        report.warnings.append(
            f"{scene.rel(scene.model_dir)}: {len(scene.unregistered)} image(s) without a pose "
            f"are ignored (e.g. {scene.unregistered[0]})"
        )
    if not scene.views:
        report.problems.append(Problem("model", f"{scene.rel(scene.model_dir)}: no registered images"))


def _check_views(scene: ColmapScene, report: ValidationReport, decode: bool) -> None:
    """The images folder, and each registered image's camera, pose and file."""
    have_images = scene.images_dir.is_dir()
    if not have_images:
        report.problems.append(Problem("images", f"{scene.images_dir}: images folder not found"))
    for v in scene.views:
        report.problems.extend(_view_model_problems(scene, v))
        if have_images and (problem := _view_file_problem(scene, v, decode)) is not None:
            report.problems.append(problem)


def _view_model_problems(scene: ColmapScene, v: ColmapView) -> list[Problem]:
    """A view's camera missing from the model; its pose not finite, or beyond the coordinate limit."""
    out = []
    if v.camera_id not in scene.cameras:
        out.append(
            Problem(
                "camera",
                f"{scene.rel(scene.model_dir)}: image {v.name!r} uses camera "
                f"{v.camera_id}, which is not in the model",
            )
        )
    if not (finite(v.R) and finite(v.t)):
        out.append(
            Problem(
                "pose",
                f"{scene.rel(scene.model_dir)}: image {v.name!r} has a non-finite pose "
                f"(R={v.R.tolist()}, t={v.t.tolist()})",
            )
        )
    elif not _in_range(v.t):
        out.append(
            Problem(
                "pose",
                f"{scene.rel(scene.model_dir)}: image {v.name!r}: its translation {v.t.tolist()} lies "
                f"beyond ±{MAX_COORDINATE:g}",
            )
        )
    return out


def _view_file_problem(scene: ColmapScene, v: ColmapView, decode: bool) -> Problem | None:
    """A view's image file missing, unreadable, not decodable (with ``decode``) or in a format not used."""
    if v.path is None:
        return Problem(
            "image",
            f"{scene.rel(scene.images_dir / v.name)}: registered image not found "
            "(nor a unique file with the same stem)",
        )
    if v.read_error is not None:
        return Problem("image", f"{scene.rel(v.path)}: {v.read_error}")
    if decode and (err := _decode_error(v.path)) is not None:
        return Problem("image", err)
    if v.format not in JPEG_FORMATS + LOSSLESS_FORMATS:
        return Problem(
            "image",
            f"{scene.rel(v.path)}: format {v.format} is not supported "
            f"(JPEG, or lossless {', '.join(LOSSLESS_FORMATS)})",
        )
    return None


def _check_sizes(scene: ColmapScene, report: ValidationReport) -> None:
    """One downscale factor for the scene (recorded in the report), one image size per camera."""
    ds = detect_downscale(scene)
    report.downscale = ds.factor
    by_name = {v.name: v for v in scene.views}
    for name, msg in ds.problems:
        v = by_name[name]
        report.problems.append(Problem("size", f"{scene.rel(v.path) if v.path else name}: {msg}"))
    per_cam: dict[int, set[tuple[int, int]]] = defaultdict(set)
    flagged = {name for name, _ in ds.problems}  # already reported once
    for v in scene.views:
        if v.size is not None and v.name not in flagged:
            per_cam[v.camera_id].add(v.size)
    for cid, sizes in sorted(per_cam.items()):
        if len(sizes) > 1:
            report.problems.append(
                Problem(
                    "size",
                    f"{scene.rel(scene.model_dir)}: camera {cid} is shared by images of "
                    f"different sizes ({', '.join(f'{w}x{h}' for w, h in sorted(sizes))})",
                )
            )


def _check_record(scene: ColmapScene, report: ValidationReport) -> None:
    """The record of a dataset made by compress (``compress.json``), when there is one, can be read."""
    record = scene.root / "compress.json"
    if record.is_file():
        import json

        try:
            rec = json.loads(record.read_text())
            if not isinstance(rec["settings"]["test_every"], int) or any(
                v["split"] not in ("train", "test") for v in rec["views"]
            ):
                raise ValueError("settings.test_every or a view's split is not what compress writes")
        except (OSError, ValueError, KeyError, TypeError, RecursionError) as e:
            report.problems.append(
                Problem("record", f"{scene.rel(record)}: unreadable ({type(e).__name__}: {e})")
            )


def _left_out_warnings(scene: ColmapScene) -> list[str]:
    """What the model leaves out: image files it does not use, other models under ``sparse/``."""
    out = []
    if scene.unused_files:
        names = ", ".join(scene.unused_files[:8]) + (" ..." if len(scene.unused_files) > 8 else "")
        out.append(
            f"{scene.rel(scene.images_dir)}: {len(scene.unused_files)} image file(s) not in the model (not "
            f"registered; no tool uses them): {names}"
        )
    for other in scene.other_models:
        out.append(
            f"{scene.rel(scene.root / other)}: another COLMAP model (every tool reads "
            f"{scene.rel(scene.model_dir)} only)"
        )
    return out


def world_warning(scene: ColmapScene) -> str | None:
    """Cameras that the trainer's world normalisation refuses (only one, all at one position, up directions
    that cancel out, most at their focus point), in one line naming the model, else None."""
    w2c = [np.block([[v.R, v.t[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]) for v in scene.views
           if finite(v.R) and _in_range(v.t)]  # fmt: skip
    if not w2c:
        return None
    with np.errstate(all="ignore"):
        c2w = np.stack([np.linalg.inv(m) for m in w2c])  # the poses the trainer computes
        lone = len(c2w) == 1 < len(scene.views)  # the others' poses are broken: problems of their own
        why = (None if lone else coincidence(c2w)) or normalization_refusal(c2w)
    if why is None:
        return None
    return (
        f"{scene.rel(scene.model_dir)}: {why}: jsgs train refuses the scene unless scene.normalize_world is "
        "false"
    )


def split_warning(
    where: str, n_views: int, n_train: int, test_every: int | None, record: str | None = None
) -> str | None:
    """One line when a split leaves no training view (one view, or ``--test-every 1``): jsgs train refuses
    such a manifest (and says this line); else None. The one wording of that advice for jsgstools validate,
    jsgstools manifest and jsgs train. ``record``: the ``compress.json`` that fixes the split of a scene
    ``jsgstools compress`` made (its test views were not compressed, so ``--test-every`` cannot change it:
    the advice is to compress a source with more views; view 0 by name is always a test view there).
    ``test_every`` None: a split that no spacing made (a manifest edited by hand)."""
    if n_train > 0 or n_views == 0:
        return None
    if record is not None:
        every = "" if test_every is None else f" (test every {test_every})"
        return (
            f"{where}: no training views: {record}{every} makes all {n_views} view(s) test views and "
            "fixes the split of a compressed scene; jsgs train needs at least one (compress a source with "
            "more views)"
        )
    larger = "; 2 or more keeps some test views" if test_every in (1, None) and n_views > 1 else ""
    why = (
        f"all {n_views} view(s) have split 'test'"
        if test_every is None
        else f"with test every {test_every}, all {n_views} view(s) are test views"
    )
    return (
        f"{where}: no training views: {why}; jsgs train needs at least one (jsgstools manifest "
        f"--test-every 0 makes every view a training view{larger})"
    )


def _split_warning(scene: ColmapScene, test_every: int) -> str | None:
    """:func:`split_warning` for the split ``jsgstools manifest --test-every`` would make (a compressed
    scene's: its record's, which ``_check_record`` checks)."""
    import json

    n, record = len(scene.views), scene.root / "compress.json"
    try:
        rec = json.loads(record.read_text())
        n_train, test_every = sum(v["split"] == "train" for v in rec["views"]), rec["settings"]["test_every"]
    except FileNotFoundError:
        n_train = n - (len(range(0, n, test_every)) if test_every > 0 else 0)
        return split_warning(scene.rel(scene.model_dir), n, n_train, test_every)
    except (OSError, ValueError, KeyError, TypeError, RecursionError):
        return None  # a problem of its own
    return split_warning(scene.rel(scene.model_dir), n, n_train, test_every, scene.rel(record))


def _check_points(scene: ColmapScene, report: ValidationReport) -> None:
    """Cameras that see none of the points3D (a warning each); no points3D at all."""
    for v, n in _points_seen(scene):
        if n == 0:
            report.warnings.append(
                f"{scene.rel(v.path) if v.path else v.name}: its camera sees none of the "
                f"{len(scene.points_xyz)} points3D (a pose or a camera that does not belong to this model?)"
            )
    if len(scene.points_xyz) == 0:
        report.problems.append(
            Problem(
                "points", f"{scene.rel(scene.model_dir)}: points3D is empty (the trainer initializes from it)"
            )
        )


def require_valid(root: str | Path, allow: tuple[str, ...] = ()) -> ValidationReport:
    """Validate and raise one JsgsError (one line) when any problem outside ``allow`` remains."""
    report = validate_scene(root)
    bad = report.blocking(allow)
    if bad:
        more = (
            f" (and {len(bad) - 1} more; run `jsgstools validate {root}` for the list)"
            if len(bad) > 1
            else ""
        )
        raise JsgsError(f"{bad[0].message}{more}")
    return report
