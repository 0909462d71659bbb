"""The JO -> L_obs -> DS chain of one view (paper eqs. obs_loss, jsgs_dct_losses) and what it needs: the
views' JPEG tables on the training device, the chain's settings, and its optional ``torch.compile``.

:func:`jpeg_terms` is the one home of the chain, for the eager hook and for the CUDA graph
(:mod:`jsgs.method.graphed`); :func:`image_terms` is its tensors-only form and :func:`terms_with_gradient`
what a graph records (the terms and the gradient of their weighted sum).
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from jsgs.base.errors import JsgsError, one_line
from jsgs.jpeg.losses import photometric_loss
from jsgs.jpeg.observe import jpeg_observe
from jsgs.jpeg.supervision import DctSupervision, TableWeights, dct_supervision, table_weights
from jsgs.jpeg.tables import SAMPLING_FACTORS
from jsgs.kernels import ssim_is_fused
from jsgs.train.data import image_target

if TYPE_CHECKING:
    from jsgs.method.options import JsgsOptions
    from jsgs.train.data import TrainingView

SUPPORTED_SAMPLING = tuple(SAMPLING_FACTORS)


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
    ssim_kernel: str = "auto",
    ssim_fused: bool | None = None,
    jo_kernel: str = "torch",
    color_kernel: str = "torch",
    ds: bool,
    gc: bool,
    eps_sm: float,
    eps_loss: float,
    eps_block: float,
    observe: Callable[..., Tensor] = jpeg_observe,
    photometric: Callable[..., Tensor] = photometric_loss,
    supervise: Callable[..., DctSupervision] = dct_supervision,
    phase: Callable[[str], AbstractContextManager[Any]] = lambda name: nullcontext(),
    first: Tensor | None = None,
    ds_weights: TableWeights | None = None,
    score_map: bool = True,
) -> tuple[Tensor, Tensor, DctSupervision | None]:
    """JO, L_obs and DS for one view: the one home of that chain, for the eager hook and for the graph.

    Args:
        x: ``(1, 3, H, W)`` the rendering; y: ``(1, 3, H, W)`` the decoded training JPEG, in [0, 1].
        luma, chroma: ``(8, 8)`` the view's tables. The settings: as
            :class:`jsgs.method.options.JsgsOptions`; ``jo_kernel``: JO's and DS's ``kernel`` ("torch" or
            "triton": :func:`jsgs.jpeg.observe.jpeg_observe`, :func:`jsgs.jpeg.supervision.dct_supervision`);
            ``color_kernel``: JO's ``color_kernel`` ("torch" or "triton"); ``ssim_fused``: L_obs's SSIM
            kernel where the caller has picked it (``photometric``'s ``ssim_fused``; None: L_obs picks).
        observe, photometric, supervise: the three functions (the hook passes torch.compile'd ones);
        phase: a profiler's ``phase(name)`` context ("jo" around JO and L_obs, "ds" around DS);
        first: ``(2, 8, 8)`` effective tables of a view compressed twice: JO quantizes with them first, then
            with ``luma``/``chroma`` (the file's history), and DS weights by their luma.
        ds_weights: DS's weights of the table it weights by (:attr:`ViewJpeg.ds_weights`), made once per
            view; None: DS makes them.
        score_map: DS makes r(p) (``DctSupervision.pixel_score``); False: only r_b.
    Returns:
        The observation ``(1, 3, H, W)``, L_obs (0-dim) and the DS terms (None without DS and GC; with GC
        alone they are computed on the detached observation, so no graph runs through DS).
    """
    # the default colour kernel is not passed: observe functions without that argument (tests') still work
    kernels = {"kernel": jo_kernel} | ({"color_kernel": color_kernel} if color_kernel != "torch" else {})
    with phase("jo"):
        if first is not None:
            x = observe(x, first[0], first[1], sampling, mode, **kernels)
        obs = observe(x, luma, chroma, sampling, mode, **kernels)
        # the pick passed only where made: photometric functions without that argument (tests') still work
        fused = {} if ssim_fused is None else {"ssim_fused": ssim_fused}
        l_obs = photometric(obs, y, ssim_lambda, padding=ssim_padding, ssim_kernel=ssim_kernel, **fused)
    if not (ds or gc):
        return obs, l_obs, None
    with phase("ds"):
        ds_table = first[0] if first is not None else luma
        sup = supervise(
            obs if ds else obs.detach(), y, ds_table, eps_sm, eps_loss, eps_block, ds_weights,
            kernel=jo_kernel, **({} if score_map else {"score_map": False}),
        )  # fmt: skip
    return obs, l_obs, sup


def image_terms(
    x: Tensor, y: Tensor, luma: Tensor, chroma: Tensor, blocks: bool = False, **settings: Any
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """:func:`jpeg_terms` as tensors only (what a CUDA graph can return): L_obs, L_low, L_mid (0-dim; the DS
    terms 0 without DS), r(p) ``(1, H, W)`` detached (0 without DS and GC) and the observation, detached.
    ``blocks``: the block scores r_b ``(1, H // 8, W // 8)`` instead of r(p) (r(p) is r_b on each block's
    pixels), so that no map of the image's size outlives the forward."""
    obs, l_obs, sup = jpeg_terms(x, y, luma, chroma, score_map=not blocks, **settings)
    zero = l_obs.new_zeros(())
    if sup is None:
        r_shape = (x.shape[2] // 8, x.shape[3] // 8) if blocks else tuple(y.shape[2:])
        return l_obs, zero, zero, y.new_zeros(y.shape[0], *r_shape), obs.detach()
    low, mid = (sup.loss_low.sum(), sup.loss_mid.sum()) if settings["ds"] else (zero, zero)
    return l_obs, low, mid, sup.block_score.detach() if blocks else sup.pixel_score, obs.detach()




def terms_with_gradient(
    x: Tensor,
    y: Tensor,
    tables: Tensor,
    *,
    weights: tuple[float, float, float],
    observation: bool = True,
    grad_into_x: bool = False,
    r_into: Tensor | None = None,
    r_blocks: bool = False,
    y_index: Tensor | None = None,
    **settings: Any,
) -> tuple[Tensor, Tensor | None, Tensor, Tensor | None]:
    """:func:`image_terms` and the gradient of their weighted sum, in one pass (what the graph records).

    Args:
        x: ``(1, 3, H, W)`` the render (a leaf; needs grad for the gradient).
        y: ``(1, 3, H, W)`` the target, or ``(H, W, 3)`` uint8 the training image it is made from
            (converted here as the trainer does, :func:`jsgs.train.data.image_target`: the same values; a
            graph then keeps 3 bytes a pixel for its target buffer instead of 12).
        tables: ``(2, 8, 8)`` the view's luma and chroma tables.
        weights: (λ_obs, λ_low, λ_mid), the last two 0 without DS.
        observation: whether to return the observation (a graph's output buffer for the rest of the run;
            only ``keep_last`` reads it).
        grad_into_x: write the gradient over ``x`` and return ``x`` (detached) as the gradient: a graph's
            render buffer, read by the chain before, then holds the gradient, so the graph keeps no second
            buffer of the render's size for it (the caller copies the next render in before each replay).
        r_into: where given, r(p) (or r_b) is written into it and it is returned (a graph's buffer, shared
            with the graphs of other image shapes of as many pixels).
        y_index: ``(1,)`` int64 on ``y``'s device, where given: ``y`` is a ``(V, H, W, 3)`` uint8 stack of
            training images and the image is ``y[y_index]`` (a graph reads it from the trainer's stack).
        r_blocks: return the block scores r_b ``(1, H // 8, W // 8)`` instead of r(p) (which is r_b on each
            block's pixels, 0 on the rest: :func:`jsgs.jpeg.supervision.pixel_score_of`), 1/64 of its size.
        settings: :func:`jpeg_terms`'s, with ``sampling``.
    Returns:
        values ``(4,)`` (the weighted sum, L_obs, L_low, L_mid), its gradient with respect to ``x`` (None when
        ``x`` needs none), r(p) ``(1, H, W)`` (r_b with ``r_blocks``) and the observation ``(1, 3, H, W)``
        (None without ``observation``), all detached. The values do not depend on ``observation``.
    """
    if y_index is not None:
        y = y.index_select(0, y_index)[0]
    if y.dtype == torch.uint8:
        y = image_target(y).permute(0, 3, 1, 2)
        # L_obs's SSIM kernel, picked once: the observation has the render's dtype, shape and device, so the
        # pick on the render is L_obs's, handed to it rather than made there again
        fused = ssim_is_fused(x, y, settings.get("ssim_kernel", "auto"))
        settings = {**settings, "ssim_fused": fused}
        if fused:
            # laid out as the fused SSIM keeps it (L_obs's L1 keeps that copy too, DS reads it as it lies):
            # the one copy of the target, not a second beside it through the forward
            y = y.contiguous()
    l_obs, low, mid, r, obs = image_terms(x, y, tables[0], tables[1], blocks=r_blocks, **settings)
    # the target made here is not needed by the backward (the fused SSIM saved its own contiguous copy):
    # freed before it, not kept beside the backward's gradients
    del y
    w_obs, w_low, w_mid = weights
    total = w_obs * l_obs + w_low * low + w_mid * mid
    grad = torch.autograd.grad(total, x)[0] if x.requires_grad else None
    if grad is not None and grad_into_x:
        with torch.no_grad():
            x.copy_(grad)
        grad = x.detach()
    if r_into is not None:
        r_into.copy_(r)
        r = r_into
    values = torch.stack([total, l_obs, low, mid]).detach()
    return values, grad, r, obs if observation else None


def image_term_settings(
    options: JsgsOptions, ssim_lambda: float, ssim_padding: str, ssim_kernel: str, jo_kernel: str = "torch",
    color_kernel: str = "torch",
) -> dict[str, Any]:
    """The settings that fix the JO / L_obs / DS chain (:func:`jpeg_terms` and its graph): the method's
    options plus the trainer's photometric-loss settings (``loss.ssim_lambda``, ``loss.ssim_padding``,
    ``speed.ssim_kernel``) and JO's kernels (``method_options.speed.fused_jo`` and ``fused_color``
    resolved: "torch" or "triton")."""
    return dict(
        mode=options.jpeg_mode, ssim_lambda=ssim_lambda, ssim_padding=ssim_padding, ssim_kernel=ssim_kernel,
        jo_kernel=jo_kernel, color_kernel=color_kernel,
        ds=options.ds, gc=options.gc, eps_sm=options.eps_sm, eps_loss=options.eps_dct_loss,
        eps_block=options.eps_dct_block,
    )  # fmt: skip


@dataclass
class ViewJpeg:
    """A training view's JPEG state (the manifest's :class:`jsgs.base.manifest.JpegState`) as the method uses
    it, on the training device: ``tables`` [2, 8, 8] float32 (luma, chroma; one tensor so that a graph
    replay copies them in once), natural order [v, u]."""

    tables: Tensor
    sampling: str
    #: σ² of the view's quantisation noise (8-bit units²): the tables' bound
    #: (:func:`quantization_noise_variance`) or the estimate from the file (:func:`jsgs.jpeg.noise`)
    noise_variance: float = 0.0
    #: blockiness of the decoded luma (:func:`jsgs.jpeg.noise.blockiness`; 1 where not measured)
    blockiness: float = 1.0
    #: ``method_options.tables: effective`` on a view compressed twice: [2, 8, 8] the effective tables (the
    #: coarser of the earlier and the header's step per coefficient), quantized with before ``tables``; DS
    #: weights by their luma. None: one quantization with ``tables``.
    first: Tensor | None = None
    #: DS's weights of the luma table it weights by (``first``'s where set, else ``tables``'s), float32 on
    #: the tables' device: fixed for the run, so made once here instead of in every step
    ds_weights: TableWeights | None = None

    def __post_init__(self) -> None:
        if self.ds_weights is None:
            ds_table = self.first[0] if self.first is not None else self.tables[0]
            self.ds_weights = table_weights(ds_table, 1, torch.float32, self.tables.device)

    @property
    def luma(self) -> Tensor:
        return self.tables[0]

    @property
    def chroma(self) -> Tensor:
        return self.tables[1]


def base_weight(opts: JsgsOptions, tab: ViewJpeg, step: int | None = None) -> float:
    """The multiplier on λ_base (ℓ_ph's weight) for a JPEG view: 1, or with ``base_by_view``
    w = 1 / (1 + (σ² / σ_ref²)^k) (k = 1: σ_ref² / (σ_ref² + σ²)), times 1 / (1 + (max(B − 1, 0) / b)^k)
    with ``base_block_ref`` b > 0 (B the view's blockiness); at 0-based ``step`` < ``base_ramp_steps`` T it
    is w + (1 − w)(1 − step / T), so the weight falls from 1 at step 0 to w at step T. ``step`` None: w."""
    if not opts.base_by_view:
        return 1.0
    w = 1.0 / (1.0 + (tab.noise_variance / opts.base_noise_ref**2) ** opts.base_noise_exponent)
    if opts.base_block_ref:
        w /= 1.0 + (max(tab.blockiness - 1.0, 0.0) / opts.base_block_ref) ** opts.base_noise_exponent
    ramp = opts.base_ramp_steps
    if step is not None and step < ramp:
        w += (1.0 - w) * (1.0 - step / ramp)
    return w


def quantization_noise_variance(luma: np.ndarray, chroma: np.ndarray) -> float:
    """Per-pixel variance (8-bit units²) of the noise that quantising with these tables adds, averaged over
    Y, Cb and Cr: a uniform quantiser of step Q adds variance Q²/12 to a coefficient, and the orthonormal
    8×8 DCT carries the mean over the 64 coefficients to the pixels. An upper bound (coefficients smaller
    than their step lose less than Q²/12), monotone in the tables: IJG's q = 90 tables give about 23,
    q = 50 about 580, q = 10 about 4,500."""
    qy = np.asarray(luma, dtype=np.float64)
    qc = np.asarray(chroma, dtype=np.float64)
    return float((np.mean(qy**2) + 2.0 * np.mean(qc**2)) / 36.0)


def view_tables(
    views: list[TrainingView],
    device: torch.device,
    where: str,
    tables: str = "header",
    noise: str = "tables",
    blocks: bool = False,
) -> dict[int, ViewJpeg]:
    """view index -> its tables and sampling for every JPEG training view. JsgsError naming the view when
    JO cannot represent its JPEG state (greyscale, a Cr table of its own, or a chroma sampling JO does not
    model: ``jsgs.jpeg.tables.SAMPLING_FACTORS``).
    ``tables`` effective: views the manifest's analysis finds compressed twice also get ``first`` (their
    effective tables); a JPEG view without an analysis is a JsgsError. ``noise``: how ``noise_variance`` is
    found, ``tables`` (the bound) or ``pixels`` (the estimate ``manifest --analyze`` recorded, made with the
    effective tables, else estimated here from the decoded file with the tables JO uses). ``blocks``: also
    take each view's ``blockiness`` from the analysis, else measure it from its decoded file."""
    checked: list[tuple[TrainingView, Tensor, Tensor | None, np.ndarray]] = []
    for v in views:
        j = v.jpeg
        if j is None:
            continue
        if j.color_space not in (None, "YCbCr", "gray"):
            raise JsgsError(
                f"{where}: view {v.name!r} is a {j.color_space} JPEG; the JPEG observation operator models "
                "YCbCr JPEGs only (train it with --method gsplat, or re-encode it as a YCbCr JPEG)"
            )
        if j.chroma_table is None or j.sampling == "gray":
            raise JsgsError(
                f"{where}: view {v.name!r} is a greyscale JPEG; the JPEG observation operator handles colour "
                "JPEGs only (train it with --method gsplat or --no-jo --no-ds --no-gc)"
            )
        if j.cr_table is not None:
            raise JsgsError(
                f"{where}: view {v.name!r} quantizes Cr with a table of its own (not Cb's); the JPEG "
                "observation operator takes one chroma table (train it with --method gsplat, or re-encode it)"
            )
        if j.sampling not in SUPPORTED_SAMPLING:
            raise JsgsError(
                f"{where}: view {v.name!r} has chroma sampling {j.sampling}; the JPEG observation operator "
                f"supports {', '.join(SUPPORTED_SAMPLING)} (re-encode it, or train with --method gsplat)"
            )
        header = torch.as_tensor(np.stack([np.asarray(j.luma_table), np.asarray(j.chroma_table)]))
        first = None
        if tables == "effective":
            if j.effective_luma_table is None:
                raise JsgsError(
                    f"{where}: view {v.name!r} has no compression analysis; method_options.tables effective "
                    "needs a manifest written with jsgstools manifest --analyze"
                )
            if j.double_compressed:
                ec = j.effective_chroma_table if j.effective_chroma_table is not None else j.chroma_table
                eff = np.stack([np.asarray(j.effective_luma_table), np.asarray(ec)])
                first = torch.as_tensor(eff).to(device, torch.float32).reshape(2, 8, 8)
        q = (first.cpu().numpy() if first is not None else header.numpy()).astype(np.float64)
        checked.append((v, header, first, q))
    # manifest --analyze's records (its estimate made with the effective tables) where present, else read from
    # the file: each file decoded once for whatever it lacks
    todo = []
    for v, _, _, q in checked:
        want_noise = noise == "pixels" and v.jpeg.noise_variance is None
        want_block = blocks and v.jpeg.blockiness is None
        if want_noise or want_block:
            todo.append((v, q if want_noise else None, want_block))
    measured = _from_files(todo)
    out: dict[int, ViewJpeg] = {}
    # views with equal tables share one tensor of them (only read): the graph copies a view's tables into
    # its input only where they are not the tensor it holds already (GraphedImageTerms)
    shared: dict[tuple[str, bytes], Tensor] = {}
    for v, header, first, q in checked:
        j = v.jpeg
        sigma2_read, b_read = measured.get(v.index, (None, None))
        if noise == "pixels":
            sigma2 = j.noise_variance if j.noise_variance is not None else sigma2_read
        else:
            sigma2 = quantization_noise_variance(q[0], q[1])
        b = (j.blockiness if j.blockiness is not None else b_read) if blocks else 1.0
        key = (str(header.dtype), header.numpy().tobytes())
        tab = shared.get(key)
        if tab is None:
            tab = shared[key] = header.to(device, torch.float32).reshape(2, 8, 8)
        out[v.index] = ViewJpeg(tab, j.sampling, sigma2, b, first)
    return out


#: estimating more views than this from their files says so on stderr first (it takes 0.1-0.7 s per photo)
ANNOUNCE_ESTIMATES = 16


def _from_files(
    todo: list[tuple[TrainingView, np.ndarray | None, bool]],
) -> dict[int, tuple[float | None, float | None]]:
    """view index -> (σ², B) read from its decoded file, for each ``(view, q, block)``: σ² estimated
    (:func:`jsgs.jpeg.noise.jpeg_noise_variance`) with the tables ``q`` ``(2, 8, 8)`` that JO uses, None
    where ``q`` is None; B the blockiness of its luma (:func:`jsgs.jpeg.noise.blockiness`) where ``block``,
    else None. Each file is decoded once; several files at once (decoding and numpy's block DCT release the
    GIL), one stderr line first when many noise estimates are due. JsgsError naming the view whose file
    cannot be read."""
    from concurrent.futures import ThreadPoolExecutor
    from os import cpu_count

    from jsgs.base.images import read_ycbcr8
    from jsgs.jpeg.noise import blockiness, jpeg_noise_variance

    estimates = sum(q is not None for _, q, _ in todo)
    if estimates > ANNOUNCE_ESTIMATES:
        print(f"estimating the quantisation noise of {estimates} JPEG views from their files "
              "(method_options.base_noise pixels) ...", file=sys.stderr, flush=True)  # fmt: skip

    def one(item: tuple[TrainingView, np.ndarray | None, bool]) -> tuple[float | None, float | None]:
        v, q, block = item
        assert v.jpeg is not None
        ycc = read_ycbcr8(v.image, f"view {v.name!r}")
        sigma2 = None if q is None else jpeg_noise_variance(ycc, q[0], q[1], v.jpeg.sampling)
        return sigma2, (blockiness(ycc[..., 0]) if block else None)

    if not todo:
        return {}
    with ThreadPoolExecutor(max(1, min(8, cpu_count() or 1, len(todo)))) as pool:
        return dict(zip((v.index for v, _, _ in todo), pool.map(one, todo), strict=True))


class CompiledOrEager:
    """``torch.compile(fn)`` that falls back to ``fn`` for the rest of the run when compilation fails.

    Compilation is an optimisation, not a result: an internal compiler error (torch 2.11's inductor fails on
    JO at 504x378 on CUDA: "ModularIndexing ... is not comparable") must not stop a training. It fails before
    anything runs, so the eager call computes the same step. One line on stderr says so, once."""

    def __init__(self, fn: Any, backend: str) -> None:
        self.fn = fn
        # dynamic=False: a scene has few image sizes; static shapes let inductor fuse the 8x8 block math
        self.compiled = torch.compile(fn, backend=backend, dynamic=False)
        self.backend = backend
        self.failure: str | None = None

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if self.failure is None:
            try:
                return self.compiled(*args, **kwargs)
            except torch._dynamo.exc.TorchDynamoException as e:
                self.failure = one_line(e)
                name = getattr(self.fn, "__name__", "fn")
                warn_eager_fallback(f"torch.compile ({self.backend}) of {name}", self.failure, "it")
        return self.fn(*args, **kwargs)


def warn_eager_fallback(what: str, reason: str, pronoun: str) -> None:
    """The one stderr line of a speed-up that failed and gave way to the eager code (same results)."""
    print(
        f"warning: {what} failed ({reason[:200]}); running {pronoun} eagerly for the rest of the run",
        file=sys.stderr,
    )


def maybe_compile(fn: Any, backend: str) -> Any:
    return fn if backend == "off" else CompiledOrEager(fn, backend)
