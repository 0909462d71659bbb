"""Reading a training manifest (``jsgs/schemas/manifest.schema.json``) into typed, numpy-backed objects.

The trainer's only view of a dataset. Imports numpy, json and (lazily) jsonschema — never pycolmap, OpenCV or
Pillow — so a GPU machine needs none of the dataset tools.

Conventions: extrinsics are world-to-camera, OpenCV axes (x right, y down, z forward):
``x_cam = R @ x_world + t``. Intrinsics in pixels with COLMAP's pixel convention (the top-left corner of the
image is (0, 0), so pixel (0, 0) is centred at (0.5, 0.5)). Quantization tables 8x8 in natural row-major
order, entry [v][u]. Image paths are relative to the manifest's folder (absolute paths are taken as they are).

Every manifest is validated against the schema on read (and by ``jsgstools`` on write). The bulky ``points``
arrays are checked with a direct, equivalent test instead of element-by-element schema validation, which would
take seconds for a real scene's tens of thousands of points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from jsgs.base.camera import Camera, Distortion
from jsgs.base.errors import JsgsError
from jsgs.base.limits import MAX_COORDINATE, MAX_FOCAL_RATIO, MIN_FOCAL_RATIO, check_coordinates, parse_json


@dataclass(frozen=True)
class JpegState:
    """The JPEG state of one view, read from its file header."""

    luma_table: np.ndarray  # (8, 8) int32, natural order [v][u]
    chroma_table: np.ndarray | None  # (8, 8) int32, or None (grayscale)
    sampling: str  # "4:2:0", "4:4:4", ...
    quality: int  # closest IJG quality
    quality_exact: bool  # tables are exactly IJG's at ``quality``
    precision: int  # 8 or 16 (bits per table entry)
    frame: str | None  # "baseline", "progressive", ...
    color_space: str | None = None  # "YCbCr", "RGB", "CMYK", "YCCK", "gray" (None: not recorded)
    #: ``jsgstools manifest --analyze``: effective_luma_table / effective_chroma_table (8, 8) int32 and the
    #: verdict, or None when the manifest was written without it
    effective_luma_table: np.ndarray | None = None
    effective_chroma_table: np.ndarray | None = None
    double_compressed: bool | None = None
    #: the analysis's estimate of the view's quantisation-noise variance (8-bit units²), when recorded
    noise_variance: float | None = None
    #: the analysis's blockiness of the view's decoded luma (jsgs.jpeg.noise.blockiness), when recorded
    blockiness: float | None = None
    #: SHA-256 of the file's decoding header segments (jsgs.jpeg.header_digest) when the manifest was
    #: written; None in manifests written before it was recorded
    header_sha256: str | None = None
    #: the digest's scheme (jsgs.jpeg.header_digest.SCHEMES): 1 where the manifest records none
    header_digest_scheme: int = 1
    #: Cr's own table (8, 8) int32 when the file quantizes Cr with another table than Cb, else None
    cr_table: np.ndarray | None = None


@dataclass(frozen=True)
class ManifestView:
    """One view as the manifest records it: its files, split, camera and pose in the manifest's world."""

    name: str  # image name in the COLMAP model
    image: Path  # the observed image, resolved against the manifest's folder
    split: str  # "train" | "test"
    camera: Camera
    R: np.ndarray  # (3, 3) float64 world-to-camera rotation
    t: np.ndarray  # (3,) float64 world-to-camera translation
    jpeg: JpegState | None  # None for a lossless image
    reference: Path | None  # lossless reference, resolved; None when there is none

    @property
    def world_to_camera(self) -> np.ndarray:
        """(4, 4) float64 homogeneous world-to-camera matrix."""
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    @property
    def camera_center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates: -R^T t."""
        return -self.R.T @ self.t


@dataclass(frozen=True)
class SceneInfo:
    name: str
    source: str
    schedule: str | None
    quality: int | None
    seed: int | None
    test_every: int
    subsampling: str | None
    downscale: float | None
    undistorted: bool


@dataclass(frozen=True)
class Manifest:
    path: Path
    producer: dict[str, Any]
    scene: SceneInfo
    views: tuple[ManifestView, ...]
    points_xyz: np.ndarray  # (N, 3) float64 world coordinates
    points_rgb: np.ndarray  # (N, 3) uint8

    @property
    def train_views(self) -> tuple[ManifestView, ...]:
        return tuple(v for v in self.views if v.split == "train")

    @property
    def test_views(self) -> tuple[ManifestView, ...]:
        return tuple(v for v in self.views if v.split == "test")


# ----------------------------------------------------------------------------------------------------
# Validation


def _is_num(x: Any) -> bool:
    return type(x) in (int, float)  # bool is not a JSON number here


def _check_points(points: Any, where: str) -> None:
    """What the schema requires of ``points`` (+ finiteness and matching lengths), without per-element schema
    validation."""
    if not isinstance(points, dict):
        return  # the schema check reports it
    xyz, rgb, count = points.get("xyz"), points.get("rgb"), points.get("count")
    if isinstance(xyz, list):
        for i, p in enumerate(xyz):
            if not (isinstance(p, list) and len(p) == 3 and all(_is_num(c) and math.isfinite(c) for c in p)):
                raise JsgsError(
                    f"{where}: not a valid manifest file: at points/xyz/{i}: {p!r} is not 3 finite numbers"
                )
    if isinstance(rgb, list):
        for i, c in enumerate(rgb):
            if not (isinstance(c, list) and len(c) == 3 and all(type(v) is int and 0 <= v <= 255 for v in c)):
                raise JsgsError(
                    f"{where}: not a valid manifest file: at points/rgb/{i}: {c!r} is not 3 integers "
                    "in 0..255"
                )
    if isinstance(xyz, list) and xyz:
        check_coordinates(xyz, f"{where}: not a valid manifest file: at points/xyz", by_row=True)
    if isinstance(xyz, list) and isinstance(rgb, list) and type(count) is int:
        if not len(xyz) == len(rgb) == count:
            raise JsgsError(
                f"{where}: not a valid manifest file: at points: count {count}, {len(xyz)} xyz, "
                f"{len(rgb)} rgb (must all be equal)"
            )


def _finite(x: Any) -> bool:
    if isinstance(x, list):
        return all(_finite(v) for v in x)
    return not isinstance(x, float) or math.isfinite(x)


def _check_camera(cam: dict[str, Any], loc: str) -> None:
    """Focal lengths within [MIN_FOCAL_RATIO, MAX_FOCAL_RATIO] x the longer side, the principal point within
    MAX_FOCAL_RATIO x the longer side of the origin, finite distortion (jsgs.base.limits)."""
    side = max(cam["width"], cam["height"])
    for key in ("fx", "fy"):
        f = cam[key]
        if not MIN_FOCAL_RATIO * side <= f <= MAX_FOCAL_RATIO * side:
            raise JsgsError(
                f"{loc}/camera/{key}: focal length {f:g} px is outside [{MIN_FOCAL_RATIO:g}, "
                f"{MAX_FOCAL_RATIO:g}] x the image's longer side ({side} px)"
            )
    for key in ("cx", "cy"):
        if abs(cam[key]) > MAX_FOCAL_RATIO * side:
            raise JsgsError(
                f"{loc}/camera/{key}: principal point {cam[key]:g} px lies beyond {MAX_FOCAL_RATIO:g} x the "
                f"image's longer side ({side} px)"
            )
    dist = cam["distortion"]
    if dist is not None and not _finite(dist["params"]):
        raise JsgsError(f"{loc}/camera/distortion: a parameter is not finite ({dist['params']})")


def validate_document(doc: Any, where: str) -> None:
    """Raise JsgsError (one line naming ``where``) unless ``doc`` is a valid manifest: the schema, plus what a
    schema cannot say — finite numbers within the limits of :mod:`jsgs.base.limits` (coordinates, focal
    lengths, principal points), matching point counts, unique view names, rotations that are rotations."""
    from jsgs.base.schema import validate

    if isinstance(doc, dict) and isinstance(doc.get("points"), dict):
        pts = doc["points"]
        light = {**pts}
        for key in ("xyz", "rgb"):
            if isinstance(pts.get(key), list):
                light[key] = []  # checked by _check_points
        validate({**doc, "points": light}, "manifest", where)
        _check_points(pts, where)
    else:
        validate(doc, "manifest", where)
    names: set[str] = set()
    for i, v in enumerate(doc["views"]):
        loc = f"{where}: not a valid manifest file: at views/{i}"
        if v["name"] in names:
            raise JsgsError(f"{loc}: view name {v['name']!r} is repeated")
        names.add(v["name"])
        cam = v["camera"]
        if not _finite([v["R"], v["t"], cam["fx"], cam["fy"], cam["cx"], cam["cy"]]):
            raise JsgsError(f"{loc}: non-finite camera or pose")
        if not all(abs(x) <= MAX_COORDINATE for x in v["t"]):
            raise JsgsError(f"{loc}/t: translation {v['t']} lies beyond ±{MAX_COORDINATE:g} (world units)")
        _check_camera(cam, loc)
        R = np.asarray(v["R"], dtype=np.float64)
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-5 or np.linalg.det(R) < 0:
            raise JsgsError(f"{loc}/R: not a rotation matrix (R R^T != I or det < 0)")


# ----------------------------------------------------------------------------------------------------
# Reading


def _jpeg(d: dict[str, Any] | None) -> JpegState | None:
    if d is None:
        return None
    chroma = d["chroma_table"]
    return JpegState(
        luma_table=np.asarray(d["luma_table"], dtype=np.int32),
        chroma_table=None if chroma is None else np.asarray(chroma, dtype=np.int32),
        sampling=d["sampling"],
        quality=int(d["quality"]),
        quality_exact=bool(d["quality_exact"]),
        precision=int(d["precision"]),
        frame=d.get("frame"),
        color_space=d.get("color_space"),
        header_sha256=d.get("header_sha256"),
        header_digest_scheme=int(d.get("header_digest_scheme", 1)),
        cr_table=None if d.get("cr_table") is None else np.asarray(d["cr_table"], dtype=np.int32),
        **_analysis(d.get("analysis")),
    )


def _analysis(a: dict[str, Any] | None) -> dict[str, Any]:
    if not a:
        return {}
    ec = a.get("effective_chroma_table")
    return {
        "effective_luma_table": np.asarray(a["effective_luma_table"], dtype=np.int32),
        "effective_chroma_table": None if ec is None else np.asarray(ec, dtype=np.int32),
        "double_compressed": bool(a["double_compressed"]),
        "noise_variance": None if a.get("noise_variance") is None else float(a["noise_variance"]),
        "blockiness": None if a.get("blockiness") is None else float(a["blockiness"]),
    }


def _camera(d: dict[str, Any]) -> Camera:
    dist = d["distortion"]
    return Camera(
        model=d["model"],
        width=int(d["width"]),
        height=int(d["height"]),
        fx=float(d["fx"]),
        fy=float(d["fy"]),
        cx=float(d["cx"]),
        cy=float(d["cy"]),
        distortion=None
        if dist is None
        else Distortion(dist["model"], tuple(float(p) for p in dist["params"])),
    )


MANIFEST_NAME = "manifest.json"


def manifest_file(path: str | Path) -> Path:
    """``path`` itself, or for a folder the ``manifest.json`` in it (what ``jsgstools compress`` and
    ``manifest --out FOLDER/manifest.json`` write); a folder without one is a JsgsError saying how to make
    it."""
    path = Path(path)
    if not path.is_dir():
        return path
    if (path / MANIFEST_NAME).is_file():
        return path / MANIFEST_NAME
    if (path / "sparse").is_dir():
        raise JsgsError(
            f"{path}: a folder without {MANIFEST_NAME}; write one with "
            f"`jsgstools manifest {path} --out {path / MANIFEST_NAME}`"
        )
    raise JsgsError(
        f"{path}: neither a manifest nor a COLMAP scene; for a folder of photos run "
        f"`jsgstools sfm {path} --out SCENE`, then `jsgstools manifest SCENE --out SCENE/{MANIFEST_NAME}`"
    )


def load_manifest(path: str | Path, check_files: bool = True) -> Manifest:
    """Read, validate and type ``path`` (a manifest, or a folder holding ``manifest.json``). Image and
    reference paths are resolved against the manifest's folder (absolute paths are taken as they are); with
    ``check_files`` each must exist. Any defect raises one JsgsError naming the file."""
    from jsgs.base.io import read_regular_text

    path = manifest_file(path)
    try:
        text = read_regular_text(path)
    except FileNotFoundError:
        raise JsgsError(f"{path}: manifest not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise JsgsError(f"{path}: cannot read the manifest: {e}") from None
    doc = parse_json(text, path)
    validate_document(doc, str(path))

    base = path.parent
    views = []
    for v in doc["views"]:
        image = base / v["image"]
        ref = None if v["reference"] is None else base / v["reference"]
        if check_files:
            if not image.is_file():
                raise JsgsError(
                    f"{path}: view {v['name']!r}: image {v['image']} not found (looked for {image})"
                )
            if ref is not None and not ref.is_file():
                raise JsgsError(
                    f"{path}: view {v['name']!r}: reference {v['reference']} not found (looked for {ref})"
                )
        views.append(
            ManifestView(
                name=v["name"],
                image=image,
                split=v["split"],
                camera=_camera(v["camera"]),
                R=np.asarray(v["R"], dtype=np.float64),
                t=np.asarray(v["t"], dtype=np.float64),
                jpeg=_jpeg(v["jpeg"]),
                reference=ref,
            )
        )
    s = doc["scene"]
    scene = SceneInfo(
        name=s["name"],
        source=s["source"],
        schedule=s["schedule"],
        quality=s.get("quality"),
        seed=s["seed"],
        test_every=int(s["test_every"]),
        subsampling=s.get("subsampling"),
        downscale=None if s.get("downscale") is None else float(s["downscale"]),
        undistorted=bool(s.get("undistorted", False)),
    )
    pts = doc["points"]
    xyz = np.asarray(pts["xyz"], dtype=np.float64).reshape(-1, 3)
    rgb = np.asarray(pts["rgb"], dtype=np.uint8).reshape(-1, 3)
    return Manifest(
        path=path, producer=doc["producer"], scene=scene, views=tuple(views), points_xyz=xyz, points_rgb=rgb
    )
