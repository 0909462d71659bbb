"""The generic trainer: gsplat 1.5.3 simple_trainer's step, evaluation, checkpoints, resume, outputs, as a
:class:`Trainer` with callbacks (:mod:`jsgs.train.callbacks`). It knows methods only through the loss-hook
protocol (:mod:`jsgs.train.hook`).

One step (0-based ``step``), as simple_trainer's ``train()``:

1. sample a training view (shuffled epochs), SH degree = min(step // 1000, 3);
2. rasterise it; ``DefaultStrategy.step_pre_backward`` (retain the screen-space means' gradient);
3. l_ph = (1 - ssim_lambda) L1 + ssim_lambda (1 - SSIM) (:func:`jsgs.jpeg.losses.photometric_terms`); plus the
   method hook's terms (see :mod:`jsgs.train.hook`);
4. backward, Adam step on every group, the means' LR decay; every term and every gradient checked for
   NaN/Inf (TrainingDiverged), then ``DefaultStrategy.step_post_backward`` (densify / prune);
5. after steps listed in ``eval_at`` (1-based counts): evaluate on the test views, write metrics.json and a
   checkpoint.

Outputs in RUN/: ``config.json`` (settings, derived values, versions), ``metrics.json`` (schema
``jsgs/schemas/metrics.schema.json``), ``point_cloud.ply`` (3DGS layout, in the normalised training world; the
transform is in config.json), ``renders/step_XXXXXX/*.png`` (test views), ``checkpoints/step_XXXXXX.pt``.
"""

from __future__ import annotations

import json
import math
import os
import platform
import random
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

import jsgs
from jsgs.base.errors import JsgsError
from jsgs.base.io import LOCK_NAME, OutputLock, write_json_atomic
from jsgs.base.run_files import RunPaths
from jsgs.kernels import use_kernels
from jsgs.train import checkpoint as ckpt
from jsgs.train import distributed as dd
from jsgs.train.callbacks import Callback, StepResult
from jsgs.train.config import (
    RUN_CONFIG_FORMAT,
    RUN_CONFIG_VERSION,
    RunConfig,
    TrainConfig,
    holds_run_config,
    read_run_config,
    say_assumed,
    to_dict,
)
from jsgs.train.data import (
    TrainingScene,
    TrainingView,
    ViewSampler,
    image_target,
    load_eval_images,
    load_train_images,
    load_training_scene,
)
from jsgs.train.evaluate import evaluate, reset_peak_allocated, synchronize
from jsgs.train.hook import HookOutput, LossHook, StepContext, make_hook
from jsgs.train.model import (
    PARAM_NAMES,
    init_splats,
    make_means_scheduler,
    make_optimizers,
    sh_degree_at,
    splats_from_state,
)
from jsgs.train.profiler import Profiler
from jsgs.train.render_view import RenderOut, render_view, resolve_backend, resolve_device
from jsgs.train.strategy import Densifier, initial_subset

if TYPE_CHECKING:
    from jsgs.train.budget import AutoBudget

METRICS_FORMAT = "jsgs-metrics"
METRICS_VERSION = 1
# What a run writes into RUN/ (--force removes exactly these, nothing else).
#: the same Gaussians in the scene's COLMAP frame (``jsgs export``'s default), written beside point_cloud.ply
COLMAP_PLY = "point_cloud_colmap.ply"
RUN_ENTRIES = (
    "config.json", "metrics.json", "point_cloud.ply", COLMAP_PLY, f"{COLMAP_PLY}.json", "renders",
    "checkpoints",
)  # fmt: skip
#: the files among them (written atomically: a killed run may leave their temporaries)
RUN_FILES = tuple(n for n in RUN_ENTRIES if "." in n)


class TrainingDiverged(JsgsError):
    """A parameter, a loss term or a gradient became NaN/Inf. The message names it and the iteration;
    ``step`` is the number of steps completed before the one that failed (metrics.json ``step``)."""

    def __init__(self, message: str, step: int | None = None) -> None:
        super().__init__(message)
        self.step = step


class RunFailed(JsgsError):
    """An error after the training steps (writing the model) ended the run: metrics.json says ``failed``."""


class TrainingInterrupted(JsgsError):
    """SIGINT (Ctrl-C) or SIGTERM stopped the run after a whole step, with a checkpoint to resume from."""


@dataclass
class LogAccumulator:
    """Sums of each logged value since the last evaluation (floats, so the averages are exact to resume).

    ``skipped`` counts the steps that did not compute a term or statistic (``HookOutput.skipped``): its sum
    leaves them out and its mean is over the other steps (a value no step computed has no mean).
    ``per_view`` holds one accumulator per training view (by name) for the loss and the terms, so a run
    shows which views its loss comes from (whether the worst JPEGs dominate training)."""

    steps: int = 0
    loss: float = 0.0
    terms: dict[str, float] = field(default_factory=dict)
    stats: dict[str, float] = field(default_factory=dict)
    per_view: dict[str, LogAccumulator] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)

    def add(
        self,
        loss: float,
        terms: dict[str, float],
        stats: dict[str, float],
        view: str | None = None,
        skipped: frozenset[str] = frozenset(),
    ) -> None:
        self.steps += 1
        self.loss += loss
        for part, sums in ((terms, self.terms), (stats, self.stats)):
            for k, v in part.items():
                if k in skipped:
                    self.skipped[k] = self.skipped.get(k, 0) + 1
                    sums.setdefault(k, 0.0)
                else:
                    sums[k] = sums.get(k, 0.0) + v
        if view is not None:
            self.per_view.setdefault(view, LogAccumulator()).add(loss, terms, {}, skipped=skipped)

    def _mean(self, sums: dict[str, float]) -> dict[str, float]:
        counts = {k: self.steps - self.skipped.get(k, 0) for k in sums}
        return {k: v / counts[k] for k, v in sums.items() if counts[k] > 0}

    def means(self) -> dict[str, Any]:
        views = {name: acc.means() for name, acc in sorted(self.per_view.items())}
        out = {
            "steps": self.steps,
            "loss": self.loss / self.steps if self.steps else None,
            "terms": self._mean(self.terms),
            "stats": self._mean(self.stats),
            "per_view": {
                name: {k: m[k] for k in ("steps", "loss", "terms", "skipped") if k in m}
                for name, m in views.items()
            },
        }
        if self.skipped:
            out["skipped"] = dict(self.skipped)
        return out

    def state(self) -> dict[str, Any]:
        return {
            "steps": self.steps,
            "loss": self.loss,
            "terms": dict(self.terms),
            "stats": dict(self.stats),
            "per_view": {k: v.state() for k, v in self.per_view.items()},
            "skipped": dict(self.skipped),
        }

    @classmethod
    def from_state(cls, s: dict[str, Any]) -> LogAccumulator:
        # checkpoints written before per-view sums (or skipped counts) existed resume with none for that
        # interval
        per_view = {k: cls.from_state(v) for k, v in s.get("per_view", {}).items()}
        skipped = {k: int(v) for k, v in s.get("skipped", {}).items()}
        return cls(int(s["steps"]), float(s["loss"]), dict(s["terms"]), dict(s["stats"]), per_view, skipped)


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


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)


def _diff_settings(
    a: dict[str, Any], b: dict[str, Any], prefix: str = "", labels: tuple[str, str] = ("in the run", "now")
) -> str | None:
    """The first dotted key whose value differs between two settings dicts (``labels``: where each is)."""
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k), b.get(k)
        if isinstance(va, dict) and isinstance(vb, dict) and k != "method_options":
            d = _diff_settings(va, vb, prefix + k + ".", labels)
            if d:
                return d
        elif va != vb:
            text = f"{prefix}{k} ({va!r} {labels[0]}, {vb!r} {labels[1]})"
            return text if len(text) <= 300 else text[:297] + "..."
    return None


def _checkpoint_agrees(doc: dict[str, Any], path: Path, run: RunConfig, cfg: TrainConfig) -> None:
    """A checkpoint is used only where it belongs to RUN as it is now: the settings of RUN/config.json, the
    manifest that config.json names, a step within the run's iterations. One line says what differs and how
    to go on otherwise."""
    from jsgs.train.config import recorded_settings

    start_over = "move it out of the way to resume from the checkpoint before it, or start over with --force"
    if doc["manifest_sha256"] != run.manifest_sha256:
        raise JsgsError(
            f"{path}: written for another manifest than the one {run.path} names (its manifest hash "
            f"differs); {start_over}"
        )
    mine = to_dict(recorded_settings(doc["settings"], str(path)))
    d = _diff_settings(to_dict(cfg), mine, labels=(f"in {run.path.name}", "in the checkpoint"))
    if d:
        raise JsgsError(
            f"{path}: written with other settings than {run.path} (edited after the checkpoint?): {d}; "
            f"restore config.json, or start over with --force"
        )
    if doc["step"] > cfg.iterations:
        raise JsgsError(
            f"{path}: at step {doc['step']}, beyond the run's {cfg.iterations} iterations; {start_over}"
        )


def _check_out(paths: RunPaths, resume: bool, force: bool) -> None:
    """Refuse a RUN that cannot be used, before anything is read or written."""
    root = paths.root
    if root.exists() and not root.is_dir():
        raise JsgsError(f"{root}: exists and is not a folder")
    if resume:
        if not paths.config.exists():
            raise JsgsError(f"{root}: nothing to resume (no config.json); start the run without --resume")
        return
    ignored = {root / LOCK_NAME, *_leftovers(paths)}  # a lock and half-written files a killed run left
    entries = [p for p in root.iterdir() if p not in ignored] if root.exists() else []
    if entries and not force:
        raise JsgsError(
            f"{root}: folder is not empty; pass --resume to continue that run or --force to overwrite it"
        )
    if entries and force:
        ours = holds_run_config(root)
        if not ours:
            raise JsgsError(
                f"{root}: --force replaces an earlier run of jsgs train, and this folder holds none (no "
                "config.json of a run); choose another --out"
            )


def _leftovers(paths: RunPaths) -> list[Path]:
    """The temporary files of RUN's atomic writes that a killed run left (its files, checkpoints and
    renders: 0-byte or partial ``.NAME.XXXXXXXX.part*``)."""
    import re

    from jsgs.base.io import atomic_leftovers

    found = atomic_leftovers(paths.root, "|".join(map(re.escape, RUN_FILES)))
    found += atomic_leftovers(paths.checkpoints, r"step_\d+\.pt")
    renders = paths.root / "renders"
    if renders.is_dir() and not renders.is_symlink():
        for d in sorted(renders.iterdir()):
            if d.is_dir() and not d.is_symlink() and d.name.startswith("step_"):
                found += atomic_leftovers(d, r"[^/]+")
    return found


def _remove_leftovers(paths: RunPaths, say: Callable[[str], None]) -> None:
    """Remove what :func:`_leftovers` finds (the caller holds RUN's lock: no writer is at work there)."""
    found = _leftovers(paths)
    for p in found:
        p.unlink(missing_ok=True)
    if found:
        say(f"note: removed {len(found)} half-written file(s) an interrupted run left in {paths.root}")


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
    """The settings of a run to resume (``RUN/config.json``, :func:`jsgs.train.config.read_run_config`)."""
    if not RunPaths(Path(run_dir)).config.exists():
        raise JsgsError(
            f"{Path(run_dir)}: nothing to resume (no config.json); start the run without --resume"
        )
    return read_run_config(run_dir).settings


def _finite_check(
    step: int,
    names: list[str],
    values: list[float],
    grad_names: list[str],
    grad_norms: list[float],
    param_norms: list[float],
    last_ckpt: str,
) -> None:
    """TrainingDiverged at the first non-finite parameter (``param_norms``: each parameter's L1 norm as it
    entered step ``step``, i.e. as step ``step - 1`` and the densification after it left it), loss term or
    gradient (``grad_norms``: each gradient's L1 norm). An L1 norm is NaN or Inf where the tensor holds
    such a value, or where its magnitudes sum beyond float32's range."""
    for n, v in zip(PARAM_NAMES, param_norms, strict=True):
        if not math.isfinite(v):
            raise TrainingDiverged(_param_message(step, n, last_ckpt), step - 1)
    for n, v in zip(names, values, strict=True):
        if not math.isfinite(v):
            kind = "NaN" if math.isnan(v) else "Inf"
            raise TrainingDiverged(
                f"iteration {step + 1}: loss term {n!r} is {kind}; training stopped (last good checkpoint: "
                f"{last_ckpt})",
                step,
            )
    for n, v in zip(grad_names, grad_norms, strict=True):
        if not math.isfinite(v):
            raise TrainingDiverged(
                f"iteration {step + 1}: the gradient of {n!r} is not finite (NaN/Inf values, or beyond "
                f"float32's range; loss terms finite); training stopped (last good checkpoint: {last_ckpt})",
                step,
            )


def _param_message(iteration: int, name: str, last_ckpt: str) -> str:
    return (
        f"iteration {iteration}: parameter {name!r} became non-finite (NaN/Inf values, or magnitudes beyond "
        f"float32's range); training stopped (last good checkpoint: {last_ckpt})"
    )


def param_norms(splats: torch.nn.ParameterDict) -> list[Tensor]:
    """Each parameter's L1 norm (PARAM_NAMES order), on the device: one fused multi-tensor reduction."""
    with torch.no_grad():
        return list(torch._foreach_norm([splats[n] for n in PARAM_NAMES], 1))


def first_nonfinite_param(splats: torch.nn.ParameterDict) -> str | None:
    """The name of the first parameter holding NaN/Inf (or magnitudes summing beyond float32), else None
    (one host sync: for checkpoint points and the start, not every step)."""
    values = torch.stack(param_norms(splats)).tolist()
    return next((n for n, v in zip(PARAM_NAMES, values, strict=True) if not math.isfinite(v)), None)


def check_params_finite(splats: torch.nn.ParameterDict, iteration: int, last_ckpt: str) -> None:
    """TrainingDiverged naming the first non-finite parameter after ``iteration`` steps."""
    bad = first_nonfinite_param(splats)
    if bad is not None:
        raise TrainingDiverged(_param_message(iteration, bad, last_ckpt), max(iteration - 1, 0))


def _stat_tensor(value: Any, device: torch.device) -> torch.Tensor:
    if isinstance(value, torch.Tensor):
        return value.detach().float().reshape(()).to(device)
    return torch.tensor(float(value), dtype=torch.float32, device=device)


def base_terms(
    rgb: Tensor, target: Tensor, splats: torch.nn.ParameterDict, cfg: TrainConfig
) -> tuple[dict[str, Tensor], dict[str, float]]:
    """gsplat's photometric loss (and its optional regularisers): unweighted terms and their weights.

    rgb, target: [1, H, W, 3]. ``photometric`` (l_ph, :func:`jsgs.jpeg.losses.photometric_terms`) carries
    weight ``loss.base_weight``; ``l1`` and ``ssim`` (= 1 - SSIM) are logged with weight 0 (they are inside
    ``photometric``)."""
    from jsgs.jpeg.losses import photometric_terms

    ph = photometric_terms(
        rgb, target, cfg.loss.ssim_lambda, padding=cfg.loss.ssim_padding, ssim_kernel=cfg.speed.ssim_kernel,
        channels_last=True,
    )  # fmt: skip
    terms = {"l1": ph.l1, "ssim": ph.d_ssim, "photometric": ph.loss}
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
    replaced by their ready-made weighted sum ``folded_loss`` (:class:`jsgs.train.hook.HookOutput`).

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


def _device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return platform.processor() or platform.machine() or "cpu"


#: set by ``jsgs bench`` for its trainings: how many share each device (metrics.json ``runs_per_device``)
RUNS_PER_DEVICE_ENV = "JSGS_RUNS_PER_DEVICE"


def runs_per_device() -> int | None:
    """The device sharing a bench stated for this run ($JSGS_RUNS_PER_DEVICE), None when unstated or not
    a positive whole number."""
    text = os.environ.get(RUNS_PER_DEVICE_ENV, "").strip()
    return int(text) if text.isdigit() and int(text) >= 1 else None



class Trainer:
    """One training run: :meth:`setup` (settings, scene, Gaussians, optimizers, resume), :meth:`step` (one
    view), :meth:`evaluate` (test views), :meth:`save_checkpoint` / :meth:`resume` (bit-exact), :meth:`train`
    (the loop, which calls the callbacks; :mod:`jsgs.train.callbacks`).

    Arguments as :func:`train`; ``callbacks`` receive the events in list order."""

    def __init__(
        self,
        manifest: str | Path,
        out: str | Path,
        cfg: TrainConfig | None = None,
        *,
        resume: bool = False,
        force: bool = False,
        stop_at: int | None = None,
        command: str | None = None,
        hook: LossHook | None = None,
        log: Callable[[str], None] | None = None,
        callbacks: Sequence[Callback] = (),
    ) -> None:
        self.say: Callable[[str], None] = log or (lambda s: print(s, file=sys.stderr))
        self.paths = RunPaths(Path(out))
        self.manifest = Path(manifest)
        self.cfg = cfg
        self.resuming = resume
        self.force = force
        self.stop_at = stop_at
        self.command = command
        self.hook = hook
        self.callbacks = list(callbacks)
        self.profiler = Profiler(False, torch.device("cpu"), memory=True)
        self.evals: list[dict[str, Any]] = []
        self.acc = LogAccumulator()
        self.train_time = 0.0
        self.setup_time = 0.0
        self.start_step = 0
        self.empty_views: set[str] = set()
        self.interrupted: str | None = None
        self.last_checkpoint = "none"
        self.lock: OutputLock | None = None
        self._clock = 0.0
        self.world = dd.World()  # one process unless started by torchrun / --gpus (setup joins the others)
        #: how a view reaches the other processes' Gaussians: "none" (one process), "gsplat" (its
        #: distributed rasterisation) or "torch" (gathered; jsgs.train.distributed)
        self.exchange = "none"
        self._exchange: dd.Exchange | None = None
        #: the torch exchange: the step's strategy statistics, summed with the gradients (distributed.py)
        self._fold_statistics: Callable[[dict[str, Any], int], Tensor | None] | None = None
        self._gathered: dict[str, Any] | None = None  # the shards gathered on rank 0 at a checkpoint point
        #: every process's number of Gaussians, by rank: as of the last step; with the torch exchange kept
        #: current on every process (gathered at setup and after each strategy step that may change them)
        self.sizes: list[int] = []
        self._signal: str | None = None
        self._stop_everywhere: str | None = None
        self._step_gather: dd.StepGather | None = None  # several processes: the step's values, shared
        #: the torch exchange sends the step's values in the gradients' reduce-scatter (False: in an
        #: all-gather of their own after the optimizer's step; the same values either way)
        self.fold_step_values = True
        self._view_names: dict[int, str] = {}

    # -- events ---------------------------------------------------------------------------------------
    def fire(self, event: str, *args: Any) -> None:
        """Call ``event`` (e.g. "on_step_end") on every callback, in order (on rank 0 only: the callbacks
        write the run folder and report progress)."""
        if not self.world.is_main:
            return
        for cb in self.callbacks:
            getattr(cb, event)(self, *args)

    # -- setup ----------------------------------------------------------------------------------------
    def setup(self) -> None:
        """Check RUN and the settings, load the scene, build the Gaussians, optimizers and strategy, resume
        from the last checkpoint (``resume``) or write ``config.json``; then ``on_setup``. On several
        processes (:mod:`jsgs.train.distributed`) every process sets up, rank 0 alone touches RUN, and an
        error on any of them stops all of them."""
        self.world = dd.world_from_environment()
        if not self.world.is_main:  # rank 0 says it once (the notes are the same on every process)
            self.say = lambda message: None
        use_cuda = torch.cuda.is_available() and (self.cfg is None or self.cfg.device != "cpu")
        dd.start(self.world, use_cuda)
        error: JsgsError | None = None
        self.lock = None
        self._run_config: dict[str, Any] | None = None
        self.recorded: RunConfig | None = None  # RUN/config.json of the run resumed
        try:
            self._setup()
        except JsgsError as e:
            error = e
        dd.agree(self.world, error)
        self.sizes = dd.gather_sizes(self.world, int(self.splats["means"].shape[0]), self.device)
        if self._run_config is not None:  # written once every process is ready
            write_json_atomic(self.paths.config, self._run_config)
        self.fire("on_setup")

    def _setup(self) -> None:
        cfg, start_ckpt = self._settle_settings()
        t_setup = time.perf_counter()
        self.device = device = dd.local_device(self.world, resolve_device(cfg.device))
        self.profiler.device = device
        self.backend = resolve_backend(cfg, device)
        _seed_everything(cfg.seed)
        scene = self._load_scene(cfg, device)
        hook_notes = self._make_hook(cfg, scene, device)
        budget = self._scene_budget(cfg, scene)
        self._make_strategy(cfg)
        initial = 0
        if start_ckpt is None:
            initial = self._initial_gaussians(cfg, scene, device)
            self.build_optimization()
        else:
            self.restore(start_ckpt)
        derived = self._derived(cfg, scene, device, initial, hook_notes, budget)
        if self.world.is_main:  # only now that the settings, manifest and checkpoint passed
            _remove_leftovers(self.paths, self.say)
        if budget is not None:
            derived["budget"] = budget.to_json()
        if not self.resuming and self.world.is_main:
            _clear_out(self.paths)  # only now that the settings and the manifest have been checked
            self._run_config = self._new_run_config(cfg, scene, derived)
        self.setup_time = time.perf_counter() - t_setup

    def _settle_settings(self) -> tuple[TrainConfig, dict[str, Any] | None]:
        """Check RUN (rank 0 takes its lock), take the run's own settings and last checkpoint when resuming
        (``cfg``, when given, must equal them), check the settings, ``stop_at`` and the process count:
        the settings (``self.cfg``) and the checkpoint to resume from (None: a new run)."""
        paths = self.paths
        if self.world.is_main:
            _check_out(paths, self.resuming, self.force)
            self.lock = OutputLock(paths.root, f"jsgs train (into {paths.root})")
        cfg = self.cfg
        start_ckpt: dict[str, Any] | None = None
        if self.resuming:
            self.recorded = read_run_config(paths.root)
            stored = self.recorded.settings
            if cfg is not None:
                d = _diff_settings(to_dict(stored), to_dict(cfg))
                if d:
                    raise JsgsError(
                        f"{paths.root}: --resume continues the run with its own settings; differs: {d}"
                    )
            cfg = stored
            start_ckpt = self.read_checkpoint(cfg)
        cfg = cfg if cfg is not None else TrainConfig()
        cfg.check()
        self.cfg = cfg
        if self.stop_at is not None and not 1 <= self.stop_at <= cfg.iterations:
            raise JsgsError(f"stop_at must lie in 1..{cfg.iterations} (got {self.stop_at})")
        self.end_step = cfg.iterations if self.stop_at is None else self.stop_at
        if self.resuming:
            assert self.recorded is not None
            ran_on = int(self.recorded.derived.get("world_size", 1))
            if ran_on != self.world.size:
                raise JsgsError(
                    f"{paths.root}: the run was trained on {ran_on} process(es); resume it on as many (now "
                    f"{self.world.size})"
                )
        return cfg, start_ckpt

    def _load_scene(self, cfg: TrainConfig, device: torch.device) -> TrainingScene:
        """The scene (``self.scene``; the one the resumed run started with), its training images and, when
        there are test views and evaluation steps, its evaluation images on ``device``."""
        self.scene = scene = load_training_scene(self.manifest, cfg)
        for note in scene.notes:
            self.say(f"note: {note}")
        if self.recorded is not None:
            if self.recorded.manifest_sha256 != scene.manifest_sha256:
                raise JsgsError(
                    f"{self.manifest}: differs from the manifest the run in {self.paths.root} was started "
                    "with"
                )
        if device.type == "cuda":
            reset_peak_allocated(device, forget=True)
            # IEEE float32 convolutions for the whole run (SSIM in the losses and metrics;
            # jsgs.base.precision), also where torch.compile'd code cannot enter jsgs.base.precision's context
            torch.backends.cudnn.allow_tf32 = False
        self.train_views = scene.train_views
        self.train_images = load_train_images(scene, device)
        # a manifest without test views (jsgstools manifest --test-every 0) trains without evaluations
        self.eval_steps = list(cfg.eval_at) if scene.test_views else []
        if cfg.eval_at and not scene.test_views:
            self.say(f"note: the manifest has no test views; no evaluation at steps {cfg.eval_at}")
        elif scene.reference_kind in ("jpeg", "mixed"):
            self.say(
                f"note: {scene.reference_kind} references: test views without a lossless image are evaluated "
                "against their JPEG (metrics.json reference)"
            )
        self.eval_images = load_eval_images(scene, device) if self.eval_steps else {}
        return scene

    def _make_hook(self, cfg: TrainConfig, scene: TrainingScene, device: torch.device) -> list[str]:
        """The method's loss hook (unless one was given), made without moving the random streams; its
        notes."""
        if self.hook is None:
            # the method's own random draws (if any) must not shift the initialisation: every method starts
            # from the same Gaussians as the baseline for a given seed
            with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
                self.hook = make_hook(cfg, scene, device)
        hook_notes = self.hook.notes() if self.hook is not None else []
        for note in hook_notes:
            self.say(f"note: {note}")
        return hook_notes

    def _scene_budget(self, cfg: TrainConfig, scene: TrainingScene) -> AutoBudget | None:
        """``strategy.cap_max_auto`` on a new MCMC run: the budget chosen from the scene, set as
        ``strategy.cap_max`` (a resumed run keeps the one its config.json records); else None."""
        if not (cfg.strategy.type == "mcmc" and cfg.strategy.cap_max_auto and not self.resuming):
            return None
        from jsgs.train.budget import scene_budget

        budget = scene_budget(scene)
        cfg.strategy.cap_max = budget.cap_max
        self.say(f"note: budget from the scene: {budget.describe()}")
        return budget

    def _make_strategy(self, cfg: TrainConfig) -> None:
        """The densification strategy (its budget this process's share on several), how the shards are
        exchanged, and the view sampler."""
        self.strategy = Densifier(cfg.strategy)
        self.exchange = self._exchange_kind(cfg)
        if self.exchange == "torch":
            fold = dd.share_strategy_statistics(self.strategy, self.world, lambda: self._exchange_rows())
            self._fold_statistics = lambda info, step: fold(info, cfg.render.packed, step)
        elif self.exchange == "gsplat":
            dd.per_camera_statistics(self.strategy, self.world)
        dd.keep_a_gaussian_per_shard(self.strategy, self.world)
        if self.exchange == "torch" and cfg.speed.exchange == "gsplat":
            self.say(
                f"note: speed.exchange gsplat: gsplat's distributed rasterisation cannot render this run's "
                f"views ({self._gsplat_cannot(cfg)}); the processes exchange the Gaussians with torch"
            )
        if self.world.enabled and self.strategy.cap_max is not None:
            # one global budget: each process grows its shard to its share
            self.strategy.gsplat.cap_max = dd.shard_cap(self.strategy.cap_max, self.world)
        self.sampler = ViewSampler(len(self.train_views), cfg.seed)

    def _initial_gaussians(self, cfg: TrainConfig, scene: TrainingScene, device: torch.device) -> int:
        """The Gaussians of a new run (``self.splats``: from the SfM points, a random subset of them past
        the budget, or random points; on several processes each keeps its shard); how many there are in
        all."""
        points = torch.from_numpy(scene.points)
        colors = torch.from_numpy(scene.points_rgb).float() / 255.0
        keep = None
        if cfg.init.type == "sfm":
            keep = initial_subset(len(points), self.strategy.cap_max, cfg.seed)
        if keep is not None:
            self.say(
                f"note: {len(points)} initial points exceed strategy.cap_max = {self.strategy.cap_max}; "
                f"starting from a random {len(keep)} of them (seed {cfg.seed})"
            )
            points, colors = points[keep], colors[keep]
        if cfg.init.type == "random" and self.strategy.cap_max is not None:
            if cfg.init.num_points > self.strategy.cap_max:
                self.say(
                    f"note: init.num_points = {cfg.init.num_points} exceeds strategy.cap_max = "
                    f"{self.strategy.cap_max}; starting from {self.strategy.cap_max} random points"
                )
        self.splats = init_splats(
            points, colors, cfg, scene.scene_scale, device, max_points=self.strategy.cap_max
        )
        bad = first_nonfinite_param(self.splats)
        if bad is not None:
            raise JsgsError(
                f"{scene.manifest_path}: the initial Gaussians' {bad!r} are not finite (the points or "
                "the cameras, after world normalisation, lie beyond float32's range)"
            )
        initial = int(self.splats["means"].shape[0])
        if self.world.enabled:  # every process made the same Gaussians: each keeps its shard
            rows = dd.shard_rows(initial, self.world, str(scene.manifest_path)).to(device)
            self.splats = torch.nn.ParameterDict(
                {n: torch.nn.Parameter(self.splats[n].data[rows].contiguous()) for n in PARAM_NAMES}
            )
            if self.world.rank > 0:  # the processes' own draws (noise, splits, backgrounds) differ
                _seed_everything(cfg.seed + self.world.rank)
        return initial

    def _derived(
        self, cfg: TrainConfig, scene: TrainingScene, device: torch.device, initial: int,
        hook_notes: list[str], budget: AutoBudget | None,
    ) -> dict[str, Any]:  # fmt: skip
        """config.json's ``derived``: what the run computed from the manifest and the settings (the budget
        is added by the caller)."""
        derived = {
            "device": str(device),
            "backend": self.backend,
            "scene_scale": scene.scene_scale,
            "camera_extent": scene.camera_extent,
            "normalization": scene.transform.tolist(),
            "num_train_views": len(self.train_views),
            "num_test_views": len(scene.test_views),
            "initial_gaussians": initial
            if self.recorded is None
            else int(self.recorded.derived["initial_gaussians"]),
            "notes": [*scene.notes, *hook_notes],
            "ssim_kernel": "cuda"
            if use_kernels(cfg.speed.ssim_kernel, device, "speed.ssim_kernel")
            else "torch",
            "method": self.hook.describe() if self.hook is not None else {},
            "world_size": self.world.size,
        }
        if self.world.enabled:
            derived["exchange"] = self.exchange
        return derived

    def _new_run_config(
        self, cfg: TrainConfig, scene: TrainingScene, derived: dict[str, Any]
    ) -> dict[str, Any]:
        """A new run's config.json document, validated (written once every process is ready)."""
        run_config = {
            "format": RUN_CONFIG_FORMAT,
            "format_version": RUN_CONFIG_VERSION,
            "versions": _versions(),
            "command": self.command or "",
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "manifest": {"path": str(scene.manifest_path), "sha256": scene.manifest_sha256},
            "settings": to_dict(cfg),
            "derived": derived,
        }
        from jsgs.base.schema import validate

        validate(run_config, "config", str(self.paths.config))
        return run_config

    # -- the shards ------------------------------------------------------------------------------------
    def _exchange_kind(self, cfg: TrainConfig) -> str:
        """How each process's view reaches the other processes' Gaussians (``self.exchange``): the torch
        exchange (gather the shards, reduce-scatter the gradients), or with ``speed.exchange: gsplat``
        gsplat's distributed rasterisation where it can render the run's views (:meth:`_gsplat_cannot`);
        "none" on one process."""
        if not self.world.enabled:
            return "none"
        if cfg.speed.exchange == "gsplat" and self._gsplat_cannot(cfg) is None:
            return "gsplat"
        return "torch"

    def _gsplat_cannot(self, cfg: TrainConfig) -> str | None:
        """Why gsplat's distributed rasterisation cannot render this run's training views, or None where it
        can: it needs the gsplat backend, pinhole cameras, no method extra channels, no absgrad and one
        image size (each process projects its shard for every process's camera with its own view's width
        and height)."""
        sizes = {(v.width, v.height) for v in self.train_views}
        reasons = (
            (self.backend != "gsplat", f"the {self.backend} backend"),
            (self.hook is not None and self.hook.renders_extra(), "the method renders extra channels"),
            (cfg.strategy.absgrad, "strategy.absgrad"),
            (any(v.distortion is not None for v in self.train_views), "lens distortion"),
            (len(sizes) > 1, f"{len(sizes)} image sizes (it projects every process's camera at one size)"),
        )
        return next((why for cannot, why in reasons if cannot), None)

    def _exchange_rows(self) -> tuple[int, int]:
        assert self._exchange is not None
        return self._exchange.rows

    def num_gaussians(self) -> int:
        """The run's number of Gaussians (every process's shard, as of the last step)."""
        if self.world.enabled and self.sizes:
            return sum(self.sizes)
        return int(self.splats["means"].shape[0])

    def _shard_state(self) -> dict[str, Any]:
        return {
            "splats": {n: self.splats[n].data for n in PARAM_NAMES},
            "optimizers": {n: o.state_dict() for n, o in self.optimizers.items()},
            "strategy": self.strategy_state,
            "rng": ckpt.rng_state(),
        }

    def gather_model(self) -> None:
        """At a checkpoint point, on every process: the shards (Gaussians, Adam moments, strategy sums,
        generators) gathered on rank 0 (:func:`jsgs.train.distributed.merge_shards`), which evaluates, writes
        the checkpoint and the model from them."""
        if not self.world.enabled:
            return
        parts = dd.gather_to_main(self.world, self._shard_state())
        self._gathered = dd.merge_shards(parts) if parts is not None else None
        if self._gathered is not None:
            self.sizes = list(self._gathered["shards"])

    def model(self) -> torch.nn.ParameterDict:
        """All the Gaussians (rank 0 after :meth:`gather_model` on several processes, else this process's)."""
        if not self.world.enabled:
            return self.splats
        assert self._gathered is not None, "gather_model first"
        splats = self._gathered["splats"]
        return torch.nn.ParameterDict(
            {n: torch.nn.Parameter(splats[n].to(self.device), requires_grad=False) for n in PARAM_NAMES}
        )

    # -- checkpoints ----------------------------------------------------------------------------------
    def checkpoint_state(self, step_done: int) -> dict[str, Any]:
        """Everything :meth:`resume` needs to continue after ``step_done`` steps bit for bit (several
        processes: the shards gathered by :meth:`gather_model`, with their row counts and every process's
        generators)."""
        cfg = self.cfg
        assert cfg is not None
        parts = self._gathered if self.world.enabled else self._shard_state()
        assert parts is not None, "gather_model first"
        return {
            "step": step_done,
            "settings": to_dict(cfg),
            "manifest_sha256": self.scene.manifest_sha256,
            **parts,
            "scheduler": self.scheduler.state_dict(),
            "sampler": self.sampler.state_dict(),
            "hook": self.hook.state_dict() if self.hook is not None else {},
            "evals": self.evals,
            "log": self.acc.state(),
            "train_time_s": self.train_time,
        }

    def save_checkpoint(self, step_done: int) -> str:
        """Write ``checkpoints/step_XXXXXX.pt`` (:meth:`checkpoint_state`), then delete the checkpoints
        older than the newest ``checkpoint_keep``; returns its path."""
        path = ckpt.checkpoint_path(self.paths.checkpoints, step_done)
        ckpt.save_checkpoint(path, self.checkpoint_state(step_done))
        self.last_checkpoint = str(path)
        self.rotate_checkpoints()
        return str(path)

    def rotate_checkpoints(self) -> None:
        """Keep the newest ``checkpoint_keep`` checkpoints of RUN/checkpoints (0: all); a file that cannot
        be removed is a note, not an error (the run goes on)."""
        assert self.cfg is not None
        keep = self.cfg.checkpoint_keep
        if keep <= 0:
            return
        for _, old in ckpt.list_checkpoints(self.paths.checkpoints)[:-keep]:
            if old.is_file() and not old.is_symlink():
                try:
                    old.unlink()
                except OSError as e:
                    self.say(f"note: {old}: could not remove an old checkpoint ({e.strerror or e})")

    def build_optimization(self) -> None:
        """The optimizers, the means' scheduler and the strategy's state, fresh, for ``self.splats``."""
        cfg = self.cfg
        assert cfg is not None
        self.optimizers = make_optimizers(self.splats, cfg, self.scene.scene_scale)
        dd.scale_optimizers(self.optimizers, self.world.size)  # a batch of world_size views per step
        self.scheduler = make_means_scheduler(self.optimizers["means"], cfg)
        self.strategy.check_sanity(self.splats, self.optimizers)
        self.strategy_state = self.strategy.initialize_state(scene_scale=self.scene.scene_scale)

    def read_checkpoint(self, cfg: TrainConfig) -> dict[str, Any]:
        """The last checkpoint in RUN/checkpoints, read (one written by an earlier version as today's, with
        one note: :func:`jsgs.train.checkpoint.fields_of_today`) and checked against the run folder (its
        structure, its step, the settings of config.json, the manifest config.json names); ``_path``: the
        file."""
        found = ckpt.list_checkpoints(self.paths.checkpoints)
        if not found:
            raise JsgsError(
                f"{self.paths.checkpoints}: no checkpoint to resume from; start the run again with --force"
            )
        ckpt_step, ckpt_path = found[-1]
        doc = ckpt.load_checkpoint(ckpt_path)
        # a checkpoint of an earlier version
        say_assumed(str(ckpt_path), ckpt.fields_of_today(doc), "checkpoint fields")
        ckpt.check_structure(doc, ckpt_path, ckpt_step)
        run = self.recorded if self.recorded is not None else read_run_config(self.paths.root)
        _checkpoint_agrees(doc, ckpt_path, run, cfg)
        doc["_path"] = str(ckpt_path)
        return doc

    def restore(self, state: dict[str, Any]) -> None:
        """The Gaussians, optimizers, scheduler, strategy and everything :meth:`resume` sets, from a
        checkpoint read by :meth:`read_checkpoint`, each part checked against this run before it is used (one
        line naming the file and the key otherwise)."""
        cfg = self.cfg
        assert cfg is not None
        path = Path(state["_path"])
        ckpt.check_splats(state, path, (cfg.render.sh_degree + 1) ** 2 - 1)
        # several processes: this one's rows of the gathered checkpoint (the whole file is checked below)
        part = dd.split_checkpoint(state, self.world, str(path)) if self.world.enabled else state
        self.splats = splats_from_state(part["splats"], self.device)
        self.build_optimization()
        self._check_checkpoint_state(state)
        try:
            self.resume(part)
        except JsgsError:
            raise
        except Exception as e:  # a defect the checks do not know of: still one line naming the file
            raise ckpt.unusable(path, e) from None

    def _check_checkpoint_state(self, state: dict[str, Any]) -> None:
        """The checkpoint's optimizer, scheduler, strategy, generator, sampler, log and evaluation states
        against this run's fresh ones (:func:`jsgs.train.checkpoint.check_state`)."""
        from jsgs.base.schema import load_schema

        metrics = load_schema("metrics")
        ckpt.check_state(
            state,
            Path(state["_path"]),
            optimizers={n: o.state_dict() for n, o in self.optimizers.items()},
            scheduler=self.scheduler.state_dict(),
            strategy=self.strategy_state,
            rng=ckpt.rng_state(),
            sampler=self.sampler.state_dict(),
            num_views=len(self.train_views),
            eval_schema={"type": "array", "items": {"$ref": "#/$defs/eval"}, "$defs": metrics["$defs"]},
        )

    def resume(self, state: dict[str, Any]) -> None:
        """Continue from a checkpoint (:meth:`checkpoint_state`; ``_path``: the file it was read from):
        optimizers, scheduler, strategy, RNGs, view order, the method's state, evaluations and log sums.
        The Gaussians themselves are built from ``state["splats"]`` by :meth:`setup`."""
        device = self.device
        for name in PARAM_NAMES:
            self.optimizers[name].load_state_dict(state["optimizers"][name])
        self.scheduler.load_state_dict(state["scheduler"])
        self.strategy_state = ckpt.to_device(state["strategy"], device)
        ckpt.set_rng_state(state["rng"])
        self.sampler.load_state_dict(state["sampler"])
        if self.hook is not None:
            self.hook.load_state_dict(ckpt.to_device(state["hook"], device))
        elif state["hook"]:
            raise JsgsError(f"{state['_path']}: holds method state but the method has no hook")
        self.evals = list(state["evals"])
        self.acc = LogAccumulator.from_state(state["log"])
        self.train_time = float(state["train_time_s"])
        self.start_step = int(state["step"])
        self.last_checkpoint = state["_path"]
        assert self.cfg is not None
        self.say(f"resuming {self.paths.root} at step {self.start_step} of {self.cfg.iterations}")

    # -- one step -------------------------------------------------------------------------------------
    def step(self, step: int) -> StepResult:
        """Train on one view (gsplat simple_trainer's step; module docstring). TrainingDiverged on NaN/Inf."""
        cfg, splats, profiler = self.cfg, self.splats, self.profiler
        assert cfg is not None
        view, target, sh_degree, shown, r, rgb = self._render_step(step, cfg)
        with profiler.phase("loss"):
            terms, weights = base_terms(rgb, target, shown, cfg)
        stats: dict[str, Any] = {}
        folded: frozenset[str] = frozenset()
        skipped: frozenset[str] = frozenset()
        folded_loss = None
        if self.hook is not None:
            with profiler.phase("hook"):
                ctx = StepContext(
                    step=step,
                    view=view,
                    render=rgb,
                    alpha=r.alpha,
                    target=target,
                    info=r.info,
                    splats=shown,
                    extra=r.extra,
                    base_terms=dict(terms),
                    sh_degree=sh_degree,
                    image=self.train_images[view.index],
                    folded_upstream_one=True,  # weighted_loss adds it unweighted; loss.backward() from 1
                )
                stats, folded, folded_loss, skipped = self._hook_terms(ctx, cfg, terms, weights)
        loss = weighted_loss(terms, weights, folded, folded_loss)
        names = list(terms)

        def pack(grads: torch.nn.ParameterDict | None) -> tuple[list[str], Tensor, Tensor | None]:
            grad_names, packed = self._pack_step_values(loss, terms, names, stats, grads)
            if grads is None:
                return grad_names, packed, None
            row = self._step_row(view, names, weights, stats, grad_names)
            return grad_names, packed, self._values_gather().rider(*row, packed)

        empty, grad_names, packed = self._backward(step, view, loss, stats, r.info, pack)
        with profiler.phase("optimizer"):
            for o in self.optimizers.values():
                o.step()
                o.zero_grad(set_to_none=True)
            self.scheduler.step()
        if self.world.enabled:  # every process's values on every process: all of them stop alike on a NaN
            views = self._gather_step_values(step, view, names, weights, stats, grad_names, packed)
            _, loss_v, term_v, logged = views[self.world.rank]
            stat_v = list(logged.values())
        else:
            loss_v, term_v, stat_v, grad_v, param_v = self._read_step_values(
                packed.tolist(), names, weights, len(stats), len(grad_names)
            )
            _finite_check(
                step, [*names, "loss"], [*term_v, loss_v], grad_names, grad_v, param_v, self.last_checkpoint
            )
            views = [(view.name, loss_v, term_v, stats)]
        with profiler.phase("densify"):
            if not empty:  # the strategies read the screen-space gradients this step does not have
                self.strategy.step_post_backward(
                    splats,
                    self.optimizers,
                    self.strategy_state,
                    step,
                    r.info,
                    lr=self.scheduler.get_last_lr()[0],
                    packed=cfg.render.packed and self.exchange != "gsplat",
                )
        self._exchange = None  # (the strategy's statistics read its rows)
        if self.exchange == "torch" and self.strategy.may_change_count(step):  # the next step's shard sizes
            self.sizes = dd.gather_sizes(self.world, int(splats["means"].shape[0]), self.device)
        result = StepResult(
            step,
            view.name,
            loss_v,
            dict(zip(names, term_v, strict=True)),
            dict(zip(stats, stat_v, strict=True)),
            skipped,
        )
        if self.world.enabled:  # (a hook skips names by the step alone: the same on every process)
            for v_name, v_loss, v_terms, v_stats in views:
                self.acc.add(v_loss, dict(zip(names, v_terms, strict=True)), v_stats, v_name, skipped)
        else:
            self.acc.add(result.loss, result.terms, result.stats, view.name, skipped)
        return result

    def _render_step(
        self, step: int, cfg: TrainConfig
    ) -> tuple[TrainingView, Tensor, int, torch.nn.ParameterDict, RenderOut, Tensor]:
        """The step's view and target, its SH degree, the Gaussians it shows (this process's shard, or every
        process's gathered for the torch exchange), the render and the image the loss sees (over a random
        background with ``render.random_background``); the strategy's pre-backward step done."""
        device, splats, hook, profiler = self.device, self.splats, self.hook, self.profiler
        # what this process renders: its shard (one process; gsplat's distributed rasterisation) or every
        # process's Gaussians gathered (the torch exchange)
        shown = splats
        with profiler.phase("data"):
            view = self.train_views[dd.pick_view(self.world, self.sampler.next)]
            target = image_target(self.train_images[view.index])
            sh_degree = sh_degree_at(step, cfg)
            if self.exchange == "torch":
                self._exchange = dd.gather_gaussians(self.world, splats, PARAM_NAMES, self.sizes, sh_degree)
                shown = self._exchange.params
            extra_feats = hook.extra_channels(step, view, shown) if hook is not None else None
            extra_kw = hook.render_kwargs(step, view) if hook is not None else None
        with profiler.phase("render"):
            r = render_view(
                shown,
                view.viewmat_tensor(device),
                view.K_tensor(device),
                view.width,
                view.height,
                sh_degree,
                cfg,
                self.backend,
                extra_feats,
                extra_kw,
                view.distortion_tensor(device),
                distributed=self.exchange == "gsplat",
            )
            rgb = r.rgb
            if cfg.render.random_background:
                bkgd = torch.rand(1, 3, device=device)
                rgb = rgb + bkgd * (1.0 - r.alpha)
            self.strategy.step_pre_backward(shown, self.optimizers, self.strategy_state, step, r.info)
        return view, target, sh_degree, shown, r, rgb

    def _hook_terms(
        self, ctx: StepContext, cfg: TrainConfig, terms: dict[str, Tensor], weights: dict[str, float]
    ) -> tuple[dict[str, Any], frozenset[str], Tensor | None, frozenset[str]]:
        """The method's terms and weights added to ``terms`` and ``weights`` (its base scale applied to the
        photometric weight); its stats, the terms it folds, their folded loss and the names it skipped."""
        assert self.hook is not None
        hout: HookOutput = self.hook.losses(ctx)
        hout.check(cfg.method)
        terms.update(hout.terms)
        weights.update(hout.weights)
        if hout.base_scale != 1.0:
            weights["photometric"] *= hout.base_scale
        return dict(hout.stats), hout.folded, hout.folded_loss, hout.skipped

    def _backward(
        self, step: int, view: TrainingView, loss: Tensor, stats: dict[str, Any], info: dict[str, Any],
        pack: Callable[[torch.nn.ParameterDict | None], tuple[list[str], Tensor, Tensor | None]],
    ) -> tuple[bool, list[str], Tensor]:  # fmt: skip
        """The backward of ``loss`` (on several processes, each Gaussian's gradient then averaged over the
        step's views on its owner, with the strategy's statistics of ``info`` in the same reduce-scatter);
        whether no gradient reached any Gaussian (an empty view: counted in ``stats``, noted once per
        view), and the step's values (``pack``: :meth:`_pack_step_values` over the gradients of the
        Gaussians given, None for this process's shard after the reduction, and the step's
        :meth:`jsgs.train.distributed.StepGather.rider` row for those given). The torch exchange packs them
        before the reduce-scatter, over the gradients of this process's view (every Gaussian's), and sends
        the row in its flag column (:attr:`fold_step_values`); otherwise they are packed after it."""
        # a view that sees no Gaussian (a camera looking away, everything culled) renders a constant: no
        # gradient reaches any parameter, so the step only logs itself
        empty = not loss.requires_grad
        if empty:
            stats["empty_view"] = 1.0
            if view.name not in self.empty_views:
                self.empty_views.add(view.name)
                self.say(
                    f"note: step {step}: view {view.name!r} sees no Gaussian; its steps are skipped and "
                    "counted (train stats empty_view)"
                )
        else:
            with self.profiler.phase("backward"):
                loss.backward()
        if self.world.enabled:
            if empty and self.exchange == "gsplat":  # the others wait in the exchange's backward
                raise JsgsError(
                    f"iteration {step + 1}: view {view.name!r}: gsplat's distributed rasterisation returned "
                    "an image without gradient; the processes cannot finish this step"
                )
            # the mean over the step's views of each Gaussian's gradient, on its owner
            params = [self.splats[n] for n in PARAM_NAMES]
            fold = self._fold_statistics
            also = fold(info, step) if fold is not None else None
            if self._exchange is not None and self.fold_step_values:
                grad_names, packed, rider = pack(self._exchange.params)
                empty = not dd.reduce_gradients(self.world, params, not empty, self._exchange, also, rider)
                return empty, grad_names, packed
            empty = not dd.reduce_gradients(self.world, params, not empty, self._exchange, also)
        grad_names, packed, _ = pack(None)
        return empty, grad_names, packed

    def _pack_step_values(
        self, loss: Tensor, terms: dict[str, Tensor], names: list[str], stats: dict[str, Any],
        grads: torch.nn.ParameterDict | None = None,
    ) -> tuple[list[str], Tensor]:  # fmt: skip
        """The names of the parameters with a gradient, and every logged value, each gradient's L1 norm and
        each parameter's L1 norm in one tensor on the device (read in one host sync after the optimizer's
        kernels are queued). The gradients are ``grads``' (the torch exchange's gathered Gaussians, before
        the reduction: this process's view's, whose sums over the processes are the shards' gradients, so
        that a non-finite one is non-finite in some process's view, or a sum beyond float32's range, which
        the next check of the parameters catches: :func:`jsgs.train.distributed.reduce_gradients`) or the
        shard's."""
        # every logged value, each gradient's L1 norm and each parameter's L1 norm (NaN/Inf wherever a value
        # is), packed on the device and read in one host sync per step, *after* the optimizer's kernels are
        # queued: the host issues the update while the device finishes the backward. A non-finite step has
        # then updated the Gaussians in memory, which nothing keeps: the run stops here and its checkpoints
        # hold the last good state. The parameters are the ones this step started from (what the previous
        # step's update and densification left); the state after the last step is checked at each
        # checkpoint point (check_params_finite). Gradients and parameters go through ONE _foreach_norm (a
        # fused multi-tensor reduction: on CUDA one kernel launch over all twelve tensors, reading each value
        # once, as the optimizer's own step does) and the same stack and host read as before: no extra sync,
        # no extra launch per parameter.
        splats = self.splats
        grads = splats if grads is None else grads
        grad_names = [n for n in PARAM_NAMES if grads[n].grad is not None]
        with torch.no_grad():
            norms = torch._foreach_norm(
                [*(grads[n].grad for n in grad_names), *(splats[n] for n in PARAM_NAMES)], 1
            )
        packed = torch.stack(
            [loss.detach().float()]
            + [terms[n].detach().float().reshape(()) for n in names]
            + [_stat_tensor(stats[k], self.device) for k in stats]
            + list(norms)
        )
        return grad_names, packed

    def _read_step_values(
        self, values: list[float], names: list[str], weights: dict[str, float], n_stats: int, n_grads: int
    ) -> tuple[float, list[float], list[float], list[float], list[float]]:
        """One process's loss, terms, statistics, gradient norms and parameter norms from its
        :meth:`_pack_step_values` read on the host (``weights``: its loss's)."""
        term_v = values[1 : 1 + len(names)]
        # Summed from the term values read *after* the backward: a method may fill a term's value during
        # the backward (JSGS's deferred L_fro), which the pre-backward total cannot include.
        loss_v = values[0] if self.hook is None else _weighted_sum(names, term_v, weights)
        stat_v = values[1 + len(names) : 1 + len(names) + n_stats]
        norm_v = values[1 + len(names) + n_stats :]
        return loss_v, term_v, stat_v, norm_v[:n_grads], norm_v[n_grads:]

    def _gather_step_values(
        self, step: int, view: TrainingView, names: list[str], weights: dict[str, float],
        stats: dict[str, Any], grad_names: list[str], packed: Tensor,
    ) -> list[tuple[str, float, list[float], dict[str, float]]]:  # fmt: skip
        """Several processes: every process's logged values on every process (``packed``, each process's
        :meth:`_pack_step_values`, with its view, loss weights, stop signal and Gaussian count: the rows the
        gradients' reduce-scatter brought, else one all-gather of a tensor,
        :class:`jsgs.train.distributed.StepGather`; read on the host once), each checked for NaN/Inf (all
        of them stop alike), a stop signal that reached any of them shared, every process's Gaussian count
        noted; each process's (view name, loss, terms, stats)."""
        import signal

        gather = self._values_gather()
        riders = self._exchange.riders if self._exchange is not None else None
        rows = gather.unpack(riders.tolist()) if riders is not None else None
        if rows is None:
            rows = gather(*self._step_row(view, names, weights, stats, grad_names), packed)
        everyone = []
        for (v_names, v_stats, v_grads), row in rows:
            v_names = list(v_names)
            n_host = 3 + len(v_names)
            v_weights = dict(zip(v_names, row[3:n_host], strict=True))
            values = self._read_step_values(row[n_host:], v_names, v_weights, len(v_stats), len(v_grads))
            everyone.append((row[:3], v_names, v_stats, v_grads, values))
        # a signal reached some process: all of them stop after this same step
        self._stop_everywhere = dd.stop_request(
            [signal.Signals(int(h[1])).name if h[1] else None for h, *_ in everyone]
        )
        # every process's parameters first (a non-finite one is the cause: its rows' gradients in every
        # process's view are not finite either), then each process's terms and gradients
        for *_, (_, _, _, _, p_v) in everyone:
            _finite_check(step, [], [], [], [], p_v, self.last_checkpoint)
        for _, v_names, _, v_grads, (v_loss, v_terms, _, g_v, p_v) in everyone:
            v_values = [*v_terms, v_loss]
            _finite_check(step, [*v_names, "loss"], v_values, list(v_grads), g_v, p_v, self.last_checkpoint)
        self.sizes = [int(h[2]) for h, *_ in everyone]
        return [
            (self._view_names[int(h[0])], v_loss, v_terms, dict(zip(v_stats, v_stat, strict=True)))
            for h, _, v_stats, _, (v_loss, v_terms, v_stat, _, _) in everyone
        ]

    def _values_gather(self) -> dd.StepGather:
        if self._step_gather is None:
            self._step_gather = dd.StepGather(self.world)
            self._view_names = {v.index: v.name for v in self.train_views}
        return self._step_gather

    def _step_row(
        self, view: TrainingView, names: list[str], weights: dict[str, float], stats: dict[str, Any],
        grad_names: list[str],
    ) -> tuple[Any, list[float]]:  # fmt: skip
        """This process's layout of the step's values and its host values for :class:`dd.StepGather`: its
        view, stop signal, Gaussian count and loss weights."""
        import signal

        code = signal.Signals[self._signal].value if self._signal is not None else 0
        host = [float(view.index), float(code), float(self.splats["means"].shape[0])]
        host += [float(weights.get(n, 0.0)) for n in names]
        return (tuple(names), tuple(stats), tuple(grad_names)), host

    def training_seconds(self) -> float:
        """Seconds spent training so far, the step in progress included (evaluations and checkpoints do not
        count: the clock that metrics.json's ``train_time_s`` reads)."""
        return self.train_time + (time.perf_counter() - self._clock if self._clock else 0.0)

    # -- evaluation -----------------------------------------------------------------------------------
    def evaluate(self, step_done: int) -> dict[str, Any]:
        """Evaluate on the test views after ``step_done`` steps (an entry of metrics.json ``evals``, with the
        training log's means since the last one); then ``on_eval``."""
        assert self.cfg is not None
        entry = evaluate(
            self.model(), self.scene, self.eval_images, self.cfg, self.backend, self.device, step_done,
            self.paths.renders(step_done),
        )  # fmt: skip
        entry["train_time_s"] = self.train_time
        entry["time_per_iteration_s"] = self.train_time / step_done
        entry["train"] = self.acc.means()
        self.evals.append(entry)
        self.acc = LogAccumulator()
        self.fire("on_eval", entry)
        return entry

    # -- the loop -------------------------------------------------------------------------------------
    def _catch_signals(self) -> Callable[[], None]:
        """SIGINT and SIGTERM end the run after the step in progress, with a checkpoint (a second signal
        stops at once, as usual). Returns the function that puts the previous handlers back. Only the main
        thread can install handlers; elsewhere signals keep their default behaviour."""
        import signal
        import threading

        if threading.current_thread() is not threading.main_thread():
            return lambda: None

        def request_stop(signum: int, frame: Any) -> None:
            if self._signal is not None:
                raise KeyboardInterrupt
            self._signal = signal.Signals(signum).name
            if not self.world.enabled:
                self.interrupted = self._signal
            self.say(f"{self._signal}: stopping after this step with a checkpoint (again: stop at once)")

        previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}

        def restore() -> None:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

        return restore

    def checkpoint_due(self, step_done: int) -> bool:
        """Whether a checkpoint follows ``step_done`` steps (evaluation steps, the end,
        ``checkpoint_every``)."""
        cfg = self.cfg
        assert cfg is not None
        return (
            step_done in self.eval_steps
            or step_done == cfg.iterations
            or step_done == self.end_step
            or (cfg.checkpoint_every > 0 and step_done % cfg.checkpoint_every == 0)
        )

    def status_at(self, step_done: int) -> str:
        """metrics.json ``status`` after ``step_done`` steps: ``complete`` only once the model is written
        (:meth:`train` writes it after the last step's checkpoint), so the last checkpoint point says
        ``running``."""
        assert self.cfg is not None
        return "stopped" if step_done == self.end_step < self.cfg.iterations else "running"

    def metrics_doc(self, status: str, step: int, error: str | None = None) -> dict[str, Any]:
        """The metrics document (``jsgs/schemas/metrics.schema.json``) of the run so far."""
        cfg, device = self.cfg, self.device
        assert cfg is not None
        return {
            "format": METRICS_FORMAT,
            "format_version": METRICS_VERSION,
            "status": status,
            "error": error,
            "method": cfg.method,
            "scene": self.scene.name,
            "manifest": str(self.scene.manifest_path),
            "reference": self.scene.reference_kind,
            "device": str(device),
            "device_name": _device_name(device),
            "backend": self.backend,
            "world_size": self.world.size,
            "iterations": cfg.iterations,
            "step": step,
            "num_gaussians": self.num_gaussians(),
            "train_time_s": self.train_time,
            "setup_time_s": self.setup_time,
            "time_per_iteration_s": self.train_time / max(step, 1) if step else None,
            "runs_per_device": runs_per_device(),
            "profile_ms_per_step": self.profiler.summary(),
            "profile_peak_memory_bytes": self.profiler.peak_memory(),
            "evals": self.evals,
        }

    def export_ply(self) -> None:
        """Write ``point_cloud.ply`` (3DGS layout, normalised training world: what resume, the viewer and the
        tests read) and ``point_cloud_colmap.ply`` (the same in the scene's COLMAP frame, for other tools;
        :func:`jsgs.train.export.export_run`)."""
        from jsgs.base.ply import save_ply
        from jsgs.train.export import export_run

        s = self.model()
        save_ply(self.paths.ply, s["means"], s["scales"], s["quats"], s["opacities"], s["sh0"], s["shN"])
        export_run(self.paths.root, self.paths.root / COLMAP_PLY, "ply", "colmap", force=True, run_owned=True)

    def train(self) -> dict[str, Any]:
        """Set up, run the steps up to ``stop_at`` (or the end) with evaluations and checkpoints, write the
        PLY at the end of the run; returns the final metrics document (callbacks: ``on_end`` with it). The
        output lock is held until the last file is written, and let go however the run ends."""
        try:
            self.setup()
            doc = self._run()
        finally:
            if self.lock is not None:
                self.lock.release()
        dd.barrier(self.world, "the end of the run")  # the others end once rank 0 has written everything
        dd.stop()
        return doc

    def _finish(self, step: int) -> dict[str, Any]:
        """Write the model after ``step`` = iterations steps, then metrics.json ``complete``; a model that
        cannot be written ends the run ``failed`` (RunFailed), never ``complete`` without its PLY."""
        try:
            if self.world.is_main:  # one writer
                self.export_ply()
        except Exception as e:
            from jsgs.base.errors import one_line

            why = str(e) if isinstance(e, JsgsError) else one_line(e)
            message = f"{self.paths.ply}: the model could not be written ({why}); the run is not complete"
            self._end_quietly(self.metrics_doc("failed", step, message))
            raise RunFailed(message) from None
        doc = self.metrics_doc("complete", step)
        self.fire("on_end", doc)
        return doc

    def _end_quietly(self, doc: dict[str, Any]) -> None:
        """``on_end`` for a run that is failing already: a second error (a full disk) does not hide the
        first."""
        try:
            self.fire("on_end", doc)
        except JsgsError:
            pass

    def _run(self) -> dict[str, Any]:
        cfg = self.cfg
        assert cfg is not None
        if self.start_step >= cfg.iterations:
            if self._complete_on_disk():
                self.say(f"{self.paths.root}: the run is already complete ({cfg.iterations} iterations)")
                doc = self.metrics_doc("complete", self.start_step)
                self.fire("on_end", doc)
                return doc
            # every step ran but the model was not written (a crash or an error after the last checkpoint)
            self.say(f"{self.paths.root}: every step has run; writing the model")
            self.gather_model()
            return self._finish(self.start_step)
        self._clock = time.perf_counter()
        step = self.start_step
        restore = self._catch_signals()
        try:
            for step in range(self.start_step, self.end_step):
                self.fire("on_step_begin", step)
                self._stop_everywhere = None
                result = self.step(step)
                if self._stop_everywhere is not None and self.interrupted is None:
                    # a signal reached some process: all of them stop after this same step
                    self.interrupted = self._stop_everywhere
                self.fire("on_step_end", result)
                done = step + 1
                if self.checkpoint_due(done) or self.interrupted is not None:
                    # the state after this step (the step checks the state it starts from): no checkpoint,
                    # evaluation or model of non-finite Gaussians
                    check_params_finite(self.splats, done, self.last_checkpoint)
                    synchronize(self.device)
                    self.train_time += time.perf_counter() - self._clock
                    self.gather_model()
                    if done in self.eval_steps and self.world.is_main:  # evaluated once, by rank 0
                        self.evaluate(done)
                    self.fire("on_checkpoint", done)
                    self._clock = time.perf_counter()
                if self.interrupted is not None and done < self.end_step:
                    message = (
                        f"{self.paths.root}: interrupted by {self.interrupted} after step {done} of "
                        f"{cfg.iterations}; checkpoint saved, continue with --resume (its own settings, no "
                        f"--preset or --config): jsgs train {self.manifest} --out {self.paths.root} --resume"
                    )
                    self.fire("on_end", self.metrics_doc("stopped", done, message))
                    raise TrainingInterrupted(message)
        except TrainingDiverged as e:
            self._end_quietly(self.metrics_doc("diverged", step if e.step is None else e.step, str(e)))
            raise
        except TrainingInterrupted:
            raise
        except JsgsError as e:  # e.g. a checkpoint that cannot be written
            self._end_quietly(self.metrics_doc("failed", step, str(e)))
            raise
        except BaseException:
            self.fire("on_end", None)
            raise
        finally:
            restore()
        if self.end_step == cfg.iterations:
            return self._finish(self.end_step)
        doc = self.metrics_doc(self.status_at(self.end_step), self.end_step)
        self.fire("on_end", doc)
        return doc

    def _complete_on_disk(self) -> bool:
        """Whether RUN holds the model and metrics.json says ``complete``."""
        from jsgs.base.io import read_regular_text

        if not self.paths.ply.is_file():
            return False
        try:
            return json.loads(read_regular_text(self.paths.metrics)).get("status") == "complete"
        except (OSError, ValueError, AttributeError, JsgsError):
            return False


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
    callbacks: Sequence[Callback] = (),
) -> dict[str, Any]:
    """Train on ``manifest`` into the folder ``out``; returns the metrics document (also in RUN/metrics.json).

    ``cfg``: the settings (when None, ``TrainConfig()``: the default preset's, what ``jsgs train`` without
    options trains; ``TrainConfig.from_preset("paper")`` for the paper's protocol). With ``resume``, the run's
    own settings are used; ``cfg``, when given, must equal them. ``stop_at``: stop (with a checkpoint) after
    that many steps, as an interruption would (for tests and time-boxed jobs). ``progress``: a progress bar.
    ``profile``: record per-phase times (synchronises the device at each phase; slower). ``hook``: a loss hook
    to use instead of the method's own (tests). ``log``: where one-line notes go (stderr by default).
    ``callbacks``: more callbacks, after the standard ones (progress, step profiler, checkpoints,
    metrics.json). Raises JsgsError on bad input, TrainingDiverged on NaN/Inf."""
    from jsgs.train.callbacks import CheckpointSaver, MetricsWriter, ProgressBar, StepProfiler

    standard: list[Callback] = [
        ProgressBar(progress), StepProfiler(profile), CheckpointSaver(), MetricsWriter()
    ]
    trainer = Trainer(
        manifest, out, cfg, resume=resume, force=force, stop_at=stop_at, command=command, hook=hook, log=log,
        callbacks=[*standard, *callbacks],
    )  # fmt: skip
    return trainer.train()
