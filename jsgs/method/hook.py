"""``--method jsgs``: the gsplat backbone plus the JSGS terms (paper eq. overall), as a trainer loss hook.

Per training step, for the sampled view i with its own JPEG state (manifest ``jpeg``: luma table T^Y,
chroma table T^C, chroma sampling)::

    L^i = λ_base ℓ_ph(Î, I)                      the trainer's baseline term (loss.base_weight, default 1)
        + λ_obs ℓ_ph(C_JPEG(Î; T^Y, T^C), I)      JO: eq. obs_loss                           "obs"  (0.2)
        + λ_low L_low + λ_mid L_mid               DS: eq. jsgs_dct_losses                    "low"  (0.02)
                                                                                             "mid"  (0.03)
        + λ_fro L_fro                             GC: eqs. gaussian_risk, controller_scale,  "fro"  (0.05)
                                                      fro

ℓ_ph is the trainer's own photometric loss (same λ_ssim and SSIM padding as the baseline term). A lossless
view (``jpeg`` null) gets ℓ_ph only: its JSGS terms are logged as 0 with weight 0 (nothing enters the loss),
so the logged means are each term's mean contribution per step.

Ablations (paper Table 2): ``jo``, ``ds``, ``gc`` (method options; ``--no-jo``, ``--no-ds``, ``--no-gc``).
DS and GC are defined on the JO output, so ``jo: false`` requires ``ds: false`` and ``gc: false``; with all
three off the method is the baseline (the factory returns no hook). Without DS but with GC, the block scores
are still computed (detached) because GC needs them; L_low and L_mid are then neither logged nor optimised.

The Gaussian Controller pools the block-score map r(p) per Gaussian with a probe (zero extra channels
rendered with the colours, ``jsgs.method.pooling``), in the same rasterisation pass. Two routes, equal
values and gradients (tested), chosen by ``gc_pooling``:

* ``"deferred"`` (default): λ_fro times ``probe_objective`` (value exactly 0; ``ProbeObjective``) rides in
  the loss (``HookOutput.folded_loss``, the ``fro`` term being its logged value), so the main backward
  itself pools ``λ_fro·(o·S_r, ν)`` into the probe's gradient; a post-accumulate hook on the probe then
  computes r̄, V_i, L_fro and L_fro's closed-form gradient and adds ``λ_fro ∂L_fro/∂θ`` to the opacity-logit
  and log-scale gradients (``jsgs.kernels.fro_from_probe_grad``; on CUDA the three fused kernels of
  ``jsgs/kernels/csrc/controller.cu``, ``method_options.speed.gc_kernel``, or that function replayed as one
  graph, ``jsgs.method.graphed.GraphedController``). No extra rasteriser pass of any kind. The ``fro`` term's
  value (and the GC statistics) are written in place during that backward: they are correct wherever the
  trainer reads them after ``loss.backward()`` (progress bar, metrics.json), but the total ``loss`` the
  trainer sums *before* the backward does not include ``λ_fro L_fro`` (its logged value; the gradient is
  complete).
* ``"now"``: ``pool_now`` runs one extra rasteriser backward before the loss is formed; L_fro is an ordinary
  autograd term (exact total loss too; costs that extra backward).

With ``lambda_fro`` 0 the term is logged only; the ``"now"`` route is used for it (nothing rides in the
loss).

With ``gc_attribution`` ``"footprint"`` no probe is rendered: r̄ is estimated from each Gaussian's 2D footprint
over the blocks around its mean, and V_i read from the main backward's conic gradients
(``jsgs.method.pooling.footprint_sums``), in a hook on ``info["conics"]`` that feeds the estimate to the
same controller code as the probe's gradient (``jsgs.method.pooling.probe_grad_from_sums``); deferred only.

With ``gc_every`` k > 1 the controller runs on the steps with ``step % k == 0`` only, weighted k·λ_fro there
(on those steps it is the exact controller with that weight); the other steps render no probe, and their
``fro`` term and GC statistics are 0 (nothing enters the loss) and named in ``HookOutput.skipped``: the
progress bar shows the latest controller step's values and the logged means are over the controller's steps.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from jsgs.base.errors import JsgsError
from jsgs.base.kept_zeros import kept_zeros
from jsgs.jpeg.supervision import pixel_score_of
from jsgs.kernels import (
    controller_matrix,
    fro_from_probe_grad,
    fro_from_probe_grad_fused,
    fro_loss,
    packed_fro_stats,
    use_kernels,
)
from jsgs.method.graphed import GraphCaptureFailed, GraphedController, GraphedImageTerms
from jsgs.method.image_terms import (
    ViewJpeg,
    base_weight,
    image_term_settings,
    jpeg_terms,
    maybe_compile,
    view_tables,
    warn_eager_fallback,
)
from jsgs.method.options import JsgsOptions, parse_options, use_cuda_graph, use_fused_color, use_fused_jo
from jsgs.train.hook import HookOutput, LossHook, StepContext
from jsgs.train.profiler import Profiler

if TYPE_CHECKING:
    from jsgs.train.config import TrainConfig
    from jsgs.train.data import TrainingScene, TrainingView

#: Term names in HookOutput.terms (and in metrics.json ``train.terms``).
TERM_NAMES = ("obs", "low", "mid", "fro")
#: GC statistics in HookOutput.stats (``train.stats``).
STAT_NAMES = ("gc_visible", "gc_rbar", "gc_damped")


class JsgsHook(LossHook):
    """The JSGS terms for the trainer (module docstring). ``profile = True`` (set by a benchmark) records
    device-synchronised wall times of the JO, DS and GC parts in ``timings`` (seconds, summed over steps;
    ``gc_backward``: the deferred GC work inside the main backward)."""

    name = "jsgs"

    def __init__(
        self,
        options: JsgsOptions,
        tables: dict[int, ViewJpeg],
        *,
        ssim_lambda: float = 0.2,
        ssim_padding: str = "valid",
        ssim_kernel: str = "auto",
        near_plane: float = 0.01,
        device: torch.device | None = None,
        view_names: dict[int, str] | None = None,
        setup_notes: list[str] | None = None,
    ) -> None:
        self.opts = options
        self.tables = tables
        # view index -> name, for the per-view weights in describe() (default: the index)
        self.view_names = view_names or {}
        self._setup_notes = list(setup_notes or [])
        self.near_plane = near_plane
        self.device = device or torch.device("cpu")
        # the trainer's own Profiler; its totals are this hook's ``timings`` (JO, DS, GC phases)
        self.profiler = Profiler(False, self.device)
        # keep_last (tests, debugging): keep what the last step computed in ``last`` (observation, DS,
        # pooled sums, r̄, V, GC terms); off in training so no step outlives its own backward
        self.keep_last = False
        self.last: dict[str, Any] = {}
        # the rasterisation outputs of the step whose deferred GC waits for its backward
        self._pending: dict[str, Any] = {}
        # λ_fro times the probe objective (jsgs.method.pooling.ProbeObjective: its map made at each call)
        self._probe_objective: Any = None
        # this step's probe map made in the backward (render_kwargs), where the render was given it
        self._deferred_map: Any = None
        # what the steps between the controller's leave out of the logs (:meth:`_skipped`)
        self._gc_skipped = frozenset(("fro", *STAT_NAMES))
        from jsgs.jpeg.losses import photometric_loss
        from jsgs.jpeg.observe import jpeg_observe
        from jsgs.jpeg.supervision import dct_supervision

        # what fixes the JO / L_obs / DS chain (jsgs.method.image_terms.jpeg_terms), in both routes
        self.jo_kernel = "triton" if options.jo and use_fused_jo(options, self.device) else "torch"
        self.color_kernel = "triton" if use_fused_color(options, self.device) else "torch"
        self._jpeg_settings = image_term_settings(
            options, ssim_lambda, ssim_padding, ssim_kernel, self.jo_kernel, self.color_kernel
        )
        self._jpeg_functions = {
            "observe": maybe_compile(jpeg_observe, options.speed.compile),
            "photometric": maybe_compile(photometric_loss, options.speed.compile),
            "supervise": maybe_compile(dct_supervision, options.speed.compile),
        }
        self._graphed = None
        # what fixes the deferred GC (jsgs.kernels.fro_from_probe_grad), eager or graphed
        self._gc_settings: dict[str, float] = dict(
            weight=self.fro_weight, near_plane=near_plane, eps_proj=options.eps_proj, tau_s=options.tau_s
        )
        self._gc_graphed: GraphedController | None = None
        self._gc_fused = (
            options.gc and self.gc_route == "deferred"
            and use_kernels(options.speed.gc_kernel, self.device, "method_options.speed.gc_kernel")
        )  # fmt: skip
        self.cuda_graph = use_cuda_graph(options, self.device)
        if self.cuda_graph:
            w = self.weights()
            image_weights = (w["obs"], w.get("low", 0.0), w.get("mid", 0.0))
            self._graphed = GraphedImageTerms(
                weights=image_weights, free_warmup=options.speed.cuda_graph_free_warmup, **self._jpeg_settings
            )
            if self.gc_route == "deferred" and options.speed.cuda_graph_gc and not self._gc_fused:
                self._gc_graphed = GraphedController(**self._gc_settings)

    def describe(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "color_kernel": self.color_kernel,
            "cuda_graph": self.cuda_graph,
            "cuda_graph_gc": self._gc_graphed is not None,
            "gc_attribution": self.opts.gc_attribution,
            "gc_kernel": "cuda" if self._gc_fused else "torch",
            "gc_route": self.gc_route,
            "jo_kernel": self.jo_kernel,
            "jpeg_mode": self.opts.jpeg_mode,
        }
        if self.opts.base_by_view:
            out["base_by_view"] = {
                self.view_names.get(i, str(i)): {
                    "noise_variance": round(tab.noise_variance, 6), "weight": round(self.base_scale(tab), 6)
                } | ({"blockiness": round(tab.blockiness, 6)} if self.opts.base_block_ref else {})
                for i, tab in sorted(self.tables.items())
            }  # fmt: skip
        return out

    def notes(self) -> list[str]:
        """With ``base_by_view``: the spread of the JPEG views' ℓ_ph weights (and how σ² was found)."""
        notes = list(self._setup_notes)
        if self.opts.base_by_view and self.tables:
            w = sorted(self.base_scale(t) for t in self.tables.values())
            o = self.opts
            notes.append(
                f"base_by_view: the {len(w)} JPEG training views keep {w[0]:.2f}–{w[-1]:.2f} of ℓ_ph (median "
                f"{w[len(w) // 2]:.2f}; σ² from the {'files' if o.base_noise == 'pixels' else 'tables'}, "
                f"σ_ref = {o.base_noise_ref:g}"
                + (f", k = {o.base_noise_exponent:g}" if o.base_noise_exponent != 1.0 else "")
                + (f"; times the blockiness factor, b = {o.base_block_ref:g}" if o.base_block_ref else "")
                + (f"; from 1 over the first {o.base_ramp_steps} steps)" if o.base_ramp_steps else ")")
            )
        return notes

    # ------------------------------------------------------------------------------------------------
    @property
    def fro_weight(self) -> float:
        """The weight of L_fro on the steps the controller runs: λ_fro·gc_every."""
        return self.opts.lambda_fro * self.opts.gc_every

    def gc_at(self, step: int) -> bool:
        """Whether the Gaussian Controller runs at 0-based ``step`` (on its JPEG views)."""
        return self.opts.gc and step % self.opts.gc_every == 0

    @property
    def gc_route(self) -> str:
        if self.opts.gc_attribution == "footprint":  # inside the main backward, whatever λ_fro
            return "deferred"
        return "now" if self.opts.lambda_fro == 0.0 else self.opts.gc_pooling

    def active_terms(self) -> list[str]:
        o = self.opts
        return [n for n, on in (("obs", o.jo), ("low", o.ds), ("mid", o.ds), ("fro", o.gc)) if on]

    def weights(self) -> dict[str, float]:
        o = self.opts
        w = {"obs": o.lambda_obs, "low": o.lambda_low, "mid": o.lambda_mid, "fro": self.fro_weight}
        return {k: w[k] for k in self.active_terms()}

    def base_scale(self, tab: ViewJpeg, step: int | None = None) -> float:
        """The multiplier on λ_base for a JPEG view at 0-based ``step`` (:func:`base_weight`)."""
        return base_weight(self.opts, tab, step)

    def renders_extra(self) -> bool:
        # the footprint attribution renders no probe but, like it, needs the step's view rendered from every
        # Gaussian (per-view screen-space values): on several GPUs both take the torch exchange
        return self.opts.gc

    def extra_channels(self, step: int, view: TrainingView, splats: torch.nn.ParameterDict) -> Tensor | None:
        """The Gaussian Controller's probe (``jsgs.method.pooling.new_probe``) on the views and steps it runs
        on."""
        if not (self.gc_at(step) and view.index in self.tables) or self.opts.gc_attribution != "probe":
            return None
        from jsgs.method.pooling import new_probe

        means = splats["means"]
        return new_probe(means.shape[0], means)

    def render_kwargs(self, step: int, view: TrainingView) -> dict[str, Any]:
        """On the deferred probe's steps, the probe's map made in the backward
        (:class:`jsgs.method.pooling.DeferredProbeMap`, ``rasterize(..., extra_upstream=)``): its node made
        with the render, the map made after ℓ_ph's backward instead of kept from the hook's call."""
        self._deferred_map = None
        if self._probe_deferred(step) and view.index in self.tables:
            from jsgs.method.pooling import DeferredProbeMap

            self._deferred_map = DeferredProbeMap(self.fro_weight)
            return {"extra_upstream": self._deferred_map}
        return {}

    def _probe_deferred(self, step: int) -> bool:
        """Whether the deferred controller pools through the probe at ``step``."""
        o = self.opts
        return o.gc and self.gc_at(step) and self.gc_route == "deferred" and o.gc_attribution == "probe"

    @property
    def profile(self) -> bool:
        return self.profiler.enabled

    @profile.setter
    def profile(self, on: bool) -> None:
        self.profiler.enabled = on

    @property
    def timings(self) -> dict[str, float]:
        """Device-synchronised seconds per phase, summed over steps (only while ``profile`` is on)."""
        return self.profiler.totals

    # ------------------------------------------------------------------------------------------------
    def losses(self, ctx: StepContext) -> HookOutput:
        o = self.opts
        self.last = {}
        self._pending.clear()  # a step whose backward never came (see _gc_deferred)
        tab = self.tables.get(ctx.view.index)
        if tab is None:  # lossless view: ℓ_ph only; the terms are logged as 0 with weight 0 (nothing to add)
            names = self.active_terms()
            stat_names = list(STAT_NAMES) if o.gc else []
            n = len(names) + len(stat_names)
            values = kept_zeros(ctx.render, (n,)).unbind()
            terms0 = dict(zip(names, values[: len(names)], strict=True))
            stats0: dict[str, float | Tensor] = dict(zip(stat_names, values[len(names) :], strict=True))
            return HookOutput(terms0, dict.fromkeys(names, 0.0), stats0, skipped=self._skipped(ctx.step))
        # every active term and statistic is set below (no placeholder kernels on the JPEG views' path)
        terms: dict[str, Tensor] = {}
        stats: dict[str, float | Tensor] = {}

        x = ctx.render.permute(0, 3, 1, 2)
        y = ctx.target.permute(0, 3, 1, 2)
        r_map = None
        graphed = None
        folded: frozenset[str] = frozenset()
        folded_loss = None
        # the deferred controller's objective: made with the render where the render was given the hook's
        # map (render_kwargs), its r set below; else riding on the graph's node where there is one (one node
        # and no addition for both known gradients): its (channels, gradient) pair, made from the replay's r
        deferred = self._probe_deferred(ctx.step)
        in_render = self._deferred_map is not None and ctx.info.get("extra_upstream") is self._deferred_map
        if in_render:  # its objective joins the folded loss as is where the trainer says so
            self._deferred_map.unit_upstream = ctx.folded_upstream_one
        deferred = deferred and not in_render
        probe_pair: tuple[Tensor, ...] = ()

        def probe_upstream(r: Tensor) -> tuple[Tensor, ...]:
            nonlocal probe_pair
            probe_pair = self._probe().upstream(ctx.info, r)
            return probe_pair

        if self._graphed is not None and tab.first is None:  # the graph holds one quantization
            try:
                with self.profiler.phase("jo"):  # JO, L_obs and DS: one graph replay ("ds" is in it)
                    more = probe_upstream if deferred else None
                    # the uint8 image the target is made from, where there is one: a smaller input buffer
                    y_in = y if ctx.image is None else ctx.image
                    # the values are the graph's buffer, no copy: the trainer packs them (and adds the
                    # weighted sum to the loss) within the step, before the next replay
                    graphed = self._graphed(
                        x, y_in, tab.tables, tab.sampling, more, observation=self.keep_last,
                        copy_values=False, unit_upstream=ctx.folded_upstream_one,
                    )  # fmt: skip
            except GraphCaptureFailed as e:
                # a speed-up, not a result: the run goes on with the eager chain, which computes the same
                self._graphed = None
                warn_eager_fallback("recording JO/L_obs/DS as a CUDA graph", str(e), "them")
        if graphed is not None:
            # the weighted sum carries the three terms' gradient; the terms themselves are logged values
            l_obs, low, mid = graphed.values.unbind()
            terms["obs"] = l_obs
            if o.ds:
                terms["low"], terms["mid"] = low, mid
            folded, folded_loss = frozenset(terms), graphed.weighted
            # the graph keeps r_b; r(p) is made only where the controller reads it (not where the probe's
            # map rode on the graph's node, made from r_b)
            if in_render:
                self._deferred_map.r = graphed.r
            elif o.gc and self.gc_at(ctx.step) and not probe_pair:
                r_map = pixel_score_of(graphed.r, x.shape[2], x.shape[3])
            if self.keep_last:
                assert graphed.obs is not None
                self.last["observation"] = graphed.obs.clone()
        else:
            obs, terms["obs"], sup = jpeg_terms(
                x, y, tab.luma, tab.chroma, sampling=tab.sampling, phase=self.profiler.phase, first=tab.first,
                ds_weights=tab.ds_weights if x.dtype == torch.float32 else None,
                **self._jpeg_settings, **self._jpeg_functions,
            )  # fmt: skip
            if self.keep_last:
                self.last["observation"] = obs.detach()
            if sup is not None:
                if o.ds:
                    # the one view's entries (views, no kernel; the sum of one value is that value)
                    terms["low"], terms["mid"] = sup.loss_low.view(()), sup.loss_mid.view(())
                r_map = sup.pixel_score  # [1, H, W], detached
                if in_render:
                    self._deferred_map.r = r_map
                if self.keep_last:
                    self.last["ds"] = sup
        if in_render:  # the objective made with the render
            obj = ctx.info["extra_objective"]
            folded_loss = obj if folded_loss is None else folded_loss + obj
        if o.gc:
            folded, folded_loss = self._controller_terms(ctx, r_map, bool(probe_pair) or in_render, terms,
                                                         stats, folded, folded_loss)  # fmt: skip
        return HookOutput(
            terms, self.weights(), stats, folded, folded_loss, self.base_scale(tab, ctx.step),
            self._skipped(ctx.step),
        )  # fmt: skip

    def _controller_terms(
        self, ctx: StepContext, r_map: Tensor | None, probe_rode: bool, terms: dict[str, Tensor],
        stats: dict[str, float | Tensor], folded: frozenset[str], folded_loss: Tensor | None,
    ) -> tuple[frozenset[str], Tensor | None]:
        """The Gaussian Controller's part of :meth:`losses` on a JPEG view: its ``fro`` term and statistics
        into ``terms`` / ``stats``; returns the folded names and loss with the controller's share. Between
        the controller's steps its values are the kept zeros (skipped in the logs); ``probe_rode``: the
        deferred objective already rode on the image terms' graph node."""  # fmt: skip
        if not self.gc_at(ctx.step):  # a step between the controller's: 0, skipped in the logs
            terms["fro"], *zero_stats = kept_zeros(ctx.render, (1 + len(STAT_NAMES),)).unbind()
            stats.update(zip(STAT_NAMES, zero_stats, strict=True))
            if folded_loss is not None:  # a value to log only: nothing to weight and add to the loss
                folded = folded | {"fro"}
            return folded, folded_loss
        assert r_map is not None or probe_rode
        with self.profiler.phase("gc"):
            if self.opts.gc_attribution == "footprint":
                assert r_map is not None
                terms["fro"], gc_stats = self._gc_footprint(ctx, r_map)
                if folded_loss is not None:  # a value to log (no gradient): nothing to add to the loss
                    folded = folded | {"fro"}
            elif self.gc_route == "now":
                assert r_map is not None
                fro, gc_stats = self._gc_now(ctx, r_map)
                terms["fro"] = fro
            else:
                # the objective is λ_fro·(probe objective) already: it joins the folded loss unweighted
                # (already in it where it rode on the graph's node)
                terms["fro"], gc_stats = self._gc_deferred(ctx)
                folded = folded | {"fro"}
                if not probe_rode:
                    assert r_map is not None
                    objective = self._probe()(ctx.info, r_map)
                    folded_loss = objective if folded_loss is None else folded_loss + objective
            stats.update(gc_stats)
        return folded, folded_loss

    def _skipped(self, step: int) -> frozenset[str]:
        """The controller's term and statistics on the steps between the controller's (any view, so that every
        process of a run skips the same names at a step): logged as 0, left out of the logs."""
        return self._gc_skipped if self.opts.gc and not self.gc_at(step) else frozenset()

    # ------------------------------------------------------------------------------------------------
    def _camera(self, ctx: StepContext) -> tuple[Tensor, Tensor, int, int]:
        """The view's world-to-camera [4, 4] and K [3, 3] in the parameters' dtype (the view's own
        per-device copies: a host-to-device copy inside the backward would stall the GPU queue), width,
        height."""
        v = ctx.view
        means = ctx.splats["means"]
        viewmat = v.viewmat_tensor(means.device, means.dtype)[0]
        return viewmat, v.K_tensor(means.device, means.dtype)[0], v.width, v.height

    def _gc_now(self, ctx: StepContext, r_map: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        from jsgs.method.pooling import pool_now

        sums = pool_now(ctx.info, r_map)
        rbar = sums.rbar(self.opts.eps_proj)[0]
        vis = sums.contributors[0]
        splats = ctx.splats
        viewmat, K, w, h = self._camera(ctx)
        A = controller_matrix(splats["means"], splats["quats"], viewmat, K, w, h, self.near_plane)
        ft = fro_loss(rbar, vis, splats["opacities"], splats["scales"], A, self.opts.tau_s)
        if self.keep_last:
            self.last.update(sums=sums, rbar=rbar, visible=vis, fro=ft, A=A)
        s = ft.stats
        return ft.loss, {"gc_visible": s.visible, "gc_rbar": s.rbar_mean, "gc_damped": s.damped}

    def _probe(self) -> Any:
        """λ_fro times the probe objective (:class:`jsgs.method.pooling.ProbeObjective`; its map made at each
        call, its probe gradient λ_fro·(o·S_r, ν) is divided out in fro_from_probe_grad)."""
        if self._probe_objective is None:
            from jsgs.method.pooling import ProbeObjective

            self._probe_objective = ProbeObjective(self.fro_weight)
        return self._probe_objective

    def _gc_deferred(self, ctx: StepContext) -> tuple[Tensor, dict[str, Tensor]]:
        """The deferred controller on the probe's gradient, once the backward has made it (the caller puts
        the probe objective in the loss): the ``fro`` term to log (0 until the backward writes L_fro into
        it) and the statistics (likewise)."""

        # The hook lives on the probe tensor, which the objective's graph holds (through the probe's
        # AccumulateGrad): a closure over the objective (or ``info``) would make a reference cycle that keeps
        # every step's rasterisation outputs (GBs on a GPU) alive until Python's cycle collector happens to
        # run. The closure holds plain tensors only, and runs once: its marker in ``pending`` is emptied by
        # the hook itself (and by the next step, if a backward never came).
        pending = self._pending
        splats = ctx.splats
        # the logged L_fro and the three statistics: one tensor, filled by one copy in the backward
        values = torch.zeros(1 + len(STAT_NAMES), dtype=ctx.render.dtype, device=ctx.render.device)
        term, *stat_list = values.unbind()
        stat_t = dict(zip(STAT_NAMES, stat_list, strict=True))
        pending["term"] = term
        viewmat, K, w, h = self._camera(ctx)

        def on_probe_grad(probe: Tensor) -> None:
            term = pending.pop("term", None)
            if term is None:
                return
            with self.profiler.phase("gc_backward"), torch.no_grad():
                grad = probe.grad[None]  # [1, N, 2]
                probe.grad = None  # served its purpose; keeps memory flat
                params = (splats["opacities"], splats["scales"], splats["means"], splats["quats"])
                values.copy_(self._controller(grad, params, viewmat, K, w, h))

        ctx.info["extra_features"].register_post_accumulate_grad_hook(on_probe_grad)
        return term, stat_t

    def _gc_footprint(self, ctx: StepContext, r_map: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """The controller with the footprint attribution: a hook on ``info["conics"]`` reads its gradient
        in the main backward (V_i: the non-zero rows), estimates the pooled sums
        (:func:`jsgs.method.pooling.footprint_sums`) and runs :meth:`_controller` on the probe gradient they
        stand for. The ``fro`` value and the statistics are written in place then, as in the deferred
        probe route."""
        from jsgs.method.pooling import footprint_sums, probe_grad_from_sums

        info = ctx.info
        conics = info["conics"]
        if not conics.requires_grad:
            raise JsgsError(
                "method_options.gc_attribution footprint: the rasteriser's conics have no gradient to read"
            )
        # the logged L_fro and the three statistics: one tensor, filled by one copy in the backward
        values = torch.zeros(1 + len(STAT_NAMES), dtype=ctx.render.dtype, device=ctx.render.device)
        term, *stat_list = values.unbind()
        stat_t = dict(zip(STAT_NAMES, stat_list, strict=True))
        # detached copies only: the hook lives on the conics, so a closure over a tensor of their graph
        # would make a reference cycle (see _gc_deferred)
        m2, con, op = info["means2d"].detach(), conics.detach(), info["opacities"].detach()
        r = r_map.detach()
        splats = ctx.splats
        viewmat, K, w, h = self._camera(ctx)
        weight = self.fro_weight
        pending = {"once": True}

        def on_conics_grad(grad: Tensor) -> None:
            if not pending.pop("once", False):  # a second backward through the same graph
                return
            with self.profiler.phase("gc_backward"), torch.no_grad():
                sums = footprint_sums(r, m2, con, op, (grad != 0).any(dim=-1))
                params = (splats["opacities"], splats["scales"], splats["means"], splats["quats"])
                if weight > 0.0:
                    g = probe_grad_from_sums(sums, op, weight)
                    packed = self._controller(g, params, viewmat, K, w, h)
                else:  # λ_fro 0: logged only, nothing to add to the gradients
                    unit = {**self._gc_settings, "weight": 1.0}
                    g = probe_grad_from_sums(sums, op)
                    packed = packed_fro_stats(fro_from_probe_grad(g, *params, viewmat, K, w, h, **unit).terms)
                values.copy_(packed)

        conics.register_hook(on_conics_grad)
        return term, stat_t

    def _controller(
        self, probe_grad: Tensor, params: tuple[Tensor, ...], viewmat: Tensor, K: Tensor, w: int, h: int
    ) -> Tensor:
        """The deferred GC inside the backward: adds λ_fro ∂L_fro/∂θ to the opacity-logit and log-scale
        gradients and returns the packed (L_fro, statistics) [4]. Fused kernels or the graph where they are
        on (and nothing asks for the intermediates, ``keep_last``), else the eager twin."""
        fast = None  # (grad_logit, grad_log_scale, packed) from the kernels or the graph
        # the gradients are new tensors of this call (stored as they are where a parameter has no gradient
        # yet) but for the graph's, which are its output buffers (copied)
        owned = True
        if self._gc_fused and not self.keep_last:
            fast = fro_from_probe_grad_fused(probe_grad, *params, viewmat, K, w, h, **self._gc_settings)
        elif self._gc_graphed is not None and not self.keep_last:
            try:
                fast = self._gc_graphed(probe_grad, *params, viewmat, K, w, h)
                owned = False
            except GraphCaptureFailed as e:
                self._gc_graphed = None
                warn_eager_fallback("recording the Gaussian Controller as a CUDA graph", str(e), "it")
        if fast is not None:
            g_logit, g_ls, packed = fast
        else:
            out = fro_from_probe_grad(probe_grad, *params, viewmat, K, w, h, **self._gc_settings)
            g_logit, g_ls, packed = out.grad_logit, out.grad_log_scale, packed_fro_stats(out.terms)
            if self.keep_last:
                self.last.update(sums=out.sums, rbar=out.rbar, visible=out.visible, fro=out.terms, A=out.A)
        _add_grad(params[0], g_logit, owned)
        _add_grad(params[1], g_ls, owned)
        return packed


def _add_grad(p: Tensor, g: Tensor, owned: bool = False) -> None:
    """Accumulate ``g`` into ``p.grad`` as autograd would (the parameter's own AccumulateGrad may run before
    or after this; both orders sum). ``g`` may be a graph's output buffer: it is stored as is only when
    ``owned`` (a new tensor nothing else holds), else copied."""
    g = g.to(p.dtype)
    if p.grad is None:
        p.grad = g if owned else g.clone()
    else:
        p.grad.add_(g)


def make_jsgs_hook(cfg: TrainConfig, scene: TrainingScene, device: torch.device) -> JsgsHook | None:
    """The ``--method jsgs`` factory: options from ``cfg.method_options``, tables from the manifest."""
    opts = parse_options(cfg.method_options)
    if not opts.any_active:
        return None  # --no-jo --no-ds --no-gc: Table 2's baseline row, the plain backbone
    if opts.gc and cfg.render.packed:
        raise JsgsError(
            "config: method jsgs: the Gaussian Controller pools through the rasteriser's probe, which needs "
            "render.packed false (or train with --no-gc)"
        )
    use_cuda_graph(opts, device)  # their errors before the tables are built
    use_fused_jo(opts, device)
    use_fused_color(opts, device)
    noise = opts.base_noise if opts.base_by_view else "tables"  # the estimate reads every view: only if used
    t0 = time.perf_counter()
    blocks = opts.base_by_view and opts.base_block_ref > 0
    tables = view_tables(scene.train_views, device, str(scene.manifest_path), opts.tables, noise, blocks)
    setup_notes = []
    jpegs = [v.jpeg for v in scene.train_views if v.jpeg is not None]
    read = sum(1 for j in jpegs if j.noise_variance is None) if noise == "pixels" else 0
    grids = sum(1 for j in jpegs if j.blockiness is None) if blocks else 0
    if read or grids:
        what = " and ".join(
            f"the {m} of {n} JPEG view(s)" for m, n in (("noise", read), ("blockiness", grids)) if n
        )
        setup_notes.append(
            f"method_options: measured {what} from their files in {time.perf_counter() - t0:.1f} s "
            "(jsgstools manifest --analyze records both in the manifest)"
        )
    return JsgsHook(
        opts,
        tables,
        ssim_lambda=cfg.loss.ssim_lambda,
        ssim_padding=cfg.loss.ssim_padding,
        ssim_kernel=cfg.speed.ssim_kernel,
        near_plane=cfg.render.near_plane,
        device=device,
        view_names={v.index: v.name for v in scene.train_views},
        setup_notes=setup_notes,
    )
