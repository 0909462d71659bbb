"""The options of ``--method jsgs`` (``method_options`` in the settings) and their checks."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, Literal

import torch

from jsgs.cuda_ext import KERNEL_CHOICES
from jsgs.errors import JsgsError
from jsgs.method.controller import EPS_PROJ, TAU_S


@dataclass
class JsgsOptions:
    """``method_options`` of ``--method jsgs`` (defaults: the paper's "Implementation details")."""

    lambda_obs: float = 0.2
    lambda_low: float = 0.02
    lambda_mid: float = 0.03
    lambda_fro: float = 0.05
    jpeg_mode: Literal["paper", "float", "exact"] = "paper"
    jo: bool = True
    ds: bool = True
    gc: bool = True
    tau_s: float = TAU_S
    eps_sm: float = 1e-3
    eps_dct_loss: float = 1e-6
    eps_dct_block: float = 1e-6
    eps_proj: float = EPS_PROJ
    gc_pooling: Literal["deferred", "now"] = "deferred"
    # torch.compile of JO, L_obs's photometric loss and DS (eager they are launch-bound on a GPU: hundreds of
    # small kernels). "inductor" is torch's default code generator; "aot_eager" only traces (a check).
    compile: Literal["off", "inductor", "aot_eager"] = "off"
    # Replay JO, L_obs and DS and their weighted gradient as one CUDA graph (jsgs.method.graphed): one launch
    # instead of a few hundred small kernels, which is what they cost on a GPU (measured 2.30x -> 1.32x of
    # gsplat's step on an H200 with two graphs, session 4). "auto": on for CUDA without compile; true needs
    # CUDA.
    cuda_graph: bool | Literal["auto"] = "auto"
    # With cuda_graph: the deferred Gaussian Controller as a graph of its own too (recorded again whenever
    # densification changes N; jsgs.method.graphed.GraphedController). false keeps it eager.
    cuda_graph_gc: bool = True
    # The deferred GC's implementation: "cuda" = jsgs/csrc/controller.cu, three kernels (no graph, no
    # re-recording); "torch" = its twin fro_from_probe_grad (graphed per cuda_graph_gc); "auto": cuda on a
    # GPU where the kernels build, torch elsewhere.
    gc_kernel: Literal["auto", "torch", "cuda"] = "auto"

    @property
    def any_active(self) -> bool:
        return self.jo or self.ds or self.gc


#: ``method_options.compile`` (``jsgs train --compile``, ``jsgs bench --compile``)
COMPILE_BACKENDS = ("off", "inductor", "aot_eager")
_CHOICES = {
    "jpeg_mode": ("paper", "float", "exact"),
    "gc_pooling": ("deferred", "now"),
    "compile": COMPILE_BACKENDS,
    "gc_kernel": KERNEL_CHOICES,
}


def use_cuda_graph(opts: JsgsOptions, device: torch.device) -> bool:
    """Whether JO, L_obs and DS run as CUDA graphs on ``device`` (``method_options.cuda_graph`` resolved);
    JsgsError (one line) for ``true`` off CUDA."""
    if opts.cuda_graph == "auto":
        return device.type == "cuda" and opts.compile == "off"
    if opts.cuda_graph and device.type != "cuda":
        raise JsgsError(
            "config: method jsgs: method_options.cuda_graph needs a CUDA device "
            f'(training on {device.type}); set it to false or "auto"'
        )
    return bool(opts.cuda_graph)


def parse_options(raw: dict[str, Any], where: str = "config") -> JsgsOptions:
    """``method_options`` -> :class:`JsgsOptions`; JsgsError (one line) on an unknown key, a wrong type or
    value, or an ablation combination the paper does not define."""
    opts = JsgsOptions()
    known = [f.name for f in fields(JsgsOptions)]
    for key, value in raw.items():
        if key == "lambda_base":
            raise JsgsError(
                f"{where}: method_options.lambda_base: λ_base is the trainer's loss.base_weight "
                "(set it there; default 1)"
            )
        if key not in known:
            raise JsgsError(
                f"{where}: unknown method_options.{key} for method jsgs (known: {', '.join(known)})"
            )
        default = getattr(opts, key)
        if key == "cuda_graph":
            if not (isinstance(value, bool) or value == "auto"):
                raise JsgsError(
                    f'{where}: method_options.cuda_graph must be true, false or "auto" (got {value!r})'
                )
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise JsgsError(f"{where}: method_options.{key} must be true or false (got {value!r})")
        elif isinstance(default, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise JsgsError(f"{where}: method_options.{key} must be a finite number (got {value!r})")
            value = float(value)
            if key.startswith("lambda_") and value < 0:
                raise JsgsError(f"{where}: method_options.{key} must be >= 0 (got {value})")
            if not key.startswith("lambda_") and value <= 0:
                raise JsgsError(f"{where}: method_options.{key} must be > 0 (got {value})")
        elif key in _CHOICES and value not in _CHOICES[key]:
            raise JsgsError(
                f"{where}: method_options.{key} must be one of {list(_CHOICES[key])} (got {value!r})"
            )
        setattr(opts, key, value)
    if opts.cuda_graph is True and opts.compile != "off":
        raise JsgsError(
            f"{where}: method_options.cuda_graph and method_options.compile ({opts.compile}) cannot be "
            "combined yet; use one of them"
        )
    if not opts.jo and (opts.ds or opts.gc):
        on = " and ".join(n for n, v in (("DS", opts.ds), ("GC", opts.gc)) if v)
        raise JsgsError(
            f"{where}: method jsgs: {on} operate on the JPEG observation (JO) output, so they need JO "
            "(paper Table 2); without JO turn them off too (--no-jo --no-ds --no-gc, which is the baseline)"
        )
    return opts
