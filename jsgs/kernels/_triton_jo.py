"""The coding pass of the JPEG observation operator (JO, :mod:`jsgs.jpeg.observe`, modes "paper" and
"float") as two Triton kernels each, one forward and one backward, reading the padded planes where they
lie; and DS's Delta (:mod:`jsgs.jpeg.supervision`) as one kernel each way (:func:`ds_delta`).

Mode "paper" (:func:`paper_code`), per 8x8 block of a plane, with ``K = kron(D, D)`` (``D`` the
orthonormal DCT-II matrix) acting on the row-major 64-vector of the block and ``Q`` the block's quantisation
table (its view's, per plane group)::

    c = K (x - 128);  z = c / Q;  deq = Q (round(z) + (z - round z)^3);  out = clamp(K^T deq + 128, 0, 255)

``round`` rounds half away from zero; the soft rounding is the paper's (eq. soft_round). The backward is
the chain's transpose with the elementwise soft-round derivative ``3 (z - round z)^2`` and the clamp's mask
(gradient strictly inside (0, 255), as ``hardtanh``): ``g_x = K^T (3 (z - round z)^2 K (mask g))``. It
recomputes ``z`` from the saved input instead of storing it.

Mode "float" (:func:`float_code`): libjpeg's islow forward DCT (two 64 x 64 integer-matrix products, each
followed by its rounding shift, as :func:`jsgs.jpeg.dct.fdct_islow` in the working dtype) and quantizer,
the float IDCT, +128, clamp and rounding; the backward is the float chain's with the soft-round derivative
at the quantizer, evaluated at the islow coefficients (the modes' shared backward). Its divisions are
correctly rounded (:func:`_div_ieee`), as torch's: the quantizer's ties are exact in the twin (with Triton's
approximate division they disagreed with it on CUDA by up to 29 8-bit units on 2 % of the pixels). On an
H100 JO then agreed with the float32 twin but for single flips at float32 rounding ties (at most 2 8-bit
units, on about 0.002 % of the values: ``tests/test_jsgs/kernels/test_triton_jo.py``'s module doc).

The torch twin is ``jsgs.jpeg.observe._code_blocks``, the reference of the tests. Each
kernel is one launch per plane group (the luma plane, the two chroma planes) with no host synchronisation
and outputs allocated by torch, so a CUDA graph records it like any other op. The 64 x 64 products run with
``input_precision="ieee"`` (no TF32): float32 stays float32 as in the twin.

Triton is optional: without it, off CUDA (unless ``TRITON_INTERPRET=1`` runs the kernels on CPU tensors
with Triton's interpreter, which the tests use) or for other dtypes than float32 on CUDA,
:func:`fused_jo_runs` is False and JO and DS run the torch code.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
from typing import Any

import numpy as np
import torch
from torch import Tensor

try:  # optional: training without Triton runs the torch twin
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - depends on the environment
    triton = None
    tl = None

#: 8x8 blocks per Triton program (the M dimension of its 64 x 64 products) and warps per program of mode
#: paper's coding pass, chosen by ``benchmarks/bench_jpeg_ops.py --fused-jo`` (both kernels, fwd + bwd, on an
#: H100, torch 2.11, triton 3.6; ms): at 1440x1920 16/4 0.517, 16/8 0.817, 32/4 0.615, 32/8 0.524, 64/8 0.780;
#: at 504x378 16/4 0.072, 16/8 0.072, 32/4 0.079, 32/8 0.103, 64/8 0.119. 16/4 is the H100's fastest at both
#: sizes (another H100 run: 0.52 against 32/4's 0.62 ms at 1440x1920). On an H200 it was the fastest at
#: 1440x1920 too (0.515 against 32/4's 0.604) and slower at 504x378 (0.122 against 0.104). Triton compiles one
#: binary per specialisation of the integer arguments (1: a constant; divisible by 16: a hint), and ptxas
#: for sm_90 allocates registers per binary (``tests/test_jsgs/kernels/test_triton_jo.py``'s sm_90 tests): at
#: 32/4 the backward's binary for llff_flower's luma launch (one plane, 63 blocks a row) keeps 32 registers
#: and spills about 11.7 KB per thread (a 9 KB stack frame), the other launches' about 1 KB at 255 registers;
#: in flower's step that backward took 0.29 ms for 4,560 blocks. At 16/4 every launch of the step spills at
#: most 12 bytes, the forward none.
BLOCKS_PER_PROGRAM = 16
WARPS = 4
#: The same for mode float's coding pass (ptxas: no spills on sm_90) and for DS.
FLOAT_BLOCKS_PER_PROGRAM = 16
FLOAT_WARPS = 8
DS_BLOCKS_PER_PROGRAM = 32
DS_WARPS = 8


def triton_available() -> bool:
    """Whether Triton imports here."""
    return triton is not None


def interpreting() -> bool:
    """Whether Triton's interpreter runs the kernels (``TRITON_INTERPRET=1``: on CPU tensors, for tests)."""
    return os.environ.get("TRITON_INTERPRET", "0") == "1"


def fused_jo_runs(x: Tensor) -> bool:
    """Whether the fused kernels can run on ``x``: Triton imports and ``x`` is a float32 CUDA tensor, or a
    float32 or float64 CPU tensor under Triton's interpreter (float64 there checks the kernels' arithmetic
    against float64 torch; on CUDA ``tl.dot`` in float64 depends on the Triton version and the GPU, and
    training renders float32)."""
    if triton is None:
        return False
    if x.is_cuda:
        return x.dtype == torch.float32 and not interpreting()
    return interpreting() and x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64)


def _check_runs(name: str, x: Tensor, *others: Tensor) -> None:
    """ValueError unless the kernels can run on ``x`` (:func:`fused_jo_runs`) and ``others`` lie on its
    device: a CPU tensor outside the interpreter would reach the CUDA launch, which refuses its host pointer
    in Triton's words ("Pointer argument (at i) cannot be accessed from Triton (cpu tensor?)")."""
    where = {t.device for t in (x, *others)}
    if not fused_jo_runs(x) or len(where) > 1:
        raise ValueError(
            f"{name} needs float32 CUDA tensors (or TRITON_INTERPRET=1 and CPU tensors) on one device, got "
            f"{x.dtype} on {', '.join(sorted(str(d) for d in where))}"
        )


@functools.cache
def _kron(dtype: torch.dtype, device: torch.device) -> Tensor:
    """``kron(D, D)`` (64 x 64, row-major ``[(v, u), (y, x)]``), built in float64 and cached per device (a
    host-to-device copy on first use only, before any graph records)."""
    k = np.arange(8)[:, None]
    n = np.arange(8)[None, :]
    d = np.cos((2 * n + 1) * k * math.pi / 16) * 0.5
    d[0, :] = math.sqrt(1 / 8)
    return torch.tensor(np.kron(d, d), dtype=dtype, device=device)


def dct_kron(dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> Tensor:
    """The 64 x 64 matrix the kernels multiply by: ``coef64 = K @ block64`` (row-major 8x8 blocks)."""
    return _kron(dtype, torch.device(device))


if triton is not None:
    # --- helpers, inlined into the kernels that call them ------------------------------------------------

    @triton.jit
    def _program_range(count, BLOCK: tl.constexpr):  # type: ignore[no-untyped-def]
        """This program's ``BLOCK`` indices along grid axis 0 and the mask of those below ``count``."""
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        return i, i < count

    @triton.jit
    def _program_blocks(n_blocks, BN: tl.constexpr):  # type: ignore[no-untyped-def]
        """The block kernels' prologue: this program's blocks ``n`` (``[BN]``), the 64 elements of a block
        ``e`` (row-major 8x8) and the mask of the blocks that exist (``[BN, 1]``)."""
        n, ok = _program_range(n_blocks, BN)
        return n, tl.arange(0, 64), ok[:, None]

    @triton.jit
    def _block_offsets(n, e, nb, nbx, planes, s_b, s_c, s_h, s_w):  # type: ignore[no-untyped-def]
        """Element offsets ``[BN, 64]`` of blocks ``n`` (``[BN]``) in a strided (B, C, H, W) tensor, and the
        view index of each block."""
        bc = n // nb
        rem = n % nb
        by = rem // nbx
        bx = rem % nbx
        view = bc // planes
        chan = bc % planes
        row = by[:, None] * 8 + (e // 8)[None, :]
        col = bx[:, None] * 8 + (e % 8)[None, :]
        base = view.to(tl.int64) * s_b + chan.to(tl.int64) * s_c
        return base[:, None] + row.to(tl.int64) * s_h + col.to(tl.int64) * s_w, view

    @triton.jit
    def _rows(n, e):  # type: ignore[no-untyped-def]
        """Element offsets ``[BN, 64]`` of blocks ``n`` in a contiguous (blocks, 64) tensor."""
        return n.to(tl.int64)[:, None] * 64 + e[None, :]

    @triton.jit
    def _matrix(ptr, e):  # type: ignore[no-untyped-def]
        """The row-major 64 x 64 matrix at ``ptr``: ``M[i, j]``."""
        return tl.load(ptr + e[:, None] * 64 + e[None, :])

    @triton.jit
    def _matrix_t(ptr, e):  # type: ignore[no-untyped-def]
        """Its transpose: ``M[j, i]``."""
        return tl.load(ptr + e[None, :] * 64 + e[:, None])

    @triton.jit
    def _samples_and_tables(x_ptr, q_ptr, x_off, view, e, valid):  # type: ignore[no-untyped-def]
        """The blocks' samples at ``x_off`` (128, level zero, past the last block) and the quantisation
        table of each block's view (``[BN, 64]`` each; ones past the last block)."""
        x = tl.load(x_ptr + x_off, mask=valid, other=128.0)
        q = tl.load(q_ptr + view.to(tl.int64)[:, None] * 64 + e[None, :], mask=valid, other=1.0)
        return x, q

    @triton.jit
    def _coding_blocks(  # type: ignore[no-untyped-def]
        n_blocks, nb, nbx, planes, xs_b, xs_c, xs_h, xs_w, os_b, os_c, os_h, os_w, BN: tl.constexpr
    ):  # fmt: skip
        """The coding-pass kernels' prologue (:func:`_program_blocks`): ``(n, e, valid, x_off, view, o_off)``,
        the blocks' offsets in the planes (strides ``xs_*``), their views, and their offsets in the
        output-shaped tensor (strides ``os_*``)."""
        n, e, valid = _program_blocks(n_blocks, BN)
        x_off, view = _block_offsets(n, e, nb, nbx, planes, xs_b, xs_c, xs_h, xs_w)
        o_off, _ = _block_offsets(n, e, nb, nbx, planes, os_b, os_c, os_h, os_w)
        return n, e, valid, x_off, view, o_off

    @triton.jit
    def _dot(a, b):  # type: ignore[no-untyped-def]
        """``a @ b`` in the operands' precision (no TF32: float32 stays float32 as in the twin)."""
        return tl.dot(a, b, input_precision="ieee")

    @triton.jit
    def _clamp(o):  # type: ignore[no-untyped-def]
        """``o`` clamped to [0, 255]."""
        return tl.minimum(tl.maximum(o, 0.0), 255.0)

    @triton.jit
    def _clamp_passes(g, o):  # type: ignore[no-untyped-def]
        """The clamp's gradient: ``g`` where ``o`` lies strictly inside (0, 255) (as ``hardtanh``), else 0."""
        return tl.where((o > 0.0) & (o < 255.0), g, 0.0)

    @triton.jit
    def _round_half_away(z):  # type: ignore[no-untyped-def]
        return tl.where(z >= 0, tl.floor(z + 0.5), -tl.floor(0.5 - z))

    # --- JO's coding pass, mode "paper" --------------------------------------------------------------------

    @triton.jit
    def _paper_rounding(x, q, kt):  # type: ignore[no-untyped-def]
        """``(round(z), z - round(z))`` of the blocks' quantised coefficients ``z = K (x - 128) / Q``."""
        z = _dot(x - 128.0, kt) / q
        r = _round_half_away(z)
        return r, z - r

    @triton.jit
    def _paper_forward(  # type: ignore[no-untyped-def]
        x_ptr, q_ptr, k_ptr, out_ptr, n_blocks, nb, nbx, planes,
        xs_b, xs_c, xs_h, xs_w, os_b, os_c, os_h, os_w, BN: tl.constexpr,
    ):  # fmt: skip
        _, e, valid, x_off, view, o_off = _coding_blocks(
            n_blocks, nb, nbx, planes, xs_b, xs_c, xs_h, xs_w, os_b, os_c, os_h, os_w, BN
        )
        k = _matrix(k_ptr, e)  # K[i, j]
        kt = _matrix_t(k_ptr, e)  # K[j, i]
        x, q = _samples_and_tables(x_ptr, q_ptr, x_off, view, e, valid)
        r, f = _paper_rounding(x, q, kt)
        deq = q * (r + f * f * f)
        out = _clamp(_dot(deq, k) + 128.0)
        tl.store(out_ptr + o_off, out, mask=valid)

    @triton.jit
    def _paper_backward(  # type: ignore[no-untyped-def]
        x_ptr, q_ptr, k_ptr, out_ptr, g_ptr, gx_ptr, n_blocks, nb, nbx, planes,
        xs_b, xs_c, xs_h, xs_w, os_b, os_c, os_h, os_w, gs_b, gs_c, gs_h, gs_w, BN: tl.constexpr,
    ):  # fmt: skip
        n, e, valid, x_off, view, o_off = _coding_blocks(
            n_blocks, nb, nbx, planes, xs_b, xs_c, xs_h, xs_w, os_b, os_c, os_h, os_w, BN
        )
        g_off, _ = _block_offsets(n, e, nb, nbx, planes, gs_b, gs_c, gs_h, gs_w)
        k = _matrix(k_ptr, e)
        kt = _matrix_t(k_ptr, e)
        x, q = _samples_and_tables(x_ptr, q_ptr, x_off, view, e, valid)
        out = tl.load(out_ptr + o_off, mask=valid, other=0.0)
        g = tl.load(g_ptr + g_off, mask=valid, other=0.0)
        _, f = _paper_rounding(x, q, kt)
        g = _clamp_passes(g, out)
        g_deq = _dot(g, kt)
        g_c = (g_deq * q) * (3.0 * f * f) / q
        g_x = _dot(g_c, k)
        tl.store(gx_ptr + o_off, g_x, mask=valid)

    # --- JO's coding pass, mode "float" --------------------------------------------------------------------

    @triton.jit
    def _div_ieee(a, b):  # type: ignore[no-untyped-def]
        """``a / b`` correctly rounded, as torch divides. Triton's ``/`` on float32 compiles to the
        approximate ``div.full.f32`` (up to 2 ulp), which the interpreter does not show: ``8Q / 8Q`` may come
        out just below 1, and a floor after it drops a level (that made mode float's fused quantizer disagree
        with the twin on an H200: up to 29 8-bit units on 2 % of the pixels). float64's ``/`` is IEEE."""
        if a.dtype == tl.float32:
            return tl.math.div_rn(a, b)
        else:
            return a / b

    @triton.jit
    def _islow_levels(x, q, m_ptr, v_ptr, e):  # type: ignore[no-untyped-def]
        """libjpeg's islow forward DCT of level-shifted blocks ``x`` ``[BN, 64]`` (two 64 x 64 products, each
        followed by its rounding shift) and its quantizer: ``(t, level)``, the twin's divisions rounded as
        torch rounds them (:func:`_div_ieee`)."""
        r1 = _matrix(m_ptr, e)
        r2 = _matrix(m_ptr + 4096, e)
        y = _dot(x, r1)
        y = tl.floor(_div_ieee(y + tl.load(v_ptr + e)[None, :], tl.load(v_ptr + 64 + e)[None, :]))
        t = _dot(y, r2)
        t = tl.floor(_div_ieee(t + tl.load(v_ptr + 128 + e)[None, :], tl.load(v_ptr + 192 + e)[None, :]))
        q8 = 8.0 * q
        a = tl.floor(_div_ieee(tl.abs(t) + q8 * 0.5, q8))
        return t, tl.where(t < 0, -a, a)

    @triton.jit
    def _float_decoded(x, q, m_ptr, v_ptr, e, k):  # type: ignore[no-untyped-def]
        """``(t, o)``: the blocks' islow coefficients and their quantised levels decoded by the float IDCT,
        +128 (before the clamp and the rounding)."""
        t, level = _islow_levels(x - 128.0, q, m_ptr, v_ptr, e)
        return t, _dot(level * q, k) + 128.0

    @triton.jit
    def _float_forward(  # type: ignore[no-untyped-def]
        x_ptr, q_ptr, m_ptr, v_ptr, out_ptr, n_blocks, nb, nbx, planes,
        xs_b, xs_c, xs_h, xs_w, os_b, os_c, os_h, os_w, BN: tl.constexpr,
    ):  # fmt: skip
        _, e, valid, x_off, view, o_off = _coding_blocks(
            n_blocks, nb, nbx, planes, xs_b, xs_c, xs_h, xs_w, os_b, os_c, os_h, os_w, BN
        )
        k = _matrix(m_ptr + 8192, e)
        x, q = _samples_and_tables(x_ptr, q_ptr, x_off, view, e, valid)
        _, o = _float_decoded(x, q, m_ptr, v_ptr, e, k)
        out = tl.floor(_clamp(o) + 0.5)
        tl.store(out_ptr + o_off, out, mask=valid)

    @triton.jit
    def _float_backward(  # type: ignore[no-untyped-def]
        x_ptr, q_ptr, m_ptr, v_ptr, g_ptr, gx_ptr, n_blocks, nb, nbx, planes,
        xs_b, xs_c, xs_h, xs_w, gs_b, gs_c, gs_h, gs_w, os_b, os_c, os_h, os_w, BN: tl.constexpr,
    ):  # fmt: skip
        n, e, valid, x_off, view, o_off = _coding_blocks(
            n_blocks, nb, nbx, planes, xs_b, xs_c, xs_h, xs_w, os_b, os_c, os_h, os_w, BN
        )
        g_off, _ = _block_offsets(n, e, nb, nbx, planes, gs_b, gs_c, gs_h, gs_w)
        k = _matrix(m_ptr + 8192, e)
        kt = _matrix_t(m_ptr + 8192, e)
        x, q = _samples_and_tables(x_ptr, q_ptr, x_off, view, e, valid)
        g = tl.load(g_ptr + g_off, mask=valid, other=0.0)
        t, o = _float_decoded(x, q, m_ptr, v_ptr, e, k)
        g = _clamp_passes(g, o)  # rounding: 1
        z = _div_ieee(t, 8.0 * q)
        f = z - _round_half_away(z)
        g_t = _div_ieee((_dot(g, kt) * q) * (3.0 * f * f), 8.0 * q)
        g_x = _dot(8.0 * g_t, k)
        tl.store(gx_ptr + o_off, g_x, mask=valid)

    # --- DS's Delta ----------------------------------------------------------------------------------------

    @triton.jit
    def _ds_delta_forward(  # type: ignore[no-untyped-def]
        o_ptr, t_ptr, w_ptr, k_ptr, d_ptr, n_blocks, nb, nbx,
        os_b, os_c, os_h, os_w, ts_b, ts_c, ts_h, ts_w, BN: tl.constexpr,
    ):  # fmt: skip
        n, e, valid = _program_blocks(n_blocks, BN)
        o_off, _ = _block_offsets(n, e, nb, nbx, 1, os_b, os_c, os_h, os_w)
        t_off, _ = _block_offsets(n, e, nb, nbx, 1, ts_b, ts_c, ts_h, ts_w)
        kt = _matrix_t(k_ptr, e)
        y = tl.zeros((BN, 64), dtype=kt.dtype)
        for c in tl.static_range(3):
            w = tl.load(w_ptr + c)
            diff = tl.load(o_ptr + o_off + c * os_c, mask=valid, other=0.0) - tl.load(
                t_ptr + t_off + c * ts_c, mask=valid, other=0.0
            )
            y += w * diff
        delta = _dot(y, kt) / 255.0
        tl.store(d_ptr + _rows(n, e), delta, mask=valid)

    @triton.jit
    def _ds_delta_backward(  # type: ignore[no-untyped-def]
        g_ptr, w_ptr, k_ptr, gx_ptr, n_blocks, nb, nbx, gs_b, gs_c, gs_h, gs_w, BN: tl.constexpr,
    ):  # fmt: skip
        n, e, valid = _program_blocks(n_blocks, BN)
        x_off, _ = _block_offsets(n, e, nb, nbx, 1, gs_b, gs_c, gs_h, gs_w)
        k = _matrix(k_ptr, e)
        g = tl.load(g_ptr + _rows(n, e), mask=valid, other=0.0) / 255.0
        g_y = _dot(g, k)
        for c in tl.static_range(3):
            tl.store(gx_ptr + x_off + c * gs_c, tl.load(w_ptr + c) * g_y, mask=valid)


def _on(device: torch.device) -> contextlib.AbstractContextManager[Any]:
    """Launch on ``device`` (Triton launches on the current CUDA device, which may be another)."""
    return torch.cuda.device(device) if device.type == "cuda" else contextlib.nullcontext()


def _grid_args(planes: Tensor, bn: int) -> tuple[tuple[int], tuple[int, int, int, int]]:
    b, c, h, w = planes.shape
    nb = (h // 8) * (w // 8)
    return (triton.cdiv(b * c * nb, bn),), (b * c * nb, nb, w // 8, c)


def paper_code_forward(
    planes: Tensor, tables: Tensor, blocks_per_program: int = BLOCKS_PER_PROGRAM, warps: int = WARPS
) -> Tensor:
    """The forward kernel alone (no autograd): ``planes`` ``(B, C, H, W)`` (H, W multiples of 8, any
    strides), ``tables`` ``(B, 64)`` contiguous in ``planes``' dtype -> decoded ``(B, C, H, W)``."""
    out = torch.empty(planes.shape, dtype=planes.dtype, device=planes.device)
    grid, (n, nb, nbx, c) = _grid_args(planes, blocks_per_program)
    with _on(planes.device):
        _paper_forward[grid](
            planes, tables, _kron(planes.dtype, planes.device), out, n, nb, nbx, c,
            *planes.stride(), *out.stride(), BN=blocks_per_program, num_warps=warps,
        )  # fmt: skip
    return out


def paper_code_backward(
    planes: Tensor, tables: Tensor, out: Tensor, grad: Tensor, blocks_per_program: int = BLOCKS_PER_PROGRAM,
    warps: int = WARPS,
) -> Tensor:
    """The backward kernel alone: the gradient with respect to ``planes`` of ``sum(grad * forward)``, given
    the forward's ``out``."""
    grad_x = torch.empty(out.shape, dtype=out.dtype, device=out.device)
    grid, (n, nb, nbx, c) = _grid_args(planes, blocks_per_program)
    with _on(planes.device):
        _paper_backward[grid](
            planes, tables, _kron(planes.dtype, planes.device), out, grad, grad_x, n, nb, nbx, c,
            *planes.stride(), *out.stride(), *grad.stride(), BN=blocks_per_program, num_warps=warps,
        )  # fmt: skip
    return grad_x


class _PaperCode(torch.autograd.Function):
    """The coding pass of mode "paper" on padded planes, differentiable in the planes (not the tables)."""

    @staticmethod
    def forward(ctx: Any, planes: Tensor, tables: Tensor) -> Tensor:  # type: ignore[override]
        out = paper_code_forward(planes, tables)
        ctx.save_for_backward(planes, tables, out)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        planes, tables, out = ctx.saved_tensors
        return paper_code_backward(planes, tables, out, grad.contiguous()), None


def paper_code(planes: Tensor, tables: Tensor) -> Tensor:
    """Mode "paper"'s coding pass (level shift, DCT, soft quantisation, dequantisation, IDCT, +128, clamp
    to [0, 255]) of every 8x8 block of ``planes`` ``(B, C, H, W)`` (H, W multiples of 8), block by block,
    with ``tables`` ``(B, 8, 8)`` (one per view, natural order ``[v, u]``; no gradient): the fused kernels.
    Equal to ``unblockify(_code_blocks(blockify(planes), tables, "paper"))`` of :mod:`jsgs.jpeg.observe`
    up to float rounding. Needs :func:`fused_jo_runs`."""
    b, _, h, w = planes.shape
    if h % 8 or w % 8 or tables.shape != (b, 8, 8):
        raise ValueError(
            f"paper_code: planes must be (B, C, 8m, 8n) and tables (B, 8, 8), got {tuple(planes.shape)}, "
            f"{tuple(tables.shape)}"
        )
    _check_runs("paper_code", planes, tables)
    q = tables.detach().to(planes.dtype).reshape(b, 64).contiguous()
    # Contiguous planes (and gradients, in the backward): the kernels take any strides, but the colour
    # map's matrix product hands over channels-last planes, which the backward kernel read 8x slower on an
    # H100 at 1440x1920 (1.74 against 0.20 ms per step); one copy each way costs a few hundredths of that.
    return _PaperCode.apply(planes.contiguous(), q)


# --- JO's coding pass, mode "float" ---------------------------------------------------------------------


@functools.cache
def _islow_constants(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """The float-mode kernels' constants: ``(3, 64, 64)`` right-hand matrices of the islow row pass, its
    column pass (``jsgs.jpeg.dct``'s integer matrices acting on row-major 64-vectors) and ``kron(D, D)``;
    ``(4, 64)`` the passes' rounding offsets and divisors per coefficient."""
    from jsgs.jpeg.dct import _islow_np

    c = _islow_np()
    eye = np.eye(8)
    dct = _kron(torch.float64, torch.device("cpu")).numpy()
    mats = np.stack([np.kron(eye, c["f1"]).T, np.kron(c["f2"], eye).T, dct])
    vecs = np.stack([np.tile(c["f1_off"], 8), np.tile(c["f1_div"], 8), np.repeat(c["f2_off"], 8),
                     np.repeat(c["f2_div"], 8)])  # fmt: skip
    return (torch.tensor(mats, dtype=dtype, device=device).contiguous(),
            torch.tensor(vecs, dtype=dtype, device=device).contiguous())  # fmt: skip


class _FloatCode(torch.autograd.Function):
    """The coding pass of mode "float" on padded planes of integer samples, differentiable in the planes."""

    @staticmethod
    def forward(ctx: Any, planes: Tensor, tables: Tensor) -> Tensor:  # type: ignore[override]
        out = torch.empty(planes.shape, dtype=planes.dtype, device=planes.device)
        mats, vecs = _islow_constants(planes.dtype, planes.device)
        grid, (n, nb, nbx, c) = _grid_args(planes, FLOAT_BLOCKS_PER_PROGRAM)
        with _on(planes.device):
            _float_forward[grid](
                planes, tables, mats, vecs, out, n, nb, nbx, c, *planes.stride(), *out.stride(),
                BN=FLOAT_BLOCKS_PER_PROGRAM, num_warps=FLOAT_WARPS,
            )  # fmt: skip
        ctx.save_for_backward(planes, tables)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        planes, tables = ctx.saved_tensors
        grad = grad.contiguous()
        grad_x = torch.empty(planes.shape, dtype=grad.dtype, device=grad.device)
        mats, vecs = _islow_constants(planes.dtype, planes.device)
        grid, (n, nb, nbx, c) = _grid_args(planes, FLOAT_BLOCKS_PER_PROGRAM)
        with _on(planes.device):
            _float_backward[grid](
                planes, tables, mats, vecs, grad, grad_x, n, nb, nbx, c, *planes.stride(), *grad.stride(),
                *grad_x.stride(), BN=FLOAT_BLOCKS_PER_PROGRAM, num_warps=FLOAT_WARPS,
            )  # fmt: skip
        return grad_x, None


def float_code(planes: Tensor, tables: Tensor) -> Tensor:
    """Mode "float"'s coding pass of ``planes`` ``(B, C, H, W)`` (integer samples 0..255, H, W multiples
    of 8) with ``tables`` ``(B, 8, 8)``: libjpeg's islow forward DCT in the working dtype (its two rounding
    shifts), libjpeg's quantizer, the float IDCT, +128, clamp, rounding to integers; the gradient of the
    float stages with the soft-round derivative at the quantizer (``jsgs.jpeg.observe``'s module doc).
    Equal to ``_code_blocks(..., "float")`` up to float rounding (the islow sums in float32 may round
    differently where they pass 2^24, which moves a rare coefficient by one unit, as the twin itself
    warns). Needs :func:`fused_jo_runs`."""
    b, _, h, w = planes.shape
    if h % 8 or w % 8 or tables.shape != (b, 8, 8):
        raise ValueError(
            f"float_code: planes must be (B, C, 8m, 8n) and tables (B, 8, 8), got {tuple(planes.shape)}, "
            f"{tuple(tables.shape)}"
        )
    _check_runs("float_code", planes, tables)
    q = tables.detach().to(planes.dtype).reshape(b, 64).contiguous()
    return _FloatCode.apply(planes.contiguous(), q)  # contiguous: see paper_code


# --- DS's block DCT ---------------------------------------------------------------------------------------

#: Y8's weights (eq. jsgs_luminance), as ``jsgs.jpeg.supervision.luma8`` multiplies them
_LUMA_WEIGHTS = (255.0 * 0.299, 255.0 * 0.587, 255.0 * 0.114)


@functools.cache
def _luma_weights(dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.tensor(_LUMA_WEIGHTS, dtype=dtype, device=device)


class _DsDelta(torch.autograd.Function):
    """DS's Delta of two images, differentiable in the observation (the target is data)."""

    @staticmethod
    def forward(ctx: Any, obs: Tensor, target: Tensor) -> Tensor:  # type: ignore[override]
        b, _, h, w = obs.shape
        nby, nbx = h // 8, w // 8
        delta = torch.empty((b, nby, nbx, 8, 8), dtype=obs.dtype, device=obs.device)
        n = b * nby * nbx
        bn = DS_BLOCKS_PER_PROGRAM
        with _on(obs.device):
            _ds_delta_forward[(triton.cdiv(n, bn),)](
                obs, target, _luma_weights(obs.dtype, obs.device), _kron(obs.dtype, obs.device), delta, n,
                nby * nbx, nbx, *obs.stride(), *target.stride(), BN=bn, num_warps=DS_WARPS,
            )  # fmt: skip
        ctx.shape = obs.shape
        return delta

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        b, _, h, w = ctx.shape
        nby, nbx = h // 8, w // 8
        grad = grad.contiguous()
        # pixels outside the valid blocks get no gradient: zeros, then the kernel writes the blocks
        grad_obs = torch.zeros(ctx.shape, dtype=grad.dtype, device=grad.device)
        n = b * nby * nbx
        bn = DS_BLOCKS_PER_PROGRAM
        with _on(grad.device):
            _ds_delta_backward[(triton.cdiv(n, bn),)](
                grad, _luma_weights(grad.dtype, grad.device), _kron(grad.dtype, grad.device), grad_obs, n,
                nby * nbx, nbx, *grad_obs.stride(), BN=bn, num_warps=DS_WARPS,
            )  # fmt: skip
        return grad_obs, None


def ds_delta(observation: Tensor, target: Tensor) -> Tensor:
    """DS's ``Delta = (C_J - C_I) / 255`` (eqs. jsgs_level_shift ... jsgs_dct_residual) in one kernel:
    the luminance ``Y8`` of both images over their valid blocks (``floor(H/8) x floor(W/8)``), the block
    DCT of their difference (the level shift cancels), ``(B, nby, nbx, 8, 8)``. Differentiable in
    ``observation``; ``target`` must need no gradient. Equal to ``jsgs.jpeg.supervision``'s torch code up
    to float rounding. Needs :func:`fused_jo_runs` and at least one valid block."""
    if observation.shape != target.shape or observation.dim() != 4 or observation.shape[1] != 3:
        raise ValueError(
            f"ds_delta needs two (B, 3, H, W) images of one shape, got {tuple(observation.shape)}, "
            f"{tuple(target.shape)}"
        )
    if observation.shape[-2] < 8 or observation.shape[-1] < 8 or target.requires_grad:
        raise ValueError("ds_delta needs images of at least 8 x 8 and a target that needs no gradient")
    _check_runs("ds_delta", observation, target)
    return _DsDelta.apply(observation, target.to(observation.dtype))


# --- JO's colour conversions ------------------------------------------------------------------------------

#: pixels per Triton program and warps per program of the colour kernel (an elementwise map: not tuned on a
#: GPU yet, ``benchmarks/bench_jpeg_ops.py --fused-jo`` times it)
COLOR_BLOCK = 1024
COLOR_WARPS = 4

if triton is not None:

    @triton.jit
    def _color_affine(  # type: ignore[no-untyped-def]
        x_ptr, c_ptr, out_ptr, hw, width, xs_b, xs_c, xs_h, xs_w, os_b, os_c,
        BLOCK: tl.constexpr, FLAT: tl.constexpr, OFFSET: tl.constexpr,
    ):  # fmt: skip
        """``out[b, j, p] = sum_i M[j, i] x[b, i, p] (+ off[j])`` for the pixels ``p`` of one program and
        view ``b``: ``c_ptr`` holds ``M`` row-major then ``off`` (12 values); ``x`` (B, 3, H, W) any strides
        (``FLAT``: each plane's H x W is contiguous), ``out`` (B, 3, H, W) with contiguous planes. Products
        and sums only: no division, so CUDA's float32 needs no correctly rounded variant."""
        p, valid = _program_range(hw, BLOCK)
        view = tl.program_id(1).to(tl.int64)
        if FLAT:
            x_off = view * xs_b + p.to(tl.int64)
        else:
            x_off = view * xs_b + (p // width).to(tl.int64) * xs_h + (p % width).to(tl.int64) * xs_w
        x0 = tl.load(x_ptr + x_off, mask=valid, other=0.0)
        x1 = tl.load(x_ptr + x_off + xs_c, mask=valid, other=0.0)
        x2 = tl.load(x_ptr + x_off + 2 * xs_c, mask=valid, other=0.0)
        o_off = view * os_b + p.to(tl.int64)
        for j in tl.static_range(3):
            m = c_ptr + 3 * j
            y = tl.load(m) * x0 + tl.load(m + 1) * x1 + tl.load(m + 2) * x2
            if OFFSET:
                y += tl.load(c_ptr + 9 + j)
            tl.store(out_ptr + o_off + j * os_c, y, mask=valid)


def color_affine_forward(x: Tensor, coefficients: Tensor, offset: bool = True) -> Tensor:
    """The colour kernel alone (no autograd): ``x`` ``(B, 3, H, W)`` any strides, ``coefficients`` (12,)
    in ``x``'s dtype -> ``(B, 3, H, W)`` contiguous, ``M x (+ off)`` per pixel."""
    b, _, h, w = x.shape
    out = torch.empty((b, 3, h, w), dtype=x.dtype, device=x.device)
    hw = h * w
    if hw == 0 or b == 0:
        return out
    flat = x.stride(3) == 1 and x.stride(2) == w
    with _on(x.device):
        _color_affine[(triton.cdiv(hw, COLOR_BLOCK), b)](
            x, coefficients, out, hw, w, *x.stride(), out.stride(0), out.stride(1), BLOCK=COLOR_BLOCK,
            FLAT=flat, OFFSET=offset, num_warps=COLOR_WARPS,
        )  # fmt: skip
    return out


class _ColorAffine(torch.autograd.Function):
    """An affine colour map of ``(B, 3, H, W)`` images, differentiable in the image (a linear map: the
    backward is the transposed matrix, same kernel, no offset; nothing saved but the coefficients)."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, forward: Tensor, backward: Tensor) -> Tensor:  # type: ignore[override]
        ctx.backward_coefficients = backward
        return color_affine_forward(x, forward)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None, None]:  # type: ignore[override]
        return color_affine_forward(grad, ctx.backward_coefficients, offset=False), None, None


def color_convert(x: Tensor, forward: Tensor, backward: Tensor) -> Tensor:
    """An affine colour map of ``x`` ``(B, 3, H, W)`` as one elementwise kernel each way instead of a matrix
    product of ``[B H W, 3] x [3, 3]`` (cuBLAS tiles a dimension of 3 poorly): ``forward`` holds ``M``
    row-major then the offset, ``backward`` ``M^T`` row-major then zeros, 12 values each in ``x``'s dtype
    and device (:func:`jsgs.jpeg.color.kernel_coefficients` gives them for the JPEG colour maps, equal to
    the torch code up to float rounding: the order of the three products and the offset). Contiguous
    output planes. Needs :func:`fused_jo_runs`."""
    if x.dim() != 4 or x.shape[1] != 3 or forward.shape != (12,) or backward.shape != (12,):
        raise ValueError(f"color_convert: x must be (B, 3, H, W) and the coefficients (12,) each, got "
                         f"{tuple(x.shape)}, {tuple(forward.shape)}, {tuple(backward.shape)}")  # fmt: skip
    _check_runs("color_convert", x)
    return _ColorAffine.apply(x, forward, backward)
