"""jpeg_observe on hard cases: extreme and 16-bit tables, black / white / saturated / constant / Nyquist
images, degenerate sizes; finiteness of outputs and gradients in every mode; batching; gradient semantics."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch
from PIL import Image

from jsgs.jpeg.losses import obs_loss, photometric_loss
from jsgs.jpeg.observe import MODES, jpeg_observe
from jsgs.jpeg.tables import SAMPLING_FACTORS, ijg_tables

SAMPLINGS = ("4:4:4", "4:2:2", "4:2:0", "4:4:0", "4:1:1")
SIZES = ((1, 1), (7, 9), (17, 33), (1, 1000))


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def hard_tables() -> tuple[torch.Tensor, torch.Tensor]:
    """Views with all-1, all-255, IJG q=50 and 16-bit tables (B = 4)."""
    l50, c50 = ijg_tables(50)
    luma = np.stack([np.ones((8, 8)), np.full((8, 8), 255), l50, np.full((8, 8), 30000)])
    chroma = np.stack([np.ones((8, 8)), np.full((8, 8), 255), c50, np.full((8, 8), 65535)])
    return torch.tensor(luma, dtype=torch.float32), torch.tensor(chroma, dtype=torch.float32)


def hard_images(h: int, w: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(h * 1000 + w)
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    checker = ((yy + xx) % 2).float().expand(3, h, w)
    return {
        "black": torch.zeros(3, h, w),
        "white": torch.ones(3, h, w),
        "saturated": (torch.rand(3, h, w, generator=g) > 0.5).float(),
        "constant": torch.tensor([0.8, 0.1, 0.35])[:, None, None].expand(3, h, w),
        "nyquist": checker,
        "noise": torch.rand(3, h, w, generator=g),
        "out_of_range": torch.rand(3, h, w, generator=g) * 1.6 - 0.3,
    }


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("sampling", SAMPLINGS)
def test_outputs_and_gradients_finite_on_hard_cases(mode: str, sampling: str) -> None:
    luma, chroma = hard_tables()
    for h, w in SIZES:
        for name, img in hard_images(h, w).items():
            x = img[None].expand(4, -1, -1, -1).clone().requires_grad_()
            out = jpeg_observe(x, luma, chroma, sampling, mode)
            assert out.shape == x.shape
            assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1, (name, h, w)
            loss = photometric_loss(out, torch.full_like(out, 0.5)) + out.square().sum()
            (g,) = torch.autograd.grad(loss, x)
            assert torch.isfinite(g).all(), (name, h, w)


@pytest.mark.parametrize("mode", MODES)
def test_batch_equals_views_one_by_one(mode: str) -> None:
    luma, chroma = hard_tables()
    x = torch.rand(4, 3, 13, 21, generator=torch.Generator().manual_seed(0)).requires_grad_()
    out = jpeg_observe(x, luma, chroma, "4:2:0", mode)
    weights = torch.linspace(0, 1, out.numel()).view_as(out)
    (g,) = torch.autograd.grad((out * weights).sum(), x)
    for i in range(4):
        xi = x[i : i + 1].detach().clone().requires_grad_()
        oi = jpeg_observe(xi, luma[i], chroma[i], "4:2:0", mode)
        (gi,) = torch.autograd.grad((oi * weights[i : i + 1]).sum(), xi)
        assert torch.equal(oi, out[i : i + 1])
        assert torch.allclose(gi, g[i : i + 1], atol=1e-6)


def test_exact_values_are_8bit_and_idempotent_inputs() -> None:
    """Mode exact/float outputs are k/255; an already-8-bit input and its float noise give the same output."""
    luma, chroma = ijg_tables(75)
    base = torch.randint(0, 256, (1, 3, 16, 16)).float() / 255
    jitter = base + (torch.rand_like(base) - 0.5) / 300  # stays within the same 8-bit level
    for mode in ("exact", "float"):
        a = jpeg_observe(base, luma, chroma, "4:2:0", mode)
        b = jpeg_observe(jitter, luma, chroma, "4:2:0", mode)
        assert torch.equal(a, b)
        assert torch.equal((a * 255).round(), a * 255)


def test_half_boundary_coefficients_match_pillow() -> None:
    """Constant blocks whose DC lands exactly on a .5 quantization boundary (libjpeg rounds away from 0)."""
    luma = np.full(64, 16)
    for level in (129, 127, 131, 125, 0, 255):
        arr = np.full((8, 8, 3), level, np.uint8)
        buf = io.BytesIO()
        Image.fromarray(arr).save(buf, "JPEG", qtables=[list(luma), list(luma)], subsampling=0)
        buf.seek(0)
        ref = np.asarray(Image.open(buf).convert("RGB"))
        x = torch.from_numpy(arr.copy()).permute(2, 0, 1)[None].float() / 255
        for mode in ("exact", "float"):
            out = jpeg_observe(x, luma.reshape(8, 8), luma.reshape(8, 8), "4:4:4", mode)
            got = (out[0] * 255).round().permute(1, 2, 0).numpy()
            assert np.array_equal(got, ref), (level, mode, got[0, 0], ref[0, 0])


def test_paper_mode_gradcheck() -> None:
    """Mode "paper" is the smooth float operator with d round = 0: numerically differentiable away from the
    rounding jumps and clamps (inputs kept inside (0.25, 0.75))."""
    g = torch.Generator().manual_seed(3)
    x = (0.25 + 0.5 * torch.rand(1, 3, 6, 7, generator=g, dtype=torch.float64)).requires_grad_()
    luma, chroma = ijg_tables(40)
    for sampling in SAMPLINGS:
        assert torch.autograd.gradcheck(
            lambda t, s=sampling: jpeg_observe(t, luma, chroma, s, "paper"), (x,), eps=1e-7, atol=1e-6
        )


def test_gradients_use_soft_round_derivative() -> None:
    """All modes share the backward; with all-1 tables a flat 8x8 grey block of an integer level sits exactly
    on a quantization level, so the soft-round derivative 3 (z - round z)^2 is 0 for every coefficient."""
    ones = np.ones((8, 8))
    x = torch.full((1, 3, 8, 8), 100 / 255, dtype=torch.float64, requires_grad=True)
    for mode in MODES:
        out = jpeg_observe(x, ones, ones, "4:4:4", mode)
        (g,) = torch.autograd.grad(out.sum(), x)
        assert g.abs().max() < 1e-12, mode
    # A view whose DC sits half-way between two levels gets the largest derivative (3/4 per coefficient).
    q = np.full((8, 8), 16.0)
    x = torch.full((1, 3, 8, 8), 129 / 255, dtype=torch.float64, requires_grad=True)  # DC = 8 / 16 = 0.5
    grads = {}
    for mode in MODES:
        out = jpeg_observe(x, q, q, "4:4:4", mode)
        (g,) = torch.autograd.grad(out.sum(), x)
        grads[mode] = g
        assert torch.isfinite(g).all() and g.abs().max() > 0
    assert torch.allclose(grads["exact"], grads["float"], atol=1e-9)


def test_obs_loss() -> None:
    luma, chroma = ijg_tables(30)
    target = torch.rand(2, 3, 16, 24)
    rendered = torch.rand(2, 3, 16, 24, requires_grad=True)
    res = obs_loss(rendered, target, luma, chroma, "4:2:0", "paper")
    assert res.loss.shape == () and res.observation.shape == rendered.shape
    ref = photometric_loss(jpeg_observe(rendered, luma, chroma, "4:2:0", "paper"), target)
    assert torch.allclose(res.loss, ref)
    res.loss.backward()
    assert torch.isfinite(rendered.grad).all()
    per_view = obs_loss(rendered, target, luma, chroma, reduction="none").loss
    assert per_view.shape == (2,)


def test_rejects_bad_arguments() -> None:
    x = torch.rand(1, 3, 8, 8)
    t = np.ones((8, 8))
    with pytest.raises(ValueError):
        jpeg_observe(x, t, t, "4:2:1")
    with pytest.raises(ValueError):
        jpeg_observe(x, t, t, mode="fast")
    with pytest.raises(ValueError):
        jpeg_observe(x, np.ones((2, 8, 8)), t)


@pytest.mark.parametrize(
    "bad",
    [np.zeros((8, 8)), -np.ones((8, 8)), np.full((8, 8), 2.5), np.full((8, 8), np.nan),
     np.full((8, 8), np.inf), np.full((8, 8), 65536), [[1] * 8] * 7 + [[1] * 7 + [0]]],
    ids=["zero", "negative", "fractional", "nan", "inf", "above_16_bits", "list_with_a_zero"],
)
def test_host_tables_must_hold_quantization_steps(bad: np.ndarray | list) -> None:
    """A table given as an array or a list (host values, checked for free) that is not integers 1..65535 is a
    ValueError naming the argument; unchecked, a 0 divides by zero (NaN output) and a negative step codes
    garbage."""
    x = torch.rand(1, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    good = np.ones((8, 8))
    for mode in MODES:
        with pytest.raises(ValueError, match=r"^luma_table: entry .* is not a quantization step"):
            jpeg_observe(x, bad, good, "4:2:0", mode)
        with pytest.raises(ValueError, match=r"^chroma_table: entry .* at \[\d, \d\] is not a quantization"):
            jpeg_observe(x, good, bad, "4:2:0", mode)
    with pytest.raises(ValueError, match=r"^luma_table: must be \(8, 8\), .* or 64 values, got \(63"):
        jpeg_observe(x, np.ones(63), good)
    edge = np.full((8, 8), 65535)  # the largest 16-bit step is a step
    assert torch.isfinite(jpeg_observe(x, edge, np.ones(64), "4:2:0", "exact")).all()


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("sampling", SAMPLINGS)
def test_non_finite_inputs(mode: str, sampling: str) -> None:
    """±inf is clamped like any value outside [0, 1] (finite output and gradient, none through that pixel).
    NaN is never hidden: it makes the output NaN over its MCU (8h x 8v pixels, all three channels) and at most
    one pixel of chroma up-sampling context beyond, in its own view only, and the same view's gradient."""
    luma, chroma = ijg_tables(75)
    h, v = SAMPLING_FACTORS[sampling]
    base = torch.rand(2, 3, 32, 48, generator=torch.Generator().manual_seed(1))
    for value, clamped in ((float("inf"), 1.0), (float("-inf"), 0.0)):
        x = base.clone()
        x[0, 1, 11, 21] = value
        x.requires_grad_()
        out = jpeg_observe(x, luma, chroma, sampling, mode)
        (g,) = torch.autograd.grad(out.sum(), x)
        ref = base.clone()
        ref[0, 1, 11, 21] = clamped
        assert torch.equal(out, jpeg_observe(ref, luma, chroma, sampling, mode))
        assert torch.isfinite(g).all() and g[0, 1, 11, 21] == 0
    x = base.clone()
    x[0, 1, 11, 21] = float("nan")
    x.requires_grad_()
    out = jpeg_observe(x, luma, chroma, sampling, mode)
    (g,) = torch.autograd.grad(out.sum(), x)
    assert out[0, :, 11, 21].isnan().all() and g[0].isnan().any()
    assert torch.isfinite(out[1]).all() and torch.isfinite(g[1]).all()
    mcu_y, mcu_x = (11 // (8 * v)) * 8 * v, (21 // (8 * h)) * 8 * h
    reach = torch.zeros(32, 48, dtype=torch.bool)
    reach[max(mcu_y - 1, 0) : mcu_y + 8 * v + 1, max(mcu_x - 1, 0) : mcu_x + 8 * h + 1] = True
    assert torch.isfinite(out[0][:, ~reach]).all()
