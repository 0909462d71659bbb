"""Full float32 arithmetic for convolutions on CUDA.

cuDNN uses TF32 (10-bit mantissa) for float32 convolutions on Ampere and later GPUs unless told otherwise.
That is fine for a network's weights but not for metrics and losses that subtract nearly equal blurred
moments (SSIM's E[x²] − μ²) or that must reproduce published values (LPIPS moved by up to ~5e-5 on an
H100). Every convolution of ours runs inside :func:`ieee_fp32`.
"""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext

import torch


def ieee_fp32(device: torch.device) -> AbstractContextManager[object]:
    """Context: cuDNN convolutions without TF32 on CUDA (a no-op elsewhere); the caller's settings are
    restored on exit."""
    if device.type != "cuda" or torch.compiler.is_compiling():
        # inside torch.compile the global setting holds (the trainer turns TF32 off for the whole run)
        return nullcontext()
    c = torch.backends.cudnn
    return c.flags(enabled=c.enabled, benchmark=c.benchmark, deterministic=c.deterministic, allow_tf32=False)
