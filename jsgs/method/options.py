"""The options of ``--method jsgs`` (``method_options`` in the settings): typed sections parsed, checked and
turned into a JSON Schema by the same code as every other setting (:mod:`jsgs.train.config`).

The algorithm's settings (weights, ablation switches, JO mode, epsilons) are :class:`JsgsOptions`; how fast
the same results are computed (``torch.compile``, CUDA graphs, the fused controller kernel) is its
``speed`` section, :class:`JsgsSpeed`: changing it changes no value beyond floating-point rounding.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import torch

from jsgs.base.errors import JsgsError
from jsgs.kernels import EPS_PROJ, TAU_S
from jsgs.train.config import check_bounds, parse_method_options, setting

#: ``method_options.speed.compile`` (``jsgs train --compile``, ``jsgs bench --compile``)
COMPILE_BACKENDS = ("off", "inductor", "aot_eager")
#: the jpeg_modes ``method_options.speed.fused_jo`` covers (mode exact runs libjpeg's integer code in torch)
FUSED_JO_MODES = ("paper", "float")


@dataclass
class JsgsSpeed:
    """Speed settings of --method jsgs (the same results, computed with fewer kernel launches)."""

    compile: Literal["off", "inductor", "aot_eager"] = setting(
        "off",
        "torch.compile of JO, L_obs's photometric loss and DS (eager they are launch-bound on a GPU: "
        "hundreds of small kernels): inductor (torch's default code generator) or aot_eager (traces only, "
        "a check).",
    )
    cuda_graph: bool | Literal["auto"] = setting(
        "auto",
        "Replay JO, L_obs and DS and their weighted gradient as one CUDA graph (jsgs.method.graphed): one "
        "launch instead of a few hundred small kernels. auto: on for CUDA without compile; true needs CUDA.",
    )
    cuda_graph_free_warmup: bool = setting(
        True,
        "With cuda_graph: once the image terms' graph is recorded, hand back to the device the memory its "
        "eager warm-up calls left cached for the recording's side stream (torch.cuda.empty_cache, once per "
        "recording; torch's caching allocator reuses a stream's freed blocks on that stream alone, so they "
        "would stay reserved for the run, about the chain's peak memory at the image size). false: keep "
        "them. The same values either way.",
    )
    cuda_graph_gc: bool = setting(
        True,
        "With cuda_graph: the deferred Gaussian Controller as a graph of its own too (recorded again "
        "whenever densification changes the number of Gaussians); false keeps it eager.",
    )
    gc_kernel: Literal["auto", "torch", "cuda"] = setting(
        "auto",
        "The deferred Gaussian Controller's implementation: cuda (jsgs/kernels/csrc/controller.cu, three "
        "fused kernels, no graph), torch (its twin jsgs.kernels.fro_from_probe_grad, graphed per "
        "cuda_graph_gc) or auto (cuda on a GPU where the kernels build, torch elsewhere).",
    )
    fused_jo: bool | Literal["auto"] = setting(
        "auto",
        "JO's coding pass in jpeg_mode paper or float (per 8x8 block: DCT, quantisation, IDCT, clamp) as "
        "two fused Triton kernels, forward and backward, and DS's Delta as one kernel each way "
        "(jsgs/kernels/_triton_jo.py), instead of a few dozen torch kernels (0.73 ms less per step at "
        "1440x1920 on an H200): auto: on for CUDA with Triton, jpeg_mode paper or float and compile off, the "
        "torch code elsewhere; true needs those; false: the torch code (its twin).",
    )
    fused_color: bool | Literal["auto"] = setting(
        "auto",
        "Where fused_jo runs: JO's two colour conversions (RGB to YCbCr and back) as one elementwise Triton "
        "kernel each way (jsgs/kernels/_triton_jo.py) instead of a [H*W x 3] x [3 x 3] matrix product, which "
        "cuBLAS runs slowly (on an H100 at 1440x1920 the JO + L_obs + DS graph replays in 2.1 ms instead of "
        "4.3 ms): true needs fused_jo to run; auto: on where it runs; false: the torch code.",
    )


@dataclass
class JsgsOptions:
    """method_options of --method jsgs (defaults: the paper's implementation details)."""

    lambda_obs: float = setting(
        0.2, "λ_obs: weight of L_obs, the photometric loss of the JPEG observation.", ge=0.0
    )
    lambda_low: float = setting(0.02, "λ_low: weight of L_low (DCT supervision, low band).", ge=0.0)
    lambda_mid: float = setting(0.03, "λ_mid: weight of L_mid (DCT supervision, middle band).", ge=0.0)
    lambda_fro: float = setting(0.05, "λ_fro: weight of L_fro (Gaussian Controller).", ge=0.0)
    base_by_view: bool = setting(
        False,
        "Scale λ_base per JPEG view by how much its tables trust its pixels: w = σ_ref² / (σ_ref² + σ²), σ² "
        "the quantisation-noise variance its luma and chroma tables imply (jsgs.method.image_terms."
        "quantization_noise_variance); near-lossless views keep ℓ_ph, coarse ones are supervised through "
        "JO. Lossless views keep λ_base.",
    )
    base_noise_ref: float = setting(
        8.0,
        "σ_ref of base_by_view, in 8-bit units: the noise level at which a view's ℓ_ph weight halves.",
        gt=0.0,
    )
    base_noise_exponent: float = setting(
        1.0,
        "k of base_by_view: w = 1 / (1 + (σ² / σ_ref²)^k); 1 is σ_ref² / (σ_ref² + σ²), larger k separates "
        "views below σ_ref (w → 1) from views above it (w → 0) more sharply.",
        gt=0.0,
    )
    base_ramp_steps: int = setting(
        0,
        "With base_by_view: the steps over which each JPEG view's ℓ_ph weight falls linearly from 1 to its w "
        "(0: w from the first step). Full pixel supervision early lets the model converge as fast as the "
        "baseline; JO takes over as the weight falls.",
        ge=0,
    )
    base_noise: Literal["tables", "pixels"] = setting(
        "tables",
        "σ² of base_by_view: tables: the bound its tables imply (every coefficient loses Q²/12); pixels: "
        "estimated from the file's own DCT coefficients (jsgs.jpeg.noise: a Laplacian per frequency fitted "
        "to the quantised values), 20-200x smaller on real images and close to the error the file carries "
        "(recorded by jsgstools manifest --analyze, else computed when training starts).",
    )
    base_block_ref: float = setting(
        0.0,
        "b of base_by_view's second factor (0: off): each JPEG view's weight is also multiplied by "
        "1 / (1 + (max(B − 1, 0) / b)^k), B the blockiness of its decoded luma (jsgs.jpeg.noise.blockiness: "
        "the steps across its 8×8 block edges over those inside, about 1 where no grid shows) and k "
        "base_noise_exponent. B ranks the views' visible damage across scenes, where σ² ranks it within one: "
        "views whose squared error is small but whose block grid shows lose ℓ_ph too.",
        ge=0.0,
    )
    jpeg_mode: Literal["paper", "float", "exact"] = setting(
        "paper", "Forward of the JPEG observation operator's rounding (jsgs.jpeg.observe)."
    )
    tables: Literal["header", "effective"] = setting(
        "header",
        "Which quantization a view went through: header (its file's tables) or effective (jsgstools "
        "manifest --analyze: JO quantizes with the earlier, coarser tables first, then the header's, and DS "
        "weights by the effective luma table; for photos saved twice).",
    )
    jo: bool = setting(True, "JPEG observation (L_obs); DS and GC need it.")
    ds: bool = setting(True, "DCT supervision (L_low, L_mid).")
    gc: bool = setting(True, "Gaussian Controller (L_fro).")
    tau_s: float = setting(
        TAU_S, "τ_s: the Gaussian Controller's projected-scale threshold (pixels).", gt=0.0
    )
    eps_sm: float = setting(1e-3, "ε of the soft maximum of the DS block scores.", gt=0.0)
    eps_dct_loss: float = setting(1e-6, "ε in the DS losses' denominators.", gt=0.0)
    eps_dct_block: float = setting(1e-6, "ε in the DS block scores' denominators.", gt=0.0)
    eps_proj: float = setting(EPS_PROJ, "ε of the Gaussian Controller's pooled projection weights.", gt=0.0)
    gc_every: int = setting(
        1,
        "The Gaussian Controller on every k-th step only (0-based steps with step % k == 0), weighted "
        "k·λ_fro there, so that its gradient summed over k steps keeps its expected value; the other steps "
        "render RGB without the probe's two channels. 1: every step (the paper's, exact).",
        ge=1,
    )
    gc_pooling: Literal["deferred", "now"] = setting(
        "deferred",
        "deferred: the GC pools inside the main backward (no extra pass); now: one extra rasteriser "
        "backward before the loss (L_fro an ordinary autograd term).",
    )
    gc_attribution: Literal["probe", "footprint"] = setting(
        "probe",
        "How the Gaussian Controller attributes the block scores to Gaussians (r̄ and V_i): probe (the "
        "paper's exact pooling through two extra rendered channels); footprint (no extra channels: each "
        "Gaussian's 2D footprint integrated over the 3x3 8x8 blocks around its mean, transmittance taken as "
        "1, V_i from the RGB backward's non-zero conic gradients; jsgs.method.pooling.footprint_sums). "
        "footprint needs gc_pooling deferred.",
    )
    speed: JsgsSpeed = setting(
        default_factory=JsgsSpeed, help="Speed settings (same results): compile, CUDA graphs, kernels."
    )

    @property
    def any_active(self) -> bool:
        return self.jo or self.ds or self.gc

    def check(self, where: str = "config") -> None:
        """JsgsError (one line) on a value out of range or an ablation combination the paper does not
        define (types and choices are checked by the parser)."""
        check_bounds(self, where, "method_options.")
        if self.speed.cuda_graph is True and self.speed.compile != "off":
            raise JsgsError(
                f"{where}: method_options.speed.cuda_graph and method_options.speed.compile "
                f"({self.speed.compile}) cannot be combined yet; use one of them"
            )
        covered = self.speed.compile == "off" and self.jpeg_mode in FUSED_JO_MODES
        if self.speed.fused_jo is True and not covered:
            raise JsgsError(
                f"{where}: method_options.speed.fused_jo covers jpeg_mode paper and float without compile "
                f"(got jpeg_mode {self.jpeg_mode}, compile {self.speed.compile}); set it to false or \"auto\""
            )
        if self.base_ramp_steps and not self.base_by_view:
            raise JsgsError(
                f"{where}: method_options.base_ramp_steps ({self.base_ramp_steps}) ramps base_by_view's "
                "weights, which are off; set base_by_view true or base_ramp_steps 0"
            )
        if self.base_block_ref and not self.base_by_view:
            raise JsgsError(
                f"{where}: method_options.base_block_ref ({self.base_block_ref:g}) scales base_by_view's "
                "weights, which are off; set base_by_view true or base_block_ref 0"
            )
        if self.gc_attribution == "footprint" and self.gc_pooling == "now":
            raise JsgsError(
                f"{where}: method_options.gc_attribution footprint reads the main backward's conic "
                'gradients, so it needs gc_pooling "deferred" (got "now")'
            )
        if not self.jo and (self.ds or self.gc):
            on = " and ".join(n for n, v in (("DS", self.ds), ("GC", self.gc)) if v)
            raise JsgsError(
                f"{where}: method jsgs: {on} operate on the JPEG observation (JO) output, so they need JO "
                "(paper Table 2); without JO turn them off too (--no-jo --no-ds --no-gc, which is the "
                "baseline)"
            )


def use_cuda_graph(opts: JsgsOptions, device: torch.device) -> bool:
    """Whether JO, L_obs and DS run as CUDA graphs on ``device`` (``method_options.speed.cuda_graph``
    resolved); JsgsError (one line) for ``true`` off CUDA."""
    s = opts.speed
    if s.cuda_graph == "auto":
        return device.type == "cuda" and s.compile == "off"
    if s.cuda_graph and device.type != "cuda":
        raise JsgsError(
            "config: method jsgs: method_options.speed.cuda_graph needs a CUDA device "
            f'(training on {device.type}); set it to false or "auto"'
        )
    return bool(s.cuda_graph)


def use_fused_jo(opts: JsgsOptions, device: torch.device) -> bool:
    """Whether JO's coding pass runs as the fused Triton kernels on ``device``
    (``method_options.speed.fused_jo`` resolved); JsgsError (one line) for ``true`` where they cannot run."""
    from jsgs.kernels._triton_jo import triton_available

    s = opts.speed
    if s.fused_jo == "auto":
        return (
            device.type == "cuda"
            and triton_available()
            and opts.jpeg_mode in FUSED_JO_MODES
            and s.compile == "off"
        )
    if s.fused_jo and device.type != "cuda":
        raise JsgsError(
            "config: method jsgs: method_options.speed.fused_jo needs a CUDA device "
            f'(training on {device.type}); set it to false or "auto"'
        )
    if s.fused_jo and not triton_available():
        raise JsgsError(
            "config: method jsgs: method_options.speed.fused_jo needs Triton (not installed); set it to "
            'false or "auto"'
        )
    return bool(s.fused_jo)


def use_fused_color(opts: JsgsOptions, device: torch.device) -> bool:
    """Whether JO's colour conversions run as the fused Triton kernel on ``device``
    (``method_options.speed.fused_color`` resolved: only with the fused coding pass); JsgsError (one line)
    for ``true`` where that does not run."""
    s = opts.speed
    if s.fused_color is False:
        return False
    fused_jo = opts.jo and use_fused_jo(opts, device)
    if s.fused_color is True and not fused_jo:
        raise JsgsError(
            "config: method jsgs: method_options.speed.fused_color runs with the fused JO kernels only "
            f'(fused_jo {s.fused_jo} does not run here: {device.type}, jpeg_mode {opts.jpeg_mode}); set it '
            'to false or "auto"'
        )
    return fused_jo


def parse_options(raw: dict[str, Any], where: str = "config") -> JsgsOptions:
    """``method_options`` -> :class:`JsgsOptions` (:func:`jsgs.train.config.parse_method_options`: the
    shared parser, then :meth:`JsgsOptions.check`); JsgsError (one line) on an unknown key, a wrong type or
    value, or an ablation combination the paper does not define."""
    opts: JsgsOptions = parse_method_options("jsgs", raw, where)
    return opts
