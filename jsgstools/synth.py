"""``jsgstools synth``: a small synthetic COLMAP scene, rendered exactly with numpy.

A textured room (floor, ceiling, four walls) holding three boxes, seen by cameras on a ring around the centre,
looking at it. Every texture is high-frequency (checkers, stripes, a random mosaic: the detail JPEG destroys)
on a low-frequency colour, with one constant shade per face, so appearance is view-independent and every pixel
hits a surface (no background). Rays are intersected analytically (slab method) and each pixel averages a
``supersample`` x ``supersample`` grid of rays.

World frame: z up, metres-like units; the room is [-4, 4] x [-4, 4] x [0, 3]. Cameras: COLMAP PINHOLE, one
camera shared by all views, principal point at the image centre (COLMAP convention: (W/2, H/2)). Extrinsics
world-to-camera, OpenCV axes. ``points3D`` are points sampled uniformly on every visible face, with the
texture colour at that point (no tracks: like the LLFF models in ``../shared/scenes``).

Output: ``OUT/images/view_NNN.png`` (lossless RGB) and ``OUT/sparse/0/{cameras,images,points3D}.bin`` (plus
the ``rigs.bin``/``frames.bin`` that pycolmap 4 writes). Deterministic given the arguments.
"""

from __future__ import annotations

import io
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from jsgs.base.camera import Camera, Distortion
from jsgs.base.errors import JsgsError
from jsgs.base.io import write_bytes_atomic
from jsgs.base.limits import MIN_VIEW_SIDE

from .scene import ColmapCamera, prepare_output_dir, removes_partial_output, write_model_atomic

Texture = Callable[
    [np.ndarray, np.ndarray], np.ndarray
]  # (u (N,), v (N,)) in world units -> (N, 3) in [0, 1]

#: What ``synth`` writes into OUT (and removes first with --force).
OWNED = ("images", "sparse")


@dataclass(frozen=True)
class Box:
    """An oriented box: ``centre`` (3,), half extents ``half`` (3,), rotation about z by ``yaw`` radians.
    ``inside``: the camera is inside it (the room) and sees its inner faces. ``textures[2*axis + (sign>0)]``
    paints the face whose outward normal is +-axis (local frame); None faces get no points (never seen)."""

    centre: np.ndarray
    half: np.ndarray
    yaw: float
    inside: bool
    textures: tuple[Texture | None, ...]

    @property
    def rot(self) -> np.ndarray:
        """(3, 3) local-to-world rotation."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------------------------------
# Textures: functions of face coordinates (world units), so the same surface looks the same from every view.


def _lowfreq(base: tuple[float, float, float], amp: float = 0.15, scale: float = 1.7) -> Texture:
    b = np.array(base)

    def tex(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        w = 0.5 + 0.5 * np.sin(u / scale) * np.cos(v / (1.3 * scale))
        return b[None, :] * (1 - amp + 2 * amp * w[:, None])

    return tex


def checker(period: float, a: tuple[float, float, float], b: tuple[float, float, float]) -> Texture:
    lo_a, lo_b = _lowfreq(a), _lowfreq(b)

    def tex(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        m = (np.floor(u / period) + np.floor(v / period)) % 2 == 0
        return np.where(m[:, None], lo_a(u, v), lo_b(u, v))

    return tex


def stripes(
    period: float,
    angle_deg: float,
    a: tuple[float, float, float],
    b: tuple[float, float, float],
    duty: float = 0.5,
) -> Texture:
    ca, sa = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    lo_a, lo_b = _lowfreq(a), _lowfreq(b)

    def tex(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        s = (u * ca + v * sa) / period
        m = (s - np.floor(s)) < duty
        return np.where(m[:, None], lo_a(u, v), lo_b(u, v))

    return tex


def mosaic(
    cell: float, rng: np.random.Generator, base: tuple[float, float, float], spread: float = 0.35, n: int = 97
) -> Texture:
    """Random colours on a square grid of ``cell`` units (nearest cell, so edges stay sharp); the grid repeats
    every ``n`` cells (n prime so the repeat does not line up with the other textures)."""
    table = np.clip(np.array(base)[None, None, :] + spread * (rng.random((n, n, 3)) - 0.5), 0, 1)
    lo = _lowfreq((1.0, 1.0, 1.0), amp=0.1)

    def tex(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        i = np.floor(u / cell).astype(np.int64) % n
        j = np.floor(v / cell).astype(np.int64) % n
        return table[i, j] * lo(u, v)

    return tex


def _shade(normal: np.ndarray) -> float:
    """Fixed per-face brightness from a distant light, so faces differ (view-independent, Lambert-like)."""
    light = np.array([0.45, 0.3, 0.84])
    light /= np.linalg.norm(light)
    return float(0.55 + 0.45 * abs(normal @ light))


def default_scene(rng: np.random.Generator, texture_scale: float = 1.0) -> list[Box]:
    """The room and its three boxes. At the default 160x120 views, texture periods span about 3 to 12 pixels
    (the boxes at about 2.5 units, the walls at 4 to 7); ``texture_scale`` multiplies every period (coarser
    textures are learnt by fewer Gaussians)."""
    k = texture_scale
    room = Box(
        centre=np.array([0.0, 0.0, 1.5]),
        half=np.array([4.0, 4.0, 1.5]),
        yaw=0.0,
        inside=True,
        textures=(
            stripes(0.2 * k, 0.0, (0.85, 0.75, 0.55), (0.35, 0.25, 0.2)),  # wall x = -4
            stripes(0.25 * k, 90.0, (0.5, 0.7, 0.85), (0.15, 0.2, 0.35)),  # wall x = +4
            mosaic(0.15 * k, rng, (0.6, 0.55, 0.45)),  # wall y = -4
            stripes(0.18 * k, 35.0, (0.8, 0.8, 0.8), (0.25, 0.3, 0.25)),  # wall y = +4
            checker(0.3 * k, (0.92, 0.9, 0.85), (0.18, 0.18, 0.2)),  # floor
            mosaic(0.3 * k, rng, (0.7, 0.7, 0.75), spread=0.25),  # ceiling
        ),
    )
    box_a = Box(
        centre=np.array([0.0, 0.0, 0.5]),
        half=np.array([0.5, 0.5, 0.5]),
        yaw=np.radians(20.0),
        inside=False,
        textures=(
            checker(0.07 * k, (0.9, 0.2, 0.15), (0.95, 0.9, 0.8)),
            stripes(0.08 * k, 45.0, (0.1, 0.35, 0.8), (0.9, 0.85, 0.3)),
            stripes(0.06 * k, 0.0, (0.1, 0.1, 0.1), (0.95, 0.95, 0.95)),
            mosaic(0.05 * k, rng, (0.3, 0.7, 0.35)),
            None,  # bottom, on the floor
            checker(0.1 * k, (0.2, 0.6, 0.65), (0.95, 0.75, 0.2)),
        ),
    )
    box_b = Box(
        centre=np.array([1.0, -0.9, 0.3]),
        half=np.array([0.3, 0.3, 0.3]),
        yaw=np.radians(-35.0),
        inside=False,
        textures=(
            mosaic(0.05 * k, rng, (0.8, 0.4, 0.6)),
            stripes(0.07 * k, 90.0, (0.95, 0.6, 0.1), (0.3, 0.1, 0.4)),
            checker(0.06 * k, (0.1, 0.1, 0.6), (0.85, 0.85, 0.95)),
            stripes(0.06 * k, -30.0, (0.2, 0.6, 0.2), (0.95, 0.95, 0.7)),
            None,
            mosaic(0.06 * k, rng, (0.55, 0.5, 0.35)),
        ),
    )
    box_c = Box(
        centre=np.array([-0.8, 0.8, 0.6]),
        half=np.array([0.12, 0.35, 0.6]),
        yaw=np.radians(50.0),
        inside=False,
        textures=(
            stripes(0.06 * k, 60.0, (0.9, 0.9, 0.2), (0.15, 0.15, 0.15)),
            checker(0.07 * k, (0.6, 0.2, 0.7), (0.9, 0.95, 0.9)),
            stripes(0.08 * k, 0.0, (0.2, 0.7, 0.9), (0.9, 0.3, 0.3), duty=0.3),
            mosaic(0.06 * k, rng, (0.45, 0.55, 0.75)),
            None,
            checker(0.06 * k, (0.1, 0.1, 0.1), (0.9, 0.9, 0.9)),
        ),
    )
    return [room, box_a, box_b, box_c]


# ----------------------------------------------------------------------------------------------------
# Ray casting


def _face_uv(local: np.ndarray, axis: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Face coordinates (world units, from the face's corner) of local hit points: the two other axes."""
    u_axis = np.where(axis == 0, 1, 0)
    v_axis = np.where(axis == 2, 1, 2)
    idx = np.arange(len(local))
    u = local[idx, u_axis] + half[u_axis]
    v = local[idx, v_axis] + half[v_axis]
    return u, v


def _intersect(box: Box, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameter of the visible hit ((N,), inf for a miss) and the face index ((N,), 2*axis + (sign>0)).
    ``origin`` (3,), ``dirs`` (N, 3) world."""
    rot = box.rot
    o = rot.T @ (origin - box.centre)
    d = dirs @ rot  # = (rot.T @ dirs.T).T
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (-box.half[None, :] - o[None, :]) * inv
        t2 = (box.half[None, :] - o[None, :]) * inv
    tmin = np.minimum(t1, t2)
    tmax = np.maximum(t1, t2)
    t_near = tmin.max(axis=1)
    t_far = tmax.min(axis=1)
    if box.inside:
        t = t_far
        axis = tmax.argmin(axis=1)
        hit = np.isfinite(t) & (t > 0)
        # leaving through the face on the side the ray travels towards
        sign_pos = np.take_along_axis(d, axis[:, None], 1)[:, 0] > 0
    else:
        t = t_near
        axis = tmin.argmax(axis=1)
        hit = (t_near <= t_far) & (t_near > 1e-9)
        sign_pos = np.take_along_axis(d, axis[:, None], 1)[:, 0] < 0  # entering against the outward normal
    return np.where(hit, t, np.inf), 2 * axis + sign_pos.astype(np.int64)


def _paint(box: Box, face: np.ndarray, world: np.ndarray) -> np.ndarray:
    """Colours ((N, 3) in [0, 1]) of points ``world`` (N, 3) on faces ``face`` (N,) of ``box``."""
    local = (world - box.centre) @ box.rot
    axis = face // 2
    u, v = _face_uv(local, axis, box.half)
    out = np.zeros((len(world), 3))
    for f in np.unique(face):
        tex = box.textures[f]
        m = face == f
        if tex is None:  # a face no camera should see: mid grey, so a bug would show
            out[m] = 0.5
            continue
        normal = box.rot[:, f // 2] * (1.0 if f % 2 else -1.0) * (-1.0 if box.inside else 1.0)
        out[m] = tex(u[m], v[m]) * _shade(normal)
    return out


def cast(boxes: list[Box], origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest visible hit of rays from ``origin`` (3,) along ``dirs`` (N, 3): (points (N, 3) world,
    colours (N, 3) in [0, 1], box index (N,))."""
    best_t = np.full(len(dirs), np.inf)
    best_box = np.full(len(dirs), -1)
    best_face = np.zeros(len(dirs), dtype=np.int64)
    for i, box in enumerate(boxes):
        tb, fb = _intersect(box, origin, dirs)
        closer = tb < best_t
        best_t = np.where(closer, tb, best_t)
        best_box = np.where(closer, i, best_box)
        best_face = np.where(closer, fb, best_face)
    if np.any(best_box < 0):
        raise RuntimeError("a ray left the room")  # cameras are inside the room by construction
    world = origin[None, :] + best_t[:, None] * dirs
    color = np.zeros((len(dirs), 3))
    for i, box in enumerate(boxes):
        m = best_box == i
        if m.any():
            color[m] = _paint(box, best_face[m], world[m])
    return world, color, best_box


def pixel_rays(
    cam: Camera, R: np.ndarray, t: np.ndarray, xy: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World rays (origin (3,), directions (N, 3), not normalized) through image points ``xy`` ((N, 2), COLMAP
    pixel convention) of a camera with world-to-camera pose (R, t)."""
    if cam.distortion is None:
        n = np.stack([(xy[:, 0] - cam.cx) / cam.fx, (xy[:, 1] - cam.cy) / cam.fy], -1)
    else:
        import pycolmap

        pc = pycolmap.Camera.create_from_model_name(1, cam.model, cam.fx, cam.width, cam.height)
        pc.params = list(ColmapCamera(1, cam).params)
        n = pc.cam_from_img(np.ascontiguousarray(xy, dtype=np.float64))  # COLMAP inverts its own distortion
    d_cam = np.concatenate([n, np.ones((len(xy), 1))], axis=1)
    return -R.T @ t, d_cam @ R  # row-wise R.T @ d


def render(
    boxes: list[Box], cam: Camera, R: np.ndarray, t: np.ndarray, supersample: int = 2
) -> np.ndarray:
    """(H, W, 3) uint8 image of ``boxes`` from world-to-camera pose (R (3, 3), t (3,)); each pixel averages
    ``supersample`` x ``supersample`` rays at sub-pixel centres (COLMAP convention: pixel (0, 0) spans
    [0, 1] x [0, 1])."""
    s = supersample
    offs = (np.arange(s) + 0.5) / s
    xs = (np.arange(cam.width)[:, None] + offs[None, :]).ravel()  # (W*s,)
    ys = (np.arange(cam.height)[:, None] + offs[None, :]).ravel()  # (H*s,)
    gx, gy = np.meshgrid(xs, ys)
    origin, dirs = pixel_rays(cam, R, t, np.stack([gx.ravel(), gy.ravel()], 1))
    _, color, _ = cast(boxes, origin, dirs)
    img = color.reshape(cam.height, s, cam.width, s, 3).mean(axis=(1, 3))
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)


def sample_points(
    boxes: list[Box], rng: np.random.Generator, density: tuple[float, float] = (6.0, 120.0)
) -> tuple[np.ndarray, np.ndarray]:
    """Points ((N, 3) world) and their colours ((N, 3) uint8) uniformly on every painted face; ``density``
    points per unit area on the room and on the boxes. The trainer starts from one Gaussian per point, so the
    defaults (about 2,500 points) keep the CPU demo quick; densification adds the detail."""
    xyz_all, rgb_all = [], []
    for box in boxes:
        dens = density[0] if box.inside else density[1]
        for f, tex in enumerate(box.textures):
            if tex is None:
                continue
            axis, pos = f // 2, f % 2
            others = [a for a in range(3) if a != axis]
            area = 4 * box.half[others[0]] * box.half[others[1]]
            n = max(int(round(area * dens)), 16)
            local = np.zeros((n, 3))
            local[:, axis] = box.half[axis] * (1.0 if pos else -1.0)
            for a in others:
                local[:, a] = (rng.random(n) * 2 - 1) * box.half[a]
            world = local @ box.rot.T + box.centre
            col = _paint(box, np.full(n, f), world)
            xyz_all.append(world)
            rgb_all.append(np.clip(np.round(col * 255), 0, 255).astype(np.uint8))
    return np.concatenate(xyz_all), np.concatenate(rgb_all)


def look_at(
    centre: np.ndarray, target: np.ndarray, up: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) of a camera at ``centre`` looking at ``target``, OpenCV axes (x right, y down,
    z forward), no roll; ``up`` defaults to world +z."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else up
    f = target - centre
    f = f / np.linalg.norm(f)
    r = np.cross(f, up)
    r = r / np.linalg.norm(r)
    d = np.cross(f, r)
    R = np.stack([r, d, f])
    return R, -R @ centre


def camera_ring(
    n: int, rng: np.random.Generator, radius: float = 3.0, target: np.ndarray | None = None
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` poses around the centre: evenly spaced azimuths (jittered by up to a quarter step), heights
    alternating between two rings, all looking at the middle of the big box."""
    target = np.array([0.0, 0.0, 0.45]) if target is None else target
    step = 2 * np.pi / n
    poses = []
    for i in range(n):
        az = i * step + (rng.random() - 0.5) * 0.5 * step
        h = (0.95 if i % 2 == 0 else 1.7) + (rng.random() - 0.5) * 0.2
        r = radius * (1 + (rng.random() - 0.5) * 0.15)
        centre = np.array([r * np.cos(az), r * np.sin(az), h])
        poses.append(look_at(centre, target))
    return poses


def parse_size(text: str) -> tuple[int, int]:
    """``"160x120"`` -> (160, 120)."""
    try:
        w, h = (int(p) for p in text.lower().split("x"))
    except ValueError:
        raise JsgsError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 160x120") from None
    if not (MIN_VIEW_SIDE <= w <= 4096 and MIN_VIEW_SIDE <= h <= 4096):
        raise JsgsError(
            f"--size {text!r}: width and height must be within {MIN_VIEW_SIDE}..4096 (the trainer's SSIM "
            f"window is {MIN_VIEW_SIDE} pixels)"
        )
    return w, h


@dataclass(frozen=True)
class SynthResult:
    out: Path
    views: int
    width: int
    height: int
    points: int
    camera: Camera


@removes_partial_output
def synth(
    out: str | Path,
    views: int = 32,
    size: tuple[int, int] = (160, 120),
    seed: int = 0,
    supersample: int = 2,
    force: bool = False,
    progress: bool = False,
    k1: float = 0.0,
    camera_scale: int = 1,
    point_density: float = 1.0,
    texture_scale: float = 1.0,
) -> SynthResult:
    """Write the synthetic scene into ``out`` (see the module docstring). ``size`` = (width, height) pixels;
    the focal length is 0.85 x width (a 61 degree horizontal field of view at 4:3).

    For tests of the real-scene paths (library only): ``k1`` renders through a SIMPLE_RADIAL camera, and
    ``camera_scale`` writes the model's camera at that many times the image size (like LLFF's cameras at
    4032x3024 for 504x378 images). ``point_density`` scales the number of points3D (the trainer starts from
    one Gaussian per point, so fewer points make a quicker CPU run). ``texture_scale`` multiplies every
    texture's period (coarser detail)."""
    import pycolmap
    from PIL import Image
    from tqdm import tqdm

    out = Path(out)
    if not 2 <= views <= 1000:
        raise JsgsError(f"--views {views}: must be within 2..1000")
    if not 1 <= supersample <= 8:
        raise JsgsError(f"supersample {supersample}: must be within 1..8")
    w, h = size
    prepare_output_dir(out, force, OWNED, tool="synth")
    rng = np.random.default_rng(seed)
    if not 0.1 <= texture_scale <= 100.0:
        raise JsgsError(f"--texture-scale {texture_scale}: must be within 0.1..100")
    boxes = default_scene(rng, texture_scale)
    poses = camera_ring(views, rng)
    if not 0.01 <= point_density <= 100:
        raise JsgsError(f"--point-density {point_density}: must be within 0.01..100")
    xyz, rgb = sample_points(boxes, rng, (6.0 * point_density, 120.0 * point_density))
    model, dist = ("PINHOLE", None) if k1 == 0.0 else ("SIMPLE_RADIAL", Distortion("SIMPLE_RADIAL", (k1,)))
    cam = Camera(model, w, h, 0.85 * w, 0.85 * w, w / 2, h / 2, dist)
    if camera_scale < 1:
        raise JsgsError(f"camera_scale {camera_scale}: must be at least 1")

    rec = pycolmap.Reconstruction()
    pc = pycolmap.Camera.create_from_model_name(1, cam.model, cam.fx, w * camera_scale, h * camera_scale)
    pc.params = list(ColmapCamera(1, cam).scaled(w * camera_scale, h * camera_scale).params)
    rec.add_camera_with_trivial_rig(pc)
    for i, (R, t) in enumerate(tqdm(poses, desc="rendering", unit="view", disable=not progress)):
        name = f"view_{i:03d}.png"
        img = render(boxes, cam, R, t, supersample)
        buf = io.BytesIO()
        Image.fromarray(img, "RGB").save(buf, format="PNG")
        write_bytes_atomic(out / "images" / name, buf.getvalue())
        im = pycolmap.Image(name=name, camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
    for p, c in zip(xyz, rgb, strict=True):
        rec.add_point3D(p, pycolmap.Track(), c)
    write_model_atomic(rec, out / "sparse" / "0")
    return SynthResult(out, views, w, h, len(xyz), cam)
