"""RGB <-> YCbCr (JFIF full range) as libjpeg-turbo computes it, in integer and float form.

All images are ``(..., 3, H, W)`` tensors in 8-bit sample units (0..255), channel order R, G, B or Y, Cb, Cr.
The integer functions reproduce ``jccolor.c`` / ``jdcolor.c`` bit for bit (16-bit fixed point, SCALEBITS =
16); they take and return float tensors holding integers and carry no gradient. The float functions are the
same linear maps with the same fixed-point constants and no rounding: the smooth relaxation whose gradient the
observation operator uses.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import torch
from torch import Tensor

SCALEBITS = 16
_ONE = float(1 << SCALEBITS)
_HALF = float(1 << (SCALEBITS - 1))
_CENTER = 128.0

# jccolor.c: FIX(0.29900), FIX(0.58700), FIX(0.11400), FIX(0.16874), FIX(0.33126), FIX(0.5), FIX(0.41869),
# FIX(0.08131).
_Y = (19595.0, 38470.0, 7471.0)
_CB = (-11059.0, -21709.0, 32768.0)
_CR = (32768.0, -27439.0, -5329.0)
# jdcolor.c: FIX(1.40200), FIX(0.71414), FIX(0.34414), FIX(1.77200).
_CR_R = 91881.0
_CR_G = -46802.0
_CB_G = -22554.0
_CB_B = 116130.0


def _dot(x: Tensor, w: tuple[float, float, float]) -> Tensor:
    r, g, b = x.unbind(-3)
    return w[0] * r + w[1] * g + w[2] * b


@cache
def _affine(name: str, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """(matrix^T [3, 3], offset [3]) of the float colour maps, per device (built once: no host-to-device copy
    inside a training step)."""
    fwd = np.array([_Y, _CB, _CR]) / _ONE
    if name == "rgb2ycc":
        m, off = fwd, np.array([0.0, _CENTER, _CENTER])
    else:
        m = np.array([[1.0, 0.0, _CR_R / _ONE], [1.0, _CB_G / _ONE, _CR_G / _ONE], [1.0, _CB_B / _ONE, 0.0]])
        off = -m @ np.array([0.0, _CENTER, _CENTER])
    return (
        torch.as_tensor(m.T.copy(), dtype=dtype, device=device),
        torch.as_tensor(off, dtype=dtype, device=device),
    )


@cache
def kernel_coefficients(name: str, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """The colour map ``name`` (``"rgb2ycc"`` or ``"ycc2rgb"``) as the fused colour kernel's two sets of 12
    values (:func:`jsgs.kernels._triton_jo.color_convert`): forward (``M`` row-major, then the offset) and
    backward (``M^T`` row-major, then zeros), from the same matrices as the torch code, cached per device
    (no host-to-device copy inside a graph)."""
    mt, off = _affine(name, dtype, device)  # M^T, off
    forward = torch.cat([mt.t().reshape(9), off]).contiguous()
    backward = torch.cat([mt.reshape(9), torch.zeros_like(off)]).contiguous()
    return forward, backward


def _apply_affine(x: Tensor, name: str) -> Tensor:
    # one matrix product with the offset fused (addmm) over all pixels: the channel-by-channel form is ~20
    # small kernels forward and as many backward, launch-bound on a GPU
    mt, off = _affine(name, x.dtype, x.device)
    pix = x.movedim(-3, -1)
    out = torch.addmm(off, pix.reshape(-1, 3), mt).reshape(pix.shape)
    return out.movedim(-1, -3)


def rgb_to_ycbcr(rgb: Tensor) -> Tensor:
    """Float RGB -> YCbCr, ``(..., 3, H, W)`` in 0..255 -> ``(..., 3, H, W)`` (Cb, Cr centred at 128).

    ``Y = 0.29900 R + 0.58700 G + 0.11400 B`` etc. with libjpeg's 16-bit constants, without rounding.
    """
    return _apply_affine(rgb, "rgb2ycc")


def rgb_to_ycbcr_libjpeg(rgb: Tensor) -> Tensor:
    """``jccolor.c`` ``rgb_ycc_convert``: integer RGB (0..255) -> integer YCbCr (0..255), bit-exact.

    ``Y = (19595 R + 38470 G + 7471 B + 32768) >> 16``; ``Cb = (-11059 R - 21709 G + 32768 B + (128 << 16) +
    32767) >> 16``; ``Cr = (32768 R - 27439 G - 5329 B + (128 << 16) + 32767) >> 16``. Input values must be
    integers; exact in float32 (every sum < 2^24) and float64. No gradient.
    """
    x = rgb.detach()
    y = torch.floor((_dot(x, _Y) + _HALF) / _ONE)
    cb = torch.floor((_dot(x, _CB) + (_CENTER * _ONE + _HALF - 1)) / _ONE)
    cr = torch.floor((_dot(x, _CR) + (_CENTER * _ONE + _HALF - 1)) / _ONE)
    return torch.stack([y, cb, cr], dim=-3)


def ycbcr_to_rgb(ycc: Tensor) -> Tensor:
    """Float YCbCr -> RGB (inverse of :func:`rgb_to_ycbcr` up to the fixed-point constants), not clamped.

    ``R = Y + 1.40200 (Cr - 128)``, ``G = Y - 0.34414 (Cb - 128) - 0.71414 (Cr - 128)``, ``B = Y + 1.77200
    (Cb - 128)`` with libjpeg's 16-bit constants."""
    return _apply_affine(ycc, "ycc2rgb")


def ycbcr_to_rgb_libjpeg(ycc: Tensor) -> Tensor:
    """``jdcolor.c`` ``ycc_rgb_convert``: integer YCbCr -> integer RGB clamped to 0..255, bit-exact.

    ``R = Y + ((91881 Cr' + 32768) >> 16)``, ``G = Y + ((-22554 Cb' - 46802 Cr' + 32768) >> 16)``,
    ``B = Y + ((116130 Cb' + 32768) >> 16)`` with ``C' = C - 128``. No gradient.
    """
    y, cb, cr = ycc.detach().unbind(-3)
    cb = cb - _CENTER
    cr = cr - _CENTER
    r = y + torch.floor((_CR_R * cr + _HALF) / _ONE)
    g = y + torch.floor((_CB_G * cb + _CR_G * cr + _HALF) / _ONE)
    b = y + torch.floor((_CB_B * cb + _HALF) / _ONE)
    return torch.stack([r, g, b], dim=-3).clamp(0.0, 255.0)
