"""``downscale``: a copy of a COLMAP scene at 1/F of its size, for a quick look on a CPU (``jsgs train
--preset preview``).

Each registered view's image is cropped at its right and bottom edges to a multiple of F pixels and reduced
with Pillow's ``Image.reduce(F)`` (the mean of each F×F block), then saved as a lossless PNG; the model is
written anew with every camera cropped the same way and rescaled by 1/F with COLMAP's own
``Camera::rescale`` (pycolmap), and every keypoint divided by F. With COLMAP's pixel convention (the first
pixel's centre at 0.5) the block mean and the rescaled camera describe the same rays. The reduced copy no
longer holds the files' 8×8 JPEG grid, so it is for the baseline, not for JSGS (docs/training.md).

Writes ``OUT/images/<stem>.png``, ``OUT/sparse/0/`` and ``OUT/downscale.json`` (jsgs/schemas/
downscale_record.schema.json: the source, the factor, each view's sizes); SCENE is never written to.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

from jsgs import __version__
from jsgs.base.errors import JsgsError
from jsgs.base.io import write_bytes_atomic

from .scene import image_stem, prepare_output_dir, removes_partial_output

#: What ``downscale`` writes into OUT (and removes first with ``force``).
OWNED = ("images", "sparse", "downscale.json")
#: the factors offered (an 8-aligned view stays whole at these for common photo sizes)
FACTORS = (2, 3, 4, 8)


def _reduced_png(path: Path, factor: int) -> tuple[bytes, tuple[int, int]]:
    """The image at ``path`` cropped to a multiple of ``factor`` and block-averaged, as PNG bytes, and its
    size."""
    from PIL import Image

    from jsgs.base.images import read_rgb8

    rgb = Image.fromarray(read_rgb8(path))
    w, h = (rgb.width // factor) * factor, (rgb.height // factor) * factor
    small = rgb.crop((0, 0, w, h)).reduce(factor)
    buf = io.BytesIO()
    small.save(buf, "PNG")
    return buf.getvalue(), small.size


@removes_partial_output
def downscale(scene_dir: str | Path, out: str | Path, factor: int = 2, force: bool = False,
              command: str | None = None) -> dict[str, Any]:  # fmt: skip
    """Write the copy of ``scene_dir`` described in the module docstring into ``out``; its record."""
    from jsgs.base.schema import validate as schema_validate

    from . import manifest_writer
    from .scene import write_model_atomic
    from .validate import require_valid

    if factor not in FACTORS:
        raise JsgsError(f"--factor: {factor} is not one of {', '.join(map(str, FACTORS))}")
    scene_dir, out = Path(scene_dir), Path(out)
    scene = require_valid(scene_dir).scene
    assert scene is not None
    sizes: dict[int, tuple[int, int]] = {}
    for v in scene.views:
        assert v.path is not None and v.size is not None  # require_valid refuses missing or unreadable files
        if sizes.setdefault(v.camera_id, v.size) != v.size:
            raise JsgsError(
                f"{scene.rel(v.path)}: {v.size[0]}x{v.size[1]}, but camera {v.camera_id}'s other views are "
                f"{sizes[v.camera_id][0]}x{sizes[v.camera_id][1]}; downscale needs one size per camera"
            )
    small = [s for s in sizes.values() if min(s) < 11 * factor]
    if small:
        w, h = small[0]
        raise JsgsError(f"--factor {factor}: views of {w}x{h} would be smaller than 11 px a side")

    prepare_output_dir(out, force, OWNED, protect=scene_dir, tool="downscale")
    (out / "images").mkdir()
    views = []
    for v in scene.views:
        assert v.path is not None and v.size is not None
        png, size = _reduced_png(v.path, factor)
        name = f"{image_stem(v.name)}.png"
        write_bytes_atomic(out / "images" / name, png)
        views.append({"name": v.name, "image": f"images/{name}", "source_size": list(v.size),
                      "size": list(size)})  # fmt: skip

    rec = scene.reconstruction
    for cid, cam in rec.cameras.items():
        w, h = sizes.get(cid, (cam.width, cam.height))
        if (w, h) != (cam.width, cam.height):  # the files are another size than the model says
            cam.rescale(w, h)
        cam.width, cam.height = (w // factor) * factor, (h // factor) * factor  # the crop: cx, cy stay
        cam.rescale(1.0 / factor)
    for im in rec.images.values():
        for p in im.points2D:
            p.xy = p.xy / factor
    for v in scene.views:
        rec.images[v.image_id].name = f"{image_stem(v.name)}.png"
    write_model_atomic(rec, out / "sparse" / "0")

    record: dict[str, Any] = {
        "format": "jsgs-downscale-record",
        "format_version": 1,
        "producer": {
            "tool": "jsgstools downscale",
            "version": __version__,
            "command": command or f"jsgstools downscale {scene_dir} --out {out} --factor {factor}",
        },
        "source": {
            "scene": str(scene_dir),
            "name": scene.name,
            "model": str(scene.model_dir.relative_to(scene_dir)),
        },
        "settings": {"factor": factor, "filter": "crop to a multiple of factor, then PIL.Image.reduce (box)"},
        "views": views,
    }
    schema_validate(record, "downscale_record", str(out / "downscale.json"))
    write_bytes_atomic(out / "downscale.json", manifest_writer.dumps(record).encode())
    return record
