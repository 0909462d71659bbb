"""``jsgs render RUN --out FILE``: a finished run rendered along a camera path (:mod:`jsgs.apps.camera_path`)
to a video (imageio with imageio-ffmpeg, whose ffmpeg ships inside its wheel) or to numbered PNG frames, with
the path written beside it as JSON so it can be edited and rendered again. ``--path test`` shows each test
view beside its reference. Rendering is the run's own rasterizer (gsplat on CUDA, the torch reference on the
CPU)."""

from __future__ import annotations

import math
import os
import re
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from jsgs.base.errors import JsgsError

VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".avi")
#: the largest width or height rendered (an 8K frame): one frame is held at a time, but the rasterizer's
#: buffers grow with the pixels, so a larger request is refused before anything is loaded
MAX_SIDE = 8192
#: frames per second accepted by --fps (ffmpeg takes any positive rate; beyond this it is a typo)
MAX_FPS = 1000.0
#: the most frames one call renders (--frames, or the cameras of a path file)
MAX_FRAMES = 100_000


def parse_size(text: str | None) -> tuple[int, int] | None:
    """``"WxH"`` -> (W, H), each side 1 .. :data:`MAX_SIDE`; None -> None."""
    if text is None:
        return None
    parts = text.lower().split("x")
    try:
        w, h = (int(p) for p in parts)
        if w < 1 or h < 1 or len(parts) != 2:
            raise ValueError
    except ValueError:
        raise JsgsError(f"--size {text!r}: give WIDTHxHEIGHT in pixels, e.g. 640x480") from None
    check_size(w, h, f"--size {text}")
    return w, h


def check_size(width: int, height: int, source: str) -> None:
    """JsgsError naming ``source`` when a side exceeds :data:`MAX_SIDE`."""
    if max(width, height) > MAX_SIDE:
        raise JsgsError(
            f"{source}: {width}x{height} is larger than jsgs render draws (at most {MAX_SIDE} pixels a side)"
        )


def check_fps(fps: float) -> None:
    """JsgsError unless ``fps`` is finite, positive and at most :data:`MAX_FPS`."""
    if not (math.isfinite(fps) and 0 < fps <= MAX_FPS):
        raise JsgsError(f"--fps {fps:g}: give frames per second above 0 and at most {MAX_FPS:g}")


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
    say: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Render ``run`` along ``path`` into ``out`` (a video for a video suffix, else a folder of PNG frames)
    and write the camera path JSON beside it; returns ``{"frames", "out", "cameras", "width", "height"}``.

    Frames are rendered one at a time and streamed to the encoder (or to their PNG files), so memory holds
    one frame whatever the path's length. The video goes through a temporary file of an unpredictable name
    in its folder, with a marker naming its writer beside it (:func:`jsgs.base.io.atomic_path`); a failure
    leaves neither it nor any frame of this call.
    The run's own files are never written (:func:`jsgs.base.run_files.refuse_run_files`), and a model that
    would draw nothing (no Gaussians, a non-finite value, a zero rotation) is refused. What a killed render
    to the same output left beside it is dealt with first (:func:`jsgs.base.io.clear_file_leftovers`,
    :func:`jsgs.base.io.clear_folder_leftovers`), one line to ``say`` (stderr by default) each."""
    from tqdm import tqdm

    from jsgs.apps.camera_path import KINDS, CameraPath, build_path, read_path, scaled_K
    from jsgs.apps.viewer import load_run_model, render_rgb
    from jsgs.base.io import clear_file_leftovers, clear_folder_leftovers
    from jsgs.base.run_files import refuse_run_files
    from jsgs.base.schema import validate
    from jsgs.train.data import load_image

    out = Path(out)
    check_fps(fps)
    if size is not None:
        check_size(*size, f"--size {size[0]}x{size[1]}")
    video = out.suffix.lower() in VIDEO_SUFFIXES
    if not video and out.suffix:
        raise JsgsError(f"{out}: give a video ({', '.join(VIDEO_SUFFIXES)}) or a folder for PNG frames")
    cameras = out.with_name(out.name + ".cameras.json") if video else out / "cameras.json"
    refuse_run_files(run, (out, cameras), "render writes only new files (choose another --out)")
    if video and out.is_dir():
        raise JsgsError(f"{out}: is a folder; give a video file name")
    for line in clear_file_leftovers(out) if video else clear_folder_leftovers(out):
        (say or (lambda s: print(s, file=sys.stderr)))(line)
    if video and (os.path.lexists(out) or os.path.lexists(cameras)) and not force:
        raise JsgsError(f"{out}: exists (use --force to replace it)")
    if not video and (os.path.lexists(out) and not out.is_dir()):
        raise JsgsError(f"{out}: exists and is not a folder")
    if not video and out.is_dir() and any(out.iterdir()):
        if not force:
            raise JsgsError(f"{out}: folder is not empty (use --force to replace its frames)")
        check_frames_folder(out)

    model = load_run_model(run, device)  # refuses a model that would draw nothing
    views = sorted(model.scene.train_views, key=lambda v: v.name)  # at least one: the scene's check
    v0 = views[0]
    width, height = size or (v0.width, v0.height)
    check_size(width, height, f"{run}: the training images' size (give --size)")
    K = scaled_K(v0.K, v0.width, v0.height, width, height)
    tests = []
    if path == "test":
        tests = sorted(model.scene.test_views, key=lambda v: v.name)
        if not tests:
            raise JsgsError(f"{run}: --path test: the run has no test views")
        c2w = np.stack([v.camtoworld for v in tests])
        cam = CameraPath(c2w, K, width, height, "test")
        Ks = [scaled_K(v.K, v.width, v.height, width, height) for v in tests]
    elif path in KINDS:
        cam = build_path(path, np.stack([v.camtoworld for v in views]), K, width, height, frames)
        Ks = [cam.K] * len(cam.camtoworld)
    else:
        cam = read_path(Path(path), frames, K, width, height, max_cameras=MAX_FRAMES)
        check_size(cam.width, cam.height, f"{path}: its width and height")
        Ks = [cam.K] * len(cam.camtoworld)

    doc = cam.to_json(fps)
    validate(doc, "camera_path", str(cameras))

    def images() -> Iterator[np.ndarray]:
        for i, c2w in enumerate(tqdm(cam.camtoworld, desc="render", unit="frame", disable=not progress)):
            img = render_rgb(model, np.linalg.inv(c2w), Ks[i], cam.width, cam.height)
            if tests:
                v = tests[i]
                ref = load_image(v.eval_image_path(), v.width, v.height, "reference").numpy()
                img = _side_by_side(img, ref)
            yield img

    if video:
        count, shape = _write_video(out, images(), fps, cameras, doc)
    else:
        count, shape = _write_frames(out, images(), doc)
    return {"frames": count, "out": str(out), "cameras": str(cameras), "width": shape[1], "height": shape[0]}


def _write_video(
    out: Path, images: Iterator[np.ndarray], fps: float, cameras: Path, doc: dict[str, Any]
) -> tuple[int, tuple[int, ...]]:
    """Stream ``images`` to an H.264 video (imageio-ffmpeg) in a temporary file of ``out``'s folder, write
    ``cameras``, then rename the video onto ``out``."""
    import imageio.v2 as iio

    from jsgs.base.errors import one_line
    from jsgs.base.io import atomic_path, write_json_atomic

    count, shape = 0, (0, 0)
    with atomic_path(out, "jsgs render") as tmp:
        try:
            writer = iio.get_writer(tmp, fps=fps, codec="libx264", quality=8, macro_block_size=1)
            try:
                for img in images:
                    writer.append_data(_even(img))
                    count, shape = count + 1, img.shape
            finally:
                writer.close()
        except (OSError, RuntimeError, ValueError) as e:  # the encoder's failures: ffmpeg's exit, a full disk
            raise JsgsError(f"{out}: the video encoder failed ({one_line(e)})") from None
        write_json_atomic(cameras, doc)
    return count, shape


#: the entries of a folder of frames jsgs render wrote: its frames, the camera path, and the temporary
#: files of its atomic writes that a killed call left
_FRAMES_ENTRY = re.compile(r"(\.)?(?:frame_\d{5}\.png|cameras\.json)(?(1)\.\w+\.part\.\w+)")


def check_frames_folder(out: Path) -> None:
    """JsgsError (one line) unless ``out`` is a folder jsgs render made: a real folder (not a link) holding
    its ``cameras.json`` and only plain files it writes (``frame_NNNNN.png``); ``--force`` replaces only such
    a folder, so nothing the tool did not write is deleted."""
    hint = "--force replaces only a folder of frames that jsgs render made (choose another --out)"
    if out.is_symlink():
        raise JsgsError(f"{out}: is a link; {hint}")
    for p in sorted(out.iterdir()):
        if not _FRAMES_ENTRY.fullmatch(p.name) or p.is_symlink() or not p.is_file():
            raise JsgsError(f"{out}: holds {p.name}, which jsgs render does not write; {hint}")
    if not (out / "cameras.json").is_file():
        raise JsgsError(f"{out}: has no cameras.json of jsgs render; {hint}")


def _write_frames(
    out: Path, images: Iterator[np.ndarray], doc: dict[str, Any]
) -> tuple[int, tuple[int, ...]]:
    """Each image to ``frame_NNNNN.png`` as it comes (atomically), then ``cameras.json``, into a temporary
    sibling folder that replaces ``out`` only when complete (:func:`jsgs.base.io.atomic_folder`): earlier
    frames (--force, :func:`check_frames_folder`) are removed only then, and a failed or interrupted call
    leaves them as they were (a killed one leaves a hidden ``.NAME.*.part`` folder beside ``out``, which the
    next render removes). A link
    to an empty folder is written through, in place (a failure removes what this call wrote)."""
    from contextlib import nullcontext

    from PIL import Image

    from jsgs.base.io import atomic_folder, write_json_atomic, write_with_atomic

    in_place = out.is_symlink()  # to an empty folder: render_run refuses a link to a non-empty one
    written: list[Path] = []
    shape: tuple[int, ...] = (0, 0)
    with nullcontext(out) if in_place else atomic_folder(out, "jsgs render") as work:
        try:
            for i, img in enumerate(images):

                def save(p: Path, a: np.ndarray = img) -> None:
                    Image.fromarray(a).save(p, format="PNG")

                written.append(work / f"frame_{i:05d}.png")
                write_with_atomic(written[-1], save)
                shape = img.shape
            write_json_atomic(work / "cameras.json", doc)
        except BaseException:
            for p in written if in_place else []:
                p.unlink(missing_ok=True)
            raise
    return len(written), shape
