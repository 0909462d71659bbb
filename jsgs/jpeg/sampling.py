"""Chroma sampling and edge handling as libjpeg-turbo does it (``jcsample.c``, ``jcprepct.c``, ``jdsample.c``,
``jdmainct.c``), in integer and float form.

Planes are ``(B, C, H, W)`` tensors in 8-bit sample units. ``h`` and ``v`` are the horizontal and vertical
sampling ratios between luma and chroma (2, 2 for 4:2:0; 2, 1 for 4:2:2; 1, 1 for 4:4:4; 1, 2 for 4:4:0;
4, 1 for 4:1:1). The integer
functions take float tensors holding integers, return the same and carry no gradient; the float ones are their
smooth relaxations (box-filter down-sampling, triangular up-sampling without rounding).
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor


class _ReplicatePad(torch.autograd.Function):
    """``F.pad(x, pad, mode="replicate")`` of a ``(B, C, H, W)`` tensor that keeps only ``x``'s shape for its
    backward: replication_pad2d's own node keeps ``x`` itself, whose backward reads nothing of it but its
    shape, so a view of a larger image (a plane of the colour map's output) kept the whole image alive. The
    backward is replication_pad2d's own kernel, given a stand-in of that shape: the same gradient."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, pad: tuple[int, int, int, int]) -> Tensor:  # type: ignore[override]
        ctx.pad, ctx.shape = pad, x.shape
        return F.pad(x, pad, mode="replicate")

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        shape_only = grad.new_empty(()).expand(ctx.shape)
        return torch.ops.aten.replication_pad2d_backward(grad, shape_only, list(ctx.pad)), None


def replicate_pad(x: Tensor, pad: tuple[int, int, int, int]) -> Tensor:
    """``F.pad(x, pad, mode="replicate")`` of a ``(B, C, H, W)`` tensor, keeping only ``x``'s shape for the
    backward where it needs one (:class:`_ReplicatePad`)."""
    if x.requires_grad and torch.is_grad_enabled() and not torch.compiler.is_compiling():
        return _ReplicatePad.apply(x, pad)
    return F.pad(x, pad, mode="replicate")


def pad_replicate(x: Tensor, height: int, width: int) -> Tensor:
    """Replicate the last row / column of ``(B, C, H, W)`` out to ``(B, C, height, width)`` (>= H, W).

    This is libjpeg's ``expand_right_edge`` / ``expand_bottom_edge``.
    """
    ph, pw = height - x.shape[-2], width - x.shape[-1]
    if ph == 0 and pw == 0:
        return x
    if torch.compiler.is_compiling():
        # torch.compile mis-traces replication_pad2d's backward on a strided (channels-last) input, such as
        # a plane of the colour transform's output: the fake kernel's strides disagree (torch 2.11-2.13).
        # Eager needs no copy; compiled, inductor fuses it.
        x = x.contiguous()
    return replicate_pad(x, (0, pw, 0, ph))


def _pairs(x: Tensor, h: int, v: int) -> Tensor:
    b, c, hh, ww = x.shape
    return x.reshape(b, c, hh // v, v, ww // h, h)


def downsample(x: Tensor, h: int, v: int) -> Tensor:
    """Float box down-sampling: ``(B, C, H, W)`` -> ``(B, C, H/v, W/h)`` (H, W multiples of v, h)."""
    if h == 1 and v == 1:
        return x
    return _pairs(x, h, v).mean(dim=(3, 5))


def downsample_libjpeg(x: Tensor, h: int, v: int) -> Tensor:
    """``h2v1_downsample`` / ``h2v2_downsample``, bit-exact: ``(sum + bias) >> log2(h v)``.

    The bias alternates along each output row, restarting on every row: 0, 1, 0, 1 ... for h2v1 and
    1, 2, 1, 2 ... for h2v2 (so that the rounding is unbiased on average). h1v2 (4:4:0) and h4v1 (4:1:1) go
    through libjpeg's generic ``int_downsample``: ``(sum + h v / 2) / (h v)``. Input ``(B, C, H, W)``
    integers, H and W multiples of v and h (pad with :func:`pad_replicate` first, as libjpeg does).
    """
    if h == 1 and v == 1:
        return x.detach()
    if (h, v) in ((1, 2), (4, 1)):  # int_downsample: (sum + n / 2) / n, no alternating bias
        n = h * v
        return torch.floor((_pairs(x.detach(), h, v).sum(dim=(3, 5)) + n // 2) / n)
    if (h, v) not in ((2, 1), (2, 2)):
        raise ValueError(f"unsupported sampling h={h}, v={v}")
    s = _pairs(x.detach(), h, v).sum(dim=(3, 5))
    odd = torch.arange(s.shape[-1], device=s.device) % 2
    bias = (1.0 + odd) if v == 2 else odd.to(s.dtype)
    return torch.floor((s + bias.to(s.dtype)) / float(h * v))


def _neighbours(x: Tensor, dim: int) -> tuple[Tensor, Tensor]:
    """(previous, next) along ``dim`` with the edge sample repeated (libjpeg's context at image edges)."""
    n = x.shape[dim]
    first = x.narrow(dim, 0, 1)
    last = x.narrow(dim, n - 1, 1)
    prev = torch.cat([first, x.narrow(dim, 0, n - 1)], dim=dim)
    nxt = torch.cat([x.narrow(dim, 1, n - 1), last], dim=dim)
    return prev, nxt


def _interleave(even: Tensor, odd: Tensor, dim: int) -> Tensor:
    """Output samples 2i = even[i], 2i + 1 = odd[i] along ``dim`` (negative dims only)."""
    return torch.stack([even, odd], dim=dim).flatten(dim - 1, dim)


def uses_fancy_upsampling(chroma_width: int) -> bool:
    """libjpeg-turbo's ``jinit_upsampler`` uses the triangular filter only when the down-sampled width is > 2;
    narrower planes are up-sampled by replication (for h2v1 and h2v2 alike)."""
    return chroma_width > 2


def _replicate_up(x: Tensor, h: int, v: int) -> Tensor:
    b, c, hh, ww = x.shape
    return x[:, :, :, None, :, None].expand(b, c, hh, v, ww, h).reshape(b, c, hh * v, ww * h)


def _triangle(x: Tensor, dim: int) -> Tensor:
    """x2 along ``dim`` (-1 or -2): outputs ``3/4 x + 1/4 neighbour`` towards each side, edges repeated."""
    pad = (1, 1, 0, 0) if dim == -1 else (0, 0, 1, 1)
    xp = replicate_pad(x, pad)
    n = x.shape[dim]
    near = 0.75 * x
    # add(a, b, alpha) is one kernel: fewer launches than 0.75 x + 0.25 y written out
    return _interleave(
        torch.add(near, xp.narrow(dim, 0, n), alpha=0.25),
        torch.add(near, xp.narrow(dim, 2, n), alpha=0.25),
        dim,
    )


def upsample(x: Tensor, h: int, v: int) -> Tensor:
    """Float "fancy" up-sampling: ``(B, C, Hc, Wc)`` -> ``(B, C, v Hc, h Wc)``.

    Triangular (3/4, 1/4) interpolation in each up-sampled direction with edge samples repeated, i.e. bilinear
    x2 with ``align_corners=False`` and border clamping; replication when ``Wc <= 2`` like libjpeg. ``x``
    must be the *real* chroma samples (``ceil(H / v)`` x ``ceil(W / h)``): libjpeg never reads the padding
    blocks.
    """
    if h == 1 and v == 1:
        return x
    if (h, v) == (1, 2):  # h1v2: triangular in the vertical alone, whatever the width
        return _triangle(x, -2)
    if (h, v) == (4, 1):  # libjpeg replicates (int_upsample)
        return _replicate_up(x, h, v)
    if not uses_fancy_upsampling(x.shape[-1]):
        return _replicate_up(x, h, v)
    if v == 2:
        x = _triangle(x, -2)
    return _triangle(x, -1)


def upsample_libjpeg(x: Tensor, h: int, v: int) -> Tensor:
    """``h2v1_fancy_upsample`` / ``h2v2_fancy_upsample`` (or plain replication when ``Wc <= 2``), bit-exact.

    h2v2: ``colsum = 3 nearer + further`` row, then ``(3 colsum + left + 8) >> 4`` for even and
    ``(3 colsum + right + 7) >> 4`` for odd output columns. h2v1: ``(3 x + left + 1) >> 2`` and
    ``(3 x + right + 2) >> 2``. Edge neighbours are the edge samples themselves, which reproduces libjpeg's
    first/ last column special cases and its bottom context rows (the last real row repeated). Input integers
    ``(B, C, Hc, Wc)``, output ``(B, C, v Hc, h Wc)``; crop to the image size afterwards. No gradient.
    """
    x = x.detach()
    if h == 1 and v == 1:
        return x
    if (h, v) == (1, 2):  # h1v2_fancy_upsample: rows (3 x + above + 1) >> 2 and (3 x + below + 2) >> 2
        up, down = _neighbours(x, -2)
        return _interleave(torch.floor((3 * x + up + 1) / 4), torch.floor((3 * x + down + 2) / 4), -2)
    if (h, v) == (4, 1):  # int_upsample: replication
        return _replicate_up(x, h, v)
    if not uses_fancy_upsampling(x.shape[-1]):
        return _replicate_up(x, h, v)
    if v == 2:
        up, down = _neighbours(x, -2)
        cs = _interleave(3 * x + up, 3 * x + down, -2)
        left, right = _neighbours(cs, -1)
        return _interleave(torch.floor((3 * cs + left + 8) / 16), torch.floor((3 * cs + right + 7) / 16), -1)
    left, right = _neighbours(x, -1)
    return _interleave(torch.floor((3 * x + left + 1) / 4), torch.floor((3 * x + right + 2) / 4), -1)
