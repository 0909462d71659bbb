"""8x8 block DCTs: the orthonormal float transform and libjpeg-turbo's integer "islow" transforms.

Conventions: a plane is ``(..., H, W)`` with H and W multiples of 8; blocks are ``(..., H/8, W/8, 8, 8)``
indexed ``[..., by, bx, y, x]`` in the sample domain and ``[..., by, bx, v, u]`` in the frequency domain (v
vertical, u horizontal frequency), so that a quantization table in natural order (``[v][u]``) multiplies a
coefficient block elementwise. With ``D`` the orthonormal DCT-II matrix, ``coef = D @ block @ D.T``.

The islow transforms (``jfdctint.c`` / ``jidctint.c``, Loeffler-Ligtenberg-Moschytz with CONST_BITS = 13,
PASS1_BITS = 2) are written here as what they are arithmetically: each pass is an *integer* 8x8 matrix
applied to the rows (or columns) followed by a rounding right shift ``DESCALE(x, n) = floor((x + 2^(n-1)) /
2^n)``; the butterflies only factor that matrix. The matrices are derived below from a literal transcription
of the C butterflies, and the products are taken in float64, where every intermediate (< 2^40) is an exact
integer, so the result is bit-exact on any device (no integer matmul is needed, which CUDA lacks).
"""

from __future__ import annotations

from functools import cache

import numpy as np
import torch
from torch import Tensor

from .tables import dct_basis

CONST_BITS = 13
PASS1_BITS = 2

# jfdctint.c / jidctint.c fixed-point constants, FIX(x) = round(x * 2^13).
FIX_0_298631336 = 2446
FIX_0_390180644 = 3196
FIX_0_541196100 = 4433
FIX_0_765366865 = 6270
FIX_0_899976223 = 7373
FIX_1_175875602 = 9633
FIX_1_501321110 = 12299
FIX_1_847759065 = 15137
FIX_1_961570560 = 16069
FIX_2_053119869 = 16819
FIX_2_562915447 = 20995
FIX_3_072711026 = 25172


# ------------------------------------------------------------------------------------------------------------
# Orthonormal float DCT
# ------------------------------------------------------------------------------------------------------------


@cache
def _dct_matrix_cached(dtype: torch.dtype, device: torch.device) -> Tensor:
    # Cached per device: building it from numpy every call would be a blocking host-to-device copy.
    return torch.tensor(dct_basis(), dtype=dtype, device=device)


def dct_matrix(dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
    """The orthonormal 8x8 DCT-II matrix ``D`` (``D[k, n] = c_k cos((2n + 1) k pi / 16)``), ``D @ D.T =
    I``: :func:`jsgs.jpeg.tables.dct_basis` as a tensor."""
    return _dct_matrix_cached(dtype, torch.device(device if device is not None else "cpu"))


def blockify(plane: Tensor) -> Tensor:
    """``(..., H, W)`` -> ``(..., H/8, W/8, 8, 8)`` non-overlapping 8x8 blocks (H, W multiples of 8)."""
    *lead, h, w = plane.shape
    x = plane.reshape(*lead, h // 8, 8, w // 8, 8)
    return x.transpose(-3, -2)


def unblockify(blocks: Tensor) -> Tensor:
    """Inverse of :func:`blockify`: ``(..., nby, nbx, 8, 8)`` -> ``(..., 8 nby, 8 nbx)``."""
    *lead, nby, nbx, _, _ = blocks.shape
    return blocks.transpose(-3, -2).reshape(*lead, nby * 8, nbx * 8)


@cache
def _kron_cached(dtype: torch.dtype, device: torch.device) -> Tensor:
    d = _dct_matrix_cached(dtype, device)
    return torch.kron(d, d)


def block_dct(blocks: Tensor) -> Tensor:
    """Orthonormal 2-D DCT of 8x8 blocks: ``(..., 8, 8)`` samples -> ``(..., 8, 8)`` coefficients ``[v, u]``.

    Same units in and out (orthonormal: a constant block of value c has DC coefficient 8c). Computed as
    ``D @ block @ D.T`` in one matrix product over the row-major 64-vectors of all blocks, with
    ``kron(D, D)``: one kernel for every block of the image (the per-block pair of 8x8 products is
    launch-bound on a GPU).
    """
    shape = blocks.shape
    k = _kron_cached(blocks.dtype, blocks.device)
    return (blocks.reshape(*shape[:-2], 64) @ k.T).reshape(shape)


def block_idct(coefs: Tensor) -> Tensor:
    """Inverse of :func:`block_dct` (``D.T @ coef @ D``), one matrix product like it."""
    shape = coefs.shape
    k = _kron_cached(coefs.dtype, coefs.device)
    return (coefs.reshape(*shape[:-2], 64) @ k).reshape(shape)


# ------------------------------------------------------------------------------------------------------------
# libjpeg-turbo islow, as integer matrices
# ------------------------------------------------------------------------------------------------------------


def _fdct_butterfly(d: list[int]) -> list[int]:
    """One 1-D pass of ``jpeg_fdct_islow`` before its final shifts: outputs 0 and 4 are ``tmp10 +/- tmp11``,
    the others the pre-DESCALE sums (literal transcription of jfdctint.c, valid for both passes)."""
    tmp0, tmp7 = d[0] + d[7], d[0] - d[7]
    tmp1, tmp6 = d[1] + d[6], d[1] - d[6]
    tmp2, tmp5 = d[2] + d[5], d[2] - d[5]
    tmp3, tmp4 = d[3] + d[4], d[3] - d[4]
    tmp10, tmp13 = tmp0 + tmp3, tmp0 - tmp3
    tmp11, tmp12 = tmp1 + tmp2, tmp1 - tmp2
    out = [0] * 8
    out[0] = tmp10 + tmp11
    out[4] = tmp10 - tmp11
    z1 = (tmp12 + tmp13) * FIX_0_541196100
    out[2] = z1 + tmp13 * FIX_0_765366865
    out[6] = z1 + tmp12 * -FIX_1_847759065
    z1 = tmp4 + tmp7
    z2 = tmp5 + tmp6
    z3 = tmp4 + tmp6
    z4 = tmp5 + tmp7
    z5 = (z3 + z4) * FIX_1_175875602
    tmp4 *= FIX_0_298631336
    tmp5 *= FIX_2_053119869
    tmp6 *= FIX_3_072711026
    tmp7 *= FIX_1_501321110
    z1 *= -FIX_0_899976223
    z2 *= -FIX_2_562915447
    z3 *= -FIX_1_961570560
    z4 *= -FIX_0_390180644
    z3 += z5
    z4 += z5
    out[7] = tmp4 + z1 + z3
    out[5] = tmp5 + z2 + z4
    out[3] = tmp6 + z2 + z3
    out[1] = tmp7 + z1 + z4
    return out


def _idct_butterfly(c: list[int]) -> list[int]:
    """One 1-D pass of ``jpeg_idct_islow`` before DESCALE (literal transcription of jidctint.c; the even
    part's ``LEFT_SHIFT(., CONST_BITS)`` is included). Input: 8 dequantized coefficients, output: 8
    samples."""
    z2, z3 = c[2], c[6]
    z1 = (z2 + z3) * FIX_0_541196100
    tmp2 = z1 + z3 * -FIX_1_847759065
    tmp3 = z1 + z2 * FIX_0_765366865
    z2, z3 = c[0], c[4]
    tmp0 = (z2 + z3) << CONST_BITS
    tmp1 = (z2 - z3) << CONST_BITS
    tmp10, tmp13 = tmp0 + tmp3, tmp0 - tmp3
    tmp11, tmp12 = tmp1 + tmp2, tmp1 - tmp2
    tmp0, tmp1, tmp2, tmp3 = c[7], c[5], c[3], c[1]
    z1 = tmp0 + tmp3
    z2 = tmp1 + tmp2
    z3 = tmp0 + tmp2
    z4 = tmp1 + tmp3
    z5 = (z3 + z4) * FIX_1_175875602
    tmp0 *= FIX_0_298631336
    tmp1 *= FIX_2_053119869
    tmp2 *= FIX_3_072711026
    tmp3 *= FIX_1_501321110
    z1 *= -FIX_0_899976223
    z2 *= -FIX_2_562915447
    z3 *= -FIX_1_961570560
    z4 *= -FIX_0_390180644
    z3 += z5
    z4 += z5
    tmp0 += z1 + z3
    tmp1 += z2 + z4
    tmp2 += z2 + z3
    tmp3 += z1 + z4
    return [
        tmp10 + tmp3,
        tmp11 + tmp2,
        tmp12 + tmp1,
        tmp13 + tmp0,
        tmp13 - tmp0,
        tmp12 - tmp1,
        tmp11 - tmp2,
        tmp10 - tmp3,
    ]


def _matrix_of(butterfly) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The integer matrix M with ``butterfly(x) = M @ x`` (the butterflies are linear with integer
    weights)."""
    cols = [butterfly([int(i == j) for i in range(8)]) for j in range(8)]
    return np.array(cols, dtype=np.int64).T


#: Pre-shift integer matrices (out x in) of one islow pass.
FDCT_MATRIX = _matrix_of(_fdct_butterfly)
IDCT_MATRIX = _matrix_of(_idct_butterfly)

_EVEN04 = np.array([1, 0, 0, 0, 1, 0, 0, 0], dtype=bool)
# Pass 1 of the forward DCT: outputs 0/4 are LEFT_SHIFT(., PASS1_BITS), the rest DESCALE(., 11).
_F1_MUL = np.where(_EVEN04, 1 << PASS1_BITS, 1)
_F1_SHIFT = np.where(_EVEN04, 0, CONST_BITS - PASS1_BITS)
# Pass 2: outputs 0/4 DESCALE(., PASS1_BITS), the rest DESCALE(., 15).
_F2_SHIFT = np.where(_EVEN04, PASS1_BITS, CONST_BITS + PASS1_BITS)
_I1_SHIFT = CONST_BITS - PASS1_BITS
_I2_SHIFT = CONST_BITS + PASS1_BITS + 3


@cache
def _islow_np() -> dict[str, np.ndarray]:
    f1 = FDCT_MATRIX * _F1_MUL[:, None]
    return {
        "f1": f1.astype(np.float64),
        "f1_off": np.where(_F1_SHIFT > 0, 2.0 ** (_F1_SHIFT - 1), 0.0),
        "f1_div": 2.0**_F1_SHIFT,
        "f2": FDCT_MATRIX.astype(np.float64),
        "f2_off": 2.0 ** (_F2_SHIFT - 1),
        "f2_div": 2.0**_F2_SHIFT,
        "i": IDCT_MATRIX.astype(np.float64),
    }


@cache
def _const(name: str, device: torch.device, dtype: torch.dtype = torch.float64) -> Tensor:
    return torch.as_tensor(_islow_np()[name], dtype=dtype, device=device)


def fdct_islow(blocks: Tensor, dtype: torch.dtype = torch.float64) -> Tensor:
    """libjpeg-turbo's ``jpeg_fdct_islow``: integer matrix products and its two rounding shifts.

    Args:
        blocks: ``(..., 8, 8)`` level-shifted integer samples (sample - 128, in [-128, 127]), any float dtype.
        dtype: arithmetic dtype. float64 (default) is bit-exact for every input. float32 is exact while the
            partial sums stay below 2^24 and otherwise may be off by one unit (1/8 of an orthonormal unit) in
            a rare coefficient: the cheap emulation used by mode "float".
    Returns:
        ``(..., 8, 8)`` integer-valued coefficients ``[v, u]`` in ``dtype``, scaled by 8 relative to the
        orthonormal DCT (as libjpeg leaves them before quantization). No gradient (integer arithmetic).
    """
    x = blocks.detach().to(dtype)
    dev = x.device
    # Pass 1 on rows: y[.., r, k] = descale(sum_n F1[k, n] x[.., r, n]).
    y = x @ _const("f1", dev, dtype).T
    y = torch.floor((y + _const("f1_off", dev, dtype)) / _const("f1_div", dev, dtype))
    # Pass 2 on columns: z[.., k, c] = descale(sum_r F2[k, r] y[.., r, c]).
    z = (y.transpose(-1, -2) @ _const("f2", dev, dtype).T).transpose(-1, -2)
    return torch.floor((z + _const("f2_off", dev, dtype)[:, None]) / _const("f2_div", dev, dtype)[:, None])


def idct_islow(coefs: Tensor) -> Tensor:
    """libjpeg-turbo's ``jpeg_idct_islow`` without the final range limit, bit-exact.

    Args:
        coefs: ``(..., 8, 8)`` integer dequantized coefficients ``[v, u]`` (quantized value x table
            entry), i.e. in orthonormal-DCT units.
    Returns:
        ``(..., 8, 8)`` float64 integer samples *before* the +128 level shift and range limiting (see
        :func:`range_limit`). No gradient.
    """
    c = coefs.detach().to(torch.float64)
    m = _const("i", c.device)
    # Pass 1 on columns, DESCALE by CONST_BITS - PASS1_BITS.
    w = (c.transpose(-1, -2) @ m.T).transpose(-1, -2)
    w = torch.floor((w + 2.0 ** (_I1_SHIFT - 1)) / 2.0**_I1_SHIFT)
    # Pass 2 on rows, DESCALE by CONST_BITS + PASS1_BITS + 3.
    s = w @ m.T
    return torch.floor((s + 2.0 ** (_I2_SHIFT - 1)) / 2.0**_I2_SHIFT)


def range_limit(x: Tensor) -> Tensor:
    """libjpeg's post-IDCT range limit: ``range_limit[x & 1023]`` with the table of
    ``prepare_range_limit_table``.

    ``x`` is the integer IDCT output before the +128 shift. For x in [-128, 127] the result is x + 128; it
    saturates to 255 for x in [128, 511] and to 0 for x in [-512, -129], and wraps with period 1024 beyond
    (libjpeg's behaviour for corrupt data; only reachable with extreme, e.g. 16-bit, tables). Returns samples
    0..255 in ``x``'s dtype.
    """
    i = torch.remainder(x, 1024.0)
    return torch.where(
        i < 128,
        i + 128,
        torch.where(i < 512, torch.full_like(i, 255.0), torch.where(i < 896, torch.zeros_like(i), i - 896)),
    )
