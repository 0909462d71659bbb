"""The Gaussian Controller's math (jsgs.kernels): A = J W R(q) and s̄ against an independent float64
evaluation and against the rasteriser's own projected covariance, L_fro's closed-form gradient against
autograd, the empty contributor set, the statistics. CPU, float64, well under a second."""

from __future__ import annotations

import math

import numpy as np
import torch

from jsgs.kernels import (
    controller_matrix,
    fro_loss,
    fro_loss_and_grads,
    projected_rms_scale_sq,
)
from jsgs.render.reference import project_gaussians

D = torch.float64


def T(x: object) -> torch.Tensor:
    return torch.tensor(x, dtype=D)


def _camera(width: int = 40, height: int = 30) -> tuple[torch.Tensor, torch.Tensor]:
    a = 0.3
    R = T([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    viewmat = torch.eye(4, dtype=D)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = T([0.1, -0.2, 0.5])
    K = T([[35.0, 0, 21.0], [0, 33.0, 14.0], [0, 0, 1]])
    return viewmat, K


def _gaussians(n: int = 12, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=D) * T([1.5, 1.0, 0.5]) + T([0.0, 0.0, 4.0])
    means[0] = T([9.0, 0.3, 3.0])  # far outside the FOV: J is clamped
    means[1] = T([-0.2, -7.0, 2.5])  # likewise, vertically
    return {
        "means": means,
        "quats": torch.randn(n, 4, generator=g, dtype=D),
        "log_scales": torch.randn(n, 3, generator=g, dtype=D) * 0.5 - 2.5,
        "logits": torch.randn(n, generator=g, dtype=D),
    }


def _ref_A(mean: np.ndarray, q: np.ndarray, viewmat: np.ndarray, K: np.ndarray, w: int, h: int) -> np.ndarray:
    """J W R(q) written out: perspective Jacobian at the camera-space mean, x/z and y/z clamped to the
    FOV widened by 30 % of tan(fov/2) on each side (gsplat's projection)."""
    W = viewmat[:3, :3]
    x, y, z = W @ mean + viewmat[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    lim_xp, lim_xn = (w - cx) / fx + 0.3 * w / (2 * fx), cx / fx + 0.3 * w / (2 * fx)
    lim_yp, lim_yn = (h - cy) / fy + 0.3 * h / (2 * fy), cy / fy + 0.3 * h / (2 * fy)
    u = min(max(x / z, -lim_xn), lim_xp)
    v = min(max(y / z, -lim_yn), lim_yp)
    J = np.array([[fx / z, 0, -fx * u / z], [0, fy / z, -fy * v / z]])
    a, b, c, d = q / np.linalg.norm(q)  # w, x, y, z
    R = np.array(
        [
            [1 - 2 * (c * c + d * d), 2 * (b * c - a * d), 2 * (b * d + a * c)],
            [2 * (b * c + a * d), 1 - 2 * (b * b + d * d), 2 * (c * d - a * b)],
            [2 * (b * d - a * c), 2 * (c * d + a * b), 1 - 2 * (b * b + c * c)],
        ]
    )
    return J @ W @ R


def test_A_and_sbar_match_the_definition_and_the_rasteriser() -> None:
    viewmat, K = _camera()
    g = _gaussians()
    A = controller_matrix(g["means"], g["quats"], viewmat, K, 40, 30)
    s = torch.exp(g["log_scales"])
    s2 = projected_rms_scale_sq(A, s)
    for j in range(len(s)):
        A_ref = _ref_A(g["means"][j].numpy(), g["quats"][j].numpy(), viewmat.numpy(), K.numpy(), 40, 30)
        np.testing.assert_allclose(A[j].numpy(), A_ref, rtol=1e-12, atol=1e-12)
        S = np.diag(s[j].numpy() ** 2)
        sbar_ref = math.sqrt(0.5 * np.trace(A_ref @ S @ A_ref.T))
        assert math.isclose(math.sqrt(s2[j].item()), sbar_ref, rel_tol=1e-12)
    # Frobenius equivalence: s̄² = ½ tr(cov2d) of the rasteriser's covariance before the 0.3 px² dilation
    proj = project_gaussians(
        g["means"], g["quats"], s, torch.ones(len(s), dtype=D), viewmat[None], K[None], 40, 30
    )
    tr = proj.covars2d[0].diagonal(dim1=-2, dim2=-1).sum(-1)
    torch.testing.assert_close(s2, 0.5 * tr, rtol=1e-12, atol=1e-12)


def test_closed_form_gradient_equals_autograd_and_reaches_opacity_and_scale_only() -> None:
    viewmat, K = _camera()
    g = _gaussians()
    n = len(g["logits"])
    gen = torch.Generator().manual_seed(1)
    rbar = torch.rand(n, generator=gen, dtype=D) * 0.05
    vis = torch.rand(n, generator=gen, dtype=D) > 0.3
    rbar = torch.where(vis, rbar, torch.zeros_like(rbar))
    means = g["means"].clone().requires_grad_()
    quats = g["quats"].clone().requires_grad_()
    logits = g["logits"].clone().requires_grad_()
    log_scales = g["log_scales"].clone().requires_grad_()
    A = controller_matrix(means, quats, viewmat, K, 40, 30)
    ft = fro_loss(rbar, vis, logits, log_scales, A, 1.0)
    gm, gq, gl, gs = torch.autograd.grad(ft.loss, [means, quats, logits, log_scales], allow_unused=True)
    assert gm is None and gq is None  # A is frozen: nothing reaches centres or rotations
    ft2, gl2, gs2 = fro_loss_and_grads(rbar, vis, logits, log_scales, A, 1.0)
    torch.testing.assert_close(ft2.loss, ft.loss.detach(), rtol=1e-14, atol=0)
    torch.testing.assert_close(gl2, gl, rtol=1e-12, atol=1e-18)
    torch.testing.assert_close(gs2, gs, rtol=1e-12, atol=1e-18)
    for a, b in zip(ft2.stats, ft.stats, strict=True):  # |V|, mean r̄, damped: the same from both forms
        torch.testing.assert_close(a, b, rtol=1e-14, atol=0)
    assert ft.stats.damped > 0
    assert (gl[~vis] == 0).all() and (gs[~vis] == 0).all()
    assert (gl[vis] > 0).all()  # more opacity, more loss: descent lowers α where disagreement remains
    assert (gs[vis] < 0).all()  # larger footprints are damped less
    # the value by the definition
    alpha = torch.sigmoid(g["logits"])
    sbar = torch.sqrt(projected_rms_scale_sq(A, torch.exp(g["log_scales"])))
    ref = (rbar * alpha**2 * torch.exp(-sbar))[vis].sum() / vis.sum()
    torch.testing.assert_close(ft.loss.detach(), ref, rtol=1e-14, atol=0)


def test_empty_contributor_set_contributes_nothing() -> None:
    viewmat, K = _camera()
    g = _gaussians()
    n = len(g["logits"])
    vis = torch.zeros(n, dtype=torch.bool)
    logits = g["logits"].clone().requires_grad_()
    log_scales = torch.full((n, 3), -80.0, dtype=D, requires_grad=True)  # s̄ → 0 where not visible: no NaN
    A = controller_matrix(g["means"], g["quats"], viewmat, K, 40, 30)
    ft = fro_loss(torch.zeros(n, dtype=D), vis, logits, log_scales, A)
    ft.loss.backward()
    assert ft.loss.item() == 0.0
    assert torch.equal(logits.grad, torch.zeros(n, dtype=D)) and torch.equal(
        log_scales.grad, torch.zeros(n, 3, dtype=D)
    )
    assert ft.stats.visible.item() == 0 and ft.stats.rbar_mean.item() == 0 and ft.stats.damped.item() == 0
    ft2, gl, gs = fro_loss_and_grads(torch.zeros(n, dtype=D), vis, logits, log_scales, A)
    assert ft2.loss.item() == 0.0 and torch.isfinite(gs).all() and not gl.any()


def test_statistics() -> None:
    # three Gaussians facing an identity camera with f = 10: s̄ = 10·s/z exactly for a scale along x, y
    viewmat, K = torch.eye(4, dtype=D), T([[10.0, 0, 5], [0, 10.0, 5], [0, 0, 1]])
    means = T([[0.0, 0, 2], [0.0, 0, 2], [0.0, 0, 2]])
    quats = T([[1.0, 0, 0, 0]] * 3)
    A = controller_matrix(means, quats, viewmat, K, 10, 10)
    # s̄ = sqrt(½ (100/4)(sx² + sy²)) with sx = sy = s: 5 s
    log_scales = torch.log(T([[0.1, 0.1, 1.0], [0.3, 0.3, 1.0], [0.1, 0.1, 1.0]]))
    rbar = T([0.02, 0.04, 0.0])
    vis = torch.tensor([True, True, True])
    ft = fro_loss(rbar, vis, torch.zeros(3, dtype=D), log_scales, A, tau_s=1.0)
    torch.testing.assert_close(ft.sbar, T([0.5, 1.5, 0.5]), rtol=1e-14, atol=0)
    assert ft.stats.visible.item() == 3
    assert math.isclose(ft.stats.rbar_mean.item(), 0.02, rel_tol=1e-14)
    assert ft.stats.damped.item() == 1  # r̄ > 0 and s̄ <= τ_s: only the first
    ref = (0.02 * 0.25 * math.exp(-0.5) + 0.04 * 0.25 * math.exp(-1.5)) / 3
    assert math.isclose(ft.loss.item(), ref, rel_tol=1e-14)
