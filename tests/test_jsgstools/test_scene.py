"""A COLMAP model's cameras and the one camera type (:class:`jsgs.base.camera.Camera`): the same intrinsics
both ways, and what the manifest writer records."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from jsgs.base.camera import Camera, Distortion
from jsgstools.scene import ColmapCamera

MODELS = [
    ("SIMPLE_PINHOLE", (500.25, 320.0, 240.5)),
    ("PINHOLE", (500.25, 510.75, 320.5, 239.5)),
    ("SIMPLE_RADIAL", (500.25, 320.0, 240.5, 0.0125)),
    ("RADIAL", (500.25, 320.0, 240.5, 0.0125, -0.003)),
    ("OPENCV", (500.25, 510.75, 320.5, 239.5, 0.0125, -0.003, 1e-4, -2e-4)),
    ("FULL_OPENCV", (500.25, 510.75, 320.5, 239.5, 0.0125, -0.003, 1e-4, -2e-4, 1e-3, 2e-3, 3e-3, 4e-3)),
]


@pytest.mark.parametrize(("model", "params"), MODELS)
def test_colmap_camera_round_trip(model: str, params: tuple[float, ...]) -> None:
    colmap = ColmapCamera(7, model, 640, 480, params)
    cam = colmap.camera
    assert (cam.model, cam.width, cam.height) == (model, 640, 480)
    assert ((cam.fx, cam.fy), (cam.cx, cam.cy)) == (colmap.focal, colmap.principal_point)
    if colmap.is_pinhole:
        assert cam.distortion is None
    else:
        assert cam.distortion == Distortion(model, params[-len(colmap.distortion) :])
    np.testing.assert_array_equal(cam.K, [[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]])
    assert ColmapCamera.from_camera(7, cam) == colmap


def test_from_camera_refuses_a_wrong_distortion() -> None:
    cam = Camera("OPENCV", 64, 48, 50.0, 50.0, 32.0, 24.0, Distortion("OPENCV", (0.1,)))
    with pytest.raises(ValueError, match="4 distortion parameters, not 1"):
        ColmapCamera.from_camera(1, cam)
    plain = Camera("SIMPLE_RADIAL", 64, 48, 50.0, 50.0, 32.0, 24.0)  # no distortion: k = 0
    assert ColmapCamera.from_camera(1, plain).params == (50.0, 32.0, 24.0, 0.0)


def test_manifest_camera_is_the_colmap_camera(synth_scene: Path) -> None:
    """The manifest writer's camera object holds what ColmapCamera.camera says (scaled to the file)."""
    from jsgstools.manifest_writer import camera_doc
    from jsgstools.scene import load_colmap_scene, view_camera

    scene = load_colmap_scene(synth_scene)
    for v in scene.views[:3]:
        cam = view_camera(scene, v).camera
        doc = camera_doc(scene, v)
        assert doc == {
            "model": cam.model,
            "width": cam.width,
            "height": cam.height,
            "fx": cam.fx,
            "fy": cam.fy,
            "cx": cam.cx,
            "cy": cam.cy,
            "distortion": None,
        }
