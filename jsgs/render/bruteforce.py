"""Brute-force rasteriser: the definitions written out per camera, per Gaussian, per pixel, in plain loops.

Slow (Python loops over pixels); meant for a handful of Gaussians on tiny images in float64, as the ground
truth of the tests (values and, through autograd, gradients) and of the pooled sums. Independent of
``reference``: it shares constants only.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .reference import ALPHA_MAX, ALPHA_THRESHOLD, EXTEND_MAX, FOV_MARGIN, T_STOP, TILE_SIZE


def _rotation(q: Tensor) -> Tensor:
    w, x, y, z = q / torch.sqrt((q * q).sum())
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
        ]
    )


def _sh_rgb(coeffs: Tensor, d: Tensor, degree: int) -> Tensor:
    """Textbook real SH (degree <= 3) in gsplat's ordering and signs, + 0.5, clamped at 0."""
    x, y, z = d / torch.sqrt((d * d).sum())
    basis = [torch.ones_like(x) * 0.5 / math.sqrt(math.pi)]
    if degree >= 1:
        k = math.sqrt(3 / (4 * math.pi))
        basis += [-k * y, k * z, -k * x]
    if degree >= 2:
        k, k0 = 0.5 * math.sqrt(15 / math.pi), 0.25 * math.sqrt(5 / math.pi)
        basis += [k * x * y, -k * y * z, k0 * (3 * z * z - 1), -k * x * z, 0.5 * k * (x * x - y * y)]
    if degree >= 3:
        k1, k2 = 0.25 * math.sqrt(35 / (2 * math.pi)), 0.5 * math.sqrt(105 / math.pi)
        k3, k4 = 0.25 * math.sqrt(21 / (2 * math.pi)), 0.25 * math.sqrt(7 / math.pi)
        z5 = 5 * z * z
        basis += [
            -k1 * y * (3 * x * x - y * y), k2 * x * y * z, -k3 * y * (z5 - 1), k4 * z * (z5 - 3),
            -k3 * x * (z5 - 1), 0.5 * k2 * z * (x * x - y * y), -k1 * x * (x * x - 3 * y * y),
        ]  # fmt: skip
    if degree > 3:
        raise ValueError("the brute force implements SH degrees 0..3")
    rgb = sum(b * coeffs[i] for i, b in enumerate(basis))
    return torch.clamp_min(rgb + 0.5, 0.0)


def render_bruteforce(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    sh_degree: int | None = None,
    backgrounds: Tensor | None = None,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    radius_clip: float = 0.0,
    r: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, dict]:
    """Render by the definitions. colors: [N, D] (or [N, K, 3] SH with ``sh_degree``). r: optional [C, H, W].

    Returns image [C, H, W, D], alpha [C, H, W, 1], radii [C, N, 2] (int) and, when r is given, a dict of
    pooled sums {"s_r", "s_1", "nu"} each [C, N] (see ``jsgs.method.pooling``)."""
    C, N = viewmats.shape[0], means.shape[0]
    images, alphas, radii_all = [], [], []
    pooled = {k: torch.zeros(C, N, dtype=means.dtype) for k in ("s_r", "s_1", "nu")}
    D = colors.shape[-1] if sh_degree is None else 3
    for c in range(C):
        gauss = []  # (depth, index, mean2d, conic, colour, tile box)
        radii = torch.zeros(N, 2, dtype=torch.int32)
        for j in range(N):
            g = _project(
                c, j, means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree,
                near_plane, far_plane, eps2d, radius_clip,
            )  # fmt: skip
            if g is not None:
                gauss.append(g[0])
                radii[j] = torch.tensor(g[1], dtype=torch.int32)
        gauss.sort(key=lambda g: (g[0], g[1]))
        radii_all.append(radii)
        bg = backgrounds[c] if backgrounds is not None else torch.zeros(D, dtype=means.dtype)
        pix_rows, alpha_rows = [], []
        for i in range(height):
            row, arow = [], []
            for jx in range(width):
                out, T = _composite(c, i, jx, gauss, opacities, D, means.dtype, r, pooled)
                row.append(out + T * bg)
                arow.append(1 - T)
            pix_rows.append(torch.stack(row))
            alpha_rows.append(torch.stack(arow))
        images.append(torch.stack(pix_rows))
        alphas.append(torch.stack(alpha_rows)[..., None])
    return torch.stack(images), torch.stack(alphas), torch.stack(radii_all), pooled


#: a projected Gaussian: (depth, index, mean2d, conic, colour, tile box)
_Projected = tuple[float, int, Tensor, Tensor, Tensor, tuple[int, int, int, int]]


def _project(
    c: int, j: int, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
    viewmats: Tensor, Ks: Tensor, width: int, height: int, sh_degree: int | None, near_plane: float,
    far_plane: float, eps2d: float, radius_clip: float,
) -> tuple[_Projected, tuple[int, int]] | None:  # fmt: skip
    """Gaussian ``j`` seen by camera ``c``: its projection and its radii in pixels, or None when it is
    culled (outside the depth range, a degenerate or transparent footprint, under the radius clip, off the
    image)."""
    W3, t3 = viewmats[c, :3, :3], viewmats[c, :3, 3]
    fx, fy, cx, cy = Ks[c, 0, 0], Ks[c, 1, 1], Ks[c, 0, 2], Ks[c, 1, 2]
    p = W3 @ means[j] + t3
    if not (near_plane <= float(p[2].detach()) <= far_plane):
        return None
    R = _rotation(quats[j])
    S = torch.diag(scales[j])
    sigma3 = R @ S @ S @ R.T
    lim_xp = (width - cx) / fx + FOV_MARGIN * 0.5 * width / fx
    lim_xn = cx / fx + FOV_MARGIN * 0.5 * width / fx
    lim_yp = (height - cy) / fy + FOV_MARGIN * 0.5 * height / fy
    lim_yn = cy / fy + FOV_MARGIN * 0.5 * height / fy
    u = p[0] / p[2]
    v = p[1] / p[2]
    # J is evaluated at the clamped direction but with the true depth
    uc = torch.clamp(u, -lim_xn, lim_xp)
    vc = torch.clamp(v, -lim_yn, lim_yp)
    z = p[2]
    J = torch.stack(
        [
            torch.stack([fx / z, torch.zeros_like(z), -fx * uc / z]),
            torch.stack([torch.zeros_like(z), fy / z, -fy * vc / z]),
        ]
    )
    cov = J @ W3 @ sigma3 @ W3.T @ J.T + eps2d * torch.eye(2, dtype=means.dtype)
    det = cov[0, 0] * cov[1, 1] - cov[0, 1] * cov[1, 0]
    if float(det.detach()) <= 0 or float(opacities[j].detach()) < ALPHA_THRESHOLD:
        return None
    conic = torch.linalg.inv(cov)
    m2 = torch.stack([fx * u + cx, fy * v + cy])
    e = min(EXTEND_MAX, math.sqrt(2 * math.log(float(opacities[j].detach()) / ALPHA_THRESHOLD)))
    rx = math.ceil(e * math.sqrt(float(cov[0, 0].detach())))
    ry = math.ceil(e * math.sqrt(float(cov[1, 1].detach())))
    if rx <= radius_clip and ry <= radius_clip:
        return None
    mx, my = float(m2[0].detach()), float(m2[1].detach())
    if mx + rx <= 0 or mx - rx >= width or my + ry <= 0 or my - ry >= height:
        return None
    box = (
        math.floor(mx / TILE_SIZE - rx / TILE_SIZE),
        math.ceil(mx / TILE_SIZE + rx / TILE_SIZE),
        math.floor(my / TILE_SIZE - ry / TILE_SIZE),
        math.ceil(my / TILE_SIZE + ry / TILE_SIZE),
    )
    if sh_degree is None:
        col = colors[j] if colors.dim() == 2 else colors[c, j]
    else:
        cam_centre = torch.linalg.inv(viewmats[c])[:3, 3]
        col = _sh_rgb(colors[j], means[j] - cam_centre, sh_degree)
    return (float(z.detach()), j, m2, conic, col, box), (rx, ry)


def _composite(
    c: int, i: int, jx: int, gauss: list[_Projected], opacities: Tensor, D: int, dtype: torch.dtype,
    r: Tensor | None, pooled: dict[str, Tensor],
) -> tuple[Tensor, Tensor]:  # fmt: skip
    """Pixel (row ``i``, column ``jx``) of camera ``c``: front-to-back compositing of the depth-sorted
    Gaussians whose tile box holds its tile; its colour and transmittance (and, with ``r``, each Gaussian's
    share added to ``pooled``)."""
    tile_x, tile_y = jx // TILE_SIZE, i // TILE_SIZE
    px = torch.tensor([jx + 0.5, i + 0.5], dtype=dtype)
    T = torch.ones((), dtype=dtype)
    out = torch.zeros(D, dtype=dtype)
    for _, j, m2, conic, col, box in gauss:
        if not (box[0] <= tile_x < box[1] and box[2] <= tile_y < box[3]):
            continue
        d = m2 - px
        sig = 0.5 * (d @ conic @ d)
        alpha = torch.clamp(opacities[j] * torch.exp(-sig), max=ALPHA_MAX)
        if float(sig.detach()) < 0 or float(alpha.detach()) < ALPHA_THRESHOLD:
            continue
        if float((T * (1 - alpha)).detach()) <= T_STOP:
            break
        out = out + alpha * T * col
        if r is not None:
            kappa = (T * alpha / opacities[j]).detach()
            pooled["s_r"][c, j] += kappa * r[c, i, jx]
            pooled["s_1"][c, j] += kappa
            pooled["nu"][c, j] += (T * alpha).detach()
        T = T * (1 - alpha)
    return out, T
