"""Domain-matched DCT supervision (DS).

Paper eqs. omega, jsgs_luminance ... jsgs_dct_losses, jsgs_block_score.

Both images are compared in the luminance block-DCT domain over the *valid* blocks: the non-overlapping 8x8
blocks lying entirely inside the image, ``floor(H / 8) x floor(W / 8)`` of them, anchored at the top-left
corner (the JPEG block grid). Coefficients are indexed ``[v, u]`` like the natural-order tables, ``F(u, v)
= u + v``.

Units: ``Y8`` is in 8-bit levels (0..255), coefficients in orthonormal-DCT units of those levels, ``Delta`` in
coefficients / 255; losses and scores are unitless.

16-bit tables (steps above 255): omega is applied as written, without clamping T to 8 bits. The exponent keeps
decreasing past its 8-bit range (omega < exp(-2 - F/14) for T > 255), so the ordering "smaller step, larger
weight" holds for every table. Since L_mid and r_b normalise by the sum of the mid-band weights plus epsilon
(1e-6), a table whose mid-band steps are all very large (above ~2000) drives those weights below epsilon and
fades L_mid and r_b towards 0; in float32 omega becomes subnormal above T ~ 11,000 and exactly 0 above ~13,000
(float64 never underflows for 16-bit steps). All outputs stay finite. That fading is consistent with what such
a table does to the image: every mid-band coefficient is quantized to 0 in both images, so there is nothing
left to supervise there.
"""

from __future__ import annotations

from functools import cache
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from .dct import block_dct, blockify
from .tables import checked_steps

EPS_SM = 1e-3
EPS_LOSS = 1e-6
EPS_BLOCK = 1e-6


_F = np.add.outer(np.arange(8), np.arange(8))


@cache
def _constant(name: str, dtype: torch.dtype, device: torch.device) -> Tensor:
    # Constants per device, built once: no host-to-device copy or mask arithmetic inside the traced step.
    table = {"F": _F, "low": _F <= 3, "mid": (_F > 3) & (_F <= 5)}[name]
    return torch.as_tensor(table.astype(np.float64), dtype=dtype, device=device)


def _dev(device: torch.device | str | None) -> torch.device:
    return torch.device(device if device is not None else "cpu")


@cache
def _luma_weights(dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.tensor([[255.0 * 0.299], [255.0 * 0.587], [255.0 * 0.114]], dtype=dtype, device=device)


def frequency_index(dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
    """``F(u, v) = u + v`` as an ``(8, 8)`` tensor indexed ``[v, u]``."""
    return _constant("F", dtype, _dev(device))


def low_mask(dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
    """``M_low = 1{F <= 3}``, ``(8, 8)`` (10 coordinates)."""
    return _constant("low", dtype, _dev(device))


def mid_mask(dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
    """``M_mid = 1{3 < F <= 5}``, i.e. F in {4, 5}, ``(8, 8)`` (11 coordinates)."""
    return _constant("mid", dtype, _dev(device))


def omega(luma_table: Tensor) -> Tensor:
    """Reliability weights ``exp(-2 (T - 1) / 254 - F / 14)`` (eq. omega), ``(..., 8, 8)`` -> ``(..., 8, 8)``.

    ``luma_table`` holds quantization steps in natural order (float or integer); no clamping (module
    docstring).
    """
    t = luma_table.to(torch.get_default_dtype()) if not luma_table.is_floating_point() else luma_table
    return torch.exp(-2.0 * (t - 1.0) / 254.0 - frequency_index(t.dtype, t.device) / 14.0)


def luma8(rgb: Tensor) -> Tensor:
    """``Y8(X) = 255 (0.299 R + 0.587 G + 0.114 B)`` (eq. jsgs_luminance): ``(B, 3, H, W)`` in [0, 1] ->
    ``(B, H, W)`` in 0..255 (float, not rounded)."""
    # one matrix product over all pixels (the channel-wise sum is 6 small kernels, launch-bound on a GPU)
    return (rgb.movedim(-3, -1) @ _luma_weights(rgb.dtype, rgb.device)).squeeze(-1)


def valid_blocks_dct(rgb: Tensor) -> Tensor:
    """Level-shifted luminance DCT over the valid blocks (eqs. jsgs_level_shift, jsgs_dct_coefficients).

    ``(B, 3, H, W)`` in [0, 1] -> ``(B, floor(H/8), floor(W/8), 8, 8)`` orthonormal coefficients ``[v, u]``.
    """
    y = luma8(rgb) - 128.0
    hb, wb = (y.shape[-2] // 8) * 8, (y.shape[-1] // 8) * 8
    return block_dct(blockify(y[..., :hb, :wb]))


def psi(x: Tensor, eps_sm: float = EPS_SM) -> Tensor:
    """Smooth absolute value ``sqrt(x^2 + eps^2) - eps`` (eq. jsgs_dct_residual); 0 at 0, ~|x| for |x| >>
    eps."""
    return torch.sqrt(x * x + eps_sm * eps_sm) - eps_sm


class DctSupervision(NamedTuple):
    """Terms of the DCT supervision for a batch of B views with ``nby x nbx`` valid blocks each.

    delta: ``(B, nby, nbx, 8, 8)`` Delta = (C_J - C_I) / 255.
    penalty: ``(B, nby, nbx, 8, 8)`` psi(Delta).
    omega: ``(B, 8, 8)`` reliability weights of the luma tables.
    w_mid: ``(B, 8, 8)`` W_mid = M_mid omega.
    block_error: ``(B, nby, nbx)`` e_b (eq. jsgs_mid_block_error).
    loss_low: ``(B,)`` L_low per view; loss_mid: ``(B,)`` L_mid per view (eq. jsgs_dct_losses).
    block_score: ``(B, nby, nbx)`` r_b (eq. jsgs_block_score), differentiable.
    pixel_score: ``(B, H, W)`` r(p) = r_b of the block holding p, **detached** (the Gaussian Controller
        only uses it under stop-gradient); 0 for pixels outside the valid blocks (the last H mod 8 rows and
        W mod 8 columns), which have no block score.
        None where :func:`dct_supervision` was asked for none (``score_map=False``).
    """

    delta: Tensor
    penalty: Tensor
    omega: Tensor
    w_mid: Tensor
    block_error: Tensor
    loss_low: Tensor
    loss_mid: Tensor
    block_score: Tensor
    pixel_score: Tensor | None


class TableWeights(NamedTuple):
    """What DS takes from a luma table alone (no image): ``omega`` ``(B, 8, 8)`` (eq. omega), ``w_mid``
    ``(B, 8, 8)`` = M_mid omega and ``w_sum`` ``(B,)`` its sum. A view's tables are fixed for the run, so the
    method computes these once per view (:func:`table_weights`) instead of once per step."""

    omega: Tensor
    w_mid: Tensor
    w_sum: Tensor


def table_weights(
    luma_table: Tensor, batch: int = 1, dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> TableWeights:  # fmt: skip
    """:class:`TableWeights` of ``luma_table`` ``(8, 8)`` or ``(batch, 8, 8)``, in ``dtype`` on ``device``:
    the operations :func:`dct_supervision` runs on them without it, so the values are bit for bit its own.
    A table given as an array or a list must hold quantization steps, integers 1..65535 (ValueError, as
    :func:`jsgs.jpeg.observe.as_tables`); a tensor is taken as given."""
    if not isinstance(luma_table, Tensor):
        luma_table = checked_steps(luma_table, "luma_table")
    table = torch.as_tensor(luma_table, device=_dev(device)).to(dtype)
    table = table.expand(batch, 8, 8)
    w = omega(table)
    w_mid = mid_mask(dtype, table.device) * w
    return TableWeights(w, w_mid, w_mid.sum(dim=(-1, -2)))


def _delta(observation: Tensor, target: Tensor, kernel: str) -> Tensor:
    """``Delta = (C_J - C_I) / 255`` ``(B, nby, nbx, 8, 8)``: the torch code, or the fused kernel (``kernel``
    "triton", where it can run)."""
    if kernel not in ("torch", "triton"):
        raise ValueError(f"kernel must be 'torch' or 'triton', got {kernel!r}")
    if kernel == "triton" and min(observation.shape[-2:]) >= 8 and not target.requires_grad:
        from jsgs.kernels._triton_jo import ds_delta, fused_jo_runs

        if fused_jo_runs(observation):
            return ds_delta(observation, target)
    return (valid_blocks_dct(observation) - valid_blocks_dct(target)) / 255.0


def dct_supervision(
    observation: Tensor,
    target: Tensor,
    luma_table: Tensor,
    eps_sm: float = EPS_SM,
    eps_loss: float = EPS_LOSS,
    eps_block: float = EPS_BLOCK,
    weights: TableWeights | None = None,
    kernel: str = "torch",
    score_map: bool = True,
) -> DctSupervision:
    """DS between the JO output and the decoded training image.

    Args:
        observation: ``(B, 3, H, W)`` the JPEG observation of the render, Î^J, in [0, 1] (gives C_J).
        target: ``(B, 3, H, W)`` the decoded training JPEG, I, in [0, 1] (gives C_I).
        luma_table: ``(B, 8, 8)`` or ``(8, 8)`` luminance quantization steps, natural order.
        eps_sm, eps_loss, eps_block: epsilon_sm, epsilon_DCT^loss, epsilon_DCT^block (paper: 1e-3,
            1e-6, 1e-6).
        weights: :func:`table_weights` of ``luma_table``, made beforehand (``B`` views, in the observation's
            dtype, on its device); None: made here.
        kernel: ``"torch"`` or ``"triton"``: Delta as one fused Triton kernel forward and one backward
            (:func:`jsgs.kernels._triton_jo.ds_delta`; CUDA tensors, or ``TRITON_INTERPRET=1`` on CPU), where
            it can run (a target that needs no gradient, at least one valid block), else the torch code.
        score_map: make r(p) (``pixel_score``); False: None there, for a caller that reads r_b alone.
    Returns:
        :class:`DctSupervision`. With no valid block (H < 8 or W < 8) the losses are 0 and the score map is 0.
    """
    b, _, height, width = observation.shape
    delta = _delta(observation, target, kernel)
    pen = psi(delta, eps_sm)

    if weights is None:
        weights = table_weights(luma_table, b, observation.dtype, observation.device)
    w, w_mid, w_sum = weights  # w_sum: (B,)
    m_low = low_mask(observation.dtype, observation.device)

    n_blocks = delta.shape[1] * delta.shape[2]
    block_error = (pen * w_mid[:, None, None]).sum(dim=(-1, -2))  # e_b
    loss_low = (pen * m_low).sum(dim=(1, 2, 3, 4)) / (n_blocks * 10 + eps_loss)  # 10 = |M_low|
    loss_mid = block_error.sum(dim=(1, 2)) / (n_blocks * w_sum + eps_loss)
    block_score = block_error / (w_sum[:, None, None] + eps_block)

    pixel_score = pixel_score_of(block_score, height, width) if score_map else None
    return DctSupervision(delta, pen, w, w_mid, block_error, loss_low, loss_mid, block_score, pixel_score)


def pixel_score_of(block_score: Tensor, height: int, width: int) -> Tensor:
    """r(p) ``(B, H, W)``, detached, from the block scores r_b ``(B, H // 8, W // 8)``: r_b on the pixels of
    its block, 0 on the last H mod 8 rows and W mod 8 columns (no block holds them)."""
    b, nby, nbx = block_score.shape
    pix = block_score.detach()[:, :, None, :, None].expand(b, nby, 8, nbx, 8).reshape(b, nby * 8, nbx * 8)
    return torch.nn.functional.pad(pix, (0, width - nbx * 8, 0, height - nby * 8))
