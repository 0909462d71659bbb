"""Camera paths for ``jsgs render``, in the run's normalised training world (OpenCV axes: +Z forward, +Y
down), each frame a camera-to-world 4x4 and pinhole intrinsics.

- ``interpolate``: through the training cameras in name order (or through the cameras of a
  ``viewer_cameras.json``), positions linear and rotations spherically interpolated between neighbours, so
  the path passes through every key camera;
- ``spiral``: LLFF's forward-facing spiral around the average camera, radii from the cameras' spread, every
  frame looking at the focus point (the point nearest all optical axes);
- ``ellipse``: the same ellipse in the average camera's image plane without the dolly, looking at the
  focus point;
- ``test``: the test views themselves (``jsgs render`` shows them beside their references).

A path is written as JSON (``jsgs/schemas/camera_path.schema.json``) and read back with ``--path FILE.json``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from jsgs.base.errors import JsgsError
from jsgs.base.limits import read_json
from jsgs.base.rotations import matrix_to_quat, quat_to_matrix

KINDS = ("interpolate", "spiral", "ellipse", "test")
PATH_FORMAT = "jsgs-camera-path"
PATH_VERSION = 1


@dataclass
class CameraPath:
    """``camtoworld`` [F, 4, 4] float64 (training world), ``K`` [3, 3] pixels for ``width`` x ``height``."""

    camtoworld: np.ndarray
    K: np.ndarray
    width: int
    height: int
    kind: str

    def to_json(self, fps: float) -> dict[str, Any]:
        import jsgs

        return {
            "format": PATH_FORMAT, "format_version": PATH_VERSION, "jsgs_version": jsgs.__version__,
            "frame": "training", "kind": self.kind, "width": self.width, "height": self.height,
            "K": self.K.tolist(), "fps": fps, "camtoworld": self.camtoworld.tolist(),
        }  # fmt: skip


def slerp(q0: np.ndarray, q1: np.ndarray, t: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions (the shorter arc)."""
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + t * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(d)
    return (math.sin((1 - t) * theta) * q0 + math.sin(t * theta) * q1) / math.sin(theta)


def interpolate(keys: np.ndarray, frames: int) -> np.ndarray:
    """``frames`` camera-to-world matrices through the key poses [K, 4, 4] (first and last included)."""
    if len(keys) == 1 or frames == 1:
        return np.repeat(keys[:1], frames, axis=0)
    qs = [matrix_to_quat(k[:3, :3]) for k in keys]
    out = []
    for u in np.linspace(0.0, len(keys) - 1, frames):
        i = min(int(u), len(keys) - 2)
        t = u - i
        c2w = np.eye(4)
        c2w[:3, :3] = quat_to_matrix(slerp(qs[i], qs[i + 1], t))
        c2w[:3, 3] = (1 - t) * keys[i][:3, 3] + t * keys[i + 1][:3, 3]
        out.append(c2w)
    return np.stack(out)


def focus_point(c2ws: np.ndarray) -> np.ndarray:
    """The point nearest (least squares) to every camera's optical axis (+Z of each camera)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c in c2ws:
        d = c[:3, 2] / np.linalg.norm(c[:3, 2])
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c[:3, 3]
    return np.linalg.lstsq(A, b, rcond=None)[0]


def look_at(position: np.ndarray, target: np.ndarray, down: np.ndarray) -> np.ndarray:
    """Camera-to-world with +Z towards ``target`` and +Y as close to ``down`` as possible (OpenCV axes)."""
    z = target - position
    z = z / np.linalg.norm(z)
    x = np.cross(down, z)
    if np.linalg.norm(x) < 1e-9:  # looking straight along the down axis
        x = np.cross([1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0], z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, y, z], axis=1)
    c2w[:3, 3] = position
    return c2w


def _average_pose(c2ws: np.ndarray) -> np.ndarray:
    z = c2ws[:, :3, 2].mean(axis=0)
    down = c2ws[:, :3, 1].mean(axis=0)
    centre = c2ws[:, :3, 3].mean(axis=0)
    return look_at(centre, centre + z, down)


def orbit(c2ws: np.ndarray, frames: int, kind: str) -> np.ndarray:
    """``spiral`` or ``ellipse`` frames around the cameras' focus point (see the module docstring)."""
    if not np.linalg.norm(c2ws[:, :3, 2].mean(axis=0)) > 1e-6:  # the average camera would look nowhere
        raise JsgsError(
            f"--path {kind}: the training cameras look all around (their mean viewing direction is zero); "
            f"{kind} circles a forward-facing capture: use --path interpolate or a camera path file"
        )
    avg = _average_pose(c2ws)
    focus = focus_point(c2ws)
    local = (c2ws[:, :3, 3] - avg[:3, 3]) @ avg[:3, :3]  # camera positions in the average camera's axes
    radii = np.percentile(np.abs(local), 90, axis=0)
    radii = np.where(radii > 1e-9, radii, 1e-3 * max(1.0, float(np.linalg.norm(focus - avg[:3, 3]))))
    down = avg[:3, 1]
    out = []
    for th in np.linspace(0.0, 2 * math.pi, frames, endpoint=False):
        # both in the average camera's image plane (x, y); the spiral also dollies slowly along z (LLFF)
        dolly = -math.sin(0.5 * th) if kind == "spiral" else 0.0
        offset = radii * np.array([math.cos(th), -math.sin(th), dolly])
        pos = avg[:3, 3] + avg[:3, :3] @ offset
        out.append(look_at(pos, focus, down))
    return np.stack(out)


def build_path(
    kind: str, train_c2w: np.ndarray, K: np.ndarray, width: int, height: int, frames: int
) -> CameraPath:
    """A generated path (``kind`` in ``interpolate``, ``spiral``, ``ellipse``) from the training cameras."""
    if frames < 1:
        raise JsgsError(f"--frames {frames}: must be at least 1")
    if len(train_c2w) == 0:
        raise JsgsError("the run has no training cameras to build a path from")
    if kind == "interpolate":
        c2w = interpolate(train_c2w, frames)
    elif kind in ("spiral", "ellipse"):
        c2w = orbit(train_c2w, frames, kind)
    else:
        raise JsgsError(f"--path {kind!r}: choose {', '.join(KINDS)} or a camera path JSON file")
    return CameraPath(c2w, K, width, height, kind)


def scaled_K(K: np.ndarray, width: int, height: int, new_width: int, new_height: int) -> np.ndarray:
    """Intrinsics for the same field of view at another image size (pixel centres at integer + 0.5)."""
    sx, sy = new_width / width, new_height / height
    out = np.array(K, dtype=np.float64)
    out[0, 0], out[0, 2] = K[0, 0] * sx, K[0, 2] * sx
    out[1, 1], out[1, 2] = K[1, 1] * sy, K[1, 2] * sy
    return out


def _poses(values: Any, where: str) -> np.ndarray:
    """(N, 4, 4) camera-to-world matrices read from a file: finite, positions within
    ±:data:`jsgs.base.limits.MAX_COORDINATE`, rotations that are rotations, last rows 0 0 0 1; JsgsError
    naming the first that is not."""
    from jsgs.base.limits import check_coordinates

    c2w = np.asarray(values, dtype=np.float64).reshape(-1, 4, 4)
    check_coordinates(c2w, where, by_row=True)
    for i, R in enumerate(c2w[:, :3, :3]):
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
            raise JsgsError(f"{where}/{i}: not a camera pose (its rotation is not a rotation)")
        if np.abs(c2w[i, 3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
            raise JsgsError(f"{where}/{i}: not a camera pose (its last row is not 0 0 0 1)")
    return c2w


def read_path(
    path: Path, frames: int, K: np.ndarray, width: int, height: int, max_cameras: int | None = None
) -> CameraPath:
    """A camera path JSON written by ``jsgs render`` (taken as it is), or ``viewer_cameras.json`` (its cameras
    are key frames: ``frames`` frames interpolated through them at the run's intrinsics). ``max_cameras``:
    a file holding more is refused before it is validated."""
    from jsgs.base.schema import validate

    if not path.exists():
        raise JsgsError(f"--path {path}: no such file (or give interpolate, spiral, ellipse, test)")
    doc = read_json(path, "a camera path JSON file")
    kind = doc.get("format") if isinstance(doc, dict) else None
    listed = doc.get("camtoworld" if kind == PATH_FORMAT else "cameras") if isinstance(doc, dict) else None
    if max_cameras is not None and isinstance(listed, list) and len(listed) > max_cameras:
        raise JsgsError(f"{path}: {len(listed)} cameras; render draws at most {max_cameras:,}")
    if kind == PATH_FORMAT:
        validate(doc, "camera_path", str(path))
        c2w = _poses(doc["camtoworld"], f"{path}: camtoworld")
        K_doc = np.asarray(doc["K"], dtype=np.float64)
        if not (K_doc[0, 0] > 0 and K_doc[1, 1] > 0):
            raise JsgsError(f"{path}: K: a focal length is not positive")
        return CameraPath(c2w, K_doc, int(doc["width"]), int(doc["height"]), str(doc["kind"]))
    if kind == "jsgs-viewer-cameras":
        validate(doc, "viewer_cameras", str(path))
        keys = _poses([c["camtoworld"] for c in doc["cameras"]], f"{path}: cameras")
        if len(keys) == 0:
            raise JsgsError(f"{path}: holds no saved camera")
        return CameraPath(interpolate(keys, frames), K, width, height, "interpolate")
    raise JsgsError(f"{path}: neither a jsgs camera path nor a viewer_cameras.json (format {kind!r})")
