"""Loading a COLMAP scene (``SCENE/sparse/0`` or ``SCENE/sparse``, binary or text, plus ``SCENE/images``) and
the camera geometry the dataset tools share: downscale-factor detection, intrinsics scaling and undistortion.

Conventions (the same as COLMAP's, and the manifest's):

- Extrinsics are world-to-camera, OpenCV axes (x right, y down, z forward): ``x_cam = R @ x_world + t``.
- Pixel coordinates follow COLMAP: the top-left *corner* of the image is (0, 0), so the centre of pixel (0, 0)
  is (0.5, 0.5) and a centred principal point is (W/2, H/2). OpenCV puts pixel centres on integers; every call
  into OpenCV below shifts by 0.5 on the way in and out.
- An image name in the model (``IMG_4026.JPG``) is found as ``images/IMG_4026.JPG`` or, failing that, as the
  only file ``images/IMG_4026.<ext>`` with the same stem: lossless copies of a capture are usually re-saved
  under another extension (``../shared/scenes`` holds ``IMG_4026.png`` for ``IMG_4026.JPG``).
"""

from __future__ import annotations

import functools
import os
import shlex
from collections.abc import Callable
from contextvars import ContextVar
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from jsgs.base.camera import Camera, Distortion
from jsgs.base.errors import JsgsError

if TYPE_CHECKING:  # pragma: no cover
    import pycolmap

#: Camera models that need no undistortion.
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
#: Distorted models that ``compress`` undistorts to PINHOLE with OpenCV (same formulas, same parameter order).
UNDISTORTABLE_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
#: Image formats read by the tools. JPEG is the observed (lossy) format; the others are lossless.
LOSSLESS_FORMATS = ("PNG", "BMP", "PPM")
JPEG_FORMATS = ("JPEG", "MPO")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".ppm")

# A downscale factor this close to an integer is that integer (4000 px / 1333 px = 3.0008 is a factor of 3).
_FACTOR_SNAP = 5e-3


@dataclass(frozen=True)
class ColmapCamera:
    """A camera of a COLMAP model: its id and its intrinsics (:class:`jsgs.base.camera.Camera`), which
    ``params`` gives as COLMAP's parameter vector for ``model`` (pixels for focal lengths and principal point,
    COLMAP pixel convention; distortion coefficients are dimensionless)."""

    camera_id: int
    camera: Camera

    @classmethod
    def from_params(
        cls, camera_id: int, model: str, width: int, height: int, params: tuple[float, ...]
    ) -> ColmapCamera:
        """The camera COLMAP records as ``model`` with ``params`` (a model with one focal length gives it as
        ``fx`` and ``fy``; a model with distortion parameters keeps them, zeros included)."""
        focal, (ix, iy), extra = _param_indices(model)
        p = [float(v) for v in params]
        fx, fy = p[focal[0]], p[focal[-1]]
        dist = Distortion(model, tuple(p[i] for i in extra)) if extra else None
        return cls(camera_id, Camera(model, width, height, fx, fy, p[ix], p[iy], dist))

    @property
    def model(self) -> str:
        return self.camera.model

    @property
    def width(self) -> int:
        return self.camera.width

    @property
    def height(self) -> int:
        return self.camera.height

    @property
    def params(self) -> tuple[float, ...]:
        """COLMAP's parameter vector of ``model``."""
        c = self.camera
        focal, (ix, iy), extra = _param_indices(c.model)
        dist = (0.0,) * len(extra) if c.distortion is None else c.distortion.params
        if len(dist) != len(extra):
            raise ValueError(f"{c.model}: {len(extra)} distortion parameters, not {len(dist)}")
        p = [0.0] * (len(focal) + 2 + len(extra))
        p[focal[0]], p[focal[-1]] = (c.fx, c.fy) if len(focal) > 1 else (c.fx, c.fx)
        p[ix], p[iy] = c.cx, c.cy
        for i, v in zip(extra, dist, strict=True):
            p[i] = float(v)
        return tuple(p)

    @property
    def is_pinhole(self) -> bool:
        return self.model in PINHOLE_MODELS

    @property
    def focal(self) -> tuple[float, float]:
        """(fx, fy) in pixels; models with one focal length give it twice."""
        return self.camera.fx, self.camera.fy

    @property
    def principal_point(self) -> tuple[float, float]:
        """(cx, cy) in pixels, COLMAP convention."""
        return self.camera.cx, self.camera.cy

    @property
    def distortion(self) -> tuple[float, ...]:
        """The model's extra (distortion) parameters, in COLMAP's order; empty for pinhole models."""
        return () if self.camera.distortion is None else self.camera.distortion.params

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix, COLMAP pixel convention."""
        return self.camera.K

    def scaled(self, width: int, height: int) -> ColmapCamera:
        """This camera for an image resized to ``width`` x ``height``: the same as COLMAP's
        ``Camera::Rescale`` (focal lengths and principal point times width/height ratios; a single focal
        length times their mean; distortion unchanged because it acts on normalized coordinates)."""
        if (width, height) == (self.width, self.height):
            return self
        c = self.camera
        sx, sy = width / c.width, height / c.height
        focal, _, _ = _param_indices(c.model)
        fx, fy = (c.fx * ((sx + sy) / 2),) * 2 if len(focal) == 1 else (c.fx * sx, c.fy * sy)
        cam = replace(c, width=width, height=height, fx=fx, fy=fy, cx=c.cx * sx, cy=c.cy * sy)
        return replace(self, camera=cam)

    def as_pinhole(self) -> ColmapCamera:
        """The same intrinsics as a PINHOLE camera; only for models without distortion."""
        if not self.is_pinhole:
            raise ValueError(f"camera {self.camera_id} ({self.model}) is distorted")
        return replace(self, camera=replace(self.camera, model="PINHOLE", distortion=None))

    def describe(self) -> str:
        return f"{self.model} {self.width}x{self.height}"


@functools.cache
def _param_indices(model: str) -> tuple[tuple[int, ...], tuple[int, int], tuple[int, ...]]:
    """Where COLMAP's parameter vector of ``model`` holds the focal length(s), the principal point and the
    extra (distortion) parameters (pycolmap's tables)."""
    import pycolmap

    cam = pycolmap.Camera.create_from_model_name(0, model, 1.0, 1, 1)
    ix, iy = cam.principal_point_idxs()
    focal = tuple(int(i) for i in cam.focal_length_idxs())
    return focal, (int(ix), int(iy)), tuple(int(i) for i in cam.extra_params_idxs())


@dataclass(frozen=True)
class ColmapView:
    """One registered image of the model and the file that holds it."""

    image_id: int
    name: str
    camera_id: int
    R: np.ndarray  # (3, 3) world-to-camera rotation
    t: np.ndarray  # (3,) world-to-camera translation
    path: Path | None  # the image file; None when not found
    size: tuple[int, int] | None  # (width, height) of the file in pixels; None when missing or unreadable
    format: str | None  # Pillow's format name ("PNG", "JPEG", ...)
    read_error: str | None = None  # why the file could not be opened
    orientation: int = 1  # EXIF Orientation tag (1: as stored; every tool uses the stored pixels, as COLMAP)


@dataclass
class ColmapScene:
    """A COLMAP model with its image files. ``views`` are the registered images sorted by name (Python string
    order), which is the order the train/test split counts in."""

    root: Path
    model_dir: Path
    model_format: str  # "binary" | "text"
    images_dir: Path
    cameras: dict[int, ColmapCamera]
    views: list[ColmapView]
    unregistered: list[str]
    points_xyz: np.ndarray  # (N, 3) float64, world coordinates
    points_rgb: np.ndarray  # (N, 3) uint8
    duplicate_names: dict[str, list[int]] = field(default_factory=dict)  # name -> image ids, when repeated
    reconstruction: Any = None  # the pycolmap.Reconstruction it was read from
    #: image files under images/ that no registered view of the model uses (photos SfM could not register)
    unused_files: list[str] = field(default_factory=list)
    #: other model folders under sparse/ (pycolmap writes one per disconnected reconstruction)
    other_models: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return self.root.resolve().name

    def rel(self, path: Path) -> str:
        """``path`` as shown to the user: paths are built on ``root`` as the user gave it, so they read the
        same way (``data/images/x.png``)."""
        return str(path)


def find_model_dir(root: Path) -> tuple[Path, str]:
    """The COLMAP model folder of a scene and its format: ``sparse/0`` first, then ``sparse``; binary
    (``cameras.bin``, ``images.bin``, ``points3D.bin``) or text (``.txt``). Raises JsgsError naming what was
    looked for."""
    from jsgs.base.io import not_regular

    if not root.is_dir():
        raise JsgsError(f"{root}: not a folder")
    broken = None  # the first model whose three files are all there but one is no regular file
    for sub in ("sparse/0", "sparse"):
        d = root / sub
        for fmt, ext in (("binary", ".bin"), ("text", ".txt")):
            files = [d / f"{n}{ext}" for n in ("cameras", "images", "points3D")]
            if all(p.is_file() for p in files):
                return d, fmt
            if broken is None and all(os.path.lexists(p) for p in files):
                broken = next((f"{p}: {why}" for p in files if (why := not_regular(p)) is not None), None)
    if broken is not None:
        raise JsgsError(f"{broken}; a COLMAP model needs cameras, images and points3D as regular files")
    raise JsgsError(
        f"{root}: no COLMAP model (looked for cameras, images and points3D .bin or .txt in sparse/0/ and "
        f"sparse/); for a folder of photos, make one with "
        f"`jsgstools sfm {shlex.quote(str(root))} --out SCENE`"
    )


def read_reconstruction(model_dir: Path) -> pycolmap.Reconstruction:
    import pycolmap

    from jsgs.base.io import refuse_non_regular

    for name in ("cameras", "images", "points3D", "rigs", "frames"):
        for ext in (".bin", ".txt"):
            refuse_non_regular(model_dir / (name + ext))  # pycolmap would wait on a FIFO forever
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises ValueError/RuntimeError with a C++ check message
        msg = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
        raise JsgsError(f"{model_dir}: cannot read the COLMAP model: {msg}") from None


def resolve_image(images_dir: Path, name: str) -> Path | None:
    """The file holding model image ``name``: the exact name, else the only same-stem file with a known
    image extension (case-insensitive). None when there is none or several."""
    exact = images_dir / name
    if exact.exists() and not exact.is_dir():  # a FIFO or device too: reading it then says what it is
        return exact
    rel = Path(name)
    folder = images_dir / rel.parent
    if not folder.is_dir():
        return None
    stem = rel.stem if rel.suffix else rel.name
    hits = [
        p
        for p in folder.glob(_glob_escape(stem) + ".*")
        if p.stem == stem and p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
    ]
    return hits[0] if len(hits) == 1 else None


def _glob_escape(s: str) -> str:
    return "".join(f"[{c}]" if c in "*?[]" else c for c in s)


def image_stem(name: str) -> str:
    """Model image name without its extension, sub-folders kept (``a/IMG_1.JPG`` -> ``a/IMG_1``)."""
    rel = Path(name)
    return (rel.parent / rel.stem).as_posix() if rel.suffix else rel.as_posix()


def _probe_image(path: Path) -> tuple[tuple[int, int] | None, str | None, str | None, int]:
    """(size, format, error, EXIF orientation) from the file header; Pillow opens lazily, so no pixels are
    decoded."""
    from PIL import Image, UnidentifiedImageError

    from jsgs.base.images import ENV_MAX_PIXELS, apply_pixel_limit
    from jsgs.base.io import open_regular

    apply_pixel_limit()
    try:
        with open_regular(path) as f, Image.open(f) as im:
            try:
                orientation = int(im.getexif().get(0x0112, 1) or 1)
            except Exception:  # noqa: BLE001 - a broken EXIF block is not the image's problem here
                orientation = 1
            return (int(im.width), int(im.height)), str(im.format), None, orientation
    except Image.DecompressionBombError as e:
        return None, None, f"exceeds the pixel limit ({e}); raise it with ${ENV_MAX_PIXELS}", 1
    except JsgsError as e:  # not a regular file
        return None, None, str(e).removeprefix(f"{path}: "), 1
    except UnidentifiedImageError:
        why = _jpeg_reason(path) or "Pillow cannot identify its format"
        return None, None, f"cannot read image: {why}", 1
    except (OSError, ValueError) as e:
        return None, None, f"cannot read image: {_jpeg_reason(path) or e}", 1


def _jpeg_reason(path: Path) -> str | None:
    """Why Pillow cannot open ``path``, when it starts as a JPEG: what its header says that Pillow's decoder
    does not take (12-bit samples, two components), or the header's own defect in the header parser's words
    (a truncated header: Pillow says "Truncated File Read"). None otherwise."""
    from jsgstools.dqt import read_header

    try:
        with path.open("rb") as f:
            is_jpeg = f.read(2) == b"\xff\xd8"
        if is_jpeg:
            h = read_header(path)
            if h.sample_precision != 8:
                return (
                    f"a {h.sample_precision}-bit JPEG ({h.frame_name}, {h.sof}): Pillow decodes 8-bit JPEGs "
                    "only; save it again as an 8-bit JPEG"
                )
            if len(h.components) == 2:
                return "a JPEG with 2 components: Pillow decodes 1, 3 or 4"
    except JsgsError as e:
        return f"a damaged JPEG: {str(e).removeprefix(f'{path}: ')}"
    except OSError:
        pass
    return None


def load_colmap_scene(root: str | Path, images: str = "images") -> ColmapScene:
    """Read the model and probe every registered image's file (header only). Raises JsgsError only when
    the model cannot be found or read; every other defect is left for :mod:`jsgstools.validate`."""
    from jsgstools.colmap_check import check_binary_model, check_camera, check_points_finite

    root = Path(root)
    model_dir, fmt = find_model_dir(root)
    if fmt == "binary":  # read to their declared end before pycolmap sees them
        check_binary_model(model_dir)
    rec = read_reconstruction(model_dir)
    if fmt == "text":
        for cid, c in rec.cameras.items():
            params = tuple(float(v) for v in c.params)
            size = (int(c.width), int(c.height))
            check_camera(model_dir / "cameras.txt", int(cid), str(c.model_name), *size, params)
    cameras = {
        int(cid): ColmapCamera.from_params(
            int(cid), str(c.model_name), int(c.width), int(c.height), tuple(float(v) for v in c.params)
        )
        for cid, c in rec.cameras.items()
    }
    images_dir = root / images
    have_dir = images_dir.is_dir()
    views: list[ColmapView] = []
    unregistered: list[str] = []
    by_name: dict[str, list[int]] = {}
    for iid, im in rec.images.items():
        by_name.setdefault(str(im.name), []).append(int(iid))
        if not im.has_pose:
            unregistered.append(str(im.name))
            continue
        pose = im.cam_from_world()
        R = np.asarray(pose.rotation.matrix(), dtype=np.float64)
        t = np.asarray(pose.translation, dtype=np.float64).reshape(3)
        path = resolve_image(images_dir, str(im.name)) if have_dir else None
        size = fmt_name = err = None
        orientation = 1
        if path is not None:
            size, fmt_name, err, orientation = _probe_image(path)
        views.append(
            ColmapView(
                int(iid), str(im.name), int(im.camera_id), R, t, path, size, fmt_name, err, orientation
            )
        )
    views.sort(key=lambda v: (v.name, v.image_id))
    n = len(rec.points3D)
    xyz = np.zeros((n, 3), dtype=np.float64)
    rgb = np.zeros((n, 3), dtype=np.uint8)
    for i, pid in enumerate(sorted(rec.points3D)):
        p = rec.points3D[pid]
        xyz[i] = p.xyz
        rgb[i] = p.color
    if fmt == "text":
        check_points_finite(model_dir / "points3D.txt", xyz)
    used = {v.path.resolve() for v in views if v.path is not None}
    unused = (
        sorted(
            p.relative_to(images_dir).as_posix()
            for p in images_dir.rglob("*")
            if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS and p.resolve() not in used
        )
        if have_dir
        else []
    )
    others = []
    if (root / "sparse").is_dir():
        for d in sorted((root / "sparse").iterdir()):
            if not d.is_dir() or d.resolve() == model_dir.resolve():
                continue
            if any((d / f"cameras{ext}").is_file() for ext in (".bin", ".txt")):
                others.append(d.relative_to(root).as_posix())
    return ColmapScene(
        unused_files=unused,
        other_models=others,
        root=root,
        model_dir=model_dir,
        model_format=fmt,
        images_dir=images_dir,
        cameras=cameras,
        views=views,
        unregistered=sorted(unregistered),
        points_xyz=xyz,
        points_rgb=rgb,
        duplicate_names={k: sorted(v) for k, v in by_name.items() if len(v) > 1},
        reconstruction=rec,
    )


# ----------------------------------------------------------------------------------------------------
# Downscale factor


@dataclass(frozen=True)
class Downscale:
    """The one factor between the COLMAP cameras and the image files (camera size / file size), and the
    per-view problems that contradict it (``(view name, message)``)."""

    factor: float | None  # None when no image could be measured
    problems: tuple[tuple[str, str], ...]


def _snap(f: float) -> float:
    r = round(f)
    return float(r) if r >= 1 and abs(f - r) <= _FACTOR_SNAP * r else f


def detect_downscale(scene: ColmapScene) -> Downscale:
    """Find the factor F with file size = camera size / F for every view.

    Rule: each view's own factor is camera width / file width, and its file height must be camera height /
    that factor to within one pixel (rounding of the resize) — otherwise its size does not match its camera at
    all. The scene's factor is the median of the views' factors, snapped to an integer when within 0.5 % of
    one; every view must match it to within one pixel in both directions. Views whose camera is unknown or
    whose file is missing are skipped here (they are reported elsewhere)."""
    measured: list[tuple[ColmapView, ColmapCamera, float]] = []
    problems: list[tuple[str, str]] = []
    for v in scene.views:
        cam = scene.cameras.get(v.camera_id)
        if cam is None or v.size is None:
            continue
        w, h = v.size
        fw = cam.width / w
        if abs(cam.height / fw - h) > 1.0:
            turned = abs(cam.height / (cam.width / h) - w) <= 1.0
            hint = (
                f"; rotated by 90° it would match (EXIF Orientation {v.orientation}: the tools use the "
                "stored pixels, as COLMAP does; store the photo upright, or give COLMAP the stored one)"
                if turned
                else ""
            )
            problems.append(
                (
                    v.name,
                    f"size {w}x{h} does not match its camera {v.camera_id} "
                    f"({cam.width}x{cam.height}) at any one factor (width ratio {cam.width / w:.4g}, "
                    f"height ratio {cam.height / h:.4g}){hint}",
                )
            )
            continue
        measured.append((v, cam, fw))
    if not measured:
        return Downscale(None, tuple(problems))
    factor = _snap(float(np.median([f for _, _, f in measured])))
    for v, cam, fw in measured:
        w, h = v.size  # type: ignore[misc]
        if abs(cam.width / factor - w) > 1.0 or abs(cam.height / factor - h) > 1.0:
            problems.append(
                (
                    v.name,
                    f"downscale factor {_snap(fw):.4g} ({w}x{h} from camera {v.camera_id} "
                    f"{cam.width}x{cam.height}) differs from the scene's {factor:.4g}",
                )
            )
    return Downscale(factor, tuple(problems))


def view_camera(scene: ColmapScene, view: ColmapView) -> ColmapCamera:
    """The view's camera scaled to the size of its file (COLMAP's rescale semantics)."""
    cam = scene.cameras[view.camera_id]
    if view.size is None:
        return cam
    return cam.scaled(*view.size)


# ----------------------------------------------------------------------------------------------------
# Undistortion (OpenCV)


def opencv_intrinsics(cam: ColmapCamera) -> tuple[np.ndarray, np.ndarray]:
    """(K, dist) for OpenCV: K with OpenCV's integer pixel centres (principal point - 0.5), and the distortion
    vector for ``cv2.initUndistortRectifyMap``/``cv2.projectPoints``. COLMAP's SIMPLE_RADIAL (k), RADIAL
    (k1, k2), OPENCV (k1, k2, p1, p2) and FULL_OPENCV (k1, k2, p1, p2, k3, k4, k5, k6) use OpenCV's formulas
    with OpenCV's coefficient order, so they map one to one."""
    K = cam.K.copy()
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    d = cam.distortion
    if cam.model in PINHOLE_MODELS:
        dist = np.zeros(4)
    elif cam.model == "SIMPLE_RADIAL":
        dist = np.array([d[0], 0.0, 0.0, 0.0])
    elif cam.model == "RADIAL":
        dist = np.array([d[0], d[1], 0.0, 0.0])
    elif cam.model in ("OPENCV", "FULL_OPENCV"):
        dist = np.array(d, dtype=np.float64)
    else:
        raise JsgsError(
            f"camera {cam.camera_id}: model {cam.model} cannot be undistorted "
            f"(supported: {', '.join(UNDISTORTABLE_MODELS)})"
        )
    return K, dist


def _source_coords(cam: ColmapCamera, new: ColmapCamera, pts: np.ndarray) -> np.ndarray:
    """Where output pixels ``pts`` ((N, 2), OpenCV convention, of pinhole ``new``) sample the distorted image
    of ``cam`` ((N, 2), OpenCV convention)."""
    import cv2

    K, dist = opencv_intrinsics(cam)
    Kn, _ = opencv_intrinsics(new)
    xn = (pts[:, 0] - Kn[0, 2]) / Kn[0, 0]
    yn = (pts[:, 1] - Kn[1, 2]) / Kn[1, 1]
    obj = np.stack([xn, yn, np.ones_like(xn)], axis=1).reshape(-1, 1, 3)
    img, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), K, dist)
    return img.reshape(-1, 2)


def _probe_points(w: int, h: int) -> np.ndarray:
    """The border pixels plus a coarse interior grid (OpenCV convention): enough to bound the sampling of a
    smooth distortion without mapping every pixel of a large image."""
    xs = np.arange(w, dtype=np.float64)
    ys = np.arange(h, dtype=np.float64)
    border = [
        np.stack([xs, np.zeros_like(xs)], 1),
        np.stack([xs, np.full_like(xs, h - 1)], 1),
        np.stack([np.zeros_like(ys), ys], 1),
        np.stack([np.full_like(ys, w - 1), ys], 1),
    ]
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 33), np.linspace(0, h - 1, 33))
    return np.concatenate(border + [np.stack([gx.ravel(), gy.ravel()], 1)])


def undistorted_camera(cam: ColmapCamera) -> tuple[ColmapCamera, float]:
    """The PINHOLE camera the undistorted image is resampled into, and its zoom.

    Choice: same image size and principal point, focal lengths times the smallest zoom ``s`` for which every
    output pixel samples inside the source image — so there are no black borders (for the usual pincushion
    k1 > 0, s > 1 and a sliver of the field of view at the edges is lost; for barrel distortion s < 1 keeps
    more of it). Pinhole models come back unchanged (as PINHOLE) with zoom 1."""
    if cam.is_pinhole:
        return cam.as_pinhole(), 1.0
    opencv_intrinsics(cam)  # raises for unsupported models
    fx, fy = cam.focal
    cx, cy = cam.principal_point
    pts = _probe_points(cam.width, cam.height)

    def pinhole(s: float) -> ColmapCamera:
        pin = replace(cam.camera, model="PINHOLE", fx=fx * s, fy=fy * s, distortion=None)
        return replace(cam, camera=pin)

    def inside(s: float) -> bool:
        src = _source_coords(cam, pinhole(s), pts)
        return bool(
            np.all(np.isfinite(src))
            and src[:, 0].min() >= 0
            and src[:, 1].min() >= 0
            and src[:, 0].max() <= cam.width - 1
            and src[:, 1].max() <= cam.height - 1
        )

    lo, hi = 0.5, 1.0
    while not inside(hi):
        lo, hi = hi, hi * 2
        if hi > 16:
            raise JsgsError(
                f"camera {cam.camera_id} ({cam.model}, distortion {cam.distortion}): "
                "cannot find a pinhole view without black borders"
            )
    if inside(lo):  # extreme barrel distortion: do not zoom out further than 2x
        hi = lo
    else:
        for _ in range(50):
            mid = (lo + hi) / 2
            lo, hi = (lo, mid) if inside(mid) else (mid, hi)
    return pinhole(hi), hi


def undistort_maps(cam: ColmapCamera, new: ColmapCamera) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (each (H, W) float32, OpenCV convention) from the distorted image of ``cam`` to the
    pinhole image of ``new`` (same size)."""
    import cv2

    K, dist = opencv_intrinsics(cam)
    Kn, _ = opencv_intrinsics(new)
    return cv2.initUndistortRectifyMap(K, dist, None, Kn, (new.width, new.height), cv2.CV_32FC1)


def undistort_image(img: np.ndarray, cam: ColmapCamera, new: ColmapCamera) -> np.ndarray:
    """Resample ``img`` ((H, W, C) uint8, taken with ``cam``) to the pinhole camera ``new``. Lanczos-4 keeps
    the high frequencies that the JPEG study is about; samples are inside the image by construction of
    ``new`` (border replication only absorbs rounding)."""
    import cv2

    if img.shape[1] != cam.width or img.shape[0] != cam.height:
        raise ValueError(f"image {img.shape[1]}x{img.shape[0]} is not camera {cam.describe()}")
    mx, my = undistort_maps(cam, new)
    return cv2.remap(img, mx, my, interpolation=cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REPLICATE)


def undistort_points(xy: np.ndarray, cam: ColmapCamera, new: ColmapCamera) -> np.ndarray:
    """Keypoints ((N, 2), COLMAP pixel convention) of ``cam`` moved to the pinhole camera ``new``: through
    OpenCV's iterative undistortion for distorted models, by the intrinsics alone for pinhole ones."""
    import cv2

    if len(xy) == 0:
        return np.zeros((0, 2))
    K, dist = opencv_intrinsics(cam)
    Kn, _ = opencv_intrinsics(new)
    pts = (np.asarray(xy, dtype=np.float64) - 0.5).reshape(-1, 1, 2)
    # COUNT + EPS, many iterations: OpenCV's default (5 iterations) leaves errors of 1e-3 px and more.
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    out = cv2.undistortPoints(pts, K, dist, None, None, Kn, crit)
    return out.reshape(-1, 2) + 0.5


def finite(a: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(a)))


def fmt_factor(f: float | None) -> str:
    if f is None:
        return "unknown"
    return str(int(f)) if float(f).is_integer() else f"{f:.4g}"


# ----------------------------------------------------------------------------------------------------
# Output folders


#: the file each writing tool leaves in its output folder; ``--force`` replaces only a folder holding its own
MARKER = ".jsgstools.json"

#: the ``format`` and ``format_version`` of :data:`MARKER` (``jsgs/schemas/output_marker.schema.json``); a
#: marker without ``format`` is the earlier form of the same record, read with the same meaning
MARKER_FORMAT = "jsgstools-output-marker"
MARKER_VERSION = 1


def marker_record(tool: str) -> dict[str, Any]:
    """The marker ``jsgstools <tool>`` writes into its output folder (:data:`MARKER`): the tool, the format,
    the version and when; checked against ``jsgs/schemas/output_marker.schema.json``."""
    import datetime

    import jsgs
    from jsgs.base.schema import validate

    doc = {
        "format": MARKER_FORMAT,
        "format_version": MARKER_VERSION,
        "tool": tool,
        "jsgstools_version": jsgs.__version__,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }
    validate(doc, "output_marker", f"the {MARKER} of jsgstools {tool}")
    return doc


def load_marker(out: Path) -> dict[str, Any] | str | None:
    """The marker of ``out`` (:data:`MARKER`): None when there is none, the record when it is valid against
    ``jsgs/schemas/output_marker.schema.json`` (the earlier form without ``format`` included), else why it is
    not, in words naming the file (a link or not a regular file, unreadable, empty, not JSON, not valid, a
    later version). Such a marker is not provably jsgstools's: callers leave the folder alone."""
    from jsgs.base.io import load_json_record

    path = out / MARKER
    if not os.path.lexists(path):
        return None
    return load_json_record(path, "output_marker", str(path), link="is a link, not a marker of jsgstools")


def read_marker(out: Path) -> str | None:
    """The tool that made ``out`` (from a valid marker, :func:`load_marker`), or None."""
    doc = load_marker(out)
    return doc["tool"] if isinstance(doc, dict) else None


#: the hidden folder inside OUT that holds an earlier output while ``--force`` writes the new one
EARLIER_PREFIX = ".jsgstools-earlier."

#: the output folders prepared inside the current call of a tool decorated with
#: :func:`removes_partial_output`: (folder, its entries, whether it kept a marker of the tool, the folder
#: holding its earlier output or None)
_PREPARED: ContextVar[list[tuple[Path, tuple[str, ...], bool, Path | None]] | None] = ContextVar(
    "_PREPARED", default=None
)

F = TypeVar("F", bound=Callable[..., Any])


def removes_partial_output(func: F) -> F:
    """For a tool that writes its folder through :func:`prepare_output_dir`: when the tool fails (an error,
    a full disk, Ctrl-C, SIGTERM), what it wrote there is removed again: its own entries (which
    :func:`prepare_output_dir` found absent or moved aside) and the marker file when the folder had none, so
    a failed command leaves no half-made dataset, nor a marker that would later claim a folder for the tool;
    an earlier output that ``--force`` moved aside is put back. When the tool succeeds, that earlier output
    is removed."""
    import shutil

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        token = _PREPARED.set([])
        try:
            result = func(*args, **kwargs)
        except BaseException:
            for out, owned, had_marker, earlier in _PREPARED.get() or []:
                _remove_written(out, owned + (() if had_marker else (MARKER,)))
                if earlier is not None:
                    _put_back(earlier, out)
            raise
        else:
            for *_, earlier in _PREPARED.get() or []:
                if earlier is not None:
                    shutil.rmtree(earlier, ignore_errors=True)
            return result
        finally:
            _PREPARED.reset(token)

    return wrapper  # type: ignore[return-value]


def _remove_written(out: Path, names: tuple[str, ...]) -> None:
    import shutil

    for name in names:
        p = out / name
        try:
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            elif p.exists() or p.is_symlink():
                p.unlink()
        except OSError:
            pass  # best effort: the failure being reported matters more


def _put_back(earlier: Path, out: Path) -> None:
    """Move the entries :func:`prepare_output_dir` moved into ``earlier`` back into ``out`` (best effort:
    what cannot move stays in ``earlier``)."""
    try:
        for p in sorted(earlier.iterdir()):
            if not os.path.lexists(out / p.name):
                os.rename(p, out / p.name)
        earlier.rmdir()
    except OSError:
        pass  # the failure being reported matters more; the earlier output is still in ``earlier``


def prepare_output_dir(
    out: Path, force: bool, owned: tuple[str, ...], protect: Path | None = None, tool: str = "compress"
) -> None:
    """Make ``out`` ready for ``jsgstools <tool>``'s output: refuse a non-empty folder unless ``force``; with
    ``force`` only a folder the same tool made (its marker file :data:`MARKER`) is accepted, and only the
    entries the tool writes (``owned``, relative names) are replaced, so nothing stale survives and nothing
    else is touched. In a tool decorated with :func:`removes_partial_output` those entries (and the marker)
    are first moved into a hidden folder ``OUT/.jsgstools-earlier.XXXXXXXX`` and removed only when the tool
    succeeds (put back when it fails; one that a killed call left is replaced with them). ``protect`` (the
    input scene) must neither contain ``out`` nor lie inside it. A marker that is not valid
    (:func:`load_marker`) is refused in one line naming it, and nothing is touched. Writes the marker."""
    import shutil
    import tempfile

    from jsgs.base.io import LOCK_NAME, write_json_atomic

    if out.exists() and not out.is_dir():
        raise JsgsError(f"{out}: exists and is not a folder")
    if protect is not None:
        a, b = out.resolve(), protect.resolve()
        if a == b or b in a.parents:
            raise JsgsError(f"{out}: is inside the input scene {protect}; the tools never write into a scene")
        if a in b.parents:
            raise JsgsError(f"{out}: contains the input scene {protect}; choose another output folder")
    prepared, earlier = _PREPARED.get(), None
    not_empty = out.is_dir() and any(p.name not in (LOCK_NAME, MARKER) for p in out.iterdir())
    if not_empty and not force:
        raise JsgsError(f"{out}: folder is not empty (use --force to replace its contents)")
    marker = load_marker(out) if out.is_dir() else None
    if isinstance(marker, str):  # never replaced: it may be anyone's, and so may the folder
        raise JsgsError(
            f"{marker}; not provably a marker of jsgstools, so {out} is left as it is "
            "(choose an empty or new folder)"
        )
    if not_empty:
        maker = marker["tool"] if marker is not None else None
        if maker != tool:
            what = f"made by jsgstools {maker}" if maker else f"not made by jsgstools (no {MARKER})"
            raise JsgsError(
                f"{out}: {what}; --force replaces only a folder that jsgstools {tool} made (choose an empty "
                "or new folder)"
            )
        if prepared is not None:  # moved aside now, removed once the tool has succeeded
            names = (*owned, MARKER, *(p.name for p in out.iterdir() if p.name.startswith(EARLIER_PREFIX)))
            try:
                earlier = Path(tempfile.mkdtemp(prefix=EARLIER_PREFIX, dir=out))
                for name in names:
                    if os.path.lexists(out / name):
                        os.rename(out / name, earlier / name)
            except OSError as e:
                if earlier is not None:
                    _put_back(earlier, out)
                raise JsgsError(f"{out}: cannot move the earlier output aside ({e.strerror or e})") from None
        else:
            for name in owned:
                p = out / name
                if p.is_dir() and not p.is_symlink():
                    shutil.rmtree(p)
                elif p.exists() or p.is_symlink():
                    p.unlink()
    out.mkdir(parents=True, exist_ok=True)
    if prepared is not None:
        prepared.append((out, owned, read_marker(out) == tool, earlier))
    write_json_atomic(out / MARKER, marker_record(tool))


def write_model_atomic(rec: pycolmap.Reconstruction, dest: Path) -> None:
    """Write ``rec`` as a binary COLMAP model into ``dest`` (e.g. ``OUT/sparse/0``) via a temporary sibling
    folder renamed into place, so a crash never leaves a partial model under the final name."""
    import shutil
    import tempfile

    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", suffix=".part", dir=dest.parent))
    try:
        rec.write_binary(str(tmp))
        if dest.is_symlink() or dest.is_file():
            dest.unlink()  # a link is replaced, never followed
        elif dest.exists():
            shutil.rmtree(dest)
        tmp.rename(dest)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
