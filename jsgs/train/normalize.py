"""World normalisation exactly as gsplat 1.5.3's ``examples/datasets`` (``normalize.py`` + ``colmap.Parser``).

A similarity transform T (4x4, x_train = T @ x_world) that (1) rotates the mean camera "up" (-y in OpenCV
camera axes) onto +z, (2) moves the median of the cameras' closest points to the origin along their optical
axes onto the origin, (3) scales the median camera distance to 1; then (4) rotates the point cloud's principal
axes onto x, y, z (largest variance first) and (5) flips z when the points' median height lies above their
mean (gsplat's "upside down" fix). Ported in float64 numpy so that the trainer does not need gsplat's
example code (which imports pycolmap, OpenCV and imageio). One difference: when the mean up is exactly camera
+y, step (1) is half a turn about x, where gsplat's matrix is a mirror (the model could not be exported).
"""

from __future__ import annotations

import numpy as np

from jsgs.base.world import focus_offsets, normalization_refusal, up_alignment


def similarity_from_cameras(c2w: np.ndarray, strict_scaling: bool = False) -> np.ndarray:
    """Steps (1)-(3). c2w: N x 4 x 4 camera-to-world (OpenCV axes). Returns the 4x4 transform. ValueError
    with :func:`jsgs.base.world.normalization_refusal`'s reason when the up or the scale is undefined."""
    if (why := normalization_refusal(c2w, strict_scaling)) is not None:
        raise ValueError(why)
    R_align = up_alignment(c2w)
    assert R_align is not None  # normalization_refusal said so
    translate, offsets = focus_offsets(c2w, R_align)

    transform = np.eye(4)
    transform[:3, 3] = translate
    transform[:3, :3] = R_align

    scale_fn = np.max if strict_scaling else np.median
    scale = 1.0 / scale_fn(np.linalg.norm(offsets, axis=-1))
    transform[:3, :] *= scale
    return transform


def align_principal_axes(points: np.ndarray) -> np.ndarray:
    """Step (4): rigid transform putting the points' median at the origin and their PCA axes on x, y, z."""
    centroid = np.median(points, axis=0)
    translated = points - centroid
    covariance = np.cov(translated, rowvar=False)
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)
    order = eigenvalues.argsort()[::-1]
    eigenvectors = eigenvectors[:, order]
    if np.linalg.det(eigenvectors) < 0:
        eigenvectors[:, 0] *= -1
    rotation = eigenvectors.T
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = -rotation @ centroid
    return transform


def transform_points(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """points: N x 3; returns matrix applied to them (N x 3)."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def transform_cameras(matrix: np.ndarray, camtoworlds: np.ndarray) -> np.ndarray:
    """camtoworlds: N x 4 x 4; returns them in the transformed world, rotations re-orthonormalised (the
    similarity's scale removed from R, kept in the positions)."""
    out = np.einsum("nij, ki -> nkj", camtoworlds, matrix)
    scaling = np.linalg.norm(out[:, 0, :3], axis=1)
    out[:, :3, :3] = out[:, :3, :3] / scaling[:, None, None]
    return out


_FLIP_Z = np.array(
    [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0, 0.0],
        [0.0, 0.0, -1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def normalize_world(camtoworlds: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """gsplat Parser's ``normalize=True`` branch. camtoworlds: N x 4 x 4, points: P x 3 (float64).

    Returns (camtoworlds', points', T) with T the 4x4 world-to-normalised similarity. With fewer than 3
    points the principal-axes and flip steps are skipped (there is no covariance to align). ValueError
    (saying why) when the cameras leave the up direction or the scale undefined."""
    T1 = similarity_from_cameras(camtoworlds)
    camtoworlds = transform_cameras(T1, camtoworlds)
    points = transform_points(T1, points)
    transform = T1
    if len(points) >= 3:
        T2 = align_principal_axes(points)
        camtoworlds = transform_cameras(T2, camtoworlds)
        points = transform_points(T2, points)
        transform = T2 @ T1
        if np.median(points[:, 2]) > np.mean(points[:, 2]):
            camtoworlds = transform_cameras(_FLIP_Z, camtoworlds)
            points = transform_points(_FLIP_Z, points)
            transform = _FLIP_Z @ transform
    return camtoworlds, points, transform


