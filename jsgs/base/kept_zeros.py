"""Zeros made once and kept: a read-only zero that a step needs again and again costs no kernel after the
first.

A JSGS step uses zeros that nothing ever writes: the value of the render's deferred probe objective and of
the probe objective (:mod:`jsgs.base.known_grad`'s scalars, which are exactly 0), and the values logged as 0
on lossless views and between the Gaussian Controller's steps. On a GPU each new zero is a fill kernel and a
launch on the host, step after step; one kept per shape, dtype and device is none.
"""

from __future__ import annotations

import torch
from torch import Tensor

#: (shape, dtype, device) -> the zeros :func:`kept_zeros` made for them, only ever read
_KEPT: dict[tuple[tuple[int, ...], torch.dtype, torch.device], Tensor] = {}


def kept_zeros(like: Tensor, shape: tuple[int, ...] = ()) -> Tensor:
    """Zeros of ``shape`` (default ``()``: a 0-dim zero) in ``like``'s dtype and device, made at the first
    call for that (shape, dtype, device) and the same tensor at every later call (no kernel, no allocation).

    The tensor is shared by every caller: read it, or return views of it that are only read (e.g.
    ``with_known_gradient(..., own_value=True)``'s result, or ``unbind()``'s values to log), never write
    into it or into a view of it. It does not require grad, and lives as long as the process (a few bytes
    per key)."""
    key = (tuple(shape), like.dtype, like.device)
    zeros = _KEPT.get(key)
    if zeros is None:
        zeros = _KEPT[key] = torch.zeros(shape, dtype=like.dtype, device=like.device)
    return zeros
