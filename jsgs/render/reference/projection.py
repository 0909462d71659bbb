"""Projection of 3D Gaussians to the screen (gsplat 1.5.3's ``ProjectionEWA3DGSFused.cu``, pinhole, classic).

Quaternions to rotations, 3D covariances ``R S Sᵀ Rᵀ``, and the EWA projection ``cov2d = J W Σ Wᵀ Jᵀ`` with J
evaluated at the camera-space mean, x/z and y/z clamped to the field of view widened by ``FOV_MARGIN``;
``eps2d`` added to the diagonal; culling (depth range, det <= 0, opacity < 1/255, radius clip, off-screen);
gsplat's opacity-aware axis-aligned radii.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
import torch
from torch import Tensor

ALPHA_THRESHOLD = 1.0 / 255.0  # gsplat's ALPHA_THRESHOLD: skip and cull below this
EXTEND_MAX = 3.33  # cap of the opacity-aware box extent, in standard deviations
FOV_MARGIN = 0.3  # J is evaluated with x/z, y/z clamped to the FOV widened by this fraction of tan(fov)


@dataclass
class Projected:
    """Screen-space Gaussians for C cameras (all tensors [C, N, ...]).

    ``means2d`` are pixels (x right, y down, pixel (i, j) has its centre at (j + 0.5, i + 0.5));
    ``covars2d`` is J W Σ Wᵀ Jᵀ before the ``eps2d`` dilation, in px²; ``conics`` the upper triangle
    (xx, xy, yy) of the inverse of the dilated covariance; ``jacobians`` the 2x3 J used (with gsplat's FOV
    clamp); ``depths`` camera z. Entries of culled Gaussians (``radii == 0``) are finite but meaningless.
    """

    radii: Tensor  # [C, N, 2] int32
    means2d: Tensor  # [C, N, 2]
    depths: Tensor  # [C, N]
    conics: Tensor  # [C, N, 3]
    covars2d: Tensor  # [C, N, 2, 2]
    jacobians: Tensor  # [C, N, 2, 3]
    means_cam: Tensor  # [C, N, 3]

    @property
    def visible(self) -> Tensor:
        """[C, N] bool: the Gaussian survived culling in this camera (gsplat: ``(radii > 0).all(-1)``)."""
        return (self.radii > 0).all(dim=-1)


def _rotmat_quadratic_np() -> np.ndarray:
    """[16, 9]: R(q) = vec(q qᵀ) @ C for a unit quaternion (w, x, y, z), row-major R; each entry of R is a
    quadratic form in q, with 1 written as w² + x² + y² + z²."""
    c = np.zeros((4, 4, 9))
    w, x, y, z = range(4)

    def put(k: int, terms: list[tuple[float, int, int]]) -> None:
        for coef, a, b in terms:
            c[a, b, k] += coef

    put(0, [(1, w, w), (1, x, x), (-1, y, y), (-1, z, z)])
    put(1, [(2, x, y), (-2, w, z)])
    put(2, [(2, x, z), (2, w, y)])
    put(3, [(2, x, y), (2, w, z)])
    put(4, [(1, w, w), (-1, x, x), (1, y, y), (-1, z, z)])
    put(5, [(2, y, z), (-2, w, x)])
    put(6, [(2, x, z), (-2, w, y)])
    put(7, [(2, y, z), (2, w, x)])
    put(8, [(1, w, w), (-1, x, x), (-1, y, y), (1, z, z)])
    return c.reshape(16, 9)


@cache
def _rotmat_quadratic(dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.as_tensor(_rotmat_quadratic_np(), dtype=dtype, device=device)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] from quaternions [..., 4] in (w, x, y, z) order, normalised first.

    The usual ``1 - 2 (y² + z²)``-style entries, written as quadratic forms of the unit quaternion so that the
    whole map is one outer product and one matrix product (5 kernels instead of ~35: it runs every step on
    every Gaussian, and on a GPU each small kernel costs more than its arithmetic)."""
    q = quats / torch.linalg.vector_norm(quats, dim=-1, keepdim=True)
    qq = (q[..., :, None] * q[..., None, :]).reshape(*q.shape[:-1], 16)
    return (qq @ _rotmat_quadratic(q.dtype, q.device)).reshape(*q.shape[:-1], 3, 3)


def covariance_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """World covariances Σ = R diag(s)² Rᵀ [N, 3, 3] from quaternions [N, 4] and activated scales [N, 3]."""
    m = quat_to_rotmat(quats) * scales[..., None, :]
    return m @ m.transpose(-1, -2)


def distort(u: Tensor, v: Tensor, dist: Tensor) -> tuple[Tensor, Tensor]:
    """OpenCV's radial-tangential model on normalised image coordinates.

    u, v: [C, N] ``x/z``, ``y/z``; dist: [C, 4] (k1, k2, p1, p2) — COLMAP's SIMPLE_RADIAL is (k, 0, 0, 0),
    RADIAL (k1, k2, 0, 0), OPENCV (k1, k2, p1, p2). Returns the distorted (u_d, v_d) [C, N]."""
    k1, k2, p1, p2 = (dist[:, i, None] for i in range(4))
    r2 = u * u + v * v
    radial = 1.0 + k1 * r2 + k2 * r2 * r2
    ud = u * radial + 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u)
    vd = v * radial + p1 * (r2 + 2.0 * v * v) + 2.0 * p2 * u * v
    return ud, vd


def distortion_jacobian(u: Tensor, v: Tensor, dist: Tensor) -> Tensor:
    """d(u_d, v_d) / d(u, v) of :func:`distort`: [C, N, 2, 2] (rows: u_d, v_d; columns: u, v)."""
    k1, k2, p1, p2 = (dist[:, i, None] for i in range(4))
    r2 = u * u + v * v
    radial = 1.0 + k1 * r2 + k2 * r2 * r2
    g = 2.0 * (k1 + 2.0 * k2 * r2)  # d radial / d(r²) x 2
    du_du = radial + u * u * g + 2.0 * p1 * v + 6.0 * p2 * u
    du_dv = u * v * g + 2.0 * p1 * u + 2.0 * p2 * v
    dv_du = u * v * g + 2.0 * p1 * u + 2.0 * p2 * v
    dv_dv = radial + v * v * g + 6.0 * p1 * v + 2.0 * p2 * u
    return torch.stack([du_du, du_dv, dv_du, dv_dv], dim=-1).reshape(*u.shape, 2, 2)


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    distortion: Tensor | None = None,
) -> Projected:
    """Project N Gaussians into C pinhole cameras exactly as gsplat's fused EWA projection.

    Args: means [N, 3] world; quats [N, 4] wxyz (any norm); scales [N, 3] activated, world units;
    opacities [N] in [0, 1] (only used for culling and the box extent, as gsplat does); viewmats [C, 4, 4]
    world-to-camera (OpenCV axes); Ks [C, 3, 3]; width/height in pixels. ``distortion`` [C, 4] (k1, k2,
    p1, p2; :func:`distort`): the means are distorted and the 2D covariance is carried through the
    distortion's Jacobian at the mean (a local linearisation, as EWA linearises the perspective), so the
    image is rendered on the photo's own distorted pixel grid, never resampled.
    """
    C = viewmats.shape[0]
    Rw = viewmats[:, :3, :3]
    tw = viewmats[:, :3, 3]
    means_c = torch.einsum("cij,nj->cni", Rw, means) + tw[:, None, :]
    cov_c = torch.einsum("cij,njk,clk->cnil", Rw, covariance_3d(quats, scales), Rw)

    x, y, z_raw = means_c.unbind(-1)
    in_depth = (z_raw >= near_plane) & (z_raw <= far_plane)
    # Culled entries still flow through autograd (with zero upstream gradient); a safe z keeps them finite
    # so that 0 · inf never turns into NaN in the backward pass.
    z = torch.where(in_depth, z_raw, torch.ones_like(z_raw))
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + FOV_MARGIN * tan_fovx
    lim_x_neg = cx / fx + FOV_MARGIN * tan_fovx
    lim_y_pos = (height - cy) / fy + FOV_MARGIN * tan_fovy
    lim_y_neg = cy / fy + FOV_MARGIN * tan_fovy
    tx = z * torch.clamp(x / z, min=-lim_x_neg, max=lim_x_pos)
    ty = z * torch.clamp(y / z, min=-lim_y_neg, max=lim_y_pos)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * tx / (z * z), zero, fy / z, -fy * ty / (z * z)], dim=-1).reshape(
        C, -1, 2, 3
    )
    if distortion is not None:
        # J = diag(fx, fy) · D(u, v) · P, P the perspective Jacobian of (x/z, y/z); D at the clamped point
        P = torch.stack([1.0 / z, zero, -tx / (z * z), zero, 1.0 / z, -ty / (z * z)], dim=-1)
        P = P.reshape(C, -1, 2, 3)
        D = distortion_jacobian(tx / z, ty / z, distortion)
        F = torch.stack([fx.expand_as(z), fy.expand_as(z)], dim=-1)[..., :, None]
        J = F * (D @ P)
        ud, vd = distort(x / z, y / z, distortion)
        means2d = torch.stack([fx * ud + cx, fy * vd + cy], dim=-1)
    else:
        means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1)
    cov2d = J @ cov_c @ J.transpose(-1, -2)

    a = cov2d[..., 0, 0] + eps2d
    b = 0.5 * (cov2d[..., 0, 1] + cov2d[..., 1, 0])
    d = cov2d[..., 1, 1] + eps2d
    det = a * d - b * b
    ok_det = det > 0
    det_safe = torch.where(ok_det, det, torch.ones_like(det))
    conics = torch.stack([d / det_safe, -b / det_safe, a / det_safe], dim=-1)

    with torch.no_grad():
        op = opacities.detach()[None, :].expand_as(a)
        ok_op = op >= ALPHA_THRESHOLD
        extend = torch.sqrt(2.0 * torch.log(op.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD))
        extend = extend.clamp(max=EXTEND_MAX)
        rx = torch.ceil(extend * torch.sqrt(a.detach().clamp_min(0)))
        ry = torch.ceil(extend * torch.sqrt(d.detach().clamp_min(0)))
        too_small = (rx <= radius_clip) & (ry <= radius_clip)
        mx, my = means2d.detach().unbind(-1)
        off = (mx + rx <= 0) | (mx - rx >= width) | (my + ry <= 0) | (my - ry >= height)
        keep = in_depth & ok_det & ok_op & ~too_small & ~off
        radii = torch.where(keep[..., None], torch.stack([rx, ry], -1), torch.zeros_like(means2d))
        radii = radii.to(torch.int32)
    return Projected(radii, means2d, z_raw, conics, cov2d, J, means_c)
