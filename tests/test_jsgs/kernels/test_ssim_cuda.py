"""The fused SSIM kernel (``jsgs/kernels/csrc/ssim.cu``) against its torch twin (``jsgs.kernels.ssim``,
kernel="torch").

On CPU: how ``kernel`` is chosen and refused. On CUDA (the kernel is built on first use, ~30 s): values and
gradients equal the twin's in float64 (tight) and float32, for both paddings, odd sizes, batches, a
non-uniform upstream gradient, flat and saturated images, and inside a CUDA graph.
"""

from __future__ import annotations

import pytest
import torch

from jsgs.kernels import ssim, ssim_map

cuda = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs CUDA (the fused SSIM kernel is CUDA-only)"
)


def test_auto_on_cpu_is_the_twin() -> None:
    g = torch.Generator().manual_seed(0)
    x, y = torch.rand(2, 3, 20, 24, generator=g), torch.rand(2, 3, 20, 24, generator=g)
    assert torch.equal(ssim_map(x, y, kernel="auto"), ssim_map(x, y, kernel="torch"))


def test_kernel_choice_is_checked() -> None:
    x = torch.rand(1, 3, 16, 16)
    with pytest.raises(ValueError, match="kernel must be one of"):
        ssim(x, x, kernel="fast")
    with pytest.raises(ValueError, match="needs CUDA tensors"):
        ssim(x, x, kernel="cuda")


def _pair(shape: tuple[int, ...], dtype: torch.dtype, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(*shape, generator=g, dtype=torch.float64)
    y = (x + 0.2 * torch.randn(*shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    return x.to("cuda", dtype), y.to("cuda", dtype)


def _both(x: torch.Tensor, y: torch.Tensor, padding: str, weight: torch.Tensor | None = None):
    out = []
    for kernel in ("cuda", "torch"):
        xa = x.clone().requires_grad_()
        m = ssim_map(xa, y, padding=padding, kernel=kernel)
        (m.mean() if weight is None else (m * weight).sum()).backward()
        out.append((m.detach(), xa.grad))
    return out


@cuda
@pytest.mark.gpu
@pytest.mark.parametrize("padding", ["same", "valid"])
@pytest.mark.parametrize("shape", [(1, 3, 37, 53), (2, 3, 64, 41), (1, 1, 11, 11)])
def test_fused_matches_twin_float64(padding: str, shape: tuple[int, ...]) -> None:
    x, y = _pair(shape, torch.float64, 1)
    (m1, g1), (m2, g2) = _both(x, y, padding)
    torch.testing.assert_close(m1, m2, rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(g1, g2, rtol=1e-10, atol=1e-14)


@cuda
@pytest.mark.gpu
@pytest.mark.parametrize("padding", ["same", "valid"])
def test_fused_matches_twin_float32_weighted(padding: str) -> None:
    x, y = _pair((2, 3, 96, 130), torch.float32, 2)
    ho, wo = (96, 130) if padding == "same" else (86, 120)
    weight = torch.rand(2, 3, ho, wo, device="cuda", generator=torch.Generator("cuda").manual_seed(0))
    (m1, g1), (m2, g2) = _both(x, y, padding, weight)
    # float32 sums in another order: the two differ by rounding, and each stays as close to float64
    torch.testing.assert_close(m1, m2, rtol=0, atol=5e-6)
    torch.testing.assert_close(g1, g2, rtol=0, atol=5e-6)
    (m64, g64), _ = _both(x.double(), y.double(), padding, weight.double())
    for m, g in ((m1, g1), (m2, g2)):
        assert (m.double() - m64).abs().max() < 5e-6 and (g.double() - g64).abs().max() < 5e-6


@cuda
@pytest.mark.gpu
@pytest.mark.parametrize("case", ["flat", "black", "saturated", "inverse"])
def test_fused_hard_cases_are_finite_and_match(case: str) -> None:
    x, y = _pair((1, 3, 40, 40), torch.float32, 3)
    if case == "flat":  # zero variance everywhere: S rests on C1 and C2 alone
        x, y = torch.full_like(x, 0.5), torch.full_like(y, 0.5)
    elif case == "black":
        x, y = torch.zeros_like(x), torch.zeros_like(y)
    elif case == "saturated":
        x, y = (x > 0.5).float(), torch.ones_like(y)
    else:  # 2 s_xy + C2 near or below 0
        y = 1.0 - x
    (m1, g1), (m2, g2) = _both(x, y, "valid")
    assert torch.isfinite(m1).all() and torch.isfinite(g1).all()
    torch.testing.assert_close(m1, m2, rtol=1e-5, atol=2e-6)
    torch.testing.assert_close(g1, g2, rtol=1e-4, atol=1e-6)


@cuda
@pytest.mark.gpu
def test_fused_inside_a_cuda_graph() -> None:
    x, y = _pair((1, 3, 70, 90), torch.float32, 4)
    xs = x.clone().requires_grad_()
    fn = torch.cuda.make_graphed_callables(lambda a, b: ssim(a, b, padding="valid", kernel="cuda"), (xs, y))
    for seed in (5, 6):
        x2, y2 = _pair((1, 3, 70, 90), torch.float32, seed)
        a = x2.clone().requires_grad_()
        fn(a, y2).backward()
        b = x2.clone().requires_grad_()
        ref = ssim(b, y2, padding="valid", kernel="torch")
        ref.backward()
        torch.testing.assert_close(a.grad, b.grad, rtol=1e-4, atol=1e-7)


@cuda
@pytest.mark.gpu
def test_fused_refuses_what_it_cannot_do() -> None:
    x, y = _pair((1, 3, 16, 16), torch.float32, 0)
    with pytest.raises(ValueError, match="must not need a gradient"):
        ssim(x, y.requires_grad_(), kernel="cuda")
    with pytest.raises(ValueError, match="needs float32 or float64"):
        ssim(x.half(), y.half(), kernel="cuda")
    with pytest.raises(ValueError, match="11-tap window"):
        ssim(x, y, window_size=7, kernel="cuda")
    # auto: the twin where the kernel does not apply (a target with a gradient)
    yy = y.detach().clone().requires_grad_()
    ssim(x, yy, kernel="auto").backward()
    assert yy.grad is not None


class _TwinExtension:
    """The fused kernels' two functions computed by the torch twin on the CPU (their arithmetic aside, what
    they take and return), recording the upstream gradient each backward is given."""

    def __init__(self) -> None:
        self.upstreams: list[torch.Tensor] = []

    def ssim_forward(self, x, y, window, c1, c2, same):  # type: ignore[no-untyped-def]
        from jsgs.kernels._torch_impl import ssim_map_torch

        m = ssim_map_torch(x, y, window, "same" if same else "valid")
        return [m, m * 0.5, m * 0.25, m * 0.125]  # three maps of the map's shape to save

    def ssim_backward(self, grad, x, y, window, d_mu, d_xx, d_xy, same):  # type: ignore[no-untyped-def]
        from jsgs.kernels._torch_impl import ssim_map_torch

        self.upstreams.append(grad)
        with torch.enable_grad():
            xr = x.detach().requires_grad_(True)
            m = ssim_map_torch(xr, y, window, "same" if same else "valid")
            return torch.autograd.grad(m, xr, grad)[0]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_fused_mean_hands_the_kernel_a_broadcast_upstream_of_the_means_value(
    monkeypatch: pytest.MonkeyPatch, dtype: torch.dtype
) -> None:
    """``ssim(..., reduction="mean")`` on the fused path: one node whose backward gives the kernel the mean's
    gradient as one value broadcast (no map of it), the value the mean's own backward would write into each
    element; the loss and the gradient those of the map's mean, bit for bit."""
    from jsgs.kernels import _wrapper

    ext = _TwinExtension()
    monkeypatch.setattr(_wrapper, "extension", lambda warn=True: ext)
    monkeypatch.setattr(_wrapper, "_use_fused", lambda *a: True)
    g = torch.Generator().manual_seed(3)
    x = torch.rand(1, 3, 30, 41, generator=g, dtype=dtype)
    y = torch.rand(1, 3, 30, 41, generator=g, dtype=dtype)
    up = torch.tensor(-0.73, dtype=dtype)
    out = []
    for fused_mean in (False, True):
        xa = x.clone().requires_grad_(True)
        value = ssim(xa, y, padding="valid") if fused_mean else ssim_map(xa, y, padding="valid").mean()
        out.append((value.detach(), torch.autograd.grad(value, xa, up)[0]))
    (v0, g0), (v1, g1) = out
    assert torch.equal(v0, v1) and torch.equal(g0, g1)
    dense, broadcast = ext.upstreams
    assert all(s == 0 for s in broadcast.stride()) and broadcast.shape == dense.shape == (1, 3, 20, 31)
    assert torch.equal(broadcast.contiguous(), dense)


@cuda
@pytest.mark.gpu
@pytest.mark.parametrize("padding", ["same", "valid"])
def test_fused_mean_equals_the_maps_mean_bit_for_bit(padding: str) -> None:
    x, y = _pair((1, 3, 96, 130), torch.float32, 4)
    out = []
    for fused_mean in (False, True):
        xa = x.clone().requires_grad_()
        v = ssim(xa, y, padding=padding, kernel="cuda") if fused_mean else ssim_map(
            xa, y, padding=padding, kernel="cuda"
        ).mean()
        out.append((v.detach(), torch.autograd.grad(v, xa, torch.tensor(0.37, device="cuda"))[0]))
    assert torch.equal(out[0][0], out[1][0]) and torch.equal(out[0][1], out[1][1])
