"""The JSGS image terms (JO, L_obs, DS) replayed as CUDA graphs: ``method_options.cuda_graph``.

At training sizes these terms are a few hundred small kernels per step, forward and backward, and on a GPU
each one costs more to launch than to run (``benchmarks/bench_kernel_count.py``). A CUDA graph records them
once per image size and replays the whole forward, and the whole backward, as one launch each. The arithmetic
is the eager code's, kernel for kernel, so values and gradients are those of the eager path
(``tests/test_graphed.py``, GPU only).

The chain itself is :func:`jpeg_terms` (the eager hook runs it too); what is recorded is
:func:`image_terms`, its tensors-only form, a pure function of tensors: the render and target of one view, its
tables (inputs, so every view replays the same graph with its own), with the JO mode, sampling, weights'
switches and epsilons fixed per graph. One graph per (image shape, dtype, sampling); the scenes we train have
one image size. Graphs need static shapes and no host synchronisation, which the JPEG code guarantees (see
``jsgs.jpeg.observe``); they are CUDA-only. Should a recording fail all the same
(:class:`GraphCaptureFailed`), the hook says so in one line and runs the eager chain for the rest of the run.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from functools import partial
from typing import Any

import torch
from torch import Tensor

from jsgs.errors import one_line
from jsgs.jpeg.losses import photometric_loss
from jsgs.jpeg.observe import jpeg_observe
from jsgs.jpeg.supervision import DctSupervision, dct_supervision


def jpeg_terms(
    x: Tensor,
    y: Tensor,
    luma: Tensor,
    chroma: Tensor,
    *,
    sampling: str,
    mode: str,
    ssim_lambda: float,
    ssim_padding: str,
    ds: bool,
    gc: bool,
    eps_sm: float,
    eps_loss: float,
    eps_block: float,
    observe: Callable[..., Tensor] = jpeg_observe,
    photometric: Callable[..., Tensor] = photometric_loss,
    supervise: Callable[..., DctSupervision] = dct_supervision,
    phase: Callable[[str], AbstractContextManager[Any]] = lambda name: nullcontext(),
) -> tuple[Tensor, Tensor, DctSupervision | None]:
    """JO, L_obs and DS for one view: the one home of that chain, for the eager hook and for the graph.

    Args:
        x: ``(1, 3, H, W)`` the rendering; y: ``(1, 3, H, W)`` the decoded training JPEG, in [0, 1].
        luma, chroma: ``(8, 8)`` the view's tables. The settings: as
            :class:`jsgs.train.jsgs_method.JsgsOptions`.
        observe, photometric, supervise: the three functions (the hook passes torch.compile'd ones);
        phase: a profiler's ``phase(name)`` context ("jo" around JO and L_obs, "ds" around DS).
    Returns:
        The observation ``(1, 3, H, W)``, L_obs (0-dim) and the DS terms (None without DS and GC; with GC
        alone they are computed on the detached observation, so no graph runs through DS).
    """
    with phase("jo"):
        obs = observe(x, luma, chroma, sampling, mode)
        l_obs = photometric(obs, y, ssim_lambda, padding=ssim_padding)
    if not (ds or gc):
        return obs, l_obs, None
    with phase("ds"):
        sup = supervise(obs if ds else obs.detach(), y, luma, eps_sm, eps_loss, eps_block)
    return obs, l_obs, sup


def image_terms(
    x: Tensor, y: Tensor, luma: Tensor, chroma: Tensor, **settings: Any
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """:func:`jpeg_terms` as tensors only (what a CUDA graph can return): L_obs, L_low, L_mid (0-dim; the DS
    terms 0 without DS), r(p) ``(1, H, W)`` detached (0 without DS and GC) and the observation, detached."""
    obs, l_obs, sup = jpeg_terms(x, y, luma, chroma, **settings)
    zero = l_obs.new_zeros(())
    if sup is None:
        return l_obs, zero, zero, y.new_zeros(y.shape[0], *y.shape[2:]), obs.detach()
    low, mid = (sup.loss_low.sum(), sup.loss_mid.sum()) if settings["ds"] else (zero, zero)
    return l_obs, low, mid, sup.pixel_score, obs.detach()


class GraphCaptureFailed(RuntimeError):
    """Recording a graph failed (the message says why); the caller runs the eager chain instead."""


class GraphedImageTerms:
    """:func:`image_terms` through ``torch.cuda.make_graphed_callables``, one graph per (shape, dtype,
    sampling), recorded on first use (three eager warm-up passes, then the capture)."""

    def __init__(self, **settings: Any) -> None:
        self.settings = settings
        self._graphs: dict[tuple[Any, ...], Any] = {}

    @staticmethod
    def _check_device(x: Tensor) -> None:
        if x.device.type != "cuda":
            raise ValueError("CUDA graphs need CUDA tensors")

    def __call__(
        self, x: Tensor, y: Tensor, luma: Tensor, chroma: Tensor, sampling: str
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        key = (tuple(x.shape), x.dtype, sampling)
        fn = self._graphs.get(key)
        if fn is None:
            self._check_device(x)
            # the graph's own input buffers: replays copy each call's tensors into them
            sample = (
                x.detach().clone().requires_grad_(x.requires_grad),
                y.clone(),
                luma.clone(),
                chroma.clone(),
            )
            try:
                fn = torch.cuda.make_graphed_callables(
                    partial(image_terms, sampling=sampling, **self.settings), sample, allow_unused_input=True
                )
            except RuntimeError as e:  # e.g. an op that synchronises with the host, refused while capturing
                raise GraphCaptureFailed(one_line(e)) from e
            self._graphs[key] = fn
        l_obs, low, mid, r, obs = fn(x, y, luma, chroma)
        # the outputs live in the graph's static memory, overwritten by the next replay; the scalars are
        # kept by the trainer (logging), so they are copied, and so is r(p), which the GC's probe reads
        return l_obs.clone(), low.clone(), mid.clone(), r.clone(), obs
