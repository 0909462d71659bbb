"""Lens distortion in the reference rasterizer: the distorted projection of points against OpenCV's
``cv2.projectPoints`` (float64), its Jacobian against autograd, the rendered Gaussian's centre where OpenCV
puts its mean, and no distortion equal to the pinhole path bit for bit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from jsgs.render import rasterize
from jsgs.render.reference.projection import distort, distortion_jacobian, project_gaussians

DISTS = [(0.08, 0.0, 0.0, 0.0), (-0.12, 0.03, 0.0, 0.0), (0.05, -0.02, 0.002, -0.003)]


@pytest.mark.parametrize("d", DISTS)
def test_projection_matches_opencv(d: tuple[float, float, float, float]) -> None:
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, (200, 2)), rng.uniform(2, 5, 200)]
    K = np.array([[300.0, 0, 160.5], [0, 310.0, 120.25], [0, 0, 1]])
    rvec = np.array([0.1, -0.2, 0.05])
    tvec = np.array([0.2, -0.1, 0.5])
    want, _ = cv2.projectPoints(pts, rvec, tvec, K, np.array(d))
    R, _ = cv2.Rodrigues(rvec)
    vm = np.eye(4)
    vm[:3, :3], vm[:3, 3] = R, tvec
    f64 = torch.float64
    proj = project_gaussians(
        torch.from_numpy(pts), torch.tensor([[1.0, 0, 0, 0]]).double().expand(200, 4),
        torch.full((200, 3), 0.01, dtype=f64), torch.full((200,), 0.9, dtype=f64), torch.from_numpy(vm)[None],
        torch.from_numpy(K)[None], 320, 240, distortion=torch.tensor([d], dtype=f64),
    )  # fmt: skip
    np.testing.assert_allclose(proj.means2d[0].numpy(), want[:, 0, :], atol=1e-9)


@pytest.mark.parametrize("d", DISTS)
def test_jacobian_matches_autograd(d: tuple[float, float, float, float]) -> None:
    u = torch.tensor([[0.3, -0.2, 0.05]], dtype=torch.float64)
    v = torch.tensor([[-0.1, 0.25, 0.0]], dtype=torch.float64)
    dist = torch.tensor([d], dtype=torch.float64)
    J = distortion_jacobian(u, v, dist)
    for i in range(3):
        def f(p: torch.Tensor, i: int = i) -> torch.Tensor:
            ud, vd = distort(p[0].reshape(1, 1), p[1].reshape(1, 1), dist)
            return torch.cat([ud.reshape(1), vd.reshape(1)])

        want = torch.autograd.functional.jacobian(f, torch.stack([u[0, i], v[0, i]]))
        torch.testing.assert_close(J[0, i], want, atol=1e-12, rtol=0)


def test_rendered_blob_sits_where_opencv_projects_it() -> None:
    mean = torch.tensor([[0.35, -0.25, 3.0]], dtype=torch.float64)
    K = torch.tensor([[[80.0, 0, 48.0], [0, 80.0, 36.0], [0, 0, 1]]], dtype=torch.float64)
    d = (0.15, 0.05, 0.0, 0.0)
    f64 = torch.float64
    img, _, info = rasterize(
        mean, torch.tensor([[1.0, 0, 0, 0]], dtype=f64), torch.full((1, 3), 0.01, dtype=f64),
        torch.tensor([0.99], dtype=torch.float64), torch.ones(1, 3, dtype=torch.float64),
        torch.eye(4, dtype=torch.float64)[None], K, 96, 72, backend="torch",
        distortion=torch.tensor([d], dtype=torch.float64),
    )  # fmt: skip
    want, _ = cv2.projectPoints(mean.numpy(), np.zeros(3), np.zeros(3), K[0].numpy(), np.array(d))
    w = img[0, ..., 0]
    ys, xs = torch.meshgrid(torch.arange(72) + 0.5, torch.arange(96) + 0.5, indexing="ij")
    centre = torch.stack([(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()])
    assert torch.allclose(centre, torch.from_numpy(want[0, 0]), atol=0.05), (centre, want)
    assert torch.allclose(info["means2d"][0, 0], torch.from_numpy(want[0, 0]), atol=1e-9)


def test_zero_distortion_is_the_pinhole_path() -> None:
    rng = np.random.default_rng(1)
    n = 50
    args = (
        torch.from_numpy(np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(2, 4, n)]), torch.randn(n, 4).double(),
        torch.full((n, 3), 0.05, dtype=torch.float64), torch.full((n,), 0.8, dtype=torch.float64),
        torch.rand(n, 3).double(), torch.eye(4).double()[None],
        torch.tensor([[[40.0, 0, 24], [0, 40.0, 18], [0, 0, 1]]]).double(), 48, 36,
    )  # fmt: skip
    a, _, _ = rasterize(*args, backend="torch")
    b, _, _ = rasterize(*args, backend="torch", distortion=torch.zeros(1, 4, dtype=torch.float64))
    torch.testing.assert_close(a, b, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match=r"\[C, 4\]"):
        rasterize(*args, backend="torch", distortion=torch.zeros(2, 4, dtype=torch.float64))
