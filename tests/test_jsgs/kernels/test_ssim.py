"""SSIM against a float64 reference written independently: a direct weighted sum over the 11x11 window with
zero padding (the 3DGS convention: conv2d with padding 5 on the 2-D outer-product window)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from jsgs.jpeg.losses import photometric_loss, photometric_terms
from jsgs.kernels import ssim, ssim_map

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def reference_ssim_map(x: np.ndarray, y: np.ndarray, valid: bool = False) -> np.ndarray:
    """x, y: C x H x W float64. Loops over the window; samples outside the image count as 0."""
    c, h, w = x.shape
    g = np.array([math.exp(-((i - 5) ** 2) / (2 * 1.5**2)) for i in range(11)])
    g /= g.sum()
    win = np.outer(g, g)
    pad = lambda a: np.pad(a, ((0, 0), (5, 5), (5, 5)))  # noqa: E731
    xp, yp = pad(x), pad(y)
    out = np.zeros((c, h, w))
    for ch in range(c):
        for i in range(h):
            for j in range(w):
                px = xp[ch, i : i + 11, j : j + 11]
                py = yp[ch, i : i + 11, j : j + 11]
                mx, my = (win * px).sum(), (win * py).sum()
                vx = (win * px * px).sum() - mx * mx
                vy = (win * py * py).sum() - my * my
                cxy = (win * px * py).sum() - mx * my
                c1, c2 = 0.01**2, 0.03**2
                num = (2 * mx * my + c1) * (2 * cxy + c2)
                out[ch, i, j] = num / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    return out[:, 5 : h - 5, 5 : w - 5] if valid else out


def test_matches_reference() -> None:
    rng = np.random.default_rng(0)
    x = rng.random((3, 14, 17))
    y = np.clip(x + rng.normal(0, 0.1, x.shape), 0, 1)
    ref = reference_ssim_map(x, y)
    tx, ty = torch.tensor(x)[None], torch.tensor(y)[None]
    assert np.allclose(ssim_map(tx, ty)[0].numpy(), ref, atol=1e-12)
    assert ssim(tx, ty).item() == pytest.approx(ref.mean(), abs=1e-12)
    ref_valid = reference_ssim_map(x, y, valid=True)
    assert np.allclose(ssim_map(tx, ty, padding="valid")[0].numpy(), ref_valid, atol=1e-12)


def test_properties() -> None:
    x = torch.rand(2, 3, 20, 30)
    assert ssim(x, x).item() == pytest.approx(1.0, abs=1e-6)
    per = ssim(x, torch.rand(2, 3, 20, 30), reduction="none")
    assert per.shape == (2,) and (per < 0.5).all()
    assert ssim(x, 1 - x).item() < 0


def test_float32_and_gradcheck() -> None:
    x = torch.rand(1, 3, 12, 13, dtype=torch.float64)
    y = torch.rand(1, 3, 12, 13, dtype=torch.float64)
    assert abs(ssim(x.float(), y.float()).double() - ssim(x, y)) < 1e-5
    xr = x[:, :, :6, :7].clone().requires_grad_()
    ys = y[:, :, :6, :7]
    assert torch.autograd.gradcheck(lambda a: ssim(a, ys), (xr,))
    assert torch.autograd.gradcheck(lambda a: photometric_loss(a, ys), (xr,))


def test_photometric_loss_formula() -> None:
    x = torch.rand(2, 3, 16, 16, dtype=torch.float64)
    y = torch.rand(2, 3, 16, 16, dtype=torch.float64)
    l1 = (x - y).abs().sum() / (2 * 3 * 16 * 16)
    expected = 0.8 * l1 + 0.2 * (1 - ssim(x, y))
    assert photometric_loss(x, y).item() == pytest.approx(expected.item(), rel=1e-12)
    per = photometric_loss(x, y, reduction="none")
    assert per.mean().item() == pytest.approx(expected.item(), rel=1e-12)


@pytest.mark.parametrize("reduction", ["mean", "none"])
def test_ssim_checks_its_pair_and_picks_its_kernel_once(
    monkeypatch: pytest.MonkeyPatch, reduction: str
) -> None:
    """One call of ``ssim`` or ``ssim_map`` checks the pair and picks the kernel once (``ssim`` reaches the
    map without a second round), with the same value as the map's own mean."""
    from jsgs.kernels import _wrapper

    calls: list[str] = []
    for name in ("_check_pair", "_use_fused"):
        real = getattr(_wrapper, name)
        monkeypatch.setattr(_wrapper, name, lambda *a, real=real, name=name: calls.append(name) or real(*a))
    g = torch.Generator().manual_seed(2)
    x, y = torch.rand(2, 3, 16, 20, generator=g), torch.rand(2, 3, 16, 20, generator=g)
    value = ssim(x, y, reduction=reduction)
    assert calls == ["_check_pair", "_use_fused"]
    calls.clear()
    m = ssim_map(x, y)
    assert calls == ["_check_pair", "_use_fused"]
    assert torch.equal(value, m.mean() if reduction == "mean" else m.flatten(1).mean(1))


@pytest.mark.parametrize(("reduction", "channels_last"), [("mean", False), ("mean", True), ("none", False)])
def test_photometric_terms_picks_the_ssim_kernel_once(
    monkeypatch: pytest.MonkeyPatch, reduction: str, channels_last: bool
) -> None:
    """``photometric_terms`` picks the SSIM kernel once a call (where it lays out the target for the fused
    SSIM it hands that pick to ``ssim``), with the terms of l1 and ``ssim`` bit for bit."""
    from jsgs.kernels import _wrapper

    calls: list[tuple[int, ...]] = []
    real = _wrapper._use_fused
    monkeypatch.setattr(_wrapper, "_use_fused", lambda x, *a: calls.append(tuple(x.shape)) or real(x, *a))
    g = torch.Generator().manual_seed(4)
    x = torch.rand(2, 3, 16, 20, generator=g, requires_grad=True)
    y = torch.rand(2, 3, 16, 20, generator=g)
    if channels_last:
        x, y = x.permute(0, 2, 3, 1), y.permute(0, 2, 3, 1)
    terms = photometric_terms(x, y, 0.3, reduction, "valid", channels_last=channels_last)
    assert calls == [(2, 3, 16, 20)]
    xs, ys = (x.permute(0, 3, 1, 2), y.permute(0, 3, 1, 2)) if channels_last else (x, y)
    d_ssim = 1.0 - ssim(xs, ys, padding="valid", reduction=reduction)
    l1 = (x - y).abs().mean() if reduction == "mean" else (x - y).abs().flatten(1).mean(1)
    assert torch.equal(terms.d_ssim, d_ssim) and torch.equal(terms.l1, l1)
    assert torch.equal(terms.loss, 0.7 * l1 + 0.3 * d_ssim)


@pytest.mark.parametrize("call", [ssim, ssim_map])
def test_bad_arguments_are_one_line_errors(call: object) -> None:
    """Each refusal ``ssim`` and ``ssim_map`` make is one ValueError line naming the setting."""
    x = torch.rand(1, 3, 16, 16)
    cases = [
        ((x, x), {"padding": "full"}, "padding must be 'same' or 'valid', got 'full'"),
        ((x, x[:, :2]), {}, r"one shape, got \(1, 3, 16, 16\), \(1, 2, 16, 16\)$"),
        ((x[0], x[0]), {}, r"ssim needs two \(B, C, H, W\) tensors of one shape"),
        ((x, x), {"kernel": "fast"}, "kernel must be one of"),
        ((x, x), {"kernel": "cuda"}, "the fused SSIM kernel needs CUDA tensors, got cpu"),
    ]
    if call is ssim:
        cases.append(((x, x), {"reduction": "sum"}, "reduction must be 'mean' or 'none', got 'sum'"))
    for args, kwargs, message in cases:
        with pytest.raises(ValueError, match=message) as e:
            call(*args, **kwargs)  # type: ignore[operator]
        assert "\n" not in str(e.value)
