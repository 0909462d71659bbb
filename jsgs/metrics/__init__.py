"""Evaluation metrics: PSNR, SSIM and LPIPS-alex v0.1 of rendered test views against their references.

``evaluate_images(pred, ref)`` is what the trainer calls at each evaluation step. Per-image metrics:
``jsgs.metrics.psnr.psnr`` and ``jsgs.metrics.lpips.lpips`` (see their modules for conventions; SSIM is
``jsgs.kernels.ssim``). The package does not re-export the function ``lpips``: that name is the submodule's.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from jsgs.metrics import lpips as _lpips
from jsgs.metrics.lpips import LpipsAlex, load_lpips
from jsgs.metrics.psnr import psnr

__all__ = ["ImageMetrics", "LpipsAlex", "evaluate_images", "load_lpips", "psnr"]


@dataclass
class ImageMetrics:
    """Means over the evaluated views, and the per-view values they came from.

    ``psnr`` in dB (may be +inf if every view is exact), ``ssim`` dimensionless in [-1, 1], ``lpips``
    dimensionless (None when LPIPS could not be computed: no backbone weights, or images under 31 px).
    """

    psnr: float
    ssim: float
    lpips: float | None
    per_view: list[dict[str, float | None]] = field(default_factory=list)
    lpips_note: str | None = None  # why ``lpips`` is None, when it is

    def as_dict(self) -> dict[str, float | None]:
        """``{"psnr", "ssim", "lpips"}`` means (for a metrics file)."""
        return {"psnr": self.psnr, "ssim": self.ssim, "lpips": self.lpips}


ImageInput = Tensor | Sequence[Tensor]


def _views(images: ImageInput, name: str) -> list[Tensor]:
    if isinstance(images, Tensor):
        if images.dim() == 3:
            return [images]
        if images.dim() != 4:
            raise ValueError(f"{name}: expected N x 3 x H x W, got shape {tuple(images.shape)}")
        return list(images)
    return list(images)


def evaluate_images(
    pred: ImageInput,
    ref: ImageInput,
    *,
    lpips_weights: str | os.PathLike[str] | None = None,
    with_lpips: bool = True,
) -> ImageMetrics:
    """PSNR, SSIM and LPIPS-alex of rendered views against their references, each averaged over the views.

    pred, ref: N x 3 x H x W tensors, or equal-length sequences of 3 x H x W tensors (views may differ in
    size; each pred matches its ref). Channel-first, RGB, values in [0, 1]: renders (channels-last from the
    rasterizer) must be permuted by the caller. ``pred`` is clamped to [0, 1] first, as gsplat's
    simple_trainer does before its metrics; ``ref`` must already lie in [0, 1].

    SSIM is ``jsgs.kernels.ssim`` (11x11 Gaussian window, sigma 1.5) per view. LPIPS uses the backbone named
    by ``lpips_weights`` or ``$JSGS_LPIPS_WEIGHTS`` on pred's device; when none is available, or a view is
    smaller than 31 px, ``lpips`` is None and a warning says why (once per process). ``with_lpips=False``
    skips it silently. No gradients are recorded.
    """
    from jsgs.kernels import ssim

    preds, refs = _views(pred, "pred"), _views(ref, "ref")
    if len(preds) != len(refs) or not preds:
        raise ValueError(f"evaluate_images: {len(preds)} predictions for {len(refs)} references")
    model: _lpips.LpipsAlex | None = None
    note: str | None = None
    if with_lpips:
        model = _lpips.load_lpips(lpips_weights, device=preds[0].device)
        if model is None:
            note = _lpips.UNAVAILABLE_MESSAGE
        elif min(min(p.shape[-2:]) for p in preds) < _lpips.MIN_SIDE:
            note = f"LPIPS not computed: LPIPS-alex needs views of at least {_lpips.MIN_SIDE} px a side"
            _lpips.warn_once(note)
            model = None
    else:
        note = "LPIPS not requested"

    per_view: list[dict[str, float | None]] = []
    with torch.no_grad():
        for i, (p, r) in enumerate(zip(preds, refs, strict=True)):
            if p.dim() != 3 or p.shape[0] != 3 or p.shape != r.shape:
                raise ValueError(
                    f"evaluate_images: view {i}: expected matching 3 x H x W images, got "
                    f"{tuple(p.shape)} and {tuple(r.shape)}"
                )
            if float(r.min()) < 0.0 or float(r.max()) > 1.0:
                raise ValueError(f"evaluate_images: view {i}: reference values outside [0, 1]")
            p = p.clamp(0.0, 1.0).unsqueeze(0)
            r = r.to(p.device, p.dtype).unsqueeze(0)
            row: dict[str, float | None] = {
                "psnr": float(psnr(p, r)[0]),
                "ssim": float(ssim(p, r)),
                "lpips": float(model(p * 2 - 1, r * 2 - 1)[0]) if model is not None else None,  # type: ignore[index]
            }
            per_view.append(row)

    def mean(key: str) -> float:
        return math.fsum(float(v[key]) for v in per_view) / len(per_view)  # type: ignore[arg-type]

    return ImageMetrics(
        psnr=mean("psnr"),
        ssim=mean("ssim"),
        lpips=mean("lpips") if model is not None else None,
        per_view=per_view,
        lpips_note=note,
    )
