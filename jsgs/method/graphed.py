"""The JSGS image terms (JO, L_obs, DS) and the deferred Gaussian Controller replayed as CUDA graphs:
``method_options.speed.cuda_graph`` (and ``cuda_graph_gc`` for the GC's own graph,
:class:`GraphedController`).

At training sizes these terms are a few hundred small kernels per step, forward and backward, and on a GPU
each one costs more to launch than to run (``tools/diagnostics/bench_kernel_count.py``). A CUDA graph records
them
once per image size and replays them as one launch. The arithmetic is the eager code's, kernel for kernel,
so values and gradients are those of the eager path (``tests/test_jsgs/method/test_graphed.py``, GPU only).

The chain itself is :func:`jsgs.method.image_terms.jpeg_terms` (the eager hook runs it too); its tensors-only
form is :func:`~jsgs.method.image_terms.image_terms`, and what is recorded is
:func:`~jsgs.method.image_terms.terms_with_gradient`: the image terms *and* the gradient
of their weighted sum with respect to the render, in one graph, so the forward call is the only replay and
the trainer's backward merely scales the stored gradient (``jsgs.base.known_grad``). The inputs are the render
and target of one view and its tables (so every view replays the same graph with its own); the JO mode,
sampling, weights and epsilons are fixed per graph. One graph per (image shape, dtype, sampling); the scenes
we train have one image size. Graphs need static shapes and no host synchronisation, which the JPEG code
guarantees (see ``jsgs.jpeg.observe``); they are CUDA-only. Should a recording fail all the same
(:class:`GraphCaptureFailed`), the hook says so in one line and runs the eager chain for the rest of the run.

Every recording on a device, of either class, is made on one side stream per device (:func:`side_stream`),
created on first use and kept for the process. torch keeps a cuBLAS workspace per (handle, stream) until
``torch._C._cuda_clearCublasWorkspaces()``, so a new stream per recording (the controller records again at
every densification) would leave one more workspace behind each time.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any, NamedTuple

import torch
from torch import Tensor

from jsgs.base.errors import one_line
from jsgs.base.known_grad import with_known_gradient
from jsgs.method.image_terms import terms_with_gradient
from jsgs.train.data import stacked_image


class ImageTerms(NamedTuple):
    """What :class:`GraphedImageTerms` returns for one view.

    - ``weighted``: 0-dim, λ_obs·L_obs + λ_low·L_low + λ_mid·L_mid, differentiable with respect to the render
      (its gradient was computed in the same replay; the backward only scales it). Its value is the first
      of the four values the graph writes, of which ``values`` is the rest: a view, no copy of its own;
    - ``values``: ``(3,)`` L_obs, L_low, L_mid (0 without DS), detached. With ``copy_values`` (the default)
      they and ``weighted``'s value are a copy made for the caller, which later calls leave as it is; with
      ``copy_values`` off they are the graph's output buffer itself, valid only until the next call, whose
      replay overwrites them and ``weighted``'s value;
    - ``r``: ``(1, H // 8, W // 8)`` the block scores r_b, detached (0 without DS and GC); the block-score
      map r(p) is r_b on each block's pixels (:func:`jsgs.jpeg.supervision.pixel_score_of`);
    - ``obs``: ``(1, 3, H, W)`` the observation, detached; None unless the call asks for it.

    ``r`` and ``obs`` live in the graph's memory: valid until the next call (the step's backward included).
    """

    weighted: Tensor
    values: Tensor
    r: Tensor
    obs: Tensor | None


class GraphCaptureFailed(RuntimeError):
    """Recording a graph failed (the message says why); the caller runs the eager chain instead."""


_SIDE_STREAMS: dict[torch.device, Any] = {}


def side_stream(device: torch.device) -> Any:
    """The stream that every graph recording on ``device`` runs on: made once per device, then reused."""
    stream = _SIDE_STREAMS.get(device)
    if stream is None:
        stream = _SIDE_STREAMS[device] = torch.cuda.Stream(device)
    return stream


def record_graph(
    fn: Callable[[], Any], device: torch.device, *, warmups: int, pool: Any, error_mode: str
) -> tuple[Any, Any]:
    """``fn()`` recorded as a CUDA graph: ``(graph, outputs)``, the outputs living in the graph's memory.

    ``warmups`` eager calls first, on the same side stream as the capture (the device's :func:`side_stream`;
    lazy library and autograd-engine state is set up outside the capture); the capture goes into ``pool``
    (None: a new one) with torch's ``capture_error_mode`` ``error_mode`` ("thread_local" when recording
    from inside a backward, whose engine threads keep working). The caller's stream waits for the side
    stream before and after. GraphCaptureFailed (one line) where recording fails, e.g. on an op that
    synchronises with the host.
    """
    try:
        here = torch.cuda.current_stream(device)
        side = side_stream(device)
        side.wait_stream(here)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.stream(side):
            for _ in range(warmups):
                fn()
            graph.capture_begin(pool=pool, capture_error_mode=error_mode)
            try:
                outputs = fn()
            finally:
                graph.capture_end()
        here.wait_stream(side)
    except RuntimeError as e:
        raise GraphCaptureFailed(one_line(e)) from e
    return graph, outputs


@dataclass
class _Recording:
    """One recorded graph: its input buffers (the replay reads them) and outputs (the replay writes them)."""

    replay: Callable[[], None]
    inputs: tuple[Tensor, Tensor, Tensor]
    outputs: tuple[Tensor, Tensor | None, Tensor, Tensor | None]


class GraphedImageTerms:
    """:func:`terms_with_gradient` replayed as one CUDA graph per (shape, dtype, sampling, needs-grad,
    observation), recorded on first use: the forward of JO, L_obs and DS *and* the gradient of their weighted
    sum with respect to the render, in one launch. The trainer's backward then multiplies that stored
    gradient by its upstream scalar (:func:`jsgs.base.known_grad.with_known_gradient`): no second replay and
    no per-term output gradients to copy in.

    This is exact for the loss the trainer forms, Σ_k λ_k·term_k + the rest, because the weights are fixed
    for the run and the weighted sum enters the loss as one term (``HookOutput.folded_loss``). Each call
    copies the render, the target (or the image's index in the trainer's stack) and the tables into the
    graph's input buffers and the four values out.

    The observation is an output buffer only in the graphs of calls that ask for it (``observation``; the
    hook's ``keep_last``): the others leave it in the graph's private pool, 12 bytes a pixel less of memory
    kept for the run. Both kinds compute the same values, gradient and r_b. The gradient is written over
    the render's input buffer at the end of the replay (``grad_into_x``; the next call copies the next render
    in): no output buffer of its own, 12 bytes a pixel less. Given the uint8 training image
    instead of the target (the hook does where the trainer says which it is, ``StepContext.image``), the
    graph copies that in and makes the target inside: 3 bytes a pixel kept instead of 12, the same values.

    The graph keeps r(p) as its block scores r_b (one value per 8×8 block: 1/64 of r(p)'s 4 bytes a pixel;
    the hook makes r(p) from them where the controller reads it, the probe's map straight from them).
    Recordings of equal sizes share their buffers: the render's, the target's, the tables' and r_b's of
    one recording are views of this object's buffer of that many elements and dtype (:meth:`_buffer`), so
    the graphs of a scene whose views come in two orientations (W×H and H×W: one recording each) keep one
    set, 15 bytes a pixel instead of 30; r_b is written into its shared buffer inside the graph. Only one
    replay's results are valid at a time, whichever graph made them (valid until the next call).

    The recording's eager warm-up calls run on the device's side stream (:func:`record_graph`), and torch's
    caching allocator keeps the blocks a stream freed for that stream alone: with ``free_warmup`` (the
    hook's ``method_options.speed.cuda_graph_free_warmup``, true by default) each recording ends with
    ``torch.cuda.empty_cache()``, so that memory goes back to the device instead of staying reserved beside
    the graph's own pool for the rest of the run (one release per recording, none per step).
    """

    def __init__(
        self, *, weights: tuple[float, float, float], free_warmup: bool = True, **settings: Any
    ) -> None:
        self.weights = tuple(float(w) for w in weights)
        self.free_warmup = free_warmup
        self.settings = settings
        self._graphs: dict[tuple[Any, ...], _Recording] = {}
        self._pool: Any = None
        # (role, elements, dtype, device) -> the flat buffer that every recording's buffer of that role and
        # size views
        self._memory: dict[tuple[str, int, torch.dtype, torch.device], Tensor] = {}
        # a tables buffer's address -> the tables tensor last copied into it (views with equal tables share
        # one tensor, jsgs.method.image_terms.view_tables: consecutive such views copy nothing; the tables are
        # only read, never written, and the reference keeps the tensor from being replaced by another at the
        # same address)
        self._tables_held: dict[int, Tensor] = {}

    @staticmethod
    def _check_device(x: Tensor) -> None:
        if x.device.type != "cuda":
            raise ValueError("CUDA graphs need CUDA tensors")

    def __call__(
        self, x: Tensor, y: Tensor, tables: Tensor, sampling: str,
        more: Callable[[Tensor], tuple[Tensor, ...]] | None = None, observation: bool = False,
        copy_values: bool = True, unit_upstream: bool = False,
    ) -> ImageTerms:  # fmt: skip
        """``x``, ``y``: ``(1, 3, H, W)`` render and target; ``tables``: ``(2, 8, 8)`` luma and chroma;
        ``more``: called with r_b (``ImageTerms.r``) after the replay, further (tensor, gradient) pairs
        whose known gradients ride on ``weighted``'s node (:func:`~jsgs.base.known_grad.with_known_gradient`);
        ``observation``: also return the observation (else ``obs`` is None); ``copy_values`` off: the values
        (and the weighted sum, a view of them) are the graph's output buffer, not a copy, for a caller that
        has read them before its next call (whose replay writes them anew); ``unit_upstream``: the caller
        guarantees the weighted sum's upstream gradient is exactly 1 (``with_known_gradient``'s: its
        gradients are handed on without the product by 1). ``y`` may be the ``(H, W, 3)``
        uint8 training image the target is made from (:func:`.terms_with_gradient`); where it is one image
        of a stack of them (:func:`jsgs.train.data.stacked_image`, as the trainer loads them), the graph
        reads it from the stack by index: no buffer of the image's size and no copy."""
        stacked = stacked_image(y) if y.dtype == torch.uint8 and y.dim() == 3 else None
        stack = None if stacked is None else (stacked[0].data_ptr(), tuple(stacked[0].shape))
        key = (tuple(x.shape), x.dtype, y.dtype, sampling, x.requires_grad, stack, observation)
        rec = self._graphs.get(key)
        if rec is None:
            rec = self._graphs[key] = self._record(x, y, tables, sampling, observation)
        with torch.no_grad():  # the render's buffer is a leaf that needs grad (the recorded gradient's input)
            x_buf, y_buf, tables_buf = rec.inputs
            x_buf.copy_(x)
            if stacked is None:
                y_buf.copy_(y)
            else:  # the image's index in the stack: a fill, no host-to-device copy
                y_buf.fill_(stacked[1])
            if self._tables_held.get(tables_buf.data_ptr()) is not tables:  # else it holds them already
                tables_buf.copy_(tables)
                self._tables_held[tables_buf.data_ptr()] = tables
        rec.replay()
        values, grad, r, obs = rec.outputs
        if copy_values:  # the caller's: read after the next replay, which rewrites the buffer
            values = values.clone()
        pairs = ((x, grad) if grad is not None else ()) + (more(r) if more is not None else ())
        # the gradients are scratch: the graph's buffer is rewritten by the next replay, the probe's
        # upstream map is made for this call alone (jsgs.method.pooling.ProbeObjective)
        # the weighted sum: a view of the values (the caller's copy, or the buffer), no copy of its own
        weighted = (
            with_known_gradient(
                pairs[0], values[0], *pairs[1:], scratch=True, own_value=True, unit_upstream=unit_upstream
            )
            if pairs else values[0]
        )  # fmt: skip
        return ImageTerms(weighted, values[1:], r, obs)

    def _buffer(self, role: str, like: Tensor, shape: tuple[int, ...] | None = None) -> Tensor:
        """A tensor of ``shape`` (default ``like``'s) and ``like``'s dtype and device, holding ``like``'s
        values where it has that shape, on this object's flat buffer for ``role`` (render, target, index,
        tables, r) of that many elements: made on first use, then shared by every recording that asks for
        the same role and size (never by two buffers of one recording)."""
        shape = tuple(like.shape) if shape is None else shape
        numel = 1
        for d in shape:
            numel *= d
        key = (role, numel, like.dtype, like.device)
        flat = self._memory.get(key)
        if flat is None:
            flat = self._memory[key] = torch.empty(numel, dtype=like.dtype, device=like.device)
        if shape != tuple(like.shape):
            return flat.view(shape).detach()  # a tensor of its own on the shared memory, not an autograd view
        # laid out as a clone of ``like`` would be (the chain's arithmetic, and so its rounding, follows the
        # layout: a channels-last render stays channels-last)
        strides = torch.empty_like(like, device="meta").stride()
        buf = flat.as_strided(shape, strides).detach()
        with torch.no_grad():
            buf.copy_(like)
        return buf

    def _recorded_function(
        self, x: Tensor, y: Tensor, tables: Tensor, sampling: str, observation: bool
    ) -> tuple[Callable[[], Any], tuple[Tensor, Tensor, Tensor]]:
        """What a new recording records, :func:`terms_with_gradient` on its input buffers (which hold ``x``,
        ``y`` and ``tables`` now; for an image of a stack, its index in the stack instead of ``y``) with r_b
        written into its shared buffer, and those input buffers."""
        stacked = stacked_image(y) if y.dtype == torch.uint8 and y.dim() == 3 else None
        if stacked is None:
            y_buf = y_in = self._buffer("target", y)
            y_index = None
        else:
            index = torch.full((1,), stacked[1], dtype=torch.int64, device=y.device)
            y_in, y_buf = stacked[0], self._buffer("index", index)
            y_index = y_buf
        x_buf = self._buffer("render", x).requires_grad_(x.requires_grad)
        tables_buf = self._buffer("tables", tables)
        r_into = self._buffer("r", x, (x.shape[0], x.shape[2] // 8, x.shape[3] // 8))
        fn = partial(terms_with_gradient, x_buf, y_in, tables_buf, weights=self.weights, sampling=sampling,
                     observation=observation, grad_into_x=True, r_into=r_into, r_blocks=True, y_index=y_index,
                     **self.settings)  # fmt: skip
        return fn, (x_buf, y_buf, tables_buf)

    def _record(self, x: Tensor, y: Tensor, tables: Tensor, sampling: str, observation: bool) -> _Recording:
        self._check_device(x)
        fn, inputs = self._recorded_function(x, y, tables, sampling, observation)
        if self._pool is None:  # one memory pool shared by all of this object's graphs
            self._pool = torch.cuda.graph_pool_handle()
        graph, outputs = record_graph(fn, x.device, warmups=2, pool=self._pool, error_mode="global")
        if self.free_warmup:
            # the warm-ups' intermediates were freed into blocks that only the side stream may reuse; the
            # graph's own live in its pool, which this leaves alone
            torch.cuda.empty_cache()
        return _Recording(graph.replay, inputs, outputs)


class GraphedController:
    """The deferred Gaussian Controller (:func:`jsgs.kernels.fro_from_probe_grad`) replayed as a
    CUDA graph: one launch instead of about sixty small kernels inside every backward.

    Unlike the image terms, its size changes during training: N changes at densification, when the
    parameters are also replaced by new tensors. The graph reads the parameters where they lie, so it is
    recorded for one (N, dtype, image size, parameter storage) and again whenever any of them changes
    (every ``refine_every`` steps while densifying, about 150 recordings in a 30k-step run, then never). The
    probe's gradient and the camera are copied into the graph's own buffers before each replay. The outputs
    live in the graph's memory, valid until the next call: ``(grad_logit [N], grad_log_scale [N, 3],
    stats [4])`` with ``stats`` = (L_fro, |V_i|, mean r̄, #damped), see
    :func:`jsgs.kernels.packed_fro_stats`.

    Recording happens inside the trainer's backward (from the probe's post-accumulate-grad hook), on a side
    stream, with no host synchronisation beyond what recording itself needs.
    """

    def __init__(self, *, weight: float, near_plane: float, eps_proj: float, tau_s: float) -> None:
        self.settings = dict(weight=weight, near_plane=near_plane, eps_proj=eps_proj, tau_s=tau_s)
        self._key: tuple[Any, ...] | None = None
        self._graph: Any = None
        self._inputs: tuple[Tensor, Tensor, Tensor] | None = None
        self._outputs: tuple[Tensor, Tensor, Tensor] | None = None
        self.recordings = 0

    def _run(
        self, probe_grad: Tensor, viewmat: Tensor, K: Tensor, params: tuple[Tensor, ...], w: int, h: int
    ) -> tuple[Tensor, Tensor, Tensor]:
        from jsgs.kernels import fro_from_probe_grad, packed_fro_stats

        logits, log_scales, means, quats = params
        out = fro_from_probe_grad(
            probe_grad, logits, log_scales, means, quats, viewmat, K, w, h, **self.settings
        )
        return out.grad_logit, out.grad_log_scale, packed_fro_stats(out.terms)

    def __call__(
        self,
        probe_grad: Tensor,
        opacity_logits: Tensor,
        log_scales: Tensor,
        means: Tensor,
        quats: Tensor,
        viewmat: Tensor,
        K: Tensor,
        width: int,
        height: int,
    ) -> tuple[Tensor, Tensor, Tensor]:
        params = tuple(p.detach() for p in (opacity_logits, log_scales, means, quats))
        key = (
            tuple(probe_grad.shape), probe_grad.dtype, width, height,
            *((p.data_ptr(), tuple(p.shape), p.dtype) for p in params),
        )  # fmt: skip
        if key != self._key:
            self._record(key, probe_grad, viewmat, K, params, width, height)
        else:
            assert self._inputs is not None
            for buf, src in zip(self._inputs, (probe_grad, viewmat, K), strict=True):
                buf.copy_(src)
            self._graph.replay()
        assert self._outputs is not None
        return self._outputs

    def _record(self, key: tuple[Any, ...], probe_grad: Tensor, viewmat: Tensor, K: Tensor,
                params: tuple[Tensor, ...], w: int, h: int) -> None:  # fmt: skip
        GraphedImageTerms._check_device(probe_grad)
        inputs = (probe_grad.detach().clone(), viewmat.detach().clone(), K.detach().clone())
        # The new graph records into the previous one's memory pool, which must still be alive while it
        # does (torch's allocator refuses a pool whose graphs are all gone); the old graph is dropped after.
        pool = self._graph.pool() if self._graph is not None else None
        try:  # recorded from the probe's hook, inside the trainer's backward
            graph, outputs = record_graph(
                partial(self._run, *inputs, params, w, h), probe_grad.device, warmups=1, pool=pool,
                error_mode="thread_local",
            )  # fmt: skip
        except GraphCaptureFailed:
            self._key = self._graph = self._inputs = self._outputs = None
            raise
        self._key, self._graph, self._inputs, self._outputs = key, graph, inputs, outputs
        self.recordings += 1
        # replay once so that this call's outputs come from the graph exactly as later calls' do
        graph.replay()
