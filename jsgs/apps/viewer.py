"""``jsgs view RUN``: a browser viewer of a trained run (viser), rendered on the server with the run's own
rasterizer (gsplat on CUDA, the torch reference on the CPU at a reduced size), the training cameras drawn as
frustums, and a button that saves the current camera to ``RUN/viewer_cameras.json``.

Camera conventions: viser reports each browser camera as ``position`` and ``wxyz`` with
``P_world = R p_camera + position`` in OpenCV axes (+Z forward, +Y down), ``fov`` the vertical field of view
in radians and ``aspect`` = width / height; the trainer's views use the same axes (normalised training
world).
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from jsgs.base.errors import JsgsError
from jsgs.base.rotations import matrix_to_quat, pose_matrix
from jsgs.train.callbacks import Callback
from jsgs.train.config import TrainConfig
from jsgs.train.data import TrainingScene

if TYPE_CHECKING:
    from jsgs.train.callbacks import StepResult
    from jsgs.train.trainer import Trainer

CAMERAS_FORMAT = "jsgs-viewer-cameras"
CAMERAS_VERSION = 1


@dataclass
class RunModel:
    """A trained run ready to render: its Gaussians (``splats``, training world), settings and cameras."""

    run: Path
    splats: torch.nn.ParameterDict
    cfg: TrainConfig
    scene: TrainingScene
    device: torch.device
    backend: str


def load_run_model(run: str | Path, device: str = "auto") -> RunModel:
    """Read ``RUN/config.json`` and ``RUN/point_cloud.ply`` and the run's manifest (its cameras).

    JsgsError (one line) when RUN is not a finished run, its manifest has moved or its scene cannot be read
    (saying so when the manifest changed since training: its sha256 differs from ``config.json``'s); the
    scene has at least one training view (:func:`jsgs.train.data.load_training_scene` refuses one without)."""
    from jsgs.base.ply import load_ply
    from jsgs.train.config import read_run_config
    from jsgs.train.data import load_training_scene
    from jsgs.train.model import splats_from_state
    from jsgs.train.render_view import resolve_backend, resolve_device

    run = Path(run)
    if not run.is_dir():
        raise JsgsError(f"{run}: no such run folder")
    recorded = read_run_config(run)
    cfg = recorded.settings
    ply = run / "point_cloud.ply"
    if not ply.is_file():
        raise JsgsError(
            f"{run}: no point_cloud.ply (the run is not finished: jsgs train --resume continues it)"
        )
    manifest = recorded.manifest
    if not manifest.is_file():
        raise JsgsError(f"{run}: its manifest {manifest} is not there any more (the cameras come from it)")
    try:
        scene = load_training_scene(manifest, cfg)
    except JsgsError as e:
        raise _changed_since_training(manifest, recorded.manifest_sha256, run, e) from None
    dev = resolve_device(device)
    a = load_ply(ply)
    state = {
        "means": a["means"], "scales": a["scales_log"], "quats": a["quats"],
        "opacities": a["opacities_logit"], "sh0": a["sh0"], "shN": a["shN"],
    }  # fmt: skip
    splats = splats_from_state({k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in state.items()}, dev)
    return RunModel(run, splats, cfg, scene, dev, resolve_backend(cfg, dev))


def _changed_since_training(manifest: Path, recorded_sha256: str, run: Path, error: JsgsError) -> JsgsError:
    """``error`` (the scene could not be read) as is when ``manifest`` is the one ``run`` was trained on, else
    one line saying it changed since, with the original reason."""
    import hashlib

    try:
        sha = hashlib.sha256(manifest.read_bytes()).hexdigest()
    except OSError:
        return error
    if sha == recorded_sha256:
        return error
    reason = str(error).removeprefix(f"{manifest}: ")
    return JsgsError(
        f"{manifest}: changed since {run} was trained (sha256 differs from config.json's); {reason}"
    )


def image_size(aspect: float, max_size: int) -> tuple[int, int]:
    """(width, height) with the longer side ``max_size`` pixels and width / height ≈ ``aspect``."""
    if aspect >= 1:
        return max_size, max(1, round(max_size / aspect))
    return max(1, round(max_size * aspect)), max_size


def camera_matrices(
    position: np.ndarray, wxyz: np.ndarray, fov: float, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """A viewer camera -> (viewmat 4x4 world-to-camera, K 3x3 in pixels), float64. ``fov``: vertical, radians;
    the principal point at the image centre (pixel centres at integer + 0.5, as in the trainer)."""
    c2w = pose_matrix(position, wxyz)
    f = 0.5 * height / math.tan(0.5 * fov)
    K = np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]])
    return np.linalg.inv(c2w), K


@torch.no_grad()
def render_rgb(model: RunModel, viewmat: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """The run's Gaussians seen by one camera: uint8 [height, width, 3]."""
    from jsgs.train.render_view import render_view

    vm: Tensor = torch.as_tensor(viewmat, dtype=torch.float32, device=model.device)[None]
    k: Tensor = torch.as_tensor(K, dtype=torch.float32, device=model.device)[None]
    sh = model.cfg.render.sh_degree
    out = render_view(model.splats, vm, k, width, height, sh, model.cfg, model.backend)
    rgb = out.rgb[0].clamp(0.0, 1.0).mul(255.0).round().to(torch.uint8)
    return rgb.cpu().numpy()


def check_camera(
    position: Any, wxyz: Any, fov: Any, aspect: Any
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """A camera as the browser reports it, checked before anything is computed from it: ``position`` 3
    finite coordinates within ±:data:`jsgs.base.limits.MAX_COORDINATE`, ``wxyz`` 4 finite numbers of norm at
    least 1e-6 (returned normalised), ``fov`` in (0, π) radians, ``aspect`` in [1e-3, 1e3]. JsgsError (one
    line) naming the value."""
    from jsgs.base.limits import check_coordinates, check_number

    try:
        p = np.asarray(position, dtype=np.float64).reshape(3)
        q = np.asarray(wxyz, dtype=np.float64).reshape(4)
    except (TypeError, ValueError):
        raise JsgsError(f"viewer camera: position {position!r} or orientation {wxyz!r} malformed") from None
    check_coordinates(p, "viewer camera position")
    norm = float(np.linalg.norm(q)) if np.isfinite(q).all() else math.nan
    if not norm >= 1e-6:
        raise JsgsError(f"viewer camera orientation: quaternion {q.tolist()} is no rotation (norm {norm:g})")
    f = check_number(fov, "viewer camera field of view (radians)", 0.0, math.pi, lo_open=True)
    if f >= math.pi:
        raise JsgsError(f"viewer camera field of view (radians) must be below π (got {f!r})")
    a = check_number(aspect, "viewer camera aspect (width / height)", 1e-3, 1e3)
    return p, q / norm, f, a


def save_camera(model: RunModel, position: np.ndarray, wxyz: np.ndarray, fov: float, aspect: float) -> Path:
    """Append a camera (checked by :func:`check_camera`) to ``RUN/viewer_cameras.json``
    (``jsgs/schemas/viewer_cameras.schema.json``, written atomically); returns the path."""
    import jsgs
    from jsgs.base.io import write_json_atomic
    from jsgs.base.limits import read_json
    from jsgs.base.schema import validate

    position, wxyz, fov, aspect = check_camera(position, wxyz, fov, aspect)
    path = model.run / "viewer_cameras.json"
    doc: dict[str, Any]
    if path.is_file():
        doc = read_json(path, "a viewer cameras file")
        validate(doc, "viewer_cameras", str(path))
    else:
        doc = {"format": CAMERAS_FORMAT, "format_version": CAMERAS_VERSION, "jsgs_version": jsgs.__version__,
               "frame": "training", "cameras": []}  # fmt: skip
    c2w = pose_matrix(position, wxyz)
    doc["cameras"].append({
        "camtoworld": c2w.tolist(), "fov_y_deg": math.degrees(fov), "aspect": float(aspect),
        "saved": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    })  # fmt: skip
    validate(doc, "viewer_cameras", str(path))
    write_json_atomic(path, doc)
    return path


def frustum_scale(positions: np.ndarray, extent: float) -> float:
    """The size of the training cameras' frustums in the viewer: a quarter of the median distance from a
    camera to its nearest neighbour, at most 2 % of the scene's camera extent, so that neighbouring frustums
    do not overlap and none fills the view of a camera next to it (1 % of the extent for a single camera or
    cameras at one place)."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    cap = 0.02 * (extent if extent > 0 else 1.0)
    if len(p) < 2:
        return 0.5 * cap
    d = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)
    np.fill_diagonal(d, np.inf)
    nearest = float(np.median(d.min(axis=1)))
    return min(0.25 * nearest, cap) if nearest > 0 else 0.5 * cap


def start_camera(camtoworld: np.ndarray, means: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where a browser starts: (position, look-at point, up direction) of a training camera (its pose
    unchanged), the look-at point on its optical axis at the depth of the model's centre (the median of the
    Gaussians' centres), so that the view orbits about the model; a centre behind the camera gives the
    median distance of the Gaussians instead."""
    c2w = np.asarray(camtoworld, dtype=np.float64)
    position, axis = c2w[:3, 3], c2w[:3, 2]  # OpenCV: +Z forward, +Y down
    m = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    m = m[np.isfinite(m).all(axis=1)]
    depth = float(np.dot(np.median(m, axis=0) - position, axis)) if len(m) else 0.0
    if depth <= 1e-6:
        dist = np.linalg.norm(m - position, axis=1) if len(m) else np.ones(1)
        depth = max(float(np.median(dist)), 1e-3)
    return position, position + depth * axis, -c2w[:3, 1]


def add_frustums(scene_api: Any, views: list[Any], scale: float, skip: int | None = None) -> list[Any]:
    """Draw ``views``' cameras as wireframe frustums of size ``scale`` with thin lines of a fixed pixel width
    on ``scene_api`` (a viser scene: the server's or one browser's), except the view of index ``skip`` (the
    camera a browser starts at, which would be seen from inside); returns their handles."""
    handles = []
    for v in views:
        if v.index == skip:
            continue
        fov = 2.0 * math.atan(0.5 * v.height / float(v.K[1, 1]))
        handles.append(scene_api.add_camera_frustum(
            f"/cameras/{v.index:04d}", fov=fov, aspect=v.width / v.height, scale=scale, thickness=1.5,
            thickness_units="screen", color=(90, 90, 90),
            wxyz=matrix_to_quat(v.camtoworld[:3, :3]), position=v.camtoworld[:3, 3],
        ))  # fmt: skip
    return handles


class Viewer:
    """A viser server showing ``model``: each connected browser starts at the first training camera looking
    at the model (:func:`start_camera`) and gets renders of its camera (latest camera wins; one render thread
    per browser), the other training cameras as small frustums (:func:`frustum_scale`) that a checkbox hides,
    and a save-camera button."""

    def __init__(self, model: RunModel, host: str = "127.0.0.1", port: int = 8080, max_size: int = 512):
        import viser

        self.model = model
        self.max_size = max_size
        self.lock = threading.Lock()  # one render at a time on the device
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        self._stop = threading.Event()
        views = model.scene.train_views
        positions = np.array([v.camtoworld[:3, 3] for v in views]).reshape(-1, 3)
        self.frustum_scale = frustum_scale(positions, float(model.scene.camera_extent or 1.0))
        self.server.on_client_connect(self._on_connect)

    def _on_connect(self, client: Any) -> None:
        views = self.model.scene.train_views
        start = None
        if views:
            v = views[0]
            start = v.index
            with self.lock:  # a live run's step holds it while it changes the Gaussians
                means = self.model.splats["means"].detach().cpu().numpy()
            position, look_at, up = start_camera(v.camtoworld, means)
            client.camera.up_direction = tuple(up)
            client.camera.position = tuple(position)
            client.camera.look_at = tuple(look_at)
            client.camera.fov = 2.0 * math.atan(0.5 * v.height / float(v.K[1, 1]))
        frustums = add_frustums(client.scene, views, self.frustum_scale, skip=start)
        show = client.gui.add_checkbox("Training cameras", initial_value=True)

        @show.on_update
        def _(_: Any) -> None:
            for h in frustums:
                h.visible = show.value

        button = client.gui.add_button("Save camera")
        changed = threading.Event()
        changed.set()

        @button.on_click
        def _(_: Any) -> None:
            c = client.camera
            try:
                path = save_camera(self.model, c.position, c.wxyz, c.fov, c.aspect)
            except JsgsError as e:  # a camera the browser reported broken: say so, save nothing
                client.add_notification("Camera not saved", str(e), auto_close_seconds=5.0)
                return
            client.add_notification("Camera saved", f"{path}", auto_close_seconds=3.0)

        @client.camera.on_update
        def _(_: Any) -> None:
            changed.set()

        def loop() -> None:
            while not self._stop.is_set():
                if not changed.wait(timeout=0.2):
                    continue
                changed.clear()
                c = client.camera
                try:
                    position, wxyz, fov, aspect = check_camera(c.position, c.wxyz, c.fov, c.aspect)
                except JsgsError:  # a broken camera from the browser: keep the last image
                    continue
                w, h = image_size(aspect, self.max_size)
                viewmat, K = camera_matrices(position, wxyz, fov, w, h)
                with self.lock:
                    img = render_rgb(self.model, viewmat, K, w, h)
                try:
                    client.scene.set_background_image(img, format="jpeg", jpeg_quality=90)
                except Exception:  # the browser went away
                    return

        threading.Thread(target=loop, daemon=True, name=f"jsgs-view-{client.client_id}").start()

    def stop(self) -> None:
        self._stop.set()
        self.server.stop()


class LiveViewer(Callback):
    """``jsgs train --viewer``: the same viewer on the model being trained. Renders happen between training
    steps (the step holds the viewer's lock), so a browser sees each state whole; the server stops with the
    run (``jsgs view RUN`` shows the finished model)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, max_size: int | None = None,
                 announce: Callable[[str], None] | None = None) -> None:  # fmt: skip
        self.host, self.port, self.max_size = host, port, max_size
        self.announce = announce or (lambda s: print(s, file=sys.stderr, flush=True))
        self.viewer: Viewer | None = None

    def on_setup(self, trainer: Trainer) -> None:
        model = RunModel(trainer.paths.root, trainer.splats, trainer.cfg, trainer.scene, trainer.device,
                         trainer.backend)  # fmt: skip
        size = self.max_size or (1024 if trainer.device.type == "cuda" else 320)
        self.viewer = Viewer(model, host=self.host, port=self.port, max_size=size)
        self.announce(f"viewer: http://localhost:{self.viewer.port} (the model as it trains)")
        if trainer.world.enabled:  # the callbacks run on rank 0, which holds its shard only
            self.announce(
                f"note: the viewer shows rank 0's shard of the Gaussians (about 1/{trainer.world.size} of "
                "them) while the run trains on several processes; `jsgs view RUN` shows the whole model"
            )

    def on_step_begin(self, trainer: Trainer, step: int) -> None:
        if self.viewer is not None:
            self.viewer.lock.acquire()

    def on_step_end(self, trainer: Trainer, result: StepResult) -> None:
        if self.viewer is not None:
            self.viewer.model.splats = trainer.splats  # densification replaces the tensors
            self.viewer.lock.release()

    def on_end(self, trainer: Trainer, doc: dict[str, Any] | None) -> None:
        if self.viewer is not None:
            if self.viewer.lock.locked():  # a step that raised
                self.viewer.lock.release()
            self.viewer.stop()
            self.viewer = None
