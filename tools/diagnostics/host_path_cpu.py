"""``profile_step.py`` on the CPU with JSGS's CUDA-only speed-ups stood in, so that the JSGS step does on the
host what it does on a GPU with the defaults, less the arithmetic the GPU replays or fuses.

    PYTHONPATH=. .venv/bin/python tools/diagnostics/host_path_cpu.py --size 64x48 --views 8 --preset mcmc \
        --warmup 120 --steps 40 --pairs 6 --no-fresh --threads 1 --python-top 40

Takes ``profile_step.py``'s arguments (``--device`` is forced to ``cpu``), and ``--cpu-time``: the windows
are timed by the main thread's CPU time (``time.thread_time``) instead of the wall clock, so that other
processes on a shared machine weigh less on the figures (the "wall ms/step" columns then hold CPU ms per
step; with ``--threads 1`` torch's work runs on that thread). On CUDA with the defaults
(``speed.cuda_graph`` auto, ``speed.gc_kernel`` auto) JO, L_obs and DS are one CUDA-graph replay and the
deferred Gaussian Controller three fused kernels; on the CPU both run as hundreds of eager ops that would
hide the step's other host work. Here:

- the image terms go through :class:`jsgs.method.graphed.GraphedImageTerms` itself (its input copies, output
  clone and known-gradient node), with a stand-in "replay" that does nothing: the recorded outputs are those
  of the first call for each shape (computed eagerly, as the warm-up of a real recording), so the image
  terms' *values and gradients are stale* from then on;
- the fused controller returns copies of the eager twin's outputs for the current parameters' size
  (recomputed when the Gaussian count changes): three ops for its three kernels.

So the counts and host times are those of the step's host path (the trainer, the hook, the probe, the
rasteriser's extra channels on the torch rasteriser), not the training's numbers: read the op counts and the
Python profile, never the losses. gsplat's rasteriser is the torch reference on the CPU, so what the
gsplat-backend path adds on CUDA (``jsgs.render.backend._rasterize_gsplat``'s SH and channel concatenation)
is not in these counts.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import profile_step  # noqa: E402

import jsgs.method.hook as hook_module  # noqa: E402
from jsgs.method.graphed import GraphedImageTerms, _Recording  # noqa: E402
from jsgs.method.image_terms import terms_with_gradient  # noqa: E402


class ReplayStandIn(GraphedImageTerms):
    """:class:`GraphedImageTerms` whose replay does nothing (module docstring): the outputs are the first
    call's."""

    def _record(self, x: Tensor, y: Tensor, tables: Tensor, sampling: str, observation: bool) -> _Recording:
        inputs = (x.detach().clone().requires_grad_(x.requires_grad), y.detach().clone(), tables.clone())
        outputs = terms_with_gradient(
            *inputs, weights=self.weights, sampling=sampling, observation=observation, **self.settings
        )
        return _Recording(lambda: None, inputs, outputs)


_CONTROLLER_CACHE: dict[int, tuple[Tensor, Tensor, Tensor]] = {}


def controller_stand_in(probe_grad: Tensor, *params_and_camera: Any, **settings: Any) -> tuple[Tensor, ...]:
    """The fused controller's outputs as fresh tensors, three ops (module docstring)."""
    from jsgs.kernels import fro_from_probe_grad, packed_fro_stats

    n = probe_grad.shape[-2]
    cached = _CONTROLLER_CACHE.get(n)
    if cached is None:
        out = fro_from_probe_grad(probe_grad, *params_and_camera, **settings)
        cached = _CONTROLLER_CACHE[n] = (out.grad_logit, out.grad_log_scale, packed_fro_stats(out.terms))
    return tuple(t.clone() for t in cached)


def install() -> None:
    """Make every JsgsHook built from now on take the CUDA path's host work (module docstring)."""
    original = hook_module.JsgsHook.__init__

    def init(self: hook_module.JsgsHook, *args: Any, **kwargs: Any) -> None:
        original(self, *args, **kwargs)
        w = self.weights()
        self.cuda_graph = True
        self._graphed = ReplayStandIn(
            weights=(w["obs"], w.get("low", 0.0), w.get("mid", 0.0)), **self._jpeg_settings
        )
        self._gc_fused = self.opts.gc and self.gc_route == "deferred"
        self._gc_graphed = None

    hook_module.JsgsHook.__init__ = init  # type: ignore[method-assign]
    hook_module.fro_from_probe_grad_fused = controller_stand_in  # type: ignore[assignment]


#: profile_step.py's options, passed on as they are (its ``--device`` is set to cpu here)
PASSED_ON = (
    "--manifest", "--size", "--views", "--methods", "--preset", "--config", "--cap-max", "--jsgs-options",
    "--warmup", "--settle", "--steps", "--top", "--python-top", "--trace", "--pairs", "--no-fresh",
    "--threads", "--workdir", "--out", "--memory-history", "--memory-steps", "--memory-stacks",
)  # fmt: skip


class _ThreadClock:
    """The ``time`` module as ``profile_step`` reads it, with ``perf_counter`` the thread's CPU time."""

    perf_counter = staticmethod(time.thread_time)

    def __getattr__(self, name: str) -> Any:
        return getattr(time, name)


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    unknown = [a for a in args if a.startswith("--") and a.split("=")[0] not in (*PASSED_ON, "--cpu-time")]
    if unknown:
        print(f"error: host_path_cpu.py takes profile_step.py's options but {unknown[0]}", file=sys.stderr)
        return 2
    install()
    clock = "perf_counter"
    if "--cpu-time" in args:
        args.remove("--cpu-time")
        profile_step.time = _ThreadClock()  # type: ignore[assignment]
        clock = "thread_time"
    run = profile_step.run

    def run_recorded(a: Any) -> dict[str, Any]:  # the output records what this wrapper changed
        doc = run(a)
        doc["settings"]["host_path_cpu"] = {
            "clock": clock, "stand_ins": ["GraphedImageTerms replay", "fused Gaussian Controller"]
        }
        return doc

    profile_step.run = run_recorded  # type: ignore[assignment]
    return profile_step.main([*args, "--device", "cpu"])


if __name__ == "__main__":
    torch.set_grad_enabled(True)
    sys.exit(main())
