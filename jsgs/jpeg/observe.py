"""The JPEG observation operator (JO, paper eq. jpeg_operator): encode and decode a rendered image with a
view's own quantization tables, differentiably.

``jpeg_observe(rgb, luma_table, chroma_table, sampling, mode)`` maps ``rgb`` (B x 3 x H x W in [0, 1]) to the
image a JPEG decoder would show for it, B x 3 x H x W in [0, 1]. Every view of the batch carries its own
tables; the sampling is one per call (views of one batch share an image size anyway; split batches by
sampling).

Stages (libjpeg-turbo 3, as Pillow writes and reads JPEG):
  RGB -> YCbCr -> edge replication -> chroma down-sampling -> level shift -> 8x8 DCT -> quantize -> dequantize
  -> IDCT -> +128, range limit -> crop -> chroma "fancy" up-sampling -> YCbCr -> RGB, clamp.

Edge rules (what makes real photos, whose sizes are not multiples of 16, come out bit-exact): each plane is
extended by replicating its last column / row. Chroma is down-sampled from the full-resolution planes
replicated to ``ceil(W / 8h) 8h`` columns and ``ceil(H / v) v`` rows; the down-sampled rows are then
replicated to a multiple of 8. On decoding only the real chroma samples (``ceil(H / v)`` x ``ceil(W / h)``)
feed the up-sampler, whose edge context is the edge sample itself. Blocks that only pad an MCU are never
visible and are not computed.

Modes (all three share one backward: the gradient of the float stages, with the soft-round derivative
``3 (z - round z)^2`` at the quantizer, zero outside the clamps):
  - ``"exact"``: the forward value is libjpeg-turbo's integer pipeline, bit for bit (8-bit input
    ``floor(255 x + 1/2)``, integer colour conversion, down-sampling bias, islow DCT, quantizer rounding
    ``sign(t) floor((|t| + 4Q) / 8Q)``, islow IDCT and range limit, integer fancy up-sampling, integer YCbCr
    -> RGB). Each stage is straight-through: value of the integer stage, gradient of its float version
    evaluated at the integer input.
  - ``"float"``: the same integer pipeline computed in the working dtype (float32) instead of float64: the
    islow forward DCT as float32 matrix products with its rounding shifts (exact while partial sums stay
    below 2^24, otherwise off by one unit in a rare coefficient), and the float orthonormal IDCT rounded to
    the nearest integer instead of the islow IDCT. The cheap approximation (PSNR against libjpeg in the
    README). A plain float forward DCT would lose ~10 dB: the encoder side decides quantization bins, and
    islow's own rounding moves coefficients by up to ~1/8 of a unit.
  - ``"paper"``: the float operator of the paper: no sample rounding anywhere, float DCT, soft rounding
    ``round(z) + (z - round z)^3`` (eq. soft_round) in the forward, triangular up-sampling, clipping. Its
    forward value under-states the JPEG error (the cubic term keeps up to 1/8 of a step).
In every mode the input is clamped to [0, 1] first (the encoder can only see 8-bit samples; pixels outside
get no gradient from this operator) and the IDCT output is clamped to [0, 255] as every decoder does (the
two inner clamps pass gradient strictly inside their range, a float landing exactly on 0 or 255 gets none).

Kernel count matters more than arithmetic here (on a GPU at training sizes each small kernel costs more to
launch than to run): all blocks of the three planes go through one coding pass, and the colour maps and
DCTs are single matrix products (``tests/test_jsgs/apps/test_opcount.py``,
``tools/diagnostics/bench_kernel_count.py``).

No data-dependent Python control flow and no host synchronisation: shapes, the sampling and the mode are
static, so ``torch.compile`` can trace the whole operator.
"""

from __future__ import annotations

from functools import partial
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .color import kernel_coefficients, rgb_to_ycbcr, rgb_to_ycbcr_libjpeg, ycbcr_to_rgb, ycbcr_to_rgb_libjpeg
from .dct import block_dct, block_idct, blockify, fdct_islow, idct_islow, range_limit, unblockify
from .rounding import quantize_libjpeg, round_soft_grad, round_ste, soft_round
from .sampling import downsample, downsample_libjpeg, pad_replicate, upsample, upsample_libjpeg
from .tables import SAMPLING_FACTORS, checked_steps

Mode = Literal["paper", "float", "exact"]
Sampling = Literal["4:4:4", "4:2:2", "4:2:0", "4:4:0", "4:1:1"]

MODES: tuple[str, ...] = ("paper", "float", "exact")
#: how the coding pass runs: "torch" (the code below) or "triton" (modes "paper" and "float": the fused
#: kernels of :mod:`jsgs.kernels._triton_jo` where they can run, equal up to float rounding; else the torch
#: code)
KERNELS: tuple[str, ...] = ("torch", "triton")


def _ceil_div(a: int, b: int) -> int:
    return -(-a // b)


def _through(exact: Tensor, smooth: Tensor) -> Tensor:
    """Value of ``exact`` (detached, cast to ``smooth``'s dtype), gradient of ``smooth``.

    Written as ``exact + (smooth - smooth.detach())`` so that the value is bit-for-bit ``exact``.
    """
    return exact.detach().to(smooth.dtype) + (smooth - smooth.detach())


def as_tables(
    table: Tensor | np.ndarray | list,
    batch: int,
    dtype: torch.dtype,
    device: torch.device,
    name: str = "quantization table",
) -> Tensor:
    """Quantization table(s) -> ``(batch, 8, 8)`` tensor in natural order ``[v, u]``.

    Accepts ``(8, 8)`` (shared by every view), ``(batch, 8, 8)``, or 64 values in natural order. Tables given
    as arrays or lists (host values) must hold quantization steps, integers 1..65535: anything else (0, a
    negative, fractional or non-finite entry) is a ValueError naming ``name``, the entry and its place. A
    tensor is taken as given (checking it would read it back to the host; the manifest reader checks the
    tables it makes).
    """
    if not isinstance(table, Tensor):
        table = checked_steps(table, name)
    t = torch.as_tensor(table).to(dtype=dtype, device=device)
    if t.shape[-2:] != (8, 8):
        if t.dim() == 0 or t.shape[-1] != 64:
            raise ValueError(f"{name}: must be (8, 8), ({batch}, 8, 8) or 64 values, got {tuple(t.shape)}")
        t = t.reshape(*t.shape[:-1], 8, 8)
    if t.dim() == 2:
        t = t.expand(batch, 8, 8)
    if t.shape != (batch, 8, 8):
        raise ValueError(f"{name}: must be (8, 8) or ({batch}, 8, 8), got {tuple(t.shape)}")
    return t


def _clamp_255(x: Tensor) -> Tensor:
    """``x.clamp(0, 255)`` in value; the gradient passes strictly inside (0, 255) (hardtanh's backward: one
    kernel instead of clamp's four; float values land exactly on a bound with probability ~0)."""
    return F.hardtanh(x, 0.0, 255.0)


class _Clamp255(torch.autograd.Function):
    """:func:`_clamp_255` that keeps a 1-byte mask for its backward instead of its input (hardtanh keeps the
    input, 4 bytes a value in float32): same values and gradient, bit for bit, but at a NaN input, where
    its gradient is 0 and CUDA's hardtanh passes the upstream (a NaN render fails the step anyway)."""

    @staticmethod
    def forward(ctx: Any, x: Tensor) -> Tensor:  # type: ignore[override]
        # hardtanh's backward passes the gradient where 0 < x < 255 and writes 0 elsewhere (at NaN: 0 here
        # and in the CPU's vectorised loop; its CUDA kernel and the CPU's scalar loop pass it)
        ctx.save_for_backward((x > 0.0) & (x < 255.0))
        return F.hardtanh(x, 0.0, 255.0)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> Tensor:  # type: ignore[override]
        (inside,) = ctx.saved_tensors
        return torch.where(inside, grad, 0.0)


def _code_blocks(blocks: Tensor, q: Tensor, mode: str) -> Tensor:
    """Level shift, 8x8 DCT, quantize + dequantize, IDCT, +128 and range limit, block by block.

    Args:
        blocks: ``(B, n, 8, 8)`` samples 0..255 (the luma and chroma blocks of each view, together: one pass
            of kernels for all planes instead of one per plane).
        q: ``(B, n, 8, 8)`` the quantization step of every coefficient (each block's own table).
    Returns:
        ``(B, n, 8, 8)`` decoded samples 0..255 (integers except in mode "paper").
    """
    blocks = blocks - 128.0
    if mode == "paper":
        deq = q * soft_round(block_dct(blocks) / q)
        return _clamp_255(block_idct(deq) + 128.0)
    # Modes "exact" and "float": libjpeg's values, float gradients. islow leaves coefficients at 8x the
    # orthonormal scale and its quantizer divides by 8Q.
    exact = mode == "exact"
    work = torch.float64 if exact else blocks.dtype
    t_value = fdct_islow(blocks, work)
    q_work = q.to(work)  # one copy for both uses (exact: float64)
    deq_value = quantize_libjpeg(t_value, q_work) * q_work
    t = _through(t_value, 8.0 * block_dct(blocks))
    deq = _through(deq_value, q * round_soft_grad(t / (8.0 * q)))
    out = _clamp_255(block_idct(deq) + 128.0)
    if exact:
        out = _through(range_limit(idct_islow(deq_value)), out)
    else:
        out = round_ste(out)
    return out


def _code_planes(
    luma: Tensor, chroma: Tensor, tab_y: Tensor, tab_c: Tensor, mode: str
) -> tuple[Tensor, Tensor]:
    """The coding pass of the padded planes, luma ``(B, 1, ., .)`` and chroma ``(B, 2, ., .)`` (multiples of
    8), with the views' tables ``(B, 8, 8)``: every block of the three planes through one
    :func:`_code_blocks`, each with its plane's table. Returns the decoded planes, same shapes."""
    b = luma.shape[0]
    luma_b, chroma_b = blockify(luma), blockify(chroma)  # (B, 1, ., ., 8, 8), (B, 2, ., ., 8, 8)
    n_y = luma_b.shape[1] * luma_b.shape[2] * luma_b.shape[3]
    n_c = chroma_b.shape[1] * chroma_b.shape[2] * chroma_b.shape[3]
    blocks = torch.cat([luma_b.reshape(b, n_y, 8, 8), chroma_b.reshape(b, n_c, 8, 8)], dim=1)
    q = torch.cat([tab_y[:, None].expand(b, n_y, 8, 8), tab_c[:, None].expand(b, n_c, 8, 8)], dim=1)
    decoded = _code_blocks(blocks, q, mode)
    # one split: its backward is one cat (two slices' are two zero-filled copies and their sum)
    luma_d, chroma_d = decoded.split([n_y, n_c], dim=1)
    return unblockify(luma_d.reshape(luma_b.shape)), unblockify(chroma_d.reshape(chroma_b.shape))


def _shares_storage(a: Tensor, b: Tensor) -> bool:
    return a.untyped_storage().data_ptr() == b.untyped_storage().data_ptr()


def _code_fused(
    luma: Tensor, chroma: Tensor, ycc: Tensor, tab_y: Tensor, tab_c: Tensor, mode: str
) -> tuple[Tensor, Tensor]:
    """:func:`_code_planes` through the fused kernels (modes "paper" and "float"). Each kernel keeps its
    planes for the backward: a luma plane that is a view of the YCbCr image ``ycc`` would keep all of it
    (3x its size) where the chroma planes do not, so it is coded from a copy of its own."""
    from jsgs.kernels._triton_jo import float_code, paper_code

    code = paper_code if mode == "paper" else float_code
    if luma.requires_grad and _shares_storage(luma, ycc) and not _shares_storage(chroma, ycc):
        luma = luma.clone()
    return code(luma, tab_y), code(chroma, tab_c)


def _check_arguments(rgb: Tensor, sampling: str, mode: str, kernel: str, color_kernel: str) -> None:
    """:func:`jpeg_observe`'s argument checks (ValueError naming the argument)."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if sampling not in SAMPLING_FACTORS:
        raise ValueError(f"sampling must be one of {tuple(SAMPLING_FACTORS)}, got {sampling!r}")
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
    if color_kernel not in KERNELS:
        raise ValueError(f"color_kernel must be one of {KERNELS}, got {color_kernel!r}")
    if rgb.dim() != 4 or rgb.shape[1] != 3:
        raise ValueError(f"rgb must be (B, 3, H, W), got {tuple(rgb.shape)}")


def jpeg_observe(
    rgb: Tensor,
    luma_table: Tensor | np.ndarray,
    chroma_table: Tensor | np.ndarray,
    sampling: str = "4:2:0",
    mode: str = "paper",
    kernel: str = "torch",
    color_kernel: str = "torch",
) -> Tensor:
    """The JPEG observation of a rendered image, ``C_JPEG(rgb; T^Y, T^C)`` (paper eq. jpeg_operator).

    Args:
        rgb: ``(B, 3, H, W)`` float RGB in [0, 1] (values outside, ±inf included, are clamped; a NaN makes its
            MCU and one pixel of chroma context beyond NaN in the output and the gradient). Any H, W >= 1.
        luma_table: quantization steps for Y, ``(8, 8)`` or ``(B, 8, 8)``, natural order ``[v, u]`` (as
            Pillow's ``Image.quantization[0]`` reshaped to 8x8, or the manifest's ``luma_table``). Integers
            1..65535, checked when given as an array or a list (:func:`as_tables`).
        chroma_table: the same for Cb and Cr.
        sampling: the file's, ``"4:4:4"``, ``"4:2:2"``, ``"4:2:0"``, ``"4:4:0"`` or ``"4:1:1"``; one per call.
        mode: ``"exact"``, ``"float"`` or ``"paper"`` (module docstring).
        kernel: ``"torch"`` or ``"triton"``: in modes "paper" and "float" the coding pass as two fused
            Triton kernels (forward, backward; :func:`jsgs.kernels._triton_jo.paper_code`,
            :func:`jsgs.kernels._triton_jo.float_code`) where they can run (Triton and float32 CUDA tensors,
            or ``TRITON_INTERPRET=1`` on CPU: ``fused_jo_runs``), else the torch code; mode "exact" ignores
            it.
        color_kernel: ``"torch"`` or ``"triton"``: where the fused coding pass runs (``kernel`` "triton"),
            the two colour conversions as one elementwise Triton kernel each way
            (:func:`jsgs.kernels._triton_jo.color_convert`) instead of :mod:`jsgs.jpeg.color`'s matrix
            product; ignored elsewhere.
    Returns:
        ``(B, 3, H, W)`` decoded RGB in [0, 1], same dtype as ``rgb``. In modes "exact" and "float" the
        values are exactly ``k / 255`` for integers k; in "exact" k equals libjpeg-turbo's decode of
        libjpeg-turbo's encode.
    """
    _check_arguments(rgb, sampling, mode, kernel, color_kernel)
    if not rgb.is_floating_point():
        rgb = rgb.float()
    fused = kernel == "triton" and mode != "exact"
    if fused:
        from jsgs.kernels._triton_jo import fused_jo_runs

        fused = fused_jo_runs(rgb)
    to_ycc, to_rgb = rgb_to_ycbcr, ycbcr_to_rgb
    if fused and color_kernel == "triton":
        from jsgs.kernels._triton_jo import color_convert

        fwd, bwd = kernel_coefficients("rgb2ycc", rgb.dtype, rgb.device)
        to_ycc = partial(color_convert, forward=fwd, backward=bwd)
        fwd, bwd = kernel_coefficients("ycc2rgb", rgb.dtype, rgb.device)
        to_rgb = partial(color_convert, forward=fwd, backward=bwd)
    b, _, height, width = rgb.shape
    h, v = SAMPLING_FACTORS[sampling]
    tab_y = as_tables(luma_table, b, rgb.dtype, rgb.device, "luma_table")
    tab_c = as_tables(chroma_table, b, rgb.dtype, rgb.device, "chroma_table")
    integer = mode != "paper"

    x = 255.0 * rgb.clamp(0.0, 1.0)
    if integer:
        x = round_ste(x)  # the encoder sees 8-bit samples
    ycc = to_ycc(x)
    if integer:
        ycc = _through(rgb_to_ycbcr_libjpeg(x), ycc)
    del x  # image-sized locals go when done with (a CUDA graph's pool holds the forward's working set)

    # Encoder edges and chroma down-sampling (jcprepct.c / jcsample.c).
    luma = pad_replicate(ycc[:, :1], 8 * _ceil_div(height, 8), 8 * _ceil_div(width, 8))
    chroma = ycc[:, 1:]
    ch, cw = _ceil_div(height, v), _ceil_div(width, h)  # real chroma samples
    if h == 1 and v == 1:
        chroma = pad_replicate(chroma, luma.shape[-2], luma.shape[-1])
    else:
        chroma = pad_replicate(chroma, v * ch, 8 * h * _ceil_div(width, 8 * h))
        small = downsample(chroma, h, v)
        chroma = _through(downsample_libjpeg(chroma, h, v), small) if integer else small
        chroma = pad_replicate(chroma, 8 * _ceil_div(ch, 8), chroma.shape[-1])

    # Every block of the three planes through the coding pass, each with its plane's table.
    if fused:
        luma, chroma = _code_fused(luma, chroma, ycc, tab_y, tab_c, mode)
    else:
        luma, chroma = _code_planes(luma, chroma, tab_y, tab_c, mode)
    del ycc
    luma, chroma = luma[..., :height, :width], chroma[..., :ch, :cw]

    # Decoder up-sampling (jdsample.c) from the real chroma samples only.
    if not (h == 1 and v == 1):
        big = upsample(chroma, h, v)
        chroma = _through(upsample_libjpeg(chroma, h, v), big) if integer else big
        del big
    chroma = chroma[..., :height, :width]

    ycc = torch.cat([luma, chroma], dim=1)
    del luma, chroma
    rgb_out = to_rgb(ycc)  # its clamp keeps a mask, not it, for the backward (nothing else keeps it)
    out = _Clamp255.apply(rgb_out) if rgb_out.requires_grad else _clamp_255(rgb_out)
    del rgb_out
    if integer:
        out = _through(ycbcr_to_rgb_libjpeg(ycc), out)
    del ycc
    return out / 255.0
