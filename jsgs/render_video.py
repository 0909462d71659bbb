"""``jsgs render RUN --out FILE``: a finished run rendered along a camera path (:mod:`jsgs.camera_path`) to a
video (imageio with imageio-ffmpeg, whose ffmpeg ships inside its wheel) or to numbered PNG frames, with the
path written beside it as JSON so it can be edited and rendered again. ``--path test`` shows each test view
beside its reference. Rendering is the run's own rasterizer (gsplat on CUDA, the torch reference on the
CPU)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from jsgs.errors import JsgsError

VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".avi")


def parse_size(text: str | None) -> tuple[int, int] | None:
    """``"WxH"`` -> (W, H); None -> None."""
    if text is None:
        return None
    parts = text.lower().split("x")
    try:
        w, h = (int(p) for p in parts)
        if w < 1 or h < 1 or len(parts) != 2:
            raise ValueError
    except ValueError:
        raise JsgsError(f"--size {text!r}: give WIDTHxHEIGHT in pixels, e.g. 640x480") from None
    return w, h


def _even(img: np.ndarray) -> np.ndarray:
    """Pad to even width and height (H.264 with 4:2:0 chroma needs them) by repeating the last row/column."""
    h, w = img.shape[:2]
    return np.pad(img, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def _side_by_side(render: np.ndarray, reference: np.ndarray) -> np.ndarray:
    from PIL import Image

    if reference.shape != render.shape:
        reference = np.asarray(Image.fromarray(reference).resize((render.shape[1], render.shape[0])))
    return np.concatenate([render, reference], axis=1)


def render_run(
    run: str | Path,
    out: str | Path,
    path: str = "interpolate",
    frames: int = 120,
    fps: float = 30.0,
    size: tuple[int, int] | None = None,
    device: str = "auto",
    progress: bool = True,
    force: bool = False,
) -> dict[str, Any]:
    """Render ``run`` along ``path`` into ``out`` (a video for a video suffix, else a folder of PNG frames)
    and write the camera path JSON beside it; returns ``{"frames", "out", "cameras", "width", "height"}``."""
    from tqdm import tqdm

    from jsgs.camera_path import KINDS, CameraPath, build_path, read_path, scaled_K
    from jsgs.io import write_json_atomic
    from jsgs.schemas import validate
    from jsgs.train.data import load_image
    from jsgs.viewer import load_run_model, render_rgb

    out = Path(out)
    if fps <= 0:
        raise JsgsError(f"--fps {fps:g}: must be positive")
    video = out.suffix.lower() in VIDEO_SUFFIXES
    if not video and out.suffix:
        raise JsgsError(f"{out}: give a video ({', '.join(VIDEO_SUFFIXES)}) or a folder for PNG frames")
    cameras = out.with_name(out.name + ".cameras.json") if video else out / "cameras.json"
    if video and (out.exists() or cameras.exists()) and not force:
        raise JsgsError(f"{out}: exists (use --force to replace it)")
    if not video and out.is_dir() and any(out.iterdir()) and not force:
        raise JsgsError(f"{out}: folder is not empty (use --force to replace its frames)")

    model = load_run_model(run, device)
    views = sorted(model.scene.train_views, key=lambda v: v.name)
    if not views:
        raise JsgsError(f"{run}: its manifest has no training views")
    v0 = views[0]
    width, height = size or (v0.width, v0.height)
    K = scaled_K(v0.K, v0.width, v0.height, width, height)
    references: list[np.ndarray] = []
    if path == "test":
        tests = sorted(model.scene.test_views, key=lambda v: v.name)
        if not tests:
            raise JsgsError(f"{run}: --path test: the run has no test views")
        c2w = np.stack([v.camtoworld for v in tests])
        cam = CameraPath(c2w, K, width, height, "test")
        Ks = [scaled_K(v.K, v.width, v.height, width, height) for v in tests]
        references = [load_image(v.eval_image_path(), v.width, v.height, "reference").numpy() for v in tests]
    elif path in KINDS:
        cam = build_path(path, np.stack([v.camtoworld for v in views]), K, width, height, frames)
        Ks = [cam.K] * len(cam.camtoworld)
    else:
        cam = read_path(Path(path), frames, K, width, height)
        Ks = [cam.K] * len(cam.camtoworld)

    doc = cam.to_json(fps)
    validate(doc, "camera_path", str(cameras))
    imgs = []
    for i, c2w in enumerate(tqdm(cam.camtoworld, desc="render", unit="frame", disable=not progress)):
        img = render_rgb(model, np.linalg.inv(c2w), Ks[i], cam.width, cam.height)
        imgs.append(_side_by_side(img, references[i]) if references else img)

    if video:
        import imageio.v2 as iio

        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.stem}.part{out.suffix}")
        try:
            writer = iio.get_writer(tmp, fps=fps, codec="libx264", quality=8, macro_block_size=1)
            try:
                for img in imgs:
                    writer.append_data(_even(img))
            finally:
                writer.close()
            os.replace(tmp, out)
        finally:
            if tmp.exists():
                tmp.unlink()
    else:
        from jsgs.io import write_with_atomic

        out.mkdir(parents=True, exist_ok=True)
        from PIL import Image

        for old in out.glob("frame_*.png"):
            old.unlink()
        for i, img in enumerate(imgs):
            def save(p: Path, a: np.ndarray = img) -> None:
                Image.fromarray(a).save(p, format="PNG")

            write_with_atomic(out / f"frame_{i:05d}.png", save)
    write_json_atomic(cameras, doc)
    return {"frames": len(imgs), "out": str(out), "cameras": str(cameras), "width": imgs[0].shape[1],
            "height": imgs[0].shape[0]}  # fmt: skip
