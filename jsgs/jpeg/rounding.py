"""Rounding for the JPEG quantizer and the 8-bit sample stages, with the gradients the training uses.

JPEG rounds half away from zero (libjpeg's quantizer computes ``sign(t) floor((|t| + 4Q) / (8Q))``), so every
``round`` here does too, including the one inside the paper's soft rounding (eq. soft_round).

Gradients (d/dz):
- :func:`soft_round` (eq. soft_round): value ``round(z) + (z - round z)^3``; the backward treats ``round`` as
  zero-gradient, so the derivative is ``3 (z - round z)^2``. It *vanishes at integers* (a coefficient sitting
  on a quantization level gets no gradient), reaches 3/4 at the bin edges and averages 1/4 over a bin. This is
  what the paper writes and what is implemented; it is not the identity straight-through estimator.
- :func:`round_soft_grad`: value ``round(z)`` exactly (hard rounding), gradient ``3 (z - round z)^2`` (the
  soft-round derivative, straight-through) - the quantizer of modes "float" and "exact".
- :func:`round_ste`: value ``floor(x + 1/2)``, gradient 1 - for 8-bit sample rounding (inputs, colour
  conversion, resampling), which libjpeg does but whose float version is the identity.
"""

from __future__ import annotations

import torch
from torch import Tensor


def round_half_away(z: Tensor) -> Tensor:
    """Round to nearest, ties away from zero (JPEG's quantizer rounding). No gradient."""
    z = z.detach()
    # trunc(z ± 1/2) = sign(z) floor(|z| + 1/2), the same float sum, in 3 kernels instead of 5
    return torch.trunc(z + torch.copysign(torch.full_like(z, 0.5), z))


def soft_round(z: Tensor) -> Tensor:
    """The paper's soft rounding (eq. soft_round): ``round(z) + (z - round z)^3``.

    d/dz = ``3 (z - round z)^2`` (round is treated as zero-gradient).

    ``z`` is a DCT coefficient divided by its quantization step (unitless). Note the forward value is *not*
    ``round(z)``: it keeps up to 1/8 of the distance to the unquantized value.
    """
    r = round_half_away(z)
    return r + (z - r) ** 3


def round_soft_grad(z: Tensor) -> Tensor:
    """Hard rounding half away from zero in value; the gradient of :func:`soft_round` (``3 (z - round
    z)^2``)."""
    r = round_half_away(z)
    c = (z - r) ** 3
    # (c - c.detach()) is exactly 0 in value, so the result is exactly r.
    return (c - c.detach()) + r


def round_ste(x: Tensor) -> Tensor:
    """``floor(x + 0.5)`` in value (8-bit sample rounding, halves up), identity gradient
    (straight-through)."""
    return (x - x.detach()) + torch.floor(x.detach() + 0.5)


def quantize_libjpeg(t: Tensor, table: Tensor) -> Tensor:
    """libjpeg's quantizer on islow coefficients: ``sign(t) floor((|t| + 4Q) / (8Q))``, exact.

    Args:
        t: integer coefficients from :func:`jsgs.jpeg.dct.fdct_islow` (8 x orthonormal scale), ``(..., 8,
        8)``. table: quantization steps Q broadcastable to ``t`` (natural order ``[v, u]``).
    Returns:
        Quantized integer levels in ``t``'s dtype. Exact in float64 and, for |t| < 2^20, in float32 too: the
        quotient's distance to the next integer is >= 1/(8Q), far above the division's rounding error.
        libjpeg-turbo computes this with a 16-bit reciprocal of 8Q, which wraps for
        16-bit tables with Q >= 8192; that case is not emulated. No gradient.
    """
    t = t.detach()
    q8 = 8.0 * table.detach().to(t.dtype)
    return torch.sign(t) * torch.floor((t.abs() + q8 / 2) / q8)
