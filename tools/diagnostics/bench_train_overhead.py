"""Time per training iteration of ``--method jsgs`` against ``--method gsplat`` on the same scene, in one
call, with a per-phase breakdown (render, ℓ_ph, JO, DS, GC, backward, optimizer, densification).

    .venv/bin/python tools/diagnostics/bench_train_overhead.py          # synthetic scene, CPU or CUDA (auto)
    .venv/bin/python tools/diagnostics/bench_train_overhead.py --manifest DATA/manifest.json \
        --iterations 2000 \
        --device cuda --jpeg-modes paper,float,exact --gc-pooling deferred,now --out overhead.json

Without ``--manifest`` a synthetic scene is built in a temporary folder (``jsgstools`` synth + compress,
gaussian schedule; ``--size``, ``--views``). Every method runs the same settings (``--config`` JSON over the
defaults, ``--iterations``, no evaluation) from the same seed.

Per method (and per JSGS variant):

1. a short untimed warm-up run (gsplat's JIT build, allocator, caches);
2. ``--repeats`` unprofiled runs, interleaved across methods: the honest number, ``time_per_iteration_s`` of
   ``RUN/metrics.json`` (the trainer's device-synchronised training time / steps); the median is reported;
3. one profiled run (the trainer's ``--profile`` phases plus the JSGS hook's own ``jo`` / ``ds`` / ``gc``
   timers): every phase boundary synchronises the device, so the phases add up to more than the
   unprofiled time on a GPU; read them as shares.

Columns of the breakdown (ms per iteration): render (rasterisation forward, incl. the GC probe channels),
l_ph (the baseline loss), JO, DS, GC (before the backward: pooling and L_fro for ``gc_pooling=now``; only the
probe objective for ``deferred``), backward (the rest of the backward pass), GC-bwd (the deferred GC work
inside the backward: r̄, V, L_fro and its closed-form gradient), optimizer, densify, other (data, view
sampling). Densification only happens from step ``strategy.refine_start_iter`` (500 by default) on: give
enough iterations (or lower it in ``--config``) to include it.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from jsgs.base.errors import JsgsError  # noqa: E402
from jsgs.train.config import (  # noqa: E402
    MCMC_CAP_MAX,
    TrainConfig,
    cap_max_settings,
    from_dict,
    load_config_file,
    to_dict,
)
from jsgs.train.data import load_training_scene  # noqa: E402
from jsgs.train.hook import make_hook  # noqa: E402
from jsgs.train.render_view import resolve_device  # noqa: E402
from jsgs.train.trainer import train  # noqa: E402

PHASES = ("render", "l_ph", "JO", "DS", "GC", "backward", "GC-bwd", "optimizer", "densify", "other")


def build_scene(root: Path, size: tuple[int, int], views: int) -> Path:
    from jsgstools.compress import compress
    from jsgstools.synth import synth

    synth(root / "scene", views=views, size=size, seed=0)
    compress(root / "scene", root / "data", "gaussian", seed=0, jobs=1)
    return root / "data" / "manifest.json"


def report_header(
    fmt: str, version: int, args: argparse.Namespace, manifest: Path, device: str
) -> dict[str, Any]:
    """The first keys of a diagnostics tool's JSON report: its format and version, jsgs's version, the
    command's settings (paths as text), what it measured on (``manifest``, or without ``args.manifest``
    the synthetic scene of ``args.size`` and ``args.views`` built there), the device and torch's version."""
    import jsgs

    return {
        "format": fmt,
        "format_version": version,
        "version": jsgs.__version__,
        "settings": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
        "manifest": f"synthetic {args.size}, {args.views} views" if args.manifest is None else str(manifest),
        "device": device,
        "torch": torch.__version__,
    }


#: ``--cap-max``'s help in the diagnostics that take it (:func:`start_config`)
CAP_MAX_HELP = (
    "strategy.type mcmc: the Gaussian budget of every method, over the preset (and --config where the tool "
    "takes one), read as jsgs train reads it: a fixed number, or auto (the budget jsgs train chooses for the "
    "scene) [300000 unless a --config gives one: the published profiles' budget]"
)


def start_config(preset: str, config: Path | None, cap_max: str | None) -> TrainConfig:
    """The settings every method of a diagnostic starts from: ``preset``; with an mcmc strategy the fixed
    budget of :data:`MCMC_CAP_MAX` over it, the one the published step profiles ran at (not the mcmc
    preset's scene-sized default); the ``config`` file over that; ``cap_max`` (``--cap-max N|auto``, read by
    :func:`jsgs.train.config.cap_max_settings`, as ``jsgs train`` reads it) over all. JsgsError (one line)
    for a ``cap_max`` that is neither a number of at least 1 nor auto, or given with another strategy."""
    cfg = TrainConfig.from_preset(preset)
    if cfg.strategy.type == "mcmc":
        cfg = from_dict({"strategy": cap_max_settings(str(MCMC_CAP_MAX))}, preset, base=cfg)
    if config is not None:
        cfg = load_config_file(config, cfg)
    if cap_max is None:
        return cfg
    if cfg.strategy.type != "mcmc":
        kind = cfg.strategy.type
        raise JsgsError(f"--cap-max applies to strategy.type mcmc (--preset mcmc); it is {kind!r}")
    return from_dict({"strategy": cap_max_settings(cap_max)}, "--cap-max", base=cfg)


def variant_config(
    base: TrainConfig, name: str, options: dict[str, Any], iterations: int, device: str
) -> TrainConfig:
    cfg = from_dict(to_dict(base), "bench")
    cfg.method = name
    cfg.method_options = dict(options) if name == "jsgs" else {}
    cfg.iterations = iterations
    cfg.eval_at = []
    cfg.device = device  # type: ignore[assignment]
    cfg.check("bench")
    return cfg


def run_once(manifest: Path, out: Path, cfg: TrainConfig, profile: bool) -> dict[str, Any]:
    """One training run; with ``profile``, also the hook's own phase timers."""
    hook = None
    if profile and cfg.method != "gsplat":
        scene = load_training_scene(manifest, cfg)
        hook = make_hook(cfg, scene, resolve_device(cfg.device))
        if hook is not None:
            hook.profile = True  # type: ignore[attr-defined]
    doc = train(
        manifest, out, cfg, force=True, progress=False, profile=profile, hook=hook, log=lambda s: None
    )
    steps = doc["step"]
    result = {
        "time_per_iteration_ms": 1000.0 * doc["time_per_iteration_s"],
        "num_gaussians": doc["num_gaussians"],
        "device_name": doc["device_name"],
        "backend": doc["backend"],
    }
    if profile:
        loop = doc["profile_ms_per_step"] or {}
        hk = {k: 1000.0 * v / steps for k, v in getattr(hook, "timings", {}).items()}
        gc_bwd = hk.get("gc_backward", 0.0)
        result["phases_ms"] = {
            "render": loop.get("render", 0.0),
            "l_ph": loop.get("loss", 0.0),
            "JO": hk.get("jo", 0.0),
            "DS": hk.get("ds", 0.0),
            "GC": hk.get("gc", 0.0),
            "backward": loop.get("backward", 0.0) - gc_bwd,
            "GC-bwd": gc_bwd,
            "optimizer": loop.get("optimizer", 0.0),
            "densify": loop.get("densify", 0.0),
            "other": loop.get("data", 0.0)
            + max(0.0, loop.get("hook", 0.0) - hk.get("jo", 0.0) - hk.get("ds", 0.0) - hk.get("gc", 0.0)),
        }
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--manifest", type=Path, help="scene manifest (default: a synthetic scene)")
    ap.add_argument("--size", default="160x120", help="synthetic scene image size WxH [160x120]")
    ap.add_argument("--views", type=int, default=16, help="synthetic scene views [16]")
    ap.add_argument("--config", type=Path, help="JSON settings over the defaults, for every method")
    ap.add_argument("--iterations", type=int, default=None, help="steps per run [CPU 30, CUDA 1000]")
    ap.add_argument(
        "--warmup", type=int, default=None, help="steps of the untimed warm-up runs [CPU 3, CUDA 50]"
    )
    ap.add_argument("--repeats", type=int, default=1, help="unprofiled runs per method (median) [1]")
    ap.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    ap.add_argument("--jpeg-modes", default="paper", help="JSGS variants: comma-separated JO modes [paper]")
    ap.add_argument("--gc-pooling", default="deferred", help="JSGS variants: deferred,now [deferred]")
    ap.add_argument(
        "--compile", default="off",
        help="JSGS variants: method_options.speed.compile, e.g. off,inductor [off]",
    )  # fmt: skip
    ap.add_argument(
        "--cuda-graph",
        default="off",
        help="JSGS variants: method_options.speed.cuda_graph: off, on, or jo (JO/L_obs/DS graphed, the GC "
        "eager: cuda_graph_gc false), e.g. off,jo,on [off]",
    )
    ap.add_argument("--no-profile", action="store_true", help="skip the profiled runs (breakdown)")
    ap.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    ap.add_argument("--out", type=Path, help="write the results as JSON here")
    ap.add_argument("--workdir", type=Path, help="run folders go here (default: a temporary folder)")
    args = ap.parse_args()

    if args.threads:
        torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    cuda = device.type == "cuda"
    iterations = args.iterations or (1000 if cuda else 30)
    warmup = args.warmup if args.warmup is not None else (50 if cuda else 3)
    paper = TrainConfig.from_preset("paper")
    base = load_config_file(args.config, paper) if args.config else paper

    variants: list[tuple[str, str, dict[str, Any]]] = [("gsplat", "gsplat", {})]
    for mode in args.jpeg_modes.split(","):
        for pooling in args.gc_pooling.split(","):
            for comp in args.compile.split(","):
                for graph in args.cuda_graph.split(","):
                    if graph != "off" and (comp != "off" or not cuda):
                        continue  # not combinable with compile (yet); CUDA graphs need CUDA
                    label = f"jsgs ({mode}, {pooling}" + ("" if comp == "off" else f", compile {comp}")
                    label += {"off": "", "on": ", CUDA graph", "jo": ", CUDA graph w/o GC"}[graph] + ")"
                    speed: dict[str, Any] = {"compile": comp, "cuda_graph": graph != "off"}
                    if graph == "jo":
                        speed["cuda_graph_gc"] = False
                    opts = {"jpeg_mode": mode, "gc_pooling": pooling, "speed": speed}
                    variants.append((label, "jsgs", opts))

    with tempfile.TemporaryDirectory() as tmp:
        work = args.workdir or Path(tmp)
        if args.manifest is None:
            w, h = (int(v) for v in args.size.lower().split("x"))
            manifest = build_scene(work / "synthetic", (w, h), args.views)
        else:
            manifest = args.manifest
        cfgs = {label: variant_config(base, m, o, iterations, str(device)) for label, m, o in variants}
        for _label, m, o in variants:
            run_once(manifest, work / "warmup", variant_config(base, m, o, warmup, str(device)), False)
        times: dict[str, list[float]] = {label: [] for label, _, _ in variants}
        results: dict[str, dict[str, Any]] = {}
        for _ in range(args.repeats):
            for label, _, _ in variants:
                r = run_once(manifest, work / "run", cfgs[label], False)
                times[label].append(r["time_per_iteration_ms"])
                results[label] = r
        for label, _, _ in variants:
            results[label]["time_per_iteration_ms"] = statistics.median(times[label])
            results[label]["all_times_ms"] = times[label]
            if not args.no_profile:
                results[label]["phases_ms"] = run_once(manifest, work / "run", cfgs[label], True)["phases_ms"]

    ref = results["gsplat"]["time_per_iteration_ms"]
    first = next(iter(results.values()))
    print(
        f"scene {manifest}, {iterations} iterations, device {first['device_name']} ({first['backend']}), "
        f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads"
    )
    print()
    print("| method | ms / it | × gsplat | #Gaussians (end) |")
    print("|---|---|---|---|")
    for label, r in results.items():
        t = r["time_per_iteration_ms"]
        print(f"| {label} | {t:.2f} | {t / ref:.3f} | {r['num_gaussians']} |")
    if not args.no_profile:
        print()
        print("Profiled breakdown (ms / it, device-synchronised at every phase boundary):")
        print()
        print("| method | " + " | ".join(PHASES) + " | sum |")
        print("|---" * (len(PHASES) + 2) + "|")
        for label, r in results.items():
            ph = r["phases_ms"]
            print(
                f"| {label} | " + " | ".join(f"{ph[p]:.2f}" for p in PHASES) + f" | {sum(ph.values()):.2f} |"
            )
    if args.out:
        import jsgs
        from jsgs.base.io import write_json_checked

        doc = {
            "format": "jsgs-overhead",
            "format_version": 1,
            "version": jsgs.__version__,
            "settings": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
            "manifest": str(manifest),
            "iterations": iterations,
            "device": str(device),
            "torch": torch.__version__,
            "results": results,
        }
        write_json_checked(args.out, doc, "overhead")


if __name__ == "__main__":
    main()
