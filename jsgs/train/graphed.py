"""The JSGS image terms (JO, L_obs, DS) replayed as CUDA graphs: ``method_options.cuda_graph``.

At training sizes these terms are a few hundred small kernels per step, forward and backward, and on a GPU
each one costs more to launch than to run (``benchmarks/bench_kernel_count.py``). A CUDA graph records them
once per image size and replays the whole forward, and the whole backward, as one launch each. The arithmetic
is the eager code's, kernel for kernel, so values and gradients are those of the eager path
(``tests/test_graphed.py``, GPU only).

What is recorded is :func:`image_terms`, a pure function of tensors: the render and target of one view, its
tables (inputs, so every view replays the same graph with its own), with the JO mode, sampling, weights'
switches and epsilons fixed per graph. One graph per (image shape, dtype, sampling); the scenes we train have
one image size. Graphs need static shapes and no host synchronisation, which the JPEG code guarantees (see
``jsgs.jpeg.observe``); they are CUDA-only.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import torch
from torch import Tensor

from jsgs.jpeg.losses import photometric_loss
from jsgs.jpeg.observe import jpeg_observe
from jsgs.jpeg.supervision import dct_supervision


def image_terms(
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
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """L_obs, L_low, L_mid, r(p) and the observation for one view.

    Args:
        x: ``(1, 3, H, W)`` the rendering; y: ``(1, 3, H, W)`` the decoded training JPEG, in [0, 1].
        luma, chroma: ``(8, 8)`` the view's tables. The rest: as :class:`jsgs.train.jsgs_method.JsgsOptions`.
    Returns:
        ``(L_obs, L_low, L_mid)`` 0-dim (L_low and L_mid are 0 without DS), r(p) ``(1, H, W)`` detached (0
        without DS and GC), and the observation ``(1, 3, H, W)`` detached.
    """
    obs = jpeg_observe(x, luma, chroma, sampling, mode)
    l_obs = photometric_loss(obs, y, ssim_lambda, padding=ssim_padding)
    zero = l_obs.new_zeros(())
    if not (ds or gc):
        return l_obs, zero, zero, y.new_zeros(y.shape[0], *y.shape[2:]), obs.detach()
    # GC alone needs only the (stop-gradient) block scores: no graph through DS then
    sup = dct_supervision(obs if ds else obs.detach(), y, luma, eps_sm, eps_loss, eps_block)
    low, mid = (sup.loss_low.sum(), sup.loss_mid.sum()) if ds else (zero, zero)
    return l_obs, low, mid, sup.pixel_score, obs.detach()


class GraphedImageTerms:
    """:func:`image_terms` through ``torch.cuda.make_graphed_callables``, one graph per (shape, dtype,
    sampling), recorded on first use (three eager warm-up passes, then the capture)."""

    def __init__(self, **settings: Any) -> None:
        self.settings = settings
        self._graphs: dict[tuple[Any, ...], Any] = {}

    def __call__(
        self, x: Tensor, y: Tensor, luma: Tensor, chroma: Tensor, sampling: str
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        key = (tuple(x.shape), x.dtype, sampling)
        fn = self._graphs.get(key)
        if fn is None:
            if x.device.type != "cuda":
                raise ValueError("CUDA graphs need CUDA tensors")
            # the graph's own input buffers: replays copy each call's tensors into them
            sample = (
                x.detach().clone().requires_grad_(x.requires_grad),
                y.clone(),
                luma.clone(),
                chroma.clone(),
            )
            fn = torch.cuda.make_graphed_callables(
                partial(image_terms, sampling=sampling, **self.settings), sample, allow_unused_input=True
            )
            self._graphs[key] = fn
        l_obs, low, mid, r, obs = fn(x, y, luma, chroma)
        # the outputs live in the graph's static memory, overwritten by the next replay; the scalars are
        # kept by the trainer (logging), so they are copied, and so is r(p), which the GC's probe reads
        return l_obs.clone(), low.clone(), mid.clone(), r.clone(), obs
