"""Lens distortion in the reference rasterizer: the distorted projection of points against OpenCV's
``cv2.projectPoints`` (float64), its Jacobian against autograd, the rendered Gaussian's centre where OpenCV
puts its mean, no distortion equal to the pinhole path bit for bit, and the gsplat backend's distorted path
(its CUDA kernels stood in for by the reference's) laying out its channels as the reference does."""

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


class _TorchGsplat:
    """gsplat's three tile kernels with gsplat's signatures, done by the reference (CPU): stands in for the
    CUDA library so that the distorted gsplat path's own code (projection, channel layout, meta) runs here."""

    def __init__(self) -> None:
        self.bins = None
        self.depths = None

    def isect_tiles(self, means2d, radii, depths, tile_size, tw, th, packed=False, n_images=None):
        from jsgs.render.reference import bin_tiles

        assert tile_size == 16 and not packed and n_images == means2d.shape[0]
        self.bins = bin_tiles(means2d, radii, depths, tw * 16, th * 16)
        self.depths = depths
        return self.bins.tiles_per_gauss, self.bins.tile_ids, self.bins.flatten_ids

    def isect_offset_encode(self, isect_ids, n_images, tw, th):
        return self.bins.offsets

    def rasterize_to_pixels(self, means2d, conics, colors, opacities, width, height, tile_size, offsets,
                            flatten_ids, backgrounds=None, absgrad=False):  # fmt: skip
        from types import SimpleNamespace

        from jsgs.render.reference.composite import composite

        proj = SimpleNamespace(means2d=means2d, conics=conics, depths=self.depths)
        return composite(proj, self.bins, opacities[0], colors, backgrounds, width, height)


@pytest.mark.parametrize("mode", ["RGB", "RGB+ED"])
def test_distorted_gsplat_path_lays_out_channels_as_the_reference(mode: str, monkeypatch) -> None:
    """The distorted camera's gsplat path, its three CUDA kernels replaced by the reference's tile binning and
    compositing: the image, the extra channels and the gradients equal the reference backend's (the same
    test with gsplat's kernels is tests/test_jsgs/render/test_render_gpu.py)."""
    import gsplat.cuda._wrapper as wrapper

    from jsgs.render.backend import _rasterize_gsplat_distorted

    fake = _TorchGsplat()
    for name in ("isect_tiles", "isect_offset_encode", "rasterize_to_pixels"):
        monkeypatch.setattr(wrapper, name, getattr(fake, name))
    rng = np.random.default_rng(3)
    n, W, H = 60, 48, 32  # W, H multiples of the tile: the fake bins on the padded grid
    f64 = torch.float64
    base = dict(
        means=torch.from_numpy(np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(2, 4, n)]),
        quats=torch.randn(n, 4, dtype=f64), scales=torch.full((n, 3), 0.08, dtype=f64),
        opacities=torch.full((n,), 0.7, dtype=f64), colors=torch.rand(n, 3, dtype=f64),
    )  # fmt: skip
    vm = torch.eye(4, dtype=f64)[None]
    K = torch.tensor([[[40.0, 0, 24], [0, 40.0, 16], [0, 0, 1]]], dtype=f64)
    dist = torch.tensor([[-0.1, 0.02, 0.003, -0.002]], dtype=f64)
    extra = torch.rand(1, n, 2, dtype=f64)
    outs = {}
    for which in ("torch", "glue"):
        p = {k: v.clone().requires_grad_(True) for k, v in base.items()}
        args = (p["means"], p["quats"], p["scales"], p["opacities"], p["colors"], vm, K, W, H)
        if which == "torch":
            kw = {"distortion": dist, "extra": extra, "render_mode": mode}
            img, alpha, info = rasterize(*args, backend="torch", **kw)
        else:
            img, alpha, info = _rasterize_gsplat_distorted(
                *args, dist, sh_degree=None, near_plane=0.01, far_plane=1e10, backgrounds=None, eps2d=0.3,
                radius_clip=0.0, absgrad=False, render_mode=mode, extra=extra,
            )  # fmt: skip
        (img.sum() + 2 * info["extra"].sum() + alpha.sum()).backward()
        outs[which] = (img.detach(), info["extra"].detach(), {k: v.grad for k, v in p.items()}, info)
    (a, ea, ga, ia), (b, eb, gb, ib) = outs["torch"], outs["glue"]
    assert a.shape == b.shape == (1, H, W, 3 if mode == "RGB" else 4) and eb.shape == (1, H, W, 2)
    torch.testing.assert_close(b, a, atol=1e-10, rtol=0)
    torch.testing.assert_close(eb, ea, atol=1e-10, rtol=0)
    for k in ga:
        torch.testing.assert_close(gb[k], ga[k], atol=1e-9, rtol=1e-7)
    assert torch.equal(ib["radii"], ia["radii"]) and ib["n_cameras"] == 1
