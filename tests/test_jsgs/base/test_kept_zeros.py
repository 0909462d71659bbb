"""jsgs.base.kept_zeros: one zero tensor per (shape, dtype, device), the same object at every call."""

from __future__ import annotations

import torch

from jsgs.base.kept_zeros import kept_zeros


def test_one_zero_per_shape_dtype_and_device_returned_again() -> None:
    f32, f64 = torch.ones(2, 3), torch.ones(4, dtype=torch.float64)
    z = kept_zeros(f32)
    assert z.shape == () and z.dtype == torch.float32 and z.device == f32.device and z.item() == 0.0
    assert not z.requires_grad
    assert kept_zeros(torch.rand(7)) is z  # any tensor of that dtype and device: the same zero
    z64 = kept_zeros(f64)
    assert z64 is not z and z64.dtype == torch.float64 and z64.item() == 0.0
    v = kept_zeros(f32, (5,))
    assert v is not z and v.shape == (5,) and v.dtype == torch.float32 and torch.equal(v, torch.zeros(5))
    assert kept_zeros(f32, (5,)) is v and kept_zeros(f64, (5,)) is not v
    assert kept_zeros(f32.requires_grad_(), (5,)) is v  # made without grad, whatever ``like`` needs

