"""COLMAP binary models checked for what they claim, before pycolmap reads them (pycolmap reads past the end
of a truncated ``cameras.bin`` silently and fails on a truncated ``images.bin`` with ``std::bad_alloc``,
naming no file), and the cameras and points checked for plausibility.

The binary layouts (COLMAP's ``src/colmap/scene/reconstruction_io.cc``), little-endian:

- ``cameras.bin``: uint64 count; per camera int32 id, int32 model id, uint64 width, uint64 height,
  float64 params[the model's count];
- ``images.bin``: uint64 count; per image int32 id, float64 qvec[4], float64 tvec[3], int32 camera id, the
  name (bytes up to a NUL), uint64 n, then n x (float64 x, float64 y, int64 point3D id);
- ``points3D.bin``: uint64 count; per point uint64 id, float64 xyz[3], uint8 rgb[3], float64 error, uint64
  track length n, then n x (int32 image id, int32 point2D index).

Every record must end inside the file and the last one exactly at its end; a file shorter or longer than
its records is a JsgsError (one line) naming the file and the record.
"""

from __future__ import annotations

import functools
import math
import struct
from pathlib import Path

import numpy as np

from jsgs.base.errors import JsgsError
from jsgs.base.limits import MAX_COORDINATE, MAX_FOCAL_RATIO, MAX_IMAGE_SIDE, MIN_FOCAL_RATIO

#: the largest |coefficient| of a radial or tangential distortion term taken as a real lens
MAX_DISTORTION = 10.0


@functools.cache
def camera_models() -> dict[int, tuple[str, int, list[int], list[int], list[int]]]:
    """COLMAP camera model id -> (name, number of parameters, focal / principal point / extra parameter
    indices), from pycolmap itself."""
    import pycolmap

    out = {}
    for name, m in pycolmap.CameraModelId.__members__.items():
        if int(m.value) < 0:
            continue
        try:
            cam = pycolmap.Camera.create_from_model_name(1, name, 1.0, 2, 2)
        except Exception:  # noqa: BLE001 - a model this pycolmap cannot build is simply not accepted
            continue
        out[int(m.value)] = (
            name, len(cam.params), list(cam.focal_length_idxs()), list(cam.principal_point_idxs()),
            list(cam.extra_params_idxs()),
        )  # fmt: skip
    return out


class _Reader:
    def __init__(self, path: Path):
        from jsgs.base.io import read_regular_bytes

        self.path = path
        self.data = read_regular_bytes(path)
        self.pos = 0

    def take(self, fmt: str, what: str) -> tuple:
        n = struct.calcsize(fmt)
        if self.pos + n > len(self.data):
            raise JsgsError(
                f"{self.path}: truncated: {what} runs past the end of the file (to byte {self.pos + n} of "
                f"{len(self.data)})"
            )
        out = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += n
        return out

    def skip(self, n: int, what: str) -> None:
        if self.pos + n > len(self.data):
            raise JsgsError(
                f"{self.path}: truncated: {what} runs past the end of the file (to byte {self.pos + n} of "
                f"{len(self.data)})"
            )
        self.pos += n

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise JsgsError(f"{self.path}: truncated: {what} has no end (no NUL before the end of the file)")
        raw = self.data[self.pos : end]
        self.pos = end + 1
        return raw.decode("utf-8", "replace")

    def count(self, what: str, per_item_min: int) -> int:
        (n,) = self.take("<Q", f"the {what} count")
        left = len(self.data) - self.pos
        if n * per_item_min > left:
            raise JsgsError(
                f"{self.path}: declares {n} {what} but holds {left} bytes after the count (at least "
                f"{per_item_min} per record): truncated or not a COLMAP {self.path.name}"
            )
        return n

    def end(self, what: str) -> None:
        extra = len(self.data) - self.pos
        if extra:
            raise JsgsError(f"{self.path}: {extra} bytes after the last of its {what} (not a COLMAP model)")


def check_cameras_bin(path: Path) -> None:
    """Structure of ``cameras.bin`` and plausibility of each camera (JsgsError naming the camera)."""
    models = camera_models()
    r = _Reader(path)
    n = r.count("cameras", 24)
    for k in range(n):
        cid, model, w, h = r.take("<iiQQ", f"camera record {k + 1} of {n}")
        if model not in models:
            raise JsgsError(f"{path}: camera {cid}: unknown camera model id {model}")
        params = r.take(f"<{models[model][1]}d", f"the parameters of camera {cid}")
        check_camera(path, cid, models[model][0], int(w), int(h), params)
    r.end("cameras")


def check_camera(path: Path, cid: int, model: str, w: int, h: int, params: tuple[float, ...]) -> None:
    """Finite positive focal lengths, the principal point inside the image, |distortion| ≤ MAX_DISTORTION
    for the models with radial and tangential terms."""
    where = f"{path}: camera {cid} ({model} {w}x{h})"
    if w < 1 or h < 1:
        raise JsgsError(f"{where}: the image size must be positive")
    if max(w, h) > MAX_IMAGE_SIDE:
        raise JsgsError(f"{where}: the image size exceeds {MAX_IMAGE_SIDE} pixels a side")
    if not all(math.isfinite(p) for p in params):
        raise JsgsError(f"{where}: a parameter is not finite ({list(params)})")
    info = {name: (fi, pi, ei) for name, _, fi, pi, ei in camera_models().values()}
    if model not in info:
        raise JsgsError(f"{where}: unknown camera model")
    fi, pi, ei = info[model]
    focal = [params[i] for i in fi]
    if any(f <= 0 for f in focal):
        raise JsgsError(f"{where}: focal length {focal} is not positive")
    side = max(w, h)
    if any(not MIN_FOCAL_RATIO * side <= f <= MAX_FOCAL_RATIO * side for f in focal):
        raise JsgsError(
            f"{where}: focal length {focal} px is outside [{MIN_FOCAL_RATIO:g}, {MAX_FOCAL_RATIO:g}] x the "
            f"image's longer side"
        )
    if len(pi) == 2:
        cx, cy = params[pi[0]], params[pi[1]]
        if not (0.0 <= cx <= w and 0.0 <= cy <= h):
            raise JsgsError(f"{where}: principal point ({cx:g}, {cy:g}) is outside the image")
    dist = [params[i] for i in ei]
    if model in ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE") and any(
        abs(d) > MAX_DISTORTION for d in dist
    ):
        raise JsgsError(f"{where}: distortion {dist} is implausible (a term beyond ±{MAX_DISTORTION:g})")


def check_images_bin(path: Path) -> None:
    r = _Reader(path)
    n = r.count("images", 64 + 1 + 8)
    for k in range(n):
        (iid, *_) = r.take("<i7di", f"image record {k + 1} of {n}")
        r.name(f"the name of image {iid}")
        (m,) = r.take("<Q", f"the 2D point count of image {iid}")
        r.skip(24 * m, f"the {m} 2D points of image {iid}")
    r.end("images")


def check_points_bin(path: Path) -> None:
    r = _Reader(path)
    n = r.count("points", 43 + 8)
    bad = 0
    for k in range(n):
        pid, x, y, z, *_rest = r.take("<Q3d3Bd", f"point record {k + 1} of {n}")
        if not (abs(x) <= MAX_COORDINATE and abs(y) <= MAX_COORDINATE and abs(z) <= MAX_COORDINATE):
            bad += 1
            if bad == 1:
                first = pid
        (m,) = r.take("<Q", f"the track length of point {pid}")
        r.skip(8 * m, f"the {m}-long track of point {pid}")
    r.end("points")
    if bad:
        raise JsgsError(
            f"{path}: {bad} point(s) with non-finite coordinates or beyond ±{MAX_COORDINATE:g} (the first: "
            f"point {first})"
        )


def check_binary_model(model_dir: Path) -> None:
    """All three files of a binary model (see the module docstring)."""
    check_cameras_bin(model_dir / "cameras.bin")
    check_images_bin(model_dir / "images.bin")
    check_points_bin(model_dir / "points3D.bin")


def check_points_finite(path: Path, xyz: np.ndarray) -> None:
    """A text model's points: finite coordinates within ±MAX_COORDINATE."""
    bad = ~(np.abs(xyz) <= MAX_COORDINATE).all(axis=1)
    if bad.any():
        raise JsgsError(
            f"{path}: {int(bad.sum())} point(s) with non-finite coordinates or beyond ±{MAX_COORDINATE:g}"
        )
