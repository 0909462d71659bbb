"""Manifest -> training scene: cameras in the normalised world, images as tensors, the initial point cloud.

Only the manifest is read (through :func:`jsgs.base.manifest.load_manifest`, which validates it); images are
the files it names, decoded with Pillow and never resampled: an image whose size differs from its camera's is
an error, and so is a camera with lens distortion (undistorting would resample a JPEG and move its 8x8
blocks).
"""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
import torch
from torch import Tensor

from jsgs.base.camera import DISTORTION_MODELS, Camera
from jsgs.base.errors import JsgsError
from jsgs.base.limits import MAX_POINT_DISTANCE, MIN_VIEW_SIDE
from jsgs.base.manifest import JpegState, Manifest, ManifestView
from jsgs.base.world import camera_extent, coincidence
from jsgs.train.config import TrainConfig
from jsgs.train.normalize import normalize_world


@dataclass
class TrainingView:
    """One view as the trainer uses it: the manifest's view (:class:`jsgs.base.manifest.ManifestView`) with
    its pose in the *training* (normalised) world and its index among the scene's views.

    ``camera``: the manifest's intrinsics (:class:`jsgs.base.camera.Camera`; ``K`` 3x3 pinhole intrinsics in
    pixels, COLMAP convention: pixel centres at integer + 0.5); ``camtoworld`` 4x4 in the training world,
    OpenCV axes; ``viewmat`` its inverse (world-to-camera, what the rasterizer takes). ``jpeg``: the
    manifest's JPEG state (:class:`jsgs.base.manifest.JpegState`: luma_table, chroma_table 8x8 natural
    order, sampling, quality, quality_exact, precision, frame) or None for a lossless image.
    ``image``: the observed/training image; ``reference``: the lossless reference or None."""

    index: int
    name: str
    split: str
    image: Path
    reference: Path | None
    jpeg: JpegState | None
    camera: Camera
    camtoworld: np.ndarray
    viewmat: np.ndarray
    # per (name, device, dtype): a host-to-device copy from pageable memory synchronises with the GPU, once
    # per call; made once, the training step has two fewer syncs (both methods), and none inside a backward
    _tensors: dict[tuple[str, torch.device, torch.dtype], Tensor] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    @property
    def width(self) -> int:
        return self.camera.width

    @property
    def height(self) -> int:
        return self.camera.height

    @functools.cached_property
    def K(self) -> np.ndarray:
        """(3, 3) float64 pinhole intrinsics (``camera.K``)."""
        return self.camera.K

    @functools.cached_property
    def distortion(self) -> np.ndarray | None:
        """(k1, k2, p1, p2) of a distorted camera (COLMAP SIMPLE_RADIAL, RADIAL, OPENCV: the models
        :data:`DISTORTION_MODELS` the loader admits), None for a pinhole one (or all-zero parameters)."""
        dist = self.camera.distortion
        if dist is None or not any(p != 0.0 for p in dist.params):
            return None
        coeffs = np.zeros(4)
        coeffs[: len(dist.params)] = dist.params  # (k1[, k2[, p1, p2]]) -> (k1, k2, p1, p2)
        return coeffs

    def _on(self, name: str, device: torch.device | str, dtype: torch.dtype) -> Tensor:
        key = (name, torch.device(device), dtype)
        t = self._tensors.get(key)
        if t is None:
            t = torch.from_numpy(getattr(self, name)).to(dtype=dtype, device=device)[None]
            self._tensors[key] = t
        return t

    def K_tensor(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> Tensor:
        """[1, 3, 3] (made once per device and dtype and shared: do not modify it in place)."""
        return self._on("K", device, dtype)

    def viewmat_tensor(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> Tensor:
        """[1, 4, 4] world-to-camera (made once per device and dtype and shared: do not modify it in
        place)."""
        return self._on("viewmat", device, dtype)

    def distortion_tensor(
        self, device: torch.device | str, dtype: torch.dtype = torch.float32
    ) -> Tensor | None:
        """[1, 4] (k1, k2, p1, p2) for the rasterizer, or None for a pinhole camera."""
        return None if self.distortion is None else self._on("distortion", device, dtype)

    def eval_image_path(self) -> Path:
        """The uncompressed image to evaluate against: the reference, else the image itself (lossless)."""
        return self.reference if self.reference is not None else self.image


@dataclass
class TrainingScene:
    """The manifest as the trainer uses it.

    ``points`` P x 3 float32 (normalised world), ``points_rgb`` P x 3 uint8. ``transform``: 4x4
    world-to-normalised similarity (identity when normalisation is off). ``camera_extent``: gsplat Parser's
    scene_scale (largest camera distance from the cameras' mean, normalised world); ``scene_scale``: that
    x ``scene_scale_margin`` x ``global_scale`` (what the learning rates and DefaultStrategy use)."""

    manifest_path: Path
    manifest_sha256: str
    name: str
    views: list[TrainingView]
    points: np.ndarray
    points_rgb: np.ndarray
    transform: np.ndarray
    camera_extent: float
    scene_scale: float
    notes: list[str] = field(default_factory=list)

    @property
    def train_views(self) -> list[TrainingView]:
        return [v for v in self.views if v.split == "train"]

    @property
    def test_views(self) -> list[TrainingView]:
        return [v for v in self.views if v.split == "test"]

    @property
    def reference_kind(self) -> str:
        """What the test views are evaluated against: ``lossless`` (every one has a lossless image), ``jpeg``
        (none has: their own JPEGs), ``mixed``, or ``none`` (no test views)."""
        tests = self.test_views
        lossy = sum(1 for v in tests if v.reference is None and v.jpeg is not None)
        if not tests:
            return "none"
        return "lossless" if lossy == 0 else ("jpeg" if lossy == len(tests) else "mixed")


def load_training_scene(manifest_path: str | Path, cfg: TrainConfig) -> TrainingScene:
    """Read and check the manifest, normalise the world (gsplat's Parser), and compute the scene scale.

    :func:`jsgs.base.manifest.load_manifest` validates the document (schema, rotations, unique names, point
    counts, files present). Raises JsgsError (one line, naming the manifest and the view) on what the
    trainer additionally refuses: distorted cameras, no training views, evaluation steps with no test
    views, test views without a lossless image (when ``scene.require_lossless_reference``), too few points
    for SfM initialisation."""
    from jsgs.base.manifest import load_manifest, manifest_file

    manifest_path = manifest_file(manifest_path)
    where = str(manifest_path)
    manifest = load_manifest(manifest_path)
    try:
        sha = hashlib.sha256(manifest_path.read_bytes()).hexdigest()
    except OSError as e:
        raise JsgsError(f"{where}: {e.strerror}") from None

    _check_cameras(manifest.views, where)
    notes = _check_jpeg_headers(manifest.views, where)
    _check_split(manifest, where)
    _check_views(manifest.views, cfg, where)
    c2w = np.stack([np.linalg.inv(v.world_to_camera) for v in manifest.views])
    centres = c2w[:, :3, 3]
    spread = camera_extent(c2w)
    coincident = coincidence(c2w)
    if coincident and cfg.scene.normalize_world:
        at = ", ".join(f"{x:g}" for x in centres[0])
        raise JsgsError(
            f"{where}: {coincident} ({at}): "
            "the world's normalisation (scene.normalize_world) scales by the cameras' distances; set "
            "scene.normalize_world to false to train in the manifest's own units"
        )
    xyz, rgb = _points_near_cameras(manifest, centres, 1.0 if coincident else spread, notes)
    if cfg.init.type == "sfm" and len(xyz) <= cfg.init.knn_neighbors:
        raise JsgsError(
            f"{where}: {len(xyz)} points: SfM initialisation needs more than {cfg.init.knn_neighbors} "
            "(set init.type to random to start without them)"
        )

    if cfg.scene.normalize_world:
        try:
            with np.errstate(all="ignore"):  # what overflows is refused just below
                c2w, xyz_n, transform = normalize_world(c2w, xyz)
            ok = np.isfinite(transform).all() and np.isfinite(c2w).all()
        except ValueError as e:  # numpy's LinAlgError included
            ok, why = False, str(e)
        else:
            why = "degenerate cameras"
        if not ok:
            raise JsgsError(
                f"{where}: world normalisation failed: {why}; set scene.normalize_world to false to train "
                "in the manifest's own units"
            )
    else:
        xyz_n, transform = xyz, np.eye(4)
    extent = camera_extent(c2w)
    if coincident or not extent > 1e-12:
        notes.append(f"{coincident or 'all cameras at one position'}: camera extent 0 replaced by 1")
        extent = 1.0
    views = [
        TrainingView(i, v.name, v.split, v.image, v.reference, v.jpeg, v.camera, cw, np.linalg.inv(cw))
        for i, (v, cw) in enumerate(zip(manifest.views, c2w, strict=True))
    ]
    return TrainingScene(
        manifest_path=manifest_path.resolve(),
        manifest_sha256=sha,
        name=manifest.scene.name,
        views=views,
        points=xyz_n.astype(np.float32),
        points_rgb=rgb,
        transform=transform,
        camera_extent=extent,
        scene_scale=extent * cfg.scene.scene_scale_margin * cfg.scene.global_scale,
        notes=notes,
    )


def _check_cameras(views: Sequence[ManifestView], where: str) -> None:
    """Refuse a camera with lens distortion the rasterizer does not model (:data:`DISTORTION_MODELS`)."""
    for v in views:
        dist = v.camera.distortion
        if dist is not None and any(p != 0.0 for p in dist.params) and dist.model not in DISTORTION_MODELS:
            raise JsgsError(
                f"{where}: view {v.name!r}: camera has lens distortion ({dist.model}); the trainer "
                "renders "
                f"{', '.join(DISTORTION_MODELS)} on the photo's own grid and never resamples images: "
                "undistort the clean images before compressing them, or model the camera as one of those"
            )


def _check_split(manifest: Manifest, where: str) -> None:
    """Refuse a manifest without training views, with the advice that fits it
    (:func:`jsgstools.validate.split_warning`): for a scene ``jsgstools compress`` made (its ``compress.json``
    fixes the split) to compress a source with more views, else ``jsgstools manifest --test-every``."""
    from jsgstools.validate import split_warning

    views = manifest.views
    if any(v.split == "train" for v in views):
        return
    every: int | None = manifest.scene.test_every
    if not (every == 1 or (every and len(views) == 1)):
        every = None  # no spacing makes every view a test view: a split edited by hand
    record = None
    settings = manifest.producer.get("settings")
    if manifest.producer.get("tool") == "jsgstools compress" or (
        isinstance(settings, dict) and "compress" in settings
    ):  # its folder holds compress.json and images/NAME
        depth, parents = len(PurePosixPath(views[0].name).parts), views[0].image.parents
        found = len(parents) > depth and parents[depth - 1].name == "images"
        record = str(parents[depth] / "compress.json") if found else "its compress.json"
        every = manifest.scene.test_every
    line = split_warning(where, len(views), 0, every, record)
    assert line is not None
    raise JsgsError(line)


def _check_views(views: Sequence[ManifestView], cfg: TrainConfig, where: str) -> None:
    """Refuse a test view without a lossless image when ``scene.require_lossless_reference`` is set, and a
    view smaller than the SSIM window."""
    if cfg.scene.require_lossless_reference:
        for v in views:
            if v.split == "test" and v.reference is None and v.jpeg is not None:
                raise JsgsError(
                    f"{where}: test view {v.name!r} has only a JPEG image and no lossless reference; "
                    "scene.require_lossless_reference is set (without it the view is evaluated against "
                    "its JPEG)"
                )
    small = [v for v in views if min(v.camera.width, v.camera.height) < MIN_VIEW_SIDE]
    if small:
        v = small[0]
        raise JsgsError(
            f"{where}: view {v.name!r} is {v.camera.width}x{v.camera.height} pixels: {len(small)} view(s) "
            f"have a side below the SSIM window ({MIN_VIEW_SIDE} pixels), which the losses and the "
            "evaluation need"
        )


def _points_near_cameras(
    manifest: Manifest, centres: np.ndarray, extent: float, notes: list[str]
) -> tuple[np.ndarray, np.ndarray]:
    """The manifest's points (float64) and colours without those farther than ``MAX_POINT_DISTANCE`` x
    ``extent`` from the cameras' mean ``centres`` (noted in ``notes``): checked before any linear algebra
    on the points, since absurdly far ones would dominate the principal axes and leave float32 once
    normalised."""
    xyz = np.asarray(manifest.points_xyz, dtype=np.float64).reshape(-1, 3)
    rgb = np.asarray(manifest.points_rgb, dtype=np.uint8).reshape(-1, 3)
    if not len(xyz):
        return xyz, rgb
    dist = np.linalg.norm(xyz - centres.mean(axis=0), axis=1)
    far = dist > MAX_POINT_DISTANCE * extent
    if far.any():
        notes.append(
            f"{int(far.sum())} of {len(xyz)} points lie farther than {MAX_POINT_DISTANCE:g} x the "
            f"cameras' extent from them (the farthest at {float(dist.max()):g}); left out"
        )
        xyz, rgb = xyz[~far], rgb[~far]
    return xyz, rgb


def _check_jpeg_headers(views: Sequence[ManifestView], where: str) -> list[str]:
    """The JPEG state the trainer uses is the manifest's: refuse (one line naming the file) a JPEG whose
    header is no longer the one the manifest recorded (``jpeg.header_sha256``;
    :mod:`jsgs.jpeg.header_digest`), each made again with the scheme the manifest records (1 where it records
    none). A manifest that records no digests (written before they existed) trains unchecked: returns a
    note."""
    from jsgs.jpeg.header_digest import header_digest

    jpegs = [v for v in views if v.jpeg is not None]
    unchecked = 0
    for v in jpegs:
        assert v.jpeg is not None
        if v.jpeg.header_sha256 is None:
            unchecked += 1
        elif header_digest(v.image, v.jpeg.header_digest_scheme) != v.jpeg.header_sha256:
            raise JsgsError(
                f"{v.image}: changed since {where} was written (its JPEG header, i.e. tables, sampling or "
                f"frame, is not the one recorded for view {v.name!r}); write the manifest again (jsgstools "
                "manifest) so that training uses the file's own JPEG state"
            )
    if not unchecked:
        return []
    return [
        f"{unchecked} of {len(jpegs)} JPEG views have no header digest in the manifest (written by an older "
        "jsgstools): those files are not checked for changes since; write the manifest again to have them "
        "checked"
    ]


def load_image(path: Path, width: int, height: int, what: str) -> Tensor:
    """Decode an image to [H, W, 3] uint8 (:func:`jsgs.base.images.read_rgb8`: RGB, greyscale replicated,
    16-bit by value, alpha dropped). Raises JsgsError if it is missing, unreadable or not ``width`` x
    ``height``."""
    from jsgs.base.images import read_rgb8

    arr = read_rgb8(path, what)
    if (arr.shape[1], arr.shape[0]) != (width, height):
        raise JsgsError(
            f"{path}: {what} is {arr.shape[1]}x{arr.shape[0]} but its camera is {width}x{height} "
            "(the trainer never resamples images)"
        )
    return torch.from_numpy(arr)


def load_train_images(scene: TrainingScene, device: torch.device) -> dict[int, Tensor]:
    """view index -> [H, W, 3] uint8 on ``device`` for every training view (observed images). The images of
    one size are one ``[V, H, W, 3]`` tensor on the device, each view's image a view of it
    (:func:`stacked_image`): the same memory, and a consumer that needs its input at a fixed address (JSGS's
    CUDA graph of the image terms) reads any view's image from it by index, with no buffer and copy of its
    own. Each image is decoded and copied into its place in turn (no second copy of them all on the host)."""
    sizes: dict[tuple[int, int], list[TrainingView]] = {}
    for v in scene.train_views:
        sizes.setdefault((v.height, v.width), []).append(v)
    out: dict[int, Tensor] = {}
    for (h, w), views in sizes.items():
        stack = torch.empty((len(views), h, w, 3), dtype=torch.uint8, device=device)
        for i, v in enumerate(views):
            stack[i].copy_(load_image(v.image, v.width, v.height, f"training image of view {v.name!r}"))
            out[v.index] = stack[i]
    return {v.index: out[v.index] for v in scene.train_views}


def stacked_image(image: Tensor) -> tuple[Tensor, int] | None:
    """``(stack, i)`` where ``image`` [H, W, 3] is exactly ``stack[i]`` of a ``[V, H, W, 3]`` tensor (as
    :func:`load_train_images` makes them), else None."""
    base = image._base
    if base is None or base.dim() != 4 or base.shape[1:] != image.shape or not base.is_contiguous():
        return None
    offset = image.storage_offset() - base.storage_offset()
    if not image.is_contiguous() or offset % image.numel():
        return None
    return base, offset // image.numel()


def image_target(image: Tensor) -> Tensor:
    """The loss's target of a training image ``[H, W, 3]`` uint8: ``[1, H, W, 3]`` float32 in [0, 1] (the
    trainer's, and the one JSGS's CUDA graph makes from the image it copies in)."""
    return image.float()[None] / 255.0


def load_eval_images(scene: TrainingScene, device: torch.device) -> dict[int, Tensor]:
    """view index -> [H, W, 3] uint8 on ``device``: the uncompressed reference of every test view."""
    return {
        v.index: load_image(v.eval_image_path(), v.width, v.height, f"reference image of view {v.name!r}").to(
            device
        )
        for v in scene.test_views
    }


class ViewSampler:
    """Uniform stochastic view sampling without replacement per epoch (gsplat's shuffled DataLoader with batch
    size 1), from its own torch generator so that the sequence is reproducible and resumable."""

    def __init__(self, num_views: int, seed: int) -> None:
        self.num_views = num_views
        self.generator = torch.Generator().manual_seed(seed)
        self.perm: list[int] = []
        self.pos = 0

    def next(self) -> int:
        """Index into the training views of the next sample."""
        if self.pos >= len(self.perm):
            self.perm = torch.randperm(self.num_views, generator=self.generator).tolist()
            self.pos = 0
        i = self.perm[self.pos]
        self.pos += 1
        return i

    def state_dict(self) -> dict[str, Any]:
        return {"generator": self.generator.get_state(), "perm": list(self.perm), "pos": self.pos}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.generator.set_state(state["generator"])
        self.perm = list(state["perm"])
        self.pos = int(state["pos"])
