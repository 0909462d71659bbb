"""The loader of jsgs's own CUDA kernels (``jsgs/kernels/csrc``): the fused SSIM and the fused Gaussian
Controller, one Python module built on first use with ``torch.utils.cpp_extension`` (nvcc; about a minute,
then cached by torch in ``$TORCH_EXTENSIONS_DIR``). Each kernel has a torch twin in
:mod:`jsgs.kernels._torch_impl` that runs anywhere and is its reference in the tests.

Where the module cannot be built (no nvcc, a CPU-only torch) the callers use the twins, after one line on
stderr.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path
from typing import Any

import torch

#: the values of a setting that picks a kernel or its twin (speed.ssim_kernel, method_options.speed.gc_kernel)
KERNEL_CHOICES = ("auto", "torch", "cuda")
_SOURCES = ("bindings.cpp", "ssim.cu", "controller.cu")
_CSRC = Path(__file__).parent / "csrc"


@functools.cache
def _build() -> tuple[Any, str | None]:
    try:
        from torch.utils.cpp_extension import load

        module = load(
            name="jsgs_cuda",
            sources=[str(_CSRC / s) for s in _SOURCES],
            extra_cuda_cflags=["-O3"],
            verbose=False,
        )
    except Exception as e:  # no nvcc, no host compiler, a CPU-only torch: the twins compute the same
        return None, " ".join(str(e).split())[:300] or type(e).__name__
    return module, None


_warned: list[bool] = []


def extension(warn: bool = True) -> Any | None:
    """The compiled module (functions ``ssim_forward``, ``ssim_backward``, ``controller_forward``), or None
    where it cannot be built (with ``warn``, one stderr line the first time)."""
    module, err = _build()
    if err is not None and warn and not _warned:
        _warned.append(True)
        print(f"warning: building jsgs's CUDA kernels failed ({err}); using their torch twins",
              file=sys.stderr)
    return module


def build_error() -> str | None:
    """Why :func:`extension` is None (None when it built)."""
    return _build()[1]


def use_kernels(choice: str, device: torch.device, setting: str) -> bool:
    """Whether a setting ``choice`` ("auto", "torch" or "cuda"; named ``setting`` in messages) runs the CUDA
    kernels on ``device``: builds them now if it does (so neither the build nor its failure lands inside
    timed training steps); JsgsError (one line) for "cuda" where they cannot run."""
    from jsgs.base.errors import JsgsError

    if choice == "torch":
        return False
    if device.type != "cuda":
        if choice == "cuda":
            raise JsgsError(f"config: {setting} cuda needs a CUDA device (training on {device.type})")
        return False
    if extension(warn=choice == "auto") is None:
        if choice == "cuda":
            raise JsgsError(f"config: {setting} cuda: the kernels cannot be built ({build_error()})")
        return False
    return True
