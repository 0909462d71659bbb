"""A COLMAP model's cameras and the one camera type (:class:`jsgs.base.camera.Camera`): COLMAP's parameter
vector both ways, COLMAP's rescaling, and what the manifest writer records."""

from __future__ import annotations

from pathlib import Path
from typing import Any

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
    ("OPENCV_FISHEYE", (500.25, 510.75, 320.5, 239.5, 0.0125, -0.003, 1e-4, -2e-4)),
    ("SIMPLE_RADIAL_FISHEYE", (500.25, 320.0, 240.5, 0.0)),  # zero distortion is kept
]


def _pycolmap(model: str, params: tuple[float, ...]) -> Any:
    import pycolmap

    cam = pycolmap.Camera.create_from_model_name(7, model, 1.0, 640, 480)
    cam.params = list(params)
    return cam


@pytest.mark.parametrize(("model", "params"), MODELS)
def test_colmap_parameters_both_ways(model: str, params: tuple[float, ...]) -> None:
    """ColmapCamera's intrinsics are pycolmap's reading of the vector, and give the vector back."""
    pc = _pycolmap(model, params)
    colmap = ColmapCamera.from_params(7, model, 640, 480, params)
    cam = colmap.camera
    assert (cam.model, cam.width, cam.height) == (model, 640, 480)
    assert (cam.fx, cam.fy) == (pc.focal_length_x, pc.focal_length_y)
    assert (cam.cx, cam.cy) == (pc.principal_point_x, pc.principal_point_y)
    extra = tuple(params[i] for i in pc.extra_params_idxs())
    assert cam.distortion == (Distortion(model, extra) if extra else None)
    assert colmap.is_pinhole == (not extra) and colmap.distortion == extra
    np.testing.assert_array_equal(colmap.K, pc.calibration_matrix())
    assert colmap.params == params


@pytest.mark.parametrize(("model", "params"), MODELS)
def test_scaled_is_colmaps_rescale(model: str, params: tuple[float, ...]) -> None:
    pc = _pycolmap(model, params)
    pc.rescale(160, 100)
    scaled = ColmapCamera.from_params(7, model, 640, 480, params).scaled(160, 100)
    assert (scaled.width, scaled.height) == (160, 100)
    np.testing.assert_allclose(scaled.params, pc.params, rtol=1e-15)


def test_the_parameter_vector_of_a_camera() -> None:
    bad = ColmapCamera(1, Camera("OPENCV", 64, 48, 50.0, 50.0, 32.0, 24.0, Distortion("OPENCV", (0.1,))))
    with pytest.raises(ValueError, match="4 distortion parameters, not 1"):
        _ = bad.params
    plain = ColmapCamera(1, Camera("SIMPLE_RADIAL", 64, 48, 50.0, 50.0, 32.0, 24.0))  # no distortion: k = 0
    assert plain.params == (50.0, 32.0, 24.0, 0.0)
    pinhole = ColmapCamera.from_params(3, "SIMPLE_PINHOLE", 64, 48, (50.0, 32.0, 24.0)).as_pinhole()
    assert (pinhole.model, pinhole.params) == ("PINHOLE", (50.0, 50.0, 32.0, 24.0))


def test_manifest_camera_is_the_colmap_camera(synth_scene: Path) -> None:
    """The manifest writer's camera object holds the view's Camera (scaled to the file)."""
    from jsgstools.manifest_writer import camera_doc
    from jsgstools.scene import load_colmap_scene, view_camera

    scene = load_colmap_scene(synth_scene)
    for v in scene.views[:3]:
        cam = view_camera(scene, v).camera
        assert camera_doc(scene, v) == {
            "model": cam.model,
            "width": cam.width,
            "height": cam.height,
            "fx": cam.fx,
            "fy": cam.fy,
            "cx": cam.cx,
            "cy": cam.cy,
            "distortion": None,
        }
