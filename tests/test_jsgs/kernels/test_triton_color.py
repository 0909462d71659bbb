"""JO's colour conversions as the Triton kernel of ``jsgs/kernels/_triton_jo.py`` (``color_convert``)
against :mod:`jsgs.jpeg.color`'s torch code (``rgb_to_ycbcr``, ``ycbcr_to_rgb``: one ``addmm``), and how
``method_options.speed.fused_color`` resolves.

On the CPU the kernel runs under Triton's interpreter (``PYTHONPATH=$PWD:/path/to/triton TRITON_INTERPRET=1
pytest tests/test_jsgs/kernels/test_triton_color.py``); those tests skip otherwise. ``-m gpu`` tests compare
on CUDA (float32, what training runs, against float32 and float64 torch), eagerly and inside a CUDA graph;
they print the largest differences. The sm_90 compile check is in ``test_triton_jo.py``
(``test_kernels_compile_for_sm90``).

Tolerances (8-bit units: the images are 0..255): float64 within 1e-11 (the kernel sums the three products
and the offset in another order than ``addmm``); float32 within 5e-4 (a few float32 ulp, 6e-5 each, of the
sums up to ~800 before the offset: CUDA contracts them to FMAs, ``addmm`` rounds each step). The gradient
is the transposed 3x3 map of the incoming gradient: 1e-11 / 1e-4 of the incoming gradient's largest value.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch
from _fused_graph import check_graph_replay, observe_with_gradients

from jsgs.base.errors import JsgsError
from jsgs.jpeg.color import kernel_coefficients, rgb_to_ycbcr, ycbcr_to_rgb
from jsgs.jpeg.observe import jpeg_observe
from jsgs.kernels._triton_jo import color_convert, interpreting, triton_available
from jsgs.method.options import parse_options, use_fused_color

needs_interpreter = pytest.mark.skipif(
    not (triton_available() and interpreting()),
    reason="needs Triton and TRITON_INTERPRET=1 (the fused colour kernel on CPU tensors)",
)
cuda_triton = pytest.mark.skipif(
    not (torch.cuda.is_available() and triton_available() and not interpreting()),
    reason="needs CUDA and Triton, without TRITON_INTERPRET",
)

TORCH: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {"rgb2ycc": rgb_to_ycbcr, "ycc2rgb": ycbcr_to_rgb}


def convert(x: torch.Tensor, name: str) -> torch.Tensor:
    """The colour map ``name`` by the kernel, with the coefficients JO hands it."""
    return color_convert(x, *kernel_coefficients(name, x.dtype, x.device))


def _both(x: torch.Tensor, name: str, g: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(value, gradient of ``sum(g * value)``) of the kernel and of the torch code."""
    out = []
    for fn in (lambda t: convert(t, name), TORCH[name]):
        xa = x.detach().clone().requires_grad_() if x.is_contiguous() else _like(x).requires_grad_()
        y = fn(xa)
        (grad,) = torch.autograd.grad(y, xa, g)
        out.append((y.detach(), grad))
    return out


def _like(x: torch.Tensor) -> torch.Tensor:
    """A copy of ``x`` with the same strides (a leaf that keeps the layout)."""
    y = torch.empty_strided(x.shape, x.stride(), dtype=x.dtype, device=x.device)
    return y.copy_(x.detach())


def _inputs(shape: tuple[int, ...], seed: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=gen, dtype=torch.float64) * 300.0 - 20.0
    return x.to(dtype), torch.randn(shape, generator=gen, dtype=torch.float64).to(dtype)


def _layouts(x: torch.Tensor) -> dict[str, torch.Tensor]:
    """``x`` (B, 3, H, W) in the layouts JO hands the map: contiguous, channels-last (the torch map's own
    output), a crop of a bigger image, H and W swapped, and every other view of a batch; all on ``x``'s
    device."""
    b, _, h, w = x.shape
    big = torch.zeros(2 * b, 3, h + 3, w + 5, dtype=x.dtype, device=x.device)
    big[::2, :, 1 : h + 1, 2 : w + 2] = x
    return {
        "contiguous": x,
        "channels_last": x.contiguous(memory_format=torch.channels_last),
        "crop": big[::2, :, 1 : h + 1, 2 : w + 2],
        "transposed": x.transpose(2, 3).contiguous().transpose(2, 3),
    }


@needs_interpreter
@pytest.mark.parametrize("name", ["rgb2ycc", "ycc2rgb"])
@pytest.mark.parametrize("shape", [(2, 3, 37, 53), (1, 3, 1, 1), (1, 3, 1, 1031), (3, 3, 13, 9)])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_matches_torch(name: str, shape: tuple[int, ...], dtype: torch.dtype) -> None:
    # odd sizes (a program's last pixels masked; 1031 pixels span two programs of 1024), every layout
    x, g = _inputs(shape, 1, dtype)
    tol, gtol = (1e-11, 1e-11) if dtype == torch.float64 else (5e-4, 1e-4)
    for layout, xl in _layouts(x).items():
        (v1, g1), (v2, g2) = _both(xl, name, g)
        assert v1.is_contiguous(), layout
        torch.testing.assert_close(v1, v2, rtol=0, atol=tol, msg=layout)
        torch.testing.assert_close(g1, g2, rtol=0, atol=gtol * float(g.abs().max()), msg=layout)
        assert float(v2.abs().max()) > 1.0 and float(g2.abs().max()) > 0.1  # something to compare
    if dtype == torch.float32:  # and against float64 torch
        (v1, _), _ = _both(x, name, g)
        torch.testing.assert_close(v1.double(), TORCH[name](x.double()), rtol=0, atol=5e-4)


def test_layouts_lie_on_the_input_device() -> None:
    # the CUDA test hands the kernel every layout of a CUDA tensor: one built on the CPU reached the launch
    # there ("Pointer argument (at 0) cannot be accessed from Triton (cpu tensor?)"), which no CPU run shows
    x = torch.zeros(2, 3, 5, 7, device="meta")
    for layout, xl in _layouts(x).items():
        assert xl.device == x.device and xl.shape == x.shape, layout


@needs_interpreter
def test_strided_gradient_and_a_round_trip() -> None:
    # the incoming gradient with its own strides (autograd hands the backward what the next op made), and
    # the two maps composed: YCbCr -> RGB undoes RGB -> YCbCr up to libjpeg's 16-bit constants
    x, g = _inputs((1, 3, 11, 17), 2, torch.float64)
    for gl in _layouts(g).values():
        xa = x.clone().requires_grad_()
        (got,) = torch.autograd.grad(convert(xa, "rgb2ycc"), xa, gl)
        xb = x.clone().requires_grad_()
        (want,) = torch.autograd.grad(rgb_to_ycbcr(xb), xb, gl)
        torch.testing.assert_close(got, want, rtol=0, atol=1e-11)
    back = convert(convert(x, "rgb2ycc"), "ycc2rgb")
    assert float((back - x).abs().max()) < 0.05


@needs_interpreter
@pytest.mark.parametrize("name", ["rgb2ycc", "ycc2rgb"])
def test_gradcheck_float64(name: str) -> None:
    x = (torch.rand(2, 3, 5, 7, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 255.0)
    assert torch.autograd.gradcheck(lambda t: convert(t, name), (x.requires_grad_(),))


@needs_interpreter
@pytest.mark.parametrize("mode", ["paper", "float"])
@pytest.mark.parametrize(("height", "width"), [(37, 53), (16, 32)])
def test_jpeg_observe_with_the_colour_kernel(mode: str, height: int, width: int) -> None:
    # JO with the fused coding pass, the colour kernel on and off: equal up to float rounding
    variants = [{"kernel": "triton", "color_kernel": color} for color in ("triton", "torch")]
    out = observe_with_gradients(4, height, width, "4:2:0", mode, variants)
    torch.testing.assert_close(out[0][0], out[1][0], rtol=0, atol=1e-11)
    torch.testing.assert_close(out[0][1], out[1][1], rtol=0, atol=1e-11)
    assert float(out[1][1].abs().max()) > 0.01


@needs_interpreter
def test_jpeg_terms_pass_the_colour_kernel_on(monkeypatch: pytest.MonkeyPatch) -> None:
    # the method's chain (JO twice, L_obs, DS) with color_kernel "triton" reaches the kernel: equal values,
    # and a broken kernel shows
    from jsgs.jpeg import observe
    from jsgs.method.image_terms import terms_with_gradient

    g = torch.Generator().manual_seed(19)
    x = torch.rand(1, 3, 29, 43, generator=g, dtype=torch.float64).requires_grad_()
    y = torch.rand(1, 3, 29, 43, generator=g, dtype=torch.float64)
    tables = torch.randint(1, 90, (2, 8, 8), generator=g).double()
    first = torch.randint(20, 120, (2, 8, 8), generator=g).double()
    settings = dict(
        mode="paper", ssim_lambda=0.2, ssim_padding="valid", ds=True, gc=True, eps_sm=1e-3, eps_loss=1e-6,
        eps_block=1e-6, first=first, weights=(0.2, 0.02, 0.03), sampling="4:2:0", jo_kernel="triton",
    )  # fmt: skip
    out = [terms_with_gradient(x, y, tables, color_kernel=k, **settings) for k in ("triton", "torch")]
    for a, b in zip(*out, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)
    # every coefficient off by one: the observation moves
    monkeypatch.setattr(observe, "kernel_coefficients", lambda *a: [c + 1.0 for c in kernel_coefficients(*a)])
    broken = terms_with_gradient(x, y, tables, color_kernel="triton", **settings)
    assert float((broken[3] - out[1][3]).abs().max()) > 1e-3


def test_the_colour_kernel_needs_the_fused_coding_pass() -> None:
    # with the torch coding pass (or mode exact) the colour kernel is ignored: the torch code, bit for bit,
    # with or without Triton
    g = torch.Generator().manual_seed(5)
    rgb = torch.rand(1, 3, 19, 21, generator=g)
    luma = torch.randint(1, 80, (8, 8), generator=g).float()
    for mode in ("paper", "float", "exact"):
        a = jpeg_observe(rgb, luma, luma, "4:2:0", mode, kernel="torch", color_kernel="triton")
        assert torch.equal(a, jpeg_observe(rgb, luma, luma, "4:2:0", mode)), mode
    with pytest.raises(ValueError, match="color_kernel must be one of"):
        jpeg_observe(rgb, luma, luma, color_kernel="cuda")
    if triton_available():
        with pytest.raises(ValueError, match="color_convert: x must be"):
            convert(rgb[:, :2], "rgb2ycc")


def test_fused_color_setting() -> None:
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert parse_options({}).speed.fused_color == "auto"  # the default: on where the fused coding pass runs
    assert not use_fused_color(parse_options({}), cpu)
    assert use_fused_color(parse_options({}), cuda) == triton_available()
    assert not use_fused_color(parse_options({"speed": {"fused_color": False}}), cuda)
    assert not use_fused_color(parse_options({"speed": {"fused_color": "auto"}}), cpu)
    with pytest.raises(JsgsError, match="fused_color runs with the fused JO kernels only"):
        use_fused_color(parse_options({"speed": {"fused_color": True}}), cpu)
    # auto on CUDA: where the fused coding pass runs (Triton, mode paper or float)
    for mode in ("paper", "float"):
        on = parse_options({"jpeg_mode": mode, "speed": {"fused_color": "auto"}})
        assert use_fused_color(on, cuda) == triton_available(), mode
    for raw in ({"jpeg_mode": "exact"}, {"speed": {"fused_jo": False}}):
        opts = parse_options({**raw, "speed": {**raw.get("speed", {}), "fused_color": "auto"}})
        assert not use_fused_color(opts, cuda), raw
        on = parse_options({**raw, "speed": {**raw.get("speed", {}), "fused_color": True}})
        with pytest.raises(JsgsError, match="fused_color runs with the fused JO kernels only"):
            use_fused_color(on, cuda)


# --- CUDA -----------------------------------------------------------------------------------------------


@cuda_triton
@pytest.mark.gpu
@pytest.mark.parametrize("name", ["rgb2ycc", "ycc2rgb"])
@pytest.mark.parametrize(("height", "width"), [(1440, 1920), (37, 53)])
def test_cuda_matches_torch(name: str, height: int, width: int) -> None:
    x, g = _inputs((1, 3, height, width), 6, torch.float64)
    print()
    for layout, xl in _layouts(x.float().cuda()).items():
        (v1, g1), (v2, g2) = _both(xl, name, g.float().cuda())
        x64 = xl.double().requires_grad_()
        v3 = TORCH[name](x64)
        (g3,) = torch.autograd.grad(v3, x64, g.cuda())
        pairs = ((v1, v2), (v1, v3), (g1, g2), (g1, g3))
        err = [float((a.double() - b.double()).abs().max()) for a, b in pairs]
        print(f"{name} {width}x{height} {layout} float32: max |kernel - addmm| {err[0]:.2e} (float64 "
              f"{err[1]:.2e}); gradient {err[2]:.2e} ({err[3]:.2e})")
        assert max(err[:2]) <= 5e-4 and max(err[2:]) <= 1e-4 * float(g.abs().max())


@cuda_triton
@pytest.mark.gpu
def test_cuda_graph_replays_the_colour_kernel() -> None:
    # the fused chain with the colour kernel, against the fused chain with the torch colour maps (addmm)
    check_graph_replay(
        {"jo_kernel": "triton", "color_kernel": "triton"}, {"jo_kernel": "triton", "color_kernel": "torch"},
        "graph (colour kernel) vs eager (addmm)",
    )
