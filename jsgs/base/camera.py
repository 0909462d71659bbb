"""A camera's intrinsics: the one camera type of the manifest, the trainer, the synthetic scenes and a COLMAP
model's cameras (``jsgstools.scene.ColmapCamera``: a camera with its id, and COLMAP's parameter vector of it).

Conventions (COLMAP's, the manifest's and gsplat's): pixels, with the top-left *corner* of the image at
(0, 0), so the centre of pixel (0, 0) is (0.5, 0.5) and a centred principal point is (W/2, H/2). The pose is
not part of the camera: COLMAP shares one camera among many images, and each view carries its own pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: the distorted COLMAP camera models the trainer renders on the photo's own grid (OpenCV's radial-tangential
#: (k1, k2, p1, p2), on both backends); any other distortion must be undistorted before training
DISTORTION_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")


@dataclass(frozen=True)
class Distortion:
    """A camera's lens distortion: the COLMAP model name and its extra parameters, in COLMAP's order."""

    model: str
    params: tuple[float, ...]


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in pixels (COLMAP convention) and the lens distortion, if any."""

    model: str  # COLMAP model name
    width: int  # pixels
    height: int
    fx: float  # pixels
    fy: float
    cx: float  # pixels, COLMAP convention
    cy: float
    distortion: Distortion | None = None  # None: a pinhole camera

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix (COLMAP pixel convention: the same as gsplat's)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
