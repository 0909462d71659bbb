"""Spherical harmonics: gsplat's real SH basis and sign convention (degrees 0..4) and the view-dependent
colours ``max(SH(dirs) + 0.5, 0)`` that gsplat composites."""

from __future__ import annotations

import torch
from torch import Tensor


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Real SH basis [..., (degree+1)²] at directions [..., 3] (normalised here), gsplat's order and signs."""
    if not 0 <= degree <= 4:
        raise ValueError(f"sh degree must be in 0..4, got {degree}")
    out = [torch.full_like(dirs[..., 0], 0.28209479177387814)]
    if degree >= 1:
        n = dirs.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(dirs.dtype).tiny)
        x, y, z = (dirs / n).unbind(-1)
        k1 = 0.48860251190291992
        out += [-k1 * y, k1 * z, -k1 * x]
    if degree >= 2:
        xy, z2 = x * y, z * z
        c1 = x * x - y * y
        s1 = 2 * xy
        k2a, k2b, k2c = 1.0925484305920792, 0.31539156525252005, 0.54627421529603959
        b6 = k2b * (3 * z2 - 1)
        out += [k2c * s1, -k2a * y * z, b6, -k2a * x * z, k2c * c1]
    if degree >= 3:
        c2 = x * c1 - y * s1  # cos(3φ)·sin³θ
        s2 = x * s1 + y * c1  # sin(3φ)·sin³θ
        k3a, k3b, k3c, k3d = 0.59004358992664352, 1.4453057213202771, 0.45704579946446572, 0.37317633259011546
        b12 = k3d * z * (5 * z2 - 3)
        p3 = -k3c * (5 * z2 - 1)
        out += [-k3a * s2, k3b * z * s1, p3 * y, b12, p3 * x, k3b * z * c1, -k3a * c2]
    if degree >= 4:
        c3 = x * c2 - y * s2
        s3 = x * s2 + y * c2
        k4a, k4b = 0.62583573544917614, 1.7701307697799304
        p41 = 3.3116114351514601 * z2 - 0.47308734787878002
        p43 = z * (2.0071396306718676 - 4.6833258049010249 * z2)
        b20 = 1.9843134832984430 * z * b12 - 1.0062305898749053 * b6
        out += [k4a * s3, -k4b * z * s2, p41 * s1, p43 * y, b20, p43 * x, p41 * c1, -k4b * z * c2, k4a * c3]
    return torch.stack(out, dim=-1)


def spherical_harmonics(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Colour [..., 3] = Σ_k basis_k(dirs) · coeffs[..., k, :] over the first (degree+1)² coefficients.

    Same as gsplat's ``spherical_harmonics`` (without the +0.5 offset that ``rasterization`` adds).
    """
    nb = (degree + 1) ** 2
    if coeffs.shape[-2] < nb:
        raise ValueError(f"sh degree {degree} needs {nb} coefficients, got {coeffs.shape[-2]}")
    return (sh_basis(degree, dirs)[..., None] * coeffs[..., :nb, :]).sum(dim=-2)


def sh_colors(means: Tensor, coeffs: Tensor, viewmats: Tensor, degree: int) -> Tensor:
    """Per-camera RGB [C, N, 3] from SH coefficients ([N, K, 3] or [C, N, K, 3]) as gsplat's rasterization:
    directions from the camera centre to the means, ``clamp_min(sh + 0.5, 0)``."""
    campos = torch.inverse(viewmats)[:, :3, 3]
    dirs = means[None, :, :] - campos[:, None, :]
    if coeffs.dim() == 3:
        coeffs = coeffs[None].expand(viewmats.shape[0], -1, -1, -1)
    return torch.clamp_min(spherical_harmonics(degree, dirs, coeffs) + 0.5, 0.0)


def prepare_colors(means: Tensor, colors: Tensor, viewmats: Tensor, sh_degree: int | None) -> Tensor:
    """Colour features [C, N, D] (possibly an expanded view) from post-activation colours [N, D] / [C, N, D]
    or, with ``sh_degree``, SH coefficients [N, K, 3] / [C, N, K, 3] (gsplat's +0.5 and clamp at 0)."""
    C = viewmats.shape[0]
    if sh_degree is not None:
        return sh_colors(means, colors, viewmats, sh_degree)
    if colors.dim() == 2:
        return colors[None].expand(C, -1, -1)
    return colors
