"""Every setting of a training run. The defaults are the default preset's, :data:`DEFAULT_PRESET` (``mcmc``:
gsplat 1.5.3 ``examples/simple_trainer.py``'s ``mcmc`` recipe with a Gaussian budget sized to the scene,
:mod:`jsgs.train.budget`, and JSGS's recipe for it): ``TrainConfig()`` and ``jsgs train`` without options
give the same settings.
:data:`PRESETS` holds the others (``TrainConfig.from_preset("paper")``: simple_trainer's default recipe with
DefaultStrategy, the paper's protocol).

A run is reproducible from ``RUN/config.json`` alone: it holds these settings in full (``settings``), the
values derived from the manifest (scene scale, normalisation transform, ...) and the software versions.

Sources of the values (gsplat tag v1.5.3):

- ``examples/simple_trainer.py`` ``Config`` and ``create_splats_with_optimizers``: SfM initialisation, scales
  from the mean squared distance to the 3 nearest neighbours, opacity 0.1 (mcmc: 0.5, scales x 0.1, opacity
  and scale regularisation 0.01, 30,000 steps), Adam learning rates (means
  1.6e-4 x scene scale with an exponential decay to 0.01x over the run, scales 5e-3, quats 1e-3, opacities
  5e-2, sh0 2.5e-3, shN 2.5e-3/20), Adam eps 1e-15, SH degree 3 raised every 1000 steps, ssim_lambda 0.2 with
  ``fused_ssim(..., padding="valid")``,
  near/far planes 0.01 / 1e10, random background off, packed off, seed 42 (classic rasterisation: the
  antialiased mode is not implemented by our rasterizers);
- ``gsplat/strategy/mcmc.py`` ``MCMCStrategy`` and ``gsplat/strategy/default.py`` ``DefaultStrategy``: the
  relocation, densification and pruning thresholds;
- ``examples/datasets/colmap.py`` ``Parser``: world normalisation on, scene scale = 1.1 x the largest
  camera distance from the cameras' mean (times ``global_scale``).

Only what our trainer implements is here (no pose/appearance optimisation, bilateral grid, depth loss,
batch size > 1): a setting that exists is a setting that is honoured.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin

from jsgs.base.errors import JsgsError
from jsgs.base.limits import MAX_INT_SETTING, MAX_SETTING, read_json

RUN_CONFIG_FORMAT = "jsgs-run-config"
RUN_CONFIG_VERSION = 1
T = TypeVar("T")
#: The fixed Gaussian budget: ``strategy.cap_max``'s default, what an mcmc run trains with
#: ``strategy.cap_max_auto`` off and no ``cap_max`` given, and the most the scene-sized budget gives a scene
#: without SfM points (:func:`jsgs.train.budget.auto_budget`).
MCMC_CAP_MAX = 300_000


#: range bounds a numeric setting may carry (JSON Schema's keyword for each)
_BOUNDS = {"ge": "minimum", "gt": "exclusiveMinimum", "le": "maximum", "lt": "exclusiveMaximum"}
_BOUND_WORDS = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<"}


def setting(default: Any = dataclasses.MISSING, help: str = "", **kw: Any) -> Any:
    """A dataclass field with a ``help`` text (used for the JSON Schema and the docs): every setting of a
    config section, the methods' option sections included (:func:`section_from_dict`). Numeric settings may
    carry bounds ``ge``, ``gt``, ``le``, ``lt``: checked when settings are read (a one-line error naming the
    key) and written into the JSON Schema. A side left open is bounded by :data:`jsgs.base.limits.MAX_SETTING`
    (numbers) or :data:`jsgs.base.limits.MAX_INT_SETTING` (integers). A ``RUN/config.json`` holds every
    setting; one written before a setting existed is read with the value that does what that version did
    (:func:`settings_of_today`)."""
    meta: dict[str, Any] = {"help": help}
    for b in _BOUNDS:
        if b in kw:
            meta[b] = kw.pop(b)
    if "default_factory" in kw:
        return field(default_factory=kw.pop("default_factory"), metadata=meta, **kw)
    return field(default=default, metadata=meta, **kw)


def check_bounds(section: Any, where: str, prefix: str = "") -> None:
    """Every numeric setting of ``section`` (a config dataclass, nested sections included) within its
    bounds; JsgsError (one line) naming the first that is not."""
    for f in dataclasses.fields(section):
        value = getattr(section, f.name)
        if dataclasses.is_dataclass(value):
            check_bounds(value, where, prefix + f.name + ".")
        else:
            _check_bounds(value, f, prefix + f.name, where)


def _limits(f: dataclasses.Field[Any], is_int: bool) -> dict[str, Any]:
    """The bounds of setting ``f``: its own, with :data:`jsgs.base.limits.MAX_INT_SETTING` (integers) or
    :data:`jsgs.base.limits.MAX_SETTING` (numbers) on a side it leaves open."""
    cap = MAX_INT_SETTING if is_int else MAX_SETTING
    out = {b: f.metadata[b] for b in _BOUNDS if b in f.metadata}
    if "ge" not in out and "gt" not in out:
        out["ge"] = -cap
    if "le" not in out and "lt" not in out:
        out["le"] = cap
    return out


def _check_bounds(value: Any, f: dataclasses.Field[Any], key: str, where: str) -> None:
    values = value if isinstance(value, list) else [value]
    for v in values:
        if not isinstance(v, (int, float)) or isinstance(v, bool):
            continue
        limits = _limits(f, isinstance(v, int))
        for b, words in _BOUND_WORDS.items():
            if b not in limits:
                continue
            bound = limits[b]
            ok = {"ge": v >= bound, "gt": v > bound, "le": v <= bound, "lt": v < bound}[b]
            if not ok:
                shown = f"{bound:g}" if isinstance(bound, float) and abs(bound) >= 1e6 else bound
                raise JsgsError(f"{where}: {key} must be {words} {shown} (got {v!r})")


_f = setting


@dataclass
class InitConfig:
    """Initial Gaussians (gsplat ``create_splats_with_optimizers``)."""

    type: Literal["sfm", "random"] = _f(
        "sfm", "sfm: one Gaussian per manifest point; random: uniform in a cube."
    )
    num_points: int = _f(100_000, "Number of Gaussians for type=random (ignored for sfm).", ge=1)
    extent: float = _f(
        3.0, "Half-side of the random cube, as a multiple of the scene scale (type=random).", gt=0.0
    )
    opacity: float = _f(0.5, "Initial opacity (after the sigmoid; --preset paper: 0.1).", gt=0.0, lt=1.0)
    scale: float = _f(0.1, "Multiplier on the kNN scale (--preset paper: 1).", gt=0.0)
    knn_neighbors: int = _f(
        3, "Initial scale = sqrt(mean of squared distances to this many nearest other points).", ge=1
    )
    min_distance: float = _f(
        1e-7,
        "Floor on that kNN distance (world units, normalised world): duplicated SfM points would otherwise "
        "give log(0) = -inf scales (gsplat has no floor; it only matters for exact duplicates).",
        gt=0.0,
    )


@dataclass
class OptimConfig:
    """Adam, one optimizer per parameter group, as gsplat (batch size 1)."""

    means_lr: float = _f(1.6e-4, "Means learning rate, multiplied by the scene scale.", ge=0.0)
    means_lr_final_factor: float = _f(
        0.01,
        "The means' learning rate decays exponentially to this fraction of its start over the run.",
        gt=0.0,
    )
    means_lr_decay_steps: int = _f(
        0,
        "The step at which the means' learning rate reaches means_lr_final_factor x its start (0: "
        "iterations, the end of the run); a run longer than this keeps decaying at the same rate past it, "
        "so its steps up to here are those of a run of this length (jsgs bench --gsplat-steps).",
        ge=0,
    )
    scales_lr: float = _f(5e-3, "Log-scales learning rate.", ge=0.0)
    quats_lr: float = _f(1e-3, "Quaternions learning rate.", ge=0.0)
    opacities_lr: float = _f(5e-2, "Opacity-logits learning rate.", ge=0.0)
    sh0_lr: float = _f(2.5e-3, "SH band 0 learning rate.", ge=0.0)
    shN_lr: float = _f(2.5e-3 / 20, "Higher SH bands learning rate.", ge=0.0)
    eps: float = _f(1e-15, "Adam epsilon.", gt=0.0)
    beta1: float = _f(0.9, "Adam beta1.", ge=0.0, lt=1.0)
    beta2: float = _f(0.999, "Adam beta2.", ge=0.0, lt=1.0)


@dataclass
class StrategyConfig:
    """Densification (``jsgs.train.strategy``): gsplat's ``DefaultStrategy`` (densify by screen-space
    gradient, prune by opacity and size) or ``MCMCStrategy`` (a fixed budget of Gaussians, ``cap_max``)."""

    type: Literal["default", "mcmc"] = _f(
        "mcmc",
        "mcmc: gsplat MCMCStrategy, at most cap_max Gaussians (equal model sizes for comparisons); default: "
        "gsplat DefaultStrategy (the count grows as the heuristics decide; --preset paper).",
    )
    cap_max: int = _f(
        MCMC_CAP_MAX,
        "mcmc: the budget, the largest number of Gaussians, when cap_max_auto is off (gsplat's "
        "MCMCStrategy: 1000000, which --preset paper records). Settings that give cap_max without "
        "cap_max_auto (a config file, --cap-max N) mean this fixed budget.",
        ge=1,
    )
    cap_max_auto: bool = _f(
        True,
        "mcmc: choose cap_max from the scene when the run starts (jsgs.train.budget: 24 Gaussians per SfM "
        "point, at most one per 30 training pixels and 1000000 in all; a manifest without SfM points: at "
        f"most {MCMC_CAP_MAX}; --cap-max auto, the mcmc preset's default); cap_max then holds the choice and "
        "config.json "
        "derived.budget its inputs. A run's config.json without this key trained with cap_max.",
    )
    noise_lr: float = _f(
        5e5,
        "mcmc: position noise scale, times the means' learning rate (gsplat MCMCStrategy noise_lr).",
        ge=0.0,
    )
    min_opacity: float = _f(0.005, "mcmc: Gaussians at or below this opacity are relocated.", ge=0.0, lt=1.0)
    prune_opa: float = _f(0.005, "Prune Gaussians with opacity below this.", ge=0.0, lt=1.0)
    grow_grad2d: float = _f(
        0.0002, "Duplicate/split Gaussians whose mean screen-space gradient exceeds this.", ge=0.0
    )
    grow_scale3d: float = _f(0.01, "Duplicate if max scale <= this x scene scale, else split.", ge=0.0)
    grow_scale2d: float = _f(
        0.05, "Split if the screen radius (fraction of image size) exceeds this.", ge=0.0
    )
    prune_scale3d: float = _f(
        0.1, "Prune Gaussians larger than this x scene scale (after reset_every).", ge=0.0
    )
    prune_scale2d: float = _f(0.15, "Prune by screen radius (only before refine_scale2d_stop_iter).", ge=0.0)
    refine_scale2d_stop_iter: int = _f(0, "Use the 2D-radius criteria before this step (0: never).", ge=0)
    refine_start_iter: int = _f(
        500, "Refine (default) or relocate and add (mcmc) only after this step.", ge=0
    )
    refine_stop_iter: int = _f(
        25_000,
        "Stop refining at this step (gsplat's MCMCStrategy default; its DefaultStrategy's, --preset paper: "
        "15000).",
        ge=0,
    )
    reset_every: int = _f(3000, "default: opacity reset period (see DefaultStrategy).", ge=1)
    refine_every: int = _f(100, "Refine (default) or relocate and add (mcmc) every this many steps.", ge=1)
    pause_refine_after_reset: int = _f(0, "Pause refinement this many steps after a reset.", ge=0)
    absgrad: bool = _f(False, "Use absolute screen-space gradients (AbsGS).")
    revised_opacity: bool = _f(False, "Revised opacity heuristic of arXiv:2404.06109 when splitting.")


@dataclass
class SceneConfig:
    """How manifest cameras and points become the training world."""

    normalize_world: bool = _f(
        True, "Similarity transform of gsplat's Parser (up axis, recentre, unit camera distance, PCA axes)."
    )
    global_scale: float = _f(1.0, "Multiplier on the scene scale.", gt=0.0)
    scene_scale_margin: float = _f(
        1.1, "Scene scale = this x largest camera distance from the cameras' mean.", gt=0.0
    )
    require_lossless_reference: bool = _f(
        False,
        "Refuse test views whose only image is a JPEG (else they are evaluated against their JPEG, stated as "
        "reference jpeg in metrics.json).",
    )


@dataclass
class RenderConfig:
    """Rasterisation settings."""

    backend: Literal["auto", "torch", "gsplat"] = _f(
        "auto", "auto: gsplat on CUDA, the torch reference rasterizer on CPU."
    )
    sh_degree: int = _f(3, "Final spherical-harmonics degree.", ge=0, le=4)
    sh_degree_interval: int = _f(1000, "Raise the SH degree by one every this many steps.", ge=1)
    near_plane: float = _f(0.01, "Near clipping plane (normalised world units).", gt=0.0)
    far_plane: float = _f(1e10, "Far clipping plane.", gt=0.0)
    packed: bool = _f(False, "gsplat packed mode.")
    random_background: bool = _f(False, "Composite renders over a random colour while training.")


@dataclass
class LossConfig:
    """l_ph = (1 - ssim_lambda) L1 + ssim_lambda (1 - SSIM), and gsplat's optional regularisers."""

    ssim_lambda: float = _f(0.2, "Weight of 1 - SSIM in l_ph.", ge=0.0, le=1.0)
    ssim_padding: Literal["valid", "same"] = _f(
        "valid",
        "SSIM window padding in l_ph: valid (gsplat simple_trainer's fused_ssim call) or same (zero padding, "
        "the original 3DGS).",
    )
    base_weight: float = _f(1.0, "lambda_base: weight of l_ph in the total loss (JSGS exposes it).", ge=0.0)
    opacity_reg: float = _f(
        0.01, "Weight of mean(opacity) (gsplat opacity_reg; --preset paper: 0).", ge=0.0
    )
    scale_reg: float = _f(
        0.01, "Weight of mean(exp(scales)) (gsplat scale_reg; --preset paper: 0).", ge=0.0
    )


@dataclass
class SpeedConfig:
    """How the trainer computes (the same values, different kernels); a method's own speed settings are in
    its method_options (jsgs: method_options.speed)."""

    ssim_kernel: Literal["auto", "torch", "cuda"] = _f(
        "auto",
        "SSIM implementation for l_ph and L_obs (same value): auto (the fused CUDA kernel "
        "jsgs/kernels/csrc/ssim.cu on a GPU, as gsplat's simple_trainer uses fused-ssim; the torch twin "
        "elsewhere), torch (separable convolutions everywhere) or cuda (the kernel, or an error).",
    )
    exchange: Literal["torch", "gsplat"] = _f(
        "torch",
        "On several processes (--gpus N), how a view reaches the other processes' Gaussians: torch (every "
        "shard gathered on every process, the gradients reduce-scattered back to their owners; any method, "
        "camera and image sizes; the faster on 2 GPUs at 1,000,000 Gaussians: docs/results/scale) or gsplat "
        "(gsplat's distributed rasterisation, rasterization(..., distributed=True), where it renders every "
        "training view: gsplat backend, pinhole cameras, one image size, no extra render channels such as "
        "JSGS's Gaussian Controller's, no absgrad; elsewhere the torch exchange, with a note saying why).",
    )


@dataclass
class EvalConfig:
    """Evaluation at the --eval-at steps."""

    lpips_weights: str | None = _f(
        None, "AlexNet backbone for LPIPS (else $JSGS_LPIPS_WEIGHTS; none: LPIPS is null)."
    )
    fps_passes: int = _f(
        5, "Timed rendering passes over the test views (FPS = views / median pass time).", ge=1
    )
    fps_warmup: int = _f(1, "Untimed passes before those.", ge=0)
    save_renders: bool = _f(True, "Write the test renders as PNG.")


@dataclass
class TrainConfig:
    """All settings of a run. Nested sections mirror the JSON (``RUN/config.json`` ``settings``). The defaults
    are the default preset's (:data:`DEFAULT_PRESET`), ``method_options`` included: when not given they are
    the method's recipe for it (:func:`jsgs.train.method.method_recipe`); :meth:`from_preset` gives another
    preset's."""

    method: str = _f("jsgs", "Training method: jsgs (the default) or gsplat (the baseline, no JPEG terms).")
    iterations: int = _f(30_000, "Training steps (one view each).", ge=1)
    eval_at: list[int] = _f(
        default_factory=lambda: [7000, 30_000],
        help="Evaluate and checkpoint after these steps (1-based: 3000 = after 3000 steps).",
        ge=1,
    )
    checkpoint_every: int = _f(
        0, "Also checkpoint every this many steps (0: only at eval steps and the end).", ge=0
    )
    checkpoint_keep: int = _f(
        3,
        "Keep the newest this many checkpoints, deleting older ones as new ones are written (0: keep every "
        "one). The default keeps one per evaluation of the presets' eval_at.",
        ge=0,
    )
    seed: int = _f(42, "Seed of every random number generator.", ge=0)
    device: Literal["auto", "cpu", "cuda"] = _f("auto", "auto: cuda when available, else cpu.")
    log_every: int = _f(10, "Refresh the progress bar every this many steps.", ge=1)
    init: InitConfig = _f(default_factory=InitConfig, help="Initial Gaussians.")
    optim: OptimConfig = _f(default_factory=OptimConfig, help="Optimizer.")
    strategy: StrategyConfig = _f(default_factory=StrategyConfig, help="Densification strategy.")
    scene: SceneConfig = _f(default_factory=SceneConfig, help="World normalisation.")
    render: RenderConfig = _f(default_factory=RenderConfig, help="Rasterisation.")
    loss: LossConfig = _f(default_factory=LossConfig, help="Loss weights.")
    eval: EvalConfig = _f(default_factory=EvalConfig, help="Evaluation.")
    speed: SpeedConfig = _f(default_factory=SpeedConfig, help="Speed settings (same results).")
    method_options: dict[str, Any] = _f(
        default_factory=lambda: _MethodDefaults(),
        help="Settings of the chosen method: its registered options section (jsgs: $defs/jsgs_options), "
        "parsed and checked like every other section; empty for gsplat. Not given: the method's recipe for "
        "the preset.",
    )

    def __post_init__(self) -> None:
        if isinstance(self.method_options, _MethodDefaults):
            self.method_options = method_defaults(self.method)

    @classmethod
    def from_preset(cls, name: str, **changes: Any) -> TrainConfig:
        """The settings of preset ``name`` (:data:`PRESETS`), with its method's recipe for it, and top-level
        ``changes`` (``method`` without ``method_options``: that method's recipe for the preset)."""
        from jsgs.train.method import method_recipe

        if name not in PRESETS:
            raise JsgsError(f"--preset: {name!r} is not one of {', '.join(PRESETS)}")
        cfg = from_dict(PRESETS[name], f"preset {name}")
        cfg.method_options = method_recipe(cfg.method, name)
        if "method" in changes and "method_options" not in changes:
            changes["method_options"] = method_recipe(changes["method"], name)
        return dataclasses.replace(cfg, **changes)

    def check(self, where: str = "config", method_options: bool = True) -> None:
        """Raise JsgsError (one line) on inconsistent settings; with ``method_options``, also parse and check
        ``method_options`` as the options of ``method`` (off for a partial settings file that names no
        method: the method, and so the options' meaning, is given later, e.g. on the command line)."""
        check_bounds(self, where)
        bad = [s for s in self.eval_at if s > self.iterations]
        if bad:
            raise JsgsError(f"{where}: eval_at steps must lie in 1..iterations={self.iterations} (got {bad})")
        if list(self.eval_at) != sorted(set(self.eval_at)):
            raise JsgsError(f"{where}: eval_at must be increasing without repeats (got {self.eval_at})")
        if self.render.far_plane <= self.render.near_plane:
            raise JsgsError(
                f"{where}: render.far_plane ({self.render.far_plane}) must exceed render.near_plane "
                f"({self.render.near_plane})"
            )
        if method_options:
            parse_method_options(self.method, self.method_options, where)


class _MethodDefaults(dict[str, Any]):
    """``TrainConfig.method_options`` not given (replaced by :func:`method_defaults` when built)."""


def method_defaults(name: str) -> dict[str, Any]:
    """The ``method_options`` method ``name`` has by default: its recipe for :data:`DEFAULT_PRESET`."""
    from jsgs.train.method import method_recipe

    return method_recipe(name, DEFAULT_PRESET)


# ---------------------------------------------------------------------------------------------------------
# dict <-> dataclass, with one-line errors naming the offending key


def _is_dataclass_type(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def to_dict(cfg: Any) -> dict[str, Any]:
    """Plain JSON-able dict of a config dataclass (nested sections become nested objects)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def _coerce(value: Any, tp: Any, key: str, where: str) -> Any:
    origin = get_origin(tp)
    if _is_dataclass_type(tp):
        if not isinstance(value, dict):
            raise JsgsError(f"{where}: {key} must be an object")
        return _from_dict(tp, value, where, prefix=key + ".", base=None)
    if origin is Literal:
        if value not in get_args(tp):
            raise JsgsError(f"{where}: {key} must be one of {list(get_args(tp))} (got {value!r})")
        return value
    if origin in (typing.Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, key, where)
            except JsgsError:
                pass
        parts = [p for a in args if a is not type(None) for p in _expected(a)]
        what = parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " or " + parts[-1]
        raise JsgsError(f"{where}: {key} must be {what} (got {value!r})")
    if origin is list:
        (item,) = get_args(tp)
        if not isinstance(value, list):
            raise JsgsError(f"{where}: {key} must be a list")
        return [_coerce(v, item, f"{key}[{i}]", where) for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise JsgsError(f"{where}: {key} must be an object")
        return dict(value)
    if tp is bool:
        if not isinstance(value, bool):
            raise JsgsError(f"{where}: {key} must be true or false (got {value!r})")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise JsgsError(f"{where}: {key} must be an integer (got {value!r})")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise JsgsError(f"{where}: {key} must be a finite number (got {value!r})")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise JsgsError(f"{where}: {key} must be a string (got {value!r})")
        return value
    if tp is Any:
        return value
    raise TypeError(f"unsupported config type {tp!r} for {key}")


def _expected(tp: Any) -> list[str]:
    """What a value of type ``tp`` may be, in words (for messages)."""
    if get_origin(tp) is Literal:
        return [json.dumps(v) for v in get_args(tp)]
    names = {bool: ["true", "false"], int: ["an integer"], float: ["a number"], str: ["a string"]}
    return names.get(tp, ["an object" if _is_dataclass_type(tp) or get_origin(tp) is dict else "a list"])


def _from_dict(cls: type, doc: dict[str, Any], where: str, prefix: str, base: Any) -> Any:
    hints = _hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(doc) - set(names))
    if unknown:
        raise JsgsError(f"{where}: unknown setting {prefix}{unknown[0]} (known: {', '.join(names)})")
    obj = base if base is not None else cls()
    for f in dataclasses.fields(cls):
        name = f.name
        if name not in doc:
            continue
        tp = hints[name]
        if _is_dataclass_type(tp):
            if not isinstance(doc[name], dict):
                raise JsgsError(f"{where}: {prefix}{name} must be an object")
            setattr(obj, name, _from_dict(tp, doc[name], where, prefix + name + ".", getattr(obj, name)))
        else:
            value = _coerce(doc[name], tp, prefix + name, where)
            _check_bounds(value, f, prefix + name, where)
            setattr(obj, name, value)
    return obj


def section_from_dict(cls: type[T], doc: Any, where: str, prefix: str = "") -> T:
    """A config section (a dataclass of :func:`setting` fields, e.g. a method's options) from a (possibly
    partial) dict over its defaults; ``prefix`` names it in messages ("method_options."). JsgsError (one line)
    on an unknown key, a wrong type or a value outside its choices."""
    if not isinstance(doc, dict):
        raise JsgsError(f"{where}: {prefix.rstrip('.') or 'settings'} must be an object")
    out: T = _from_dict(cls, doc, where, prefix=prefix, base=None)
    return out


def parse_method_options(name: str, raw: dict[str, Any], where: str = "config") -> Any:
    """``method_options`` of method ``name`` parsed into its options dataclass and checked (None for a method
    without options, which must then be empty). JsgsError (one line) naming the setting."""
    from jsgs.train.method import options_class

    cls = options_class(name)
    if cls is None:
        if raw:
            key = sorted(raw)[0]
            raise JsgsError(f"{where}: method {name} takes no method_options (got {key!r})")
        return None
    if "lambda_base" in raw:
        raise JsgsError(
            f"{where}: method_options.lambda_base: λ_base is the trainer's loss.base_weight "
            "(set it there; default 1)"
        )
    opts = section_from_dict(cls, raw, where, "method_options.")
    check = getattr(opts, "check", None)
    if check is not None:
        check(where)
    return opts


def fixed_budget_given(doc: Any) -> Any:
    """A settings object whose ``strategy`` gives ``cap_max`` without ``cap_max_auto``, with ``cap_max_auto``
    false (a copy): whoever writes a budget means that budget, not the one the scene would get (a config
    file's ``cap_max: 300000``; a run's config.json written before ``cap_max_auto`` existed). Anything else
    is returned as it is."""
    strategy = doc.get("strategy") if isinstance(doc, dict) else None
    if not isinstance(strategy, dict) or "cap_max" not in strategy or "cap_max_auto" in strategy:
        return doc
    return {**doc, "strategy": {**strategy, "cap_max_auto": False}}


def from_dict(doc: dict[str, Any], where: str = "config", base: TrainConfig | None = None) -> TrainConfig:
    """Settings from a (possibly partial) nested dict over ``base`` (defaults when None). ``method_options``,
    when given, is taken whole; a ``method`` other than the base's without it starts from that method's
    default options; a ``strategy.cap_max`` without ``strategy.cap_max_auto`` is a fixed budget
    (:func:`fixed_budget_given`)."""
    if not isinstance(doc, dict):
        raise JsgsError(f"{where}: settings must be a JSON object")
    base = from_dict(to_dict(base), where) if base is not None else TrainConfig()
    method = base.method
    cfg = _from_dict(TrainConfig, fixed_budget_given(doc), where, prefix="", base=base)
    if cfg.method != method and "method_options" not in doc:
        # the options of another method: the new one starts from its defaults
        cfg.method_options = method_defaults(cfg.method)
    return cfg


#: Values that files written by earlier versions hold for a setting, by (section, key), and the value of
#: today that does the same: ``speed.exchange: auto`` chose gsplat's distributed rasterisation where it
#: renders every training view, which ``gsplat`` does.
_RECORDED_VALUES: dict[tuple[str, str], dict[str, str]] = {("speed", "exchange"): {"auto": "gsplat"}}


def current_values(settings: Any) -> Any:
    """A recorded settings object with the values of :data:`_RECORDED_VALUES` replaced by today's (a copy;
    anything else is returned as it is)."""
    if not isinstance(settings, dict):
        return settings
    out = dict(settings)
    for (section, key), values in _RECORDED_VALUES.items():
        part = out.get(section)
        if isinstance(part, dict) and isinstance(part.get(key), str) and part[key] in values:
            out[section] = {**part, key: values[part[key]]}
    return out


#: Settings recorded under another name by earlier versions: the earlier key -> today's (dotted).
_RECORDED_NAMES: dict[str, str] = {
    "loss.ssim_kernel": "speed.ssim_kernel",
    **{f"method_options.{k}": f"method_options.speed.{k}" for k in ("compile", "cuda_graph", "cuda_graph_gc",
                                                                   "gc_kernel")},
}
#: In :data:`_EARLIER_VALUES`: the ``paper`` preset's value.
_AS_PAPER = object()
#: Settings that a run's config.json written before they existed lacks, and the value that does what jsgs
#: did then (none of them changes what a run trains but the strategy's, whose earlier value is known): every
#: checkpoint was kept; the SSIM was the torch one before the fused kernel; several processes used gsplat's
#: distributed rasterisation where it rendered every view (as a recorded ``speed.exchange: auto``);
#: DefaultStrategy was the only strategy (:data:`_AS_PAPER`: the ``paper`` preset's value, which is that; the
#: MCMC settings unused), the means' learning rate decayed over the run. A setting of today that such a file
#: lacks and that is not here is refused (:func:`settings_of_today`).
_EARLIER_VALUES: dict[str, Any] = {
    "checkpoint_keep": 0,
    "speed.ssim_kernel": "torch",
    "speed.exchange": "gsplat",
    "optim.means_lr_decay_steps": 0,
    "strategy.type": "default",
    "strategy.cap_max": _AS_PAPER,
    "strategy.cap_max_auto": False,
    "strategy.noise_lr": _AS_PAPER,
    "strategy.min_opacity": _AS_PAPER,
}


def _renamed(settings: dict[str, Any]) -> dict[str, Any]:
    """``settings`` (a copy) with the keys of :data:`_RECORDED_NAMES` moved to today's names (where today's
    is not also given)."""
    out = json.loads(json.dumps(settings))
    for old, new in _RECORDED_NAMES.items():
        *head, key = old.split(".")
        part = _part(out, head)
        if part is None or key not in part:
            continue
        *new_head, new_key = new.split(".")
        target = _part(out, new_head, make=True)
        if target is not None and new_key not in target:
            target[new_key] = part.pop(key)
    return out


def _part(doc: dict[str, Any], keys: list[str], make: bool = False) -> dict[str, Any] | None:
    """The nested object of ``doc`` at ``keys`` (created where ``make``); None where one is not an object."""
    for k in keys:
        if make and k not in doc:
            doc[k] = {}
        doc = doc.get(k)  # type: ignore[assignment]
        if not isinstance(doc, dict):
            return None
    return doc


def settings_of_today(settings: Any, where: str) -> tuple[Any, list[str]]:
    """A run's recorded ``settings`` (``RUN/config.json``, a checkpoint's, a configs.json entry) as today's
    code reads them, whichever version wrote them: values and keys recorded under earlier names read as
    today's (:func:`current_values`, :data:`_RECORDED_NAMES`), and each setting the file was written before
    given the value that does what that version did (:data:`_EARLIER_VALUES`); with those settings, as
    ``key value`` texts (empty for a file of today). ``method_options`` take their options' defaults, as in
    every file. JsgsError (one line naming ``where`` and the setting) for a missing setting whose earlier
    value is not known. Anything not an object is returned as it is (the schema refuses it)."""
    if not isinstance(settings, dict):
        return settings, []
    out = _renamed(current_values(settings))
    assumed: list[str] = []
    paper = to_dict(TrainConfig.from_preset("paper"))
    for section, value in paper.items():
        if section == "method_options":
            continue
        keys = [f"{section}.{k}" for k in value] if isinstance(value, dict) else [section]
        if isinstance(value, dict) and section in out and not isinstance(out[section], dict):
            continue  # the schema names it
        for key in keys:
            *head, name = key.split(".")
            part = _part(out, head, make=True)
            if part is None or name in part:
                continue
            if key not in _EARLIER_VALUES:
                raise JsgsError(
                    f"{where}: lacks the setting {key}, which changes what the run trains and whose value "
                    "there is not known"
                )
            earlier = _EARLIER_VALUES[key]
            part[name] = _part(paper, head)[name] if earlier is _AS_PAPER else earlier  # type: ignore[index]
            assumed.append(f"{key} {json.dumps(part[name])}")
    return out, assumed


_said: set[tuple[str, str]] = set()


def say_once(where: str, line: str) -> None:
    """Print the note ``line`` about ``where`` on stderr, once per process."""
    if (where, line) not in _said:
        _said.add((where, line))
        print(line, file=sys.stderr, flush=True)


def say_assumed(where: str, assumed: list[str], what: str = "settings") -> None:
    """The note (stderr, once per file and process) that ``where`` was read with the ``what`` ``assumed``
    (settings: :func:`settings_of_today`; a checkpoint's fields:
    :func:`jsgs.train.checkpoint.fields_of_today`); nothing when there are none."""
    if not assumed:
        return
    line = (
        f"note: {where} was written before some {what} existed; read with the values that do what "
        f"that version did: {', '.join(assumed)}"
    )
    say_once(where, line)


def say_unused_budget(settings: Any, cfg: TrainConfig, where: str) -> None:
    """The note (stderr, once per file and process) that the ``strategy.cap_max`` which the settings
    ``settings`` read from ``where`` give is not used because they also turn ``strategy.cap_max_auto`` on
    in the settings ``cfg`` finally used (the explicit choice wins); nothing otherwise. For settings a user
    gives (a ``--config`` file of partial settings), not a run's config.json, which records the budget auto
    chose as ``cap_max``."""
    strategy = settings.get("strategy") if isinstance(settings, dict) else None
    given = isinstance(strategy, dict) and "cap_max" in strategy and strategy.get("cap_max_auto") is True
    if not given or cfg.strategy.type != "mcmc" or not cfg.strategy.cap_max_auto:
        return
    line = (
        f"note: {where}: strategy.cap_max {strategy['cap_max']} is not used: strategy.cap_max_auto is on "
        "(the budget comes from the scene; give --cap-max N for a fixed one)"
    )
    say_once(where, line)


def recorded_settings(settings: Any, where: str) -> TrainConfig:
    """The complete settings a run recorded (``RUN/config.json`` or a checkpoint's ``settings``), read as
    today's code reads them (:func:`settings_of_today`: a setting the file was written before takes the
    value that does what that version did, e.g. ``strategy.cap_max_auto`` off: the run trained with the
    ``cap_max`` it records)."""
    return from_dict(settings_of_today(settings, where)[0], where, base=TrainConfig.from_preset("paper"))


#: The preview preset's training length (steps).
PREVIEW_ITERATIONS = 1_000
#: The paper's protocol over the defaults: gsplat simple_trainer's default recipe with DefaultStrategy,
#: trained 10,000 steps with evaluations at 3,000, 7,000 and 10,000 (``cap_max``: MCMCStrategy's own, a
#: fixed budget, unused by DefaultStrategy, recorded as before).
_PAPER: dict[str, Any] = {
    "iterations": 10_000,
    "eval_at": [3000, 7000, 10_000],
    "init": {"opacity": 0.1, "scale": 1.0},
    "loss": {"opacity_reg": 0.0, "scale_reg": 0.0},
    "strategy": {"type": "default", "refine_stop_iter": 15_000, "cap_max": 1_000_000, "cap_max_auto": False},
}
#: Named starting points for the settings (``jsgs train --preset NAME``, :meth:`TrainConfig.from_preset`),
#: each over the defaults; a config file and the command line apply over them, and each method's recipe for
#: the preset (:func:`jsgs.train.method.method_recipe`: JSGS's in :mod:`jsgs.method.recipes`) gives its
#: ``method_options``. ``mcmc``, the defaults (:data:`DEFAULT_PRESET`): simple_trainer's ``mcmc`` recipe at
#: its full length (``max_steps`` 30,000, evaluations at 7,000 and 30,000, the means' learning rate decaying
#: over the 30,000 steps, MCMCStrategy refining until 25,000), measured better than DefaultStrategy for
#: gsplat on all four shared scenes (docs/results/budget), with a Gaussian budget sized to the scene
#: (``strategy.cap_max_auto``, :mod:`jsgs.train.budget`; docs/training.md, "A budget sized to the scene").
#: ``paper``: the paper's protocol (:data:`_PAPER`). ``preview``: a quick look at a capture on a CPU
#: (docs/training.md, "A preview on a CPU"): the baseline (``method`` gsplat) with the paper's
#: DefaultStrategy, :data:`PREVIEW_ITERATIONS` steps and one evaluation at the end, meant for a copy of the
#: photos downscaled by 2, whose pixels no longer carry the files' 8×8 JPEG grid (so JSGS's terms have nothing
#: to read).
PRESETS: dict[str, dict[str, Any]] = {
    "mcmc": {},
    "paper": _PAPER,
    "preview": {
        **_PAPER, "method": "gsplat", "iterations": PREVIEW_ITERATIONS, "eval_at": [PREVIEW_ITERATIONS]
    },
}
#: the preset of the defaults, and so of a new ``jsgs train`` run given none
DEFAULT_PRESET = "mcmc"


def cap_max_settings(text: str) -> dict[str, Any]:
    """``--cap-max N`` or ``--cap-max auto`` as strategy settings; JsgsError (one line) on anything else."""
    if text.strip().lower() == "auto":
        return {"cap_max_auto": True}
    try:
        n = int(text)
    except ValueError:
        raise JsgsError(f"--cap-max: expected a number of Gaussians or auto (got {text!r})") from None
    return {"cap_max": n, "cap_max_auto": False}


def preset_iterations(name: str) -> int:
    """The training length of preset ``name`` (``jsgs bench`` follows it unless given --iterations)."""
    return TrainConfig.from_preset(name).iterations


def cut_eval_at(eval_at: list[int], iterations: int) -> list[int]:
    """The evaluation steps of a run shortened or lengthened to ``iterations``: those below it, and it."""
    return [s for s in eval_at if s < iterations] + [iterations]


def command_settings(
    *,
    preset_name: str | None = None,
    config_file: str | Path | None = None,
    resume_settings: TrainConfig | None = None,
    overrides: dict[str, Any] | None = None,
    switches: dict[str, Any] | None = None,
    eval_at_given: bool = False,
) -> TrainConfig:
    """The settings of a ``jsgs train`` invocation, in layers: the defaults, the preset (a new run:
    :data:`DEFAULT_PRESET` unless ``preset_name``), the config file (or, when resuming, the run's own
    settings), the command line's ``overrides`` (dotted-free top-level keys); then, for a new run, the
    ``method_options`` of the method so chosen are its recipe for the preset
    (:func:`jsgs.train.method.method_recipe`) under the config file's (not with an earlier run's
    config.json, whose settings are complete); then the method's ``switches`` (flag -> value, e.g.
    ``{"--no-gc": True}``; :class:`jsgs.train.method.MethodFlag`) merged over ``method_options``. With
    ``iterations`` changed (on the command line, or by a config file over the preset) and the preset's
    ``eval_at`` kept, the evaluation steps are cut at the new length, which is always evaluated (a longer
    run: the same steps, and its end). JsgsError (one line) on conflicting choices."""
    from jsgs.train.method import method_recipe

    overrides = dict(overrides or {})
    if resume_settings is not None and preset_name is not None:
        raise JsgsError(
            "--preset applies to a new run; --resume takes the run's own settings (drop --preset)"
        )
    if preset_name is None and resume_settings is None:
        preset_name = DEFAULT_PRESET
    start = TrainConfig.from_preset(preset_name) if preset_name is not None else TrainConfig()
    whole = False  # an earlier run's config.json: its settings are complete, the preset adds nothing
    given_options: Any = {}  # the method_options a partial config file gives
    if config_file is not None:
        doc = read_config_document(config_file)
        whole = is_run_config(doc)
        if isinstance(doc, dict) and not whole:
            given_options = doc.get("method_options", {})
            keeps_steps = "eval_at" not in doc and "iterations" not in overrides
            if isinstance(doc.get("iterations"), int) and keeps_steps:
                # partial settings of another length that keep the preset's evaluation steps: cut them
                doc = {**doc, "eval_at": cut_eval_at(start.eval_at, doc["iterations"])}
        base = config_from_document(doc, config_file, base=start)
    elif resume_settings is not None:
        base = resume_settings
    else:
        base = start
    cfg = from_dict(overrides, "command line", base=base)
    if preset_name is not None and not whole:
        cfg.method_options = {**method_recipe(cfg.method, preset_name), **given_options}
    if switches:
        cfg.method_options = _merged(cfg.method_options, _switch_options(cfg.method, switches))
    if "iterations" in overrides and not eval_at_given and cfg.eval_at and cfg.eval_at[-1] != cfg.iterations:
        cfg.eval_at = cut_eval_at(cfg.eval_at, cfg.iterations)
    if config_file is not None and not whole:  # a run's config.json records auto's choice as cap_max
        say_unused_budget(doc, cfg, str(config_file))
    return cfg


def _switch_options(method: str, switches: dict[str, Any]) -> dict[str, Any]:
    """The ``method_options`` that ``switches`` (flag -> value) set; JsgsError (one line) when one belongs
    to another method than ``method``."""
    from jsgs.train.method import method_flags, method_names

    out: dict[str, Any] = {}
    for name in method_names():
        flags = method_flags(name)
        given = [f for f in flags if f.flag in switches]
        if given and name != method:
            names = [f.flag for f in flags]
            listed = names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]
            raise JsgsError(f"{listed} apply to --method {name} (method is {method!r})")
        for f in given:
            out = _merged(out, f.options(switches[f.flag]))
    return out


def _merged(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``over`` merged into a copy of ``base``, nested objects key by key."""
    out = dict(base)
    for k, v in over.items():
        out[k] = _merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def is_run_config(doc: Any) -> bool:
    """Whether a ``--config`` document is an earlier run's ``RUN/config.json`` (validated, its ``settings``
    taken whole) rather than a JSON object of partial settings."""
    return isinstance(doc, dict) and "format" in doc


def read_config_document(path: str | Path) -> Any:
    """The parsed JSON of ``--config FILE``; JsgsError (one line) when it is missing or not JSON."""
    path = Path(path)
    if not path.exists():
        raise JsgsError(f"{path}: no such config file")
    return read_json(path, "a JSON config file")


def config_from_document(doc: Any, path: str | Path, base: TrainConfig | None = None) -> TrainConfig:
    """The settings of a ``--config`` document read from ``path``: an earlier run's (validated against the
    schema, taken whole; :func:`is_run_config`) or partial settings over ``base`` (default: the defaults)."""
    from jsgs.base.schema import validate

    whole = is_run_config(doc)
    if whole:
        assumed: list[str] = []
        if "settings" in doc:  # a file of an earlier version: its settings as today's, then validated
            settings, assumed = settings_of_today(doc["settings"], str(path))
            doc = {**doc, "settings": settings}
        validate(doc, "config", str(path))
        say_assumed(str(path), assumed)
        settings = doc["settings"]
    else:
        # a bare settings object: from_dict checks names, types and choices with one-line messages
        settings = doc
    cfg = recorded_settings(settings, str(path)) if whole else from_dict(settings, str(path), base=base)
    cfg.check(str(path), method_options=isinstance(settings, dict) and "method" in settings)
    return cfg


def load_config_file(path: str | Path, base: TrainConfig | None = None) -> TrainConfig:
    """Read ``--config FILE``: either a ``RUN/config.json`` of an earlier run (validated against the schema;
    its ``settings`` are taken whole) or a JSON object of (partial) settings over ``base`` (default: the
    defaults)."""
    doc = read_config_document(path)
    cfg = config_from_document(doc, path, base)
    if not is_run_config(doc):
        say_unused_budget(doc, cfg, str(path))
    return cfg


# ---------------------------------------------------------------------------------------------------------
# A run's config.json, read in one place (the trainer's resume, jsgs render / export / view)


@dataclass
class RunConfig:
    """A run folder's ``config.json`` (:func:`read_run_config`): the document, validated against the schema,
    and its settings."""

    path: Path
    doc: dict[str, Any]
    settings: TrainConfig

    @property
    def manifest(self) -> Path:
        """The manifest the run was trained on."""
        return Path(self.doc["manifest"]["path"])

    @property
    def manifest_sha256(self) -> str:
        """The hash of that manifest when the run started."""
        return str(self.doc["manifest"]["sha256"])

    @property
    def derived(self) -> dict[str, Any]:
        """What the run derived from the manifest and its settings (``normalization``, ``world_size``)."""
        out: dict[str, Any] = self.doc["derived"]
        return out


def read_run_config(run: str | Path) -> RunConfig:
    """``RUN/config.json`` of the run folder ``run``, the one reader of it: the document validated against the
    schema and its settings read (:func:`recorded_settings`) and checked. JsgsError (one line) when ``run``
    holds none, or one that is not a run's or does not validate."""
    from jsgs.base.io import not_regular
    from jsgs.base.run_files import RunPaths

    run = Path(run)
    path = RunPaths(run).config
    if not path.is_file():
        why = not_regular(path)
        raise JsgsError(f"{path}: {why}" if why else f"{run}: not a run folder (no config.json)")
    doc = read_config_document(path)
    if not is_run_config(doc):
        raise JsgsError(f"{path}: not the config.json of a jsgs train run (no format)")
    return RunConfig(path, doc, config_from_document(doc, path))


def holds_run_config(run: str | Path) -> bool:
    """Whether the folder ``run`` holds the ``config.json`` of a run (its ``format``), however damaged the
    rest (``jsgs train --force`` replaces only such a folder's outputs)."""
    from jsgs.base.io import read_regular_text
    from jsgs.base.run_files import RunPaths

    path = RunPaths(Path(run)).config
    try:  # a FIFO named config.json is refused at once, never waited on
        return bool(json.loads(read_regular_text(path)).get("format") == RUN_CONFIG_FORMAT)
    except (OSError, ValueError, AttributeError, RecursionError, JsgsError):
        return False


# ---------------------------------------------------------------------------------------------------------
# JSON Schema of the settings, generated from the dataclasses (jsgs/schemas/config.schema.json holds it;
# a test checks that the file is up to date).


def _schema_of(tp: Any, help_text: str) -> dict[str, Any]:
    origin = get_origin(tp)
    out: dict[str, Any]
    if _is_dataclass_type(tp):
        out = _section_schema(tp)
    elif origin is Literal:
        out = {"enum": list(get_args(tp))}
    elif origin in (typing.Union, types.UnionType):
        args = get_args(tp)
        subs = [_schema_of(a, "") for a in args if a is not type(None)]
        if type(None) in args:
            subs.append({"type": "null"})
        if all(set(s) == {"type"} for s in subs):
            out = {"type": [s["type"] for s in subs]}
        else:
            out = {"anyOf": subs}
    elif origin is list:
        (item,) = get_args(tp)
        out = {"type": "array", "items": _schema_of(item, "")}
    elif origin is dict:
        out = {"type": "object"}
    elif tp is bool:
        out = {"type": "boolean"}
    elif tp is int:
        out = {"type": "integer"}
    elif tp is float:
        out = {"type": "number"}
    elif tp is str:
        out = {"type": "string"}
    else:  # pragma: no cover - guarded by the schema test
        raise TypeError(tp)
    if help_text:
        out = {"description": help_text, **out}
    return out


def _section_schema(cls: type) -> dict[str, Any]:
    hints = _hints(cls)
    props = {}
    for f in dataclasses.fields(cls):
        prop = _schema_of(hints[f.name], f.metadata.get("help", ""))
        kind = (prop.get("items", {}) if prop.get("type") == "array" else prop).get("type")
        kinds = kind if isinstance(kind, list) else [kind]
        numeric = "integer" in kinds or "number" in kinds
        limits = _limits(f, "number" not in kinds) if numeric else {}
        bounds = {kw: limits[b] for b, kw in _BOUNDS.items() if b in limits}
        if bounds and prop.get("type") == "array":
            prop["items"] = {**prop["items"], **bounds}
        elif bounds:
            prop.update(bounds)
        props[f.name] = prop
    return {
        "type": "object",
        "description": (cls.__doc__ or "").strip().splitlines()[0],
        "additionalProperties": False,
        "properties": props,
    }


def _method_options_schemas() -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The registered methods' option sections as $defs (``<method>_options``) and the conditions that tie
    ``method_options`` to ``method``."""
    from jsgs.train.method import method_names, options_class

    defs: dict[str, Any] = {}
    conditions: list[dict[str, Any]] = []
    for name in method_names():
        cls = options_class(name)
        ref: dict[str, Any]
        if cls is None:
            ref = {"type": "object", "maxProperties": 0}
        else:
            defs[f"{name}_options"] = _section_schema(cls)
            ref = {"$ref": f"#/$defs/{name}_options"}
        conditions.append(
            {
                "if": {"properties": {"method": {"const": name}}, "required": ["method"]},
                "then": {"properties": {"method_options": ref}},
            }
        )
    return defs, conditions


def config_schema() -> dict[str, Any]:
    """The JSON Schema of ``RUN/config.json`` (and of ``--config`` files, whose settings may be partial)."""
    settings = _section_schema(TrainConfig)
    option_defs, conditions = _method_options_schemas()
    settings["allOf"] = conditions
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": "https://jsgs.dev/schemas/config.schema.json",
        "title": "JSGS training run configuration",
        "description": (
            "RUN/config.json: every setting of a run (`settings`, complete) plus what was derived from the "
            "manifest and the software versions, so that the run can be reproduced from this file and the "
            "manifest (`jsgs train MANIFEST --config RUN/config.json --out NEW`). A `--config` file is "
            "either "
            "such a document or a bare, possibly partial, settings object ($defs/settings). Generated by "
            "jsgs.train.config.config_schema: regenerate with "
            "`python -m jsgs.train.config > jsgs/schemas/config.schema.json`."
        ),
        "type": "object",
        "required": ["format", "format_version", "versions", "command", "manifest", "settings", "derived"],
        "additionalProperties": False,
        "properties": {
            "format": {"const": RUN_CONFIG_FORMAT},
            "format_version": {"const": RUN_CONFIG_VERSION},
            "versions": {
                "type": "object",
                "required": ["jsgs", "torch", "gsplat", "python"],
                "properties": {
                    "jsgs": {"type": "string"},
                    "torch": {"type": "string"},
                    "gsplat": {"type": ["string", "null"]},
                    "python": {"type": "string"},
                },
            },
            "command": {"type": "string", "description": "The command line that started the run."},
            "created": {"type": "string"},
            "manifest": {
                "type": "object",
                "required": ["path", "sha256"],
                "properties": {"path": {"type": "string"}, "sha256": {"type": "string"}},
            },
            "settings": {"allOf": [{"$ref": "#/$defs/settings"}, {"required": _all_names()}]},
            "derived": _derived_schema(),
        },
        "$defs": {"settings": settings, **option_defs},
    }


def _derived_schema() -> dict[str, Any]:
    """The schema of config.json's ``derived``: what the run computed from the manifest and the settings."""
    return {
        "type": "object",
        "description": "Values computed from the manifest and the settings.",
        "required": [
            "device",
            "backend",
            "scene_scale",
            "normalization",
            "num_train_views",
            "num_test_views",
            "initial_gaussians",
        ],
        "properties": {
            "device": {"type": "string"},
            "backend": {"enum": ["torch", "gsplat"]},
            "scene_scale": {
                "type": "number",
                "description": "camera_extent x margin x global_scale (what the lrs use).",
            },
            "camera_extent": {"type": "number"},
            "normalization": {
                "description": "4x4 world-to-training-world similarity (row-major); the PLY and "
                "checkpoints are in the training world.",
                "type": "array",
                "minItems": 4,
                "maxItems": 4,
                "items": {"type": "array", "minItems": 4, "maxItems": 4, "items": {"type": "number"}},
            },
            "num_train_views": {"type": "integer"},
            "num_test_views": {"type": "integer"},
            "initial_gaussians": {"type": "integer"},
            "world_size": {
                "type": "integer",
                "minimum": 1,
                "description": "Processes that trained the run (torchrun / jsgs train --gpus N), "
                "each holding a shard of the Gaussians and rendering one view per step; 1 when "
                "absent.",
            },
            "exchange": {
                "enum": ["gsplat", "torch"],
                "description": "On several processes, how a view reaches the other shards' "
                "Gaussians (gsplat: rasterization(..., distributed=True), non-packed; torch: the "
                "shards gathered on every process, the gradients reduce-scattered back to their owners).",
            },
            "notes": {"type": "array", "items": {"type": "string"}},
            "ssim_kernel": {
                "enum": ["torch", "cuda"],
                "description": "The SSIM implementation that speed.ssim_kernel resolved to on this "
                "device (cuda: the fused kernel, built before training starts).",
            },
            "budget": {
                "type": "object",
                "description": "strategy.cap_max_auto: the budget chosen from the scene and its "
                "inputs (jsgs.train.budget.AutoBudget).",
                "required": ["cap_max", "sfm_points", "train_views", "train_pixels", "by_points",
                             "by_pixels", "gaussians_per_point", "pixels_per_gaussian", "rule"],
                "properties": {
                    "cap_max": {"type": "integer", "minimum": 1},
                    "sfm_points": {"type": "integer", "minimum": 0},
                    "train_views": {"type": "integer", "minimum": 0},
                    "train_pixels": {"type": "integer", "minimum": 0},
                    "by_points": {"type": "integer", "minimum": 0},
                    "by_pixels": {"type": "integer", "minimum": 0},
                    "gaussians_per_point": {"type": "integer", "minimum": 1},
                    "pixels_per_gaussian": {"type": "integer", "minimum": 1},
                    "rule": {"type": "string"},
                    "max_budget": {
                        "type": "integer", "minimum": 1,
                        "description": "The largest budget the rule gives (absent: written before the rule "
                        "had one).",
                    },
                },
            },
            "method": {
                "type": "object",
                "description": "What the method resolved from its options for this run (JSGS: "
                "color_kernel, cuda_graph, cuda_graph_gc, gc_kernel, gc_route, jo_kernel, jpeg_mode; with "
                "base_by_view, "
                "base_by_view: each JPEG training view's noise_variance and ℓ_ph weight by name).",
            },
        },
    }


def _all_names() -> list[str]:
    return [f.name for f in dataclasses.fields(TrainConfig)]


def main() -> None:  # pragma: no cover - a one-line generator
    print(json.dumps(config_schema(), indent=1))


if __name__ == "__main__":  # pragma: no cover
    main()
