"""The training loop: gsplat 1.5.3 simple_trainer's step, evaluation, checkpoints, resume, outputs.

One step (0-based ``step``), as simple_trainer's ``train()``:

1. sample a training view (shuffled epochs), SH degree = min(step // 1000, 3);
2. rasterise it; ``DefaultStrategy.step_pre_backward`` (retain the screen-space means' gradient);
3. l_ph = (1 - ssim_lambda) L1 + ssim_lambda (1 - SSIM); plus the method hook's terms (see
   :mod:`jsgs.train.method`); check every term and every gradient for NaN/Inf;
4. backward, Adam step on every group, the means' LR decay, ``DefaultStrategy.step_post_backward``
   (densify / prune);
5. after steps listed in ``eval_at`` (1-based counts): evaluate on the test views, write metrics.json and a
   checkpoint.

Outputs in RUN/: ``config.json`` (settings, derived values, versions), ``metrics.json`` (schema
``schemas/metrics.schema.json``), ``point_cloud.ply`` (3DGS layout, in the normalised training world; the
transform is in config.json), ``renders/step_XXXXXX/*.png`` (test views), ``checkpoints/step_XXXXXX.pt``.
"""

from __future__ import annotations

import math
import platform
import random
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

import jsgs
from jsgs.cuda_ext import use_kernels
from jsgs.errors import JsgsError
from jsgs.io import write_json_atomic
from jsgs.train import checkpoint as ckpt
from jsgs.train.config import RUN_CONFIG_FORMAT, RUN_CONFIG_VERSION, TrainConfig, from_dict, to_dict
from jsgs.train.data import ViewSampler, load_eval_images, load_scene, load_train_images
from jsgs.train.evaluate import evaluate, synchronize
from jsgs.train.method import HookOutput, LossHook, StepContext, make_hook
from jsgs.train.model import (
    PARAM_NAMES,
    init_splats,
    make_means_scheduler,
    make_optimizers,
    sh_degree_at,
    splats_from_state,
)
from jsgs.train.profiler import Profiler
from jsgs.train.render_view import render_view, resolve_backend, resolve_device

METRICS_FORMAT = "jsgs-metrics"
METRICS_VERSION = 1
# What a run writes into RUN/ (--force removes exactly these, nothing else).
RUN_ENTRIES = ("config.json", "metrics.json", "point_cloud.ply", "renders", "checkpoints")


class TrainingDiverged(JsgsError):
    """A loss term or a gradient became NaN/Inf. The message names it and the iteration."""


@dataclass
class RunPaths:
    root: Path

    @property
    def config(self) -> Path:
        return self.root / "config.json"

    @property
    def metrics(self) -> Path:
        return self.root / "metrics.json"

    @property
    def ply(self) -> Path:
        return self.root / "point_cloud.ply"

    @property
    def checkpoints(self) -> Path:
        return self.root / "checkpoints"

    def renders(self, step: int) -> Path:
        return self.root / "renders" / f"step_{step:06d}"


@dataclass
class LogAccumulator:
    """Sums of each logged value since the last evaluation (floats, so the averages are exact to resume).

    ``per_view`` holds one accumulator per training view (by name) for the loss and the terms, so a run
    shows which views its loss comes from (issue 6: do the worst JPEGs dominate training?)."""

    steps: int = 0
    loss: float = 0.0
    terms: dict[str, float] = field(default_factory=dict)
    stats: dict[str, float] = field(default_factory=dict)
    per_view: dict[str, LogAccumulator] = field(default_factory=dict)

    def add(
        self, loss: float, terms: dict[str, float], stats: dict[str, float], view: str | None = None
    ) -> None:
        self.steps += 1
        self.loss += loss
        for k, v in terms.items():
            self.terms[k] = self.terms.get(k, 0.0) + v
        for k, v in stats.items():
            self.stats[k] = self.stats.get(k, 0.0) + v
        if view is not None:
            self.per_view.setdefault(view, LogAccumulator()).add(loss, terms, {})

    def means(self) -> dict[str, Any]:
        n = max(self.steps, 1)
        views = {name: acc.means() for name, acc in sorted(self.per_view.items())}
        return {
            "steps": self.steps,
            "loss": self.loss / n if self.steps else None,
            "terms": {k: v / n for k, v in self.terms.items()},
            "stats": {k: v / n for k, v in self.stats.items()},
            "per_view": {name: {k: m[k] for k in ("steps", "loss", "terms")} for name, m in views.items()},
        }

    def state(self) -> dict[str, Any]:
        return {
            "steps": self.steps,
            "loss": self.loss,
            "terms": dict(self.terms),
            "stats": dict(self.stats),
            "per_view": {k: v.state() for k, v in self.per_view.items()},
        }

    @classmethod
    def from_state(cls, s: dict[str, Any]) -> LogAccumulator:
        # checkpoints written before per-view sums existed resume with none for that interval
        per_view = {k: cls.from_state(v) for k, v in s.get("per_view", {}).items()}
        return cls(int(s["steps"]), float(s["loss"]), dict(s["terms"]), dict(s["stats"]), per_view)


def _versions() -> dict[str, Any]:
    try:
        import gsplat

        gv: str | None = gsplat.__version__
    except Exception:  # gsplat is optional on a CPU-only install
        gv = None
    return {
        "jsgs": jsgs.__version__,
        "torch": torch.__version__,
        "gsplat": gv,
        "python": platform.python_version(),
    }


def _strategy(cfg: TrainConfig) -> Any:
    from gsplat.strategy import DefaultStrategy

    s = cfg.strategy
    return DefaultStrategy(
        prune_opa=s.prune_opa,
        grow_grad2d=s.grow_grad2d,
        grow_scale3d=s.grow_scale3d,
        grow_scale2d=s.grow_scale2d,
        prune_scale3d=s.prune_scale3d,
        prune_scale2d=s.prune_scale2d,
        refine_scale2d_stop_iter=s.refine_scale2d_stop_iter,
        refine_start_iter=s.refine_start_iter,
        refine_stop_iter=s.refine_stop_iter,
        reset_every=s.reset_every,
        refine_every=s.refine_every,
        pause_refine_after_reset=s.pause_refine_after_reset,
        absgrad=s.absgrad,
        revised_opacity=s.revised_opacity,
        verbose=False,
    )


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)


def _diff_settings(a: dict[str, Any], b: dict[str, Any], prefix: str = "") -> str | None:
    """The first dotted key whose value differs between two settings dicts."""
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k), b.get(k)
        if isinstance(va, dict) and isinstance(vb, dict) and k != "method_options":
            d = _diff_settings(va, vb, prefix + k + ".")
            if d:
                return d
        elif va != vb:
            return f"{prefix}{k} ({va!r} in the run, {vb!r} now)"
    return None


def _check_out(paths: RunPaths, resume: bool, force: bool) -> None:
    """Refuse a RUN that cannot be used, before anything is read or written."""
    root = paths.root
    if root.exists() and not root.is_dir():
        raise JsgsError(f"{root}: exists and is not a folder")
    if resume:
        if not paths.config.exists():
            raise JsgsError(f"{root}: nothing to resume (no config.json); start the run without --resume")
        return
    if root.exists() and any(root.iterdir()) and not force:
        raise JsgsError(
            f"{root}: folder is not empty; pass --resume to continue that run or --force to overwrite it"
        )


def _clear_out(paths: RunPaths) -> None:
    """--force: remove what an earlier run wrote (RUN_ENTRIES only; anything else in RUN is left alone)."""
    for name in RUN_ENTRIES:
        p = paths.root / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    paths.root.mkdir(parents=True, exist_ok=True)


def load_run_settings(run_dir: str | Path) -> TrainConfig:
    """The settings of an existing run (``RUN/config.json``)."""
    from jsgs.train.config import load_config_file

    path = Path(run_dir) / "config.json"
    if not path.exists():
        raise JsgsError(
            f"{Path(run_dir)}: nothing to resume (no config.json); start the run without --resume"
        )
    return load_config_file(path)


def _finite_check(
    step: int,
    names: list[str],
    values: list[float],
    grad_names: list[str],
    grad_ok: list[float],
    last_ckpt: str,
) -> None:
    for n, v in zip(names, values, strict=True):
        if not math.isfinite(v):
            kind = "NaN" if math.isnan(v) else "Inf"
            raise TrainingDiverged(
                f"iteration {step + 1}: loss term {n!r} is {kind}; training stopped (last good checkpoint: "
                f"{last_ckpt})"
            )
    for n, ok in zip(grad_names, grad_ok, strict=True):
        if not ok:
            raise TrainingDiverged(
                f"iteration {step + 1}: the gradient of {n!r} has NaN/Inf values (loss terms finite); "
                "training "
                f"stopped (last good checkpoint: {last_ckpt})"
            )


def train(
    manifest: str | Path,
    out: str | Path,
    cfg: TrainConfig | None = None,
    *,
    resume: bool = False,
    force: bool = False,
    stop_at: int | None = None,
    progress: bool = True,
    profile: bool = False,
    command: str | None = None,
    hook: LossHook | None = None,
    log: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Train on ``manifest`` into the folder ``out``; returns the metrics document (also in RUN/metrics.json).

    ``cfg``: the settings (defaults when None). With ``resume``, the run's own settings are used; ``cfg``,
    when given, must equal them. ``stop_at``: stop (with a checkpoint) after that many steps, as an
    interruption would (for tests and time-boxed jobs). ``profile``: record per-phase times (synchronises
    the device at each phase; slower). ``hook``: a loss hook to use instead of the method's own (tests).
    ``log``: where one-line notes go (stderr by default). Raises JsgsError on bad input, TrainingDiverged
    on NaN/Inf."""
    say = log or (lambda s: print(s, file=sys.stderr))
    paths = RunPaths(Path(out))
    manifest = Path(manifest)
    _check_out(paths, resume, force)

    start_ckpt: dict[str, Any] | None = None
    if resume:
        stored = load_run_settings(paths.root)
        if cfg is not None:
            d = _diff_settings(to_dict(stored), to_dict(cfg))
            if d:
                raise JsgsError(
                    f"{paths.root}: --resume continues the run with its own settings; differs: {d}"
                )
        cfg = stored
        found = ckpt.list_checkpoints(paths.checkpoints)
        if not found:
            raise JsgsError(
                f"{paths.checkpoints}: no checkpoint to resume from; start the run again with --force"
            )
        start_ckpt = ckpt.load_checkpoint(found[-1][1])
        start_ckpt["_path"] = str(found[-1][1])
    cfg = cfg if cfg is not None else TrainConfig()
    cfg.check()
    if stop_at is not None and not 1 <= stop_at <= cfg.iterations:
        raise JsgsError(f"stop_at must lie in 1..{cfg.iterations} (got {stop_at})")

    t_setup = time.perf_counter()
    device = resolve_device(cfg.device)
    backend = resolve_backend(cfg, device)
    _seed_everything(cfg.seed)
    scene = load_scene(manifest, cfg)
    for note in scene.notes:
        say(f"note: {note}")
    if resume:
        old = json_load(paths.config)
        if old.get("manifest", {}).get("sha256") != scene.manifest_sha256:
            raise JsgsError(f"{manifest}: differs from the manifest the run in {paths.root} was started with")
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        # IEEE float32 convolutions for the whole run (SSIM in the losses and metrics; jsgs.precision), also
        # where torch.compile'd code cannot enter jsgs.precision's context
        torch.backends.cudnn.allow_tf32 = False
    train_views = scene.train_views
    train_images = load_train_images(scene, device)
    eval_images = load_eval_images(scene, device) if cfg.eval_at else {}
    if hook is None:
        # the method's own random draws (if any) must not shift the initialisation: every method starts
        # from the same Gaussians as the baseline for a given seed
        with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
            hook = make_hook(cfg, scene, device)
    strategy = _strategy(cfg)
    sampler = ViewSampler(len(train_views), cfg.seed)

    if start_ckpt is None:
        splats = init_splats(
            torch.from_numpy(scene.points),
            torch.from_numpy(scene.points_rgb).float() / 255.0,
            cfg,
            scene.scene_scale,
            device,
        )
    else:
        splats = splats_from_state(start_ckpt["splats"], device)
    optimizers = make_optimizers(splats, cfg, scene.scene_scale)
    scheduler = make_means_scheduler(optimizers["means"], cfg)
    strategy.check_sanity(splats, optimizers)
    strategy_state = strategy.initialize_state(scene_scale=scene.scene_scale)

    evals: list[dict[str, Any]] = []
    acc = LogAccumulator()
    train_time = 0.0
    start_step = 0
    last_ckpt = "none"
    if start_ckpt is not None:
        for name in PARAM_NAMES:
            optimizers[name].load_state_dict(start_ckpt["optimizers"][name])
        scheduler.load_state_dict(start_ckpt["scheduler"])
        strategy_state = ckpt.to_device(start_ckpt["strategy"], device)
        ckpt.set_rng_state(start_ckpt["rng"])
        sampler.load_state_dict(start_ckpt["sampler"])
        if hook is not None:
            hook.load_state_dict(ckpt.to_device(start_ckpt["hook"], device))
        elif start_ckpt["hook"]:
            raise JsgsError(f"{start_ckpt['_path']}: holds method state but the method has no hook")
        evals = list(start_ckpt["evals"])
        acc = LogAccumulator.from_state(start_ckpt["log"])
        train_time = float(start_ckpt["train_time_s"])
        start_step = int(start_ckpt["step"])
        last_ckpt = start_ckpt["_path"]
        say(f"resuming {paths.root} at step {start_step} of {cfg.iterations}")

    derived = {
        "device": str(device),
        "backend": backend,
        "scene_scale": scene.scene_scale,
        "camera_extent": scene.camera_extent,
        "normalization": scene.transform.tolist(),
        "num_train_views": len(train_views),
        "num_test_views": len(scene.test_views),
        "initial_gaussians": int(splats["means"].shape[0])
        if start_ckpt is None
        else int(json_load(paths.config)["derived"]["initial_gaussians"]),
        "notes": scene.notes,
        "ssim_kernel": "cuda" if use_kernels(cfg.loss.ssim_kernel, device, "loss.ssim_kernel") else "torch",
        "method": hook.describe() if hook is not None else {},
    }
    if not resume:
        _clear_out(paths)  # only now that the settings and the manifest have been checked
        run_config = {
            "format": RUN_CONFIG_FORMAT,
            "format_version": RUN_CONFIG_VERSION,
            "versions": _versions(),
            "command": command or "",
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "manifest": {"path": str(scene.manifest_path), "sha256": scene.manifest_sha256},
            "settings": to_dict(cfg),
            "derived": derived,
        }
        from jsgs.schemas import validate

        validate(run_config, "config", str(paths.config))
        write_json_atomic(paths.config, run_config)
    setup_time = time.perf_counter() - t_setup

    def metrics_doc(status: str, step: int, error: str | None = None) -> dict[str, Any]:
        return {
            "format": METRICS_FORMAT,
            "format_version": METRICS_VERSION,
            "status": status,
            "error": error,
            "method": cfg.method,
            "scene": scene.name,
            "manifest": str(scene.manifest_path),
            "device": str(device),
            "device_name": _device_name(device),
            "backend": backend,
            "iterations": cfg.iterations,
            "step": step,
            "num_gaussians": int(splats["means"].shape[0]),
            "train_time_s": train_time,
            "setup_time_s": setup_time,
            "time_per_iteration_s": train_time / max(step, 1) if step else None,
            "profile_ms_per_step": profiler.summary(),
            "evals": evals,
        }

    def write_metrics(doc: dict[str, Any]) -> None:
        from jsgs.schemas import validate

        validate(doc, "metrics", str(paths.metrics))
        write_json_atomic(paths.metrics, doc)

    def save(step_done: int) -> str:
        path = ckpt.checkpoint_path(paths.checkpoints, step_done)
        ckpt.save_checkpoint(
            path,
            {
                "step": step_done,
                "settings": to_dict(cfg),
                "manifest_sha256": scene.manifest_sha256,
                "splats": {n: splats[n].data for n in PARAM_NAMES},
                "optimizers": {n: o.state_dict() for n, o in optimizers.items()},
                "scheduler": scheduler.state_dict(),
                "strategy": strategy_state,
                "rng": ckpt.rng_state(),
                "sampler": sampler.state_dict(),
                "hook": hook.state_dict() if hook is not None else {},
                "evals": evals,
                "log": acc.state(),
                "train_time_s": train_time,
            },
        )
        return str(path)

    profiler = Profiler(profile, device)
    if start_step >= cfg.iterations:
        say(f"{paths.root}: the run is already complete ({cfg.iterations} iterations)")
        doc = metrics_doc("complete", start_step)
        write_metrics(doc)
        return doc

    eval_steps = set(cfg.eval_at)
    end_step = cfg.iterations if stop_at is None else stop_at
    bar = _progress(progress, start_step, cfg.iterations)
    seg_start = time.perf_counter()
    step = start_step
    try:
        for step in range(start_step, end_step):
            with profiler.phase("data"):
                view = train_views[sampler.next()]
                target = train_images[view.index].float()[None] / 255.0
                sh_degree = sh_degree_at(step, cfg)
                extra_feats = hook.extra_channels(step, view, splats) if hook is not None else None
                extra_kw = hook.render_kwargs(step, view) if hook is not None else None
            with profiler.phase("render"):
                r = render_view(
                    splats,
                    view.viewmat_tensor(device),
                    view.K_tensor(device),
                    view.width,
                    view.height,
                    sh_degree,
                    cfg,
                    backend,
                    extra_feats,
                    extra_kw,
                )
                rgb = r.rgb
                if cfg.render.random_background:
                    bkgd = torch.rand(1, 3, device=device)
                    rgb = rgb + bkgd * (1.0 - r.alpha)
                strategy.step_pre_backward(splats, optimizers, strategy_state, step, r.info)
            with profiler.phase("loss"):
                terms, weights = _base_terms(rgb, target, splats, cfg)
            stats: dict[str, Any] = {}
            folded: frozenset[str] = frozenset()
            folded_loss = None
            if hook is not None:
                with profiler.phase("hook"):
                    ctx = StepContext(
                        step=step,
                        view=view,
                        render=rgb,
                        alpha=r.alpha,
                        target=target,
                        info=r.info,
                        splats=splats,
                        extra=r.extra,
                        base_terms=dict(terms),
                        sh_degree=sh_degree,
                    )
                    hout: HookOutput = hook.losses(ctx)
                    hout.check(cfg.method)
                    terms.update(hout.terms)
                    weights.update(hout.weights)
                    stats = dict(hout.stats)
                    folded, folded_loss = hout.folded, hout.folded_loss
            loss = weighted_loss(terms, weights, folded, folded_loss)
            with profiler.phase("backward"):
                loss.backward()
            # one host sync per step: every logged value and the gradients' finiteness together
            names = list(terms)
            grad_names = [n for n in PARAM_NAMES if splats[n].grad is not None]
            packed_vals = torch.stack(
                [loss.detach().float()]
                + [terms[n].detach().float().reshape(()) for n in names]
                + [_stat_tensor(stats[k], device) for k in stats]
                + [torch.isfinite(splats[n].grad).all().float() for n in grad_names]
            ).tolist()
            term_v = packed_vals[1 : 1 + len(names)]
            # Summed from the term values read *after* the backward: a method may fill a term's value during
            # the backward (JSGS's deferred L_fro), which the pre-backward total cannot include.
            loss_v = packed_vals[0] if hook is None else _weighted_sum(names, term_v, weights)
            stat_v = packed_vals[1 + len(names) : 1 + len(names) + len(stats)]
            grad_ok = packed_vals[1 + len(names) + len(stats) :]
            _finite_check(step, [*names, "loss"], [*term_v, loss_v], grad_names, grad_ok, last_ckpt)
            with profiler.phase("optimizer"):
                for o in optimizers.values():
                    o.step()
                    o.zero_grad(set_to_none=True)
                scheduler.step()
            with profiler.phase("densify"):
                strategy.step_post_backward(
                    splats, optimizers, strategy_state, step, r.info, packed=cfg.render.packed
                )
            profiler.steps += 1
            acc.add(
                loss_v,
                dict(zip(names, term_v, strict=True)),
                dict(zip(stats, stat_v, strict=True)),
                view.name,
            )
            done = step + 1
            if bar is not None:
                bar.update(1)
                if done % cfg.log_every == 0 or done == end_step:
                    parts = [f"loss={loss_v:.4f}", f"#G={splats['means'].shape[0]}"]
                    parts += [
                        f"{k}={v:.4g}"
                        for k, v in zip(names, term_v, strict=True)
                        if k not in ("photometric",)
                    ]
                    parts += [f"{k}={v:.4g}" for k, v in zip(stats, stat_v, strict=True)]
                    bar.set_postfix_str(" ".join(parts), refresh=False)
            is_eval = done in eval_steps
            is_ckpt = (
                is_eval
                or done == cfg.iterations
                or done == end_step
                or (cfg.checkpoint_every > 0 and done % cfg.checkpoint_every == 0)
            )
            if is_ckpt:
                synchronize(device)
                train_time += time.perf_counter() - seg_start
                if is_eval:
                    entry = evaluate(
                        splats, scene, eval_images, cfg, backend, device, done, paths.renders(done)
                    )
                    entry["train_time_s"] = train_time
                    entry["time_per_iteration_s"] = train_time / done
                    entry["train"] = acc.means()
                    evals.append(entry)
                    acc = LogAccumulator()
                    if bar is not None:
                        bar.write(_eval_line(entry))
                    else:
                        say(_eval_line(entry))
                last_ckpt = save(done)
                status = (
                    "complete" if done == cfg.iterations else ("stopped" if done == end_step else "running")
                )
                write_metrics(metrics_doc(status, done))
                seg_start = time.perf_counter()
    except TrainingDiverged as e:
        if bar is not None:
            bar.close()
            bar = None
        write_metrics(metrics_doc("diverged", step, str(e)))
        raise
    finally:
        if bar is not None:
            bar.close()

    doc = metrics_doc("complete" if end_step == cfg.iterations else "stopped", end_step)
    if end_step == cfg.iterations:
        from jsgs.ply import save_ply

        save_ply(
            paths.ply,
            splats["means"],
            splats["scales"],
            splats["quats"],
            splats["opacities"],
            splats["sh0"],
            splats["shN"],
        )
    write_metrics(doc)
    return doc


def _stat_tensor(value: Any, device: torch.device) -> torch.Tensor:
    if isinstance(value, torch.Tensor):
        return value.detach().float().reshape(()).to(device)
    return torch.tensor(float(value), dtype=torch.float32, device=device)


def _base_terms(
    rgb: torch.Tensor, target: torch.Tensor, splats: torch.nn.ParameterDict, cfg: TrainConfig
) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
    """gsplat's photometric loss (and its optional regularisers): unweighted terms and their weights.

    rgb, target: [1, H, W, 3]. ``photometric`` carries weight ``base_weight``; ``l1`` and ``ssim``
    (= 1 - SSIM) are logged with weight 0 (they are inside ``photometric``)."""
    from jsgs.ssim import ssim

    lam = cfg.loss.ssim_lambda
    l1 = F.l1_loss(rgb, target)
    ssim_term = 1.0 - ssim(
        rgb.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2), padding=cfg.loss.ssim_padding,
        kernel=cfg.loss.ssim_kernel,
    )
    photometric = (1.0 - lam) * l1 + lam * ssim_term
    terms = {"l1": l1, "ssim": ssim_term, "photometric": photometric}
    weights = {"l1": 0.0, "ssim": 0.0, "photometric": cfg.loss.base_weight}
    if cfg.loss.opacity_reg > 0.0:
        terms["opacity_reg"] = torch.sigmoid(splats["opacities"]).mean()
        weights["opacity_reg"] = cfg.loss.opacity_reg
    if cfg.loss.scale_reg > 0.0:
        terms["scale_reg"] = torch.exp(splats["scales"]).mean()
        weights["scale_reg"] = cfg.loss.scale_reg
    return terms, weights


def weighted_loss(
    terms: dict[str, torch.Tensor],
    weights: dict[str, float],
    folded: frozenset[str] = frozenset(),
    folded_loss: torch.Tensor | None = None,
) -> torch.Tensor:
    """The step's loss Σ weights[k]·terms[k] (terms of weight 0 left out) with the terms in ``folded``
    replaced by their ready-made weighted sum ``folded_loss`` (:class:`jsgs.train.method.HookOutput`).

    Each multiplication and addition is a kernel and an autograd node, which on a GPU cost more host time
    than device time, so a weight of 1 is not multiplied and the sum starts from the first part, not 0."""
    parts = [
        terms[k] if weights[k] == 1.0 else weights[k] * terms[k]
        for k in weights
        if weights[k] != 0.0 and k not in folded
    ]
    if folded_loss is not None:
        parts.append(folded_loss)
    if not parts:
        raise JsgsError("every loss term has weight 0: nothing to optimise")
    loss = parts[0]
    for p in parts[1:]:
        loss = loss + p
    return loss


def _weighted_sum(names: list[str], values: list[float], weights: dict[str, float]) -> float:
    pairs = zip(names, values, strict=True)
    return float(sum(weights[n] * v for n, v in pairs if weights.get(n, 0.0) != 0.0))


def _eval_line(e: dict[str, Any]) -> str:
    def f(x: Any, fmt: str) -> str:
        return "n/a" if x is None else format(x, fmt)

    return (
        f"eval @ {e['step']}: PSNR {f(e['psnr'], '.3f')} SSIM {f(e['ssim'], '.4f')} "
        f"LPIPS {f(e['lpips'], '.4f')} "
        f"| {e['num_gaussians']} Gaussians | {f(e['fps'], '.1f')} FPS | train {e['train_time_s']:.1f} s"
    )


def _progress(enabled: bool, initial: int, total: int) -> Any:
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, dynamic_ncols=True, unit="it", desc="train")


def _device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return platform.processor() or platform.machine() or "cpu"


def json_load(path: Path) -> dict[str, Any]:
    import json

    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise JsgsError(f"{path}: cannot read ({e})") from None


def settings_for_resume(run_dir: str | Path, overrides: dict[str, Any]) -> TrainConfig:
    """The run's stored settings with ``overrides`` (nested dict) applied — what the CLI compares on
    ``--resume`` so that a flag that would change the run is refused rather than ignored."""
    return from_dict(overrides, "command line", base=load_run_settings(run_dir))
