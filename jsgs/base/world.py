"""Camera poses that leave the trainer's world normalisation undefined (:mod:`jsgs.train.normalize`, gsplat's
``similarity_from_cameras``), in the base layer so that ``jsgstools validate`` warns before a run starts.

Pure float64 numpy on camera-to-world matrices (N x 4 x 4, OpenCV camera axes: -y is up, +z looks forward).
"""

from __future__ import annotations

import numpy as np

from jsgs.base.limits import COINCIDENT_CAMERAS

#: the cameras' mean up direction is zero: there is no "up" to rotate onto +z
CANCELLING_UPS = "the cameras' up directions cancel out: their mean is zero"


def focus_refusal(strict_scaling: bool = False) -> str:
    """The reason given when the median (``strict_scaling``: largest) camera distance from the focus is 0."""
    how = "largest" if strict_scaling else "median"
    return f"most cameras sit at their common focus point: their {how} distance from it is 0"


def up_alignment(c2w: np.ndarray) -> np.ndarray | None:
    """The rotation taking the cameras' mean up (camera -y) onto camera up (world -y after it, gsplat's
    convention); half a turn about x when the mean up is exactly camera +y. None when the ups cancel out."""
    ups = np.sum(c2w[:, :3, :3] * np.array([0, -1.0, 0]), axis=-1)
    world_up = np.mean(ups, axis=0)
    norm = np.linalg.norm(world_up)
    if not norm > 0:
        return None
    world_up = world_up / norm
    up_camspace = np.array([0.0, -1.0, 0.0])
    c = (up_camspace * world_up).sum()
    cross = np.cross(world_up, up_camspace)
    skew = np.array(
        [
            [0.0, -cross[2], cross[1]],
            [cross[2], 0.0, -cross[0]],
            [-cross[1], cross[0], 0.0],
        ]
    )
    if c > -1:
        return np.eye(3) + skew + (skew @ skew) * 1 / (1 + c)
    # the mean up is exactly camera +y: half a turn about x (gsplat's diag(-1, 1, 1) is a mirror)
    return np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def focus_offsets(c2w: np.ndarray, R_align: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """gsplat's ``center_method="focus"`` after the rotation ``R_align``: (translate, offsets), translate
    moving the median of the cameras' closest points to the origin along their optical axes onto the origin,
    offsets (N x 3) the rotated camera centres plus translate."""
    R = R_align @ c2w[:, :3, :3]
    fwds = np.sum(R * np.array([0, 0.0, 1.0]), axis=-1)
    t = (R_align @ c2w[:, :3, 3][..., None])[..., 0]
    nearest = t + (fwds * -t).sum(-1)[:, None] * fwds
    translate = -np.median(nearest, axis=0)
    return translate, t + translate


def normalization_refusal(c2w: np.ndarray, strict_scaling: bool = False) -> str | None:
    """Why the cameras leave the normalisation's up direction or scale undefined (one line), or None.
    Call under ``np.errstate(all="ignore")`` for poses that may overflow."""
    R_align = up_alignment(c2w)
    if R_align is None:
        return CANCELLING_UPS
    scale_fn = np.max if strict_scaling else np.median
    distance = scale_fn(np.linalg.norm(focus_offsets(c2w, R_align)[1], axis=-1))
    if not distance > 0:
        return focus_refusal(strict_scaling)
    return None


def camera_extent(c2w: np.ndarray) -> float:
    """gsplat Parser.scene_scale: the largest distance of a camera centre from the centres' mean."""
    centres = c2w[:, :3, 3]
    return float(np.max(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))


def cameras_coincide(c2w: np.ndarray) -> bool:
    """Every camera at one position (their extent within :data:`COINCIDENT_CAMERAS` of the coordinates'
    size): the normalisation has no distance to scale by."""
    return camera_extent(c2w) <= COINCIDENT_CAMERAS * max(1.0, float(np.abs(c2w[:, :3, 3]).max()))


def coincidence(c2w: np.ndarray) -> str | None:
    """Why the cameras give the normalisation no distance to scale by, in words (``"only one camera"``, or
    ``"all N cameras are at one position"``: :func:`cameras_coincide`), else None."""
    if len(c2w) == 1:
        return "only one camera"
    if cameras_coincide(c2w):
        return f"all {len(c2w)} cameras are at one position"
    return None
