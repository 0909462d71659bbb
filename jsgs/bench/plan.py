"""What a bench consists of: datasets (one ``jstools compress`` output per scene x schedule x seed) and
training runs (one ``jsgs train`` per dataset x method), with their folders and command lines.

Layout under RESULTS::

    data/<scene>/<schedule>_s<seed>/            compress output (images/, reference/, sparse/, manifest.json)
    runs/<scene>/<schedule>/<method>/s<seed>/   jsgs train output (metrics.json, config.json, ...)
    runs/<scene>/<schedule>/<method>/mcmc-<cap>/s<seed>/   the same under gsplat's MCMCStrategy, cap <cap>
    logs/<scene>/<schedule>/<method>/[mcmc-<cap>/]s<seed>.log   the run's stdout + stderr

``schedule`` is uniform / gaussian / descending / clean / fixed<Q>, or a mixed schedule saved twice,
``<schedule>+r<Q2>`` (every JPEG training view decoded and saved once more at quality Q2, as an app does; its
manifest records the compression analysis); ``method`` is gsplat / jsgs, a JSGS variant (jsgs_eff: the
effective tables of views compressed twice) or an ablation name (jo, jo_ds, jo_gc). Every method of one
scene x schedule x seed trains on the same files.

With ``--strategy mcmc`` every method and the clean ceiling train once per budget (a Gaussian count, a
multiple of the scene's clean DefaultStrategy run's final count: those reference runs train first, or
``auto``: each run sizes it to its scene, in ``runs/.../mcmc-auto/``; without ``--budgets``, the mcmc
preset's own budget, ``auto``).
"""

from __future__ import annotations

import math
import re
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from jsgs.base.errors import JsgsError

MIXED_SCHEDULES = ("uniform", "gaussian", "descending")
SCHEDULES = (*MIXED_SCHEDULES, "clean")
METHODS = ("gsplat", "jsgs", "jsgs_eff")
#: bench methods that are ``jsgs train --method jsgs`` with flags
VARIANTS: dict[str, tuple[str, list[str]]] = {"jsgs_eff": ("jsgs", ["--tables", "effective"])}
#: ``gaussian+r90``: a mixed schedule whose JPEG training views were saved once more at quality 90
_TWICE = re.compile(r"(?P<schedule>" + "|".join(MIXED_SCHEDULES) + r")\+r(?P<q>\d+)")
STRATEGIES = ("default", "mcmc")
#: Table 2 of the paper: variant -> (method, flags). ``baseline`` and ``full`` are the gsplat and jsgs runs
#: of the same scene (gaussian schedule, seed 0) and are not trained twice.
ABLATIONS: dict[str, tuple[str, list[str]]] = {
    "baseline": ("gsplat", []),
    "jo": ("jsgs", ["--no-ds", "--no-gc"]),
    "jo_ds": ("jsgs", ["--no-gc"]),
    "jo_gc": ("jsgs", ["--no-ds"]),
    "full": ("jsgs", []),
}
#: which components each ablation row has (JO, DS, GC)
ABLATION_PARTS: dict[str, tuple[bool, bool, bool]] = {
    "baseline": (False, False, False),
    "jo": (True, False, False),
    "jo_ds": (True, True, False),
    "jo_gc": (True, False, True),
    "full": (True, True, True),
}
ABLATION_SCHEDULE = "gaussian"
#: the run a shared ablation row is read from
ABLATION_ALIAS = {"baseline": "gsplat", "full": "jsgs"}


@dataclass
class Dataset:
    scene: str  # scene name (folder name)
    source: str  # clean scene folder
    schedule: str  # label: uniform / gaussian / descending / clean / fixed30 ...
    compress_schedule: str  # jsgstools schedule name
    quality: int | None
    seed: int
    out: str  # RESULTS/data/<scene>/<schedule>_s<seed>
    recompress: int | None = None  # <schedule>+r<Q2>: saved once more at Q2 (and analysed)

    @property
    def key(self) -> str:
        return f"{self.scene}/{self.schedule}_s{self.seed}"

    @property
    def manifest(self) -> str:
        return str(Path(self.out) / "manifest.json")


@dataclass
class Run:
    scene: str
    schedule: str
    method: str  # gsplat / jsgs / jo / jo_ds / jo_gc
    seed: int
    train_method: str  # what --method gets
    flags: list[str]
    data: str  # dataset key
    manifest: str
    out: str
    log: str
    iterations: int
    eval_at: list[int]
    strategy: str = "default"  # default / mcmc
    budget: str | None = None  # mcmc: the budget as given (300000, 0.5x)
    cap: int | None = None  # mcmc: strategy.cap_max (None until a multiple is resolved)
    config: str | None = None  # its own --config (the bench's --config with --jsgs-config over it)
    # --gsplat-steps: the recipe's length when the run trains past it (its schedules laid out over this many
    # steps, optim.means_lr_decay_steps); None: iterations
    schedule_steps: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def auto(self) -> bool:
        """mcmc with the budget chosen from the scene by the run itself (``--cap-max auto``)."""
        return self.strategy == "mcmc" and self.budget == AUTO

    @property
    def unresolved(self) -> bool:
        """mcmc with a budget given as a multiple whose cap is not known yet."""
        return self.strategy == "mcmc" and self.cap is None and not self.auto

    @property
    def folder(self) -> str:
        """``<scene>/<schedule>/<method>[/mcmc-<cap>]``: where its seeds live under runs/ and logs/."""
        base = f"{self.scene}/{self.schedule}/{self.method}"
        if self.strategy == "default":
            return base
        return f"{base}/mcmc-{self.cap if self.cap is not None else self.budget}"

    @property
    def id(self) -> str:
        return f"{self.folder}/s{self.seed}"

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["id"] = self.id
        d.pop("extra")
        return d


@dataclass
class BenchPlan:
    datasets: list[Dataset]
    runs: list[Run]

    def references(self) -> list[Run]:
        """The clean DefaultStrategy runs that budgets given as multiples are resolved from."""
        if not any(r.unresolved for r in self.runs):
            return []
        return [r for r in self.runs if r.strategy == "default" and r.schedule == "clean"]


@dataclass(frozen=True)
class Budget:
    """A Gaussian budget: a count (``300k`` -> 300000), a multiple of the scene's clean DefaultStrategy
    run's final count (``0.5x``), or ``auto``: each run chooses it from its scene (``jsgs train --cap-max
    auto``; results.csv's budget column reads ``auto``)."""

    label: str
    count: int | None = None
    multiple: float | None = None

    @property
    def auto(self) -> bool:
        return self.label == AUTO

    def cap(self, reference_count: float | None) -> int:
        """The cap for a scene whose clean DefaultStrategy run ended with ``reference_count`` Gaussians."""
        if self.count is not None:
            return self.count
        assert self.multiple is not None and reference_count is not None
        return max(1, round(self.multiple * reference_count))


_SUFFIX = {"": 1, "k": 1_000, "m": 1_000_000}
#: the scene-sized budget (jsgs.train.budget)
AUTO = "auto"


def preset_budget() -> Budget:
    """The mcmc preset's budget as a bench budget: ``auto`` (sized to each scene) or its fixed count."""
    from jsgs.train.config import TrainConfig

    strategy = TrainConfig.from_preset("mcmc").strategy
    return Budget(AUTO) if strategy.cap_max_auto else Budget(str(strategy.cap_max), count=strategy.cap_max)


def parse_budgets(text: str | None) -> list[Budget]:
    """``"300k,0.5x,1x,250000,auto"`` -> budgets (JsgsError, one line, on anything else)."""
    out: list[Budget] = []
    for part in parse_list(text, "--budgets"):
        p = part.lower()
        m = re.fullmatch(r"(\d+(?:\.\d+)?)([km]?)", p)
        x = re.fullmatch(r"(\d+(?:\.\d+)?)x", p)
        if p == AUTO:
            b = Budget(AUTO)
        elif m:
            n = float(m.group(1)) * _SUFFIX[m.group(2)]
            if n < 1 or n != math.floor(n):
                raise JsgsError(f"--budgets: {part!r} is not a whole number of Gaussians (at least 1)")
            b = Budget(part, count=int(n))
        elif x and float(x.group(1)) > 0:
            b = Budget(part, multiple=float(x.group(1)))
        else:
            raise JsgsError(
                f"--budgets: {part!r} is neither a count (300000, 300k, 1.5m), a positive multiple of the "
                "clean DefaultStrategy count (0.5x) nor auto"
            )
        if b in out:
            raise JsgsError(f"--budgets: {part!r} is given twice")
        out.append(b)
    return out


def parse_list(text: str | None, what: str, kind: type = str) -> list[Any]:
    """``"a,b"`` -> ``["a", "b"]`` (``kind`` int: ints). Empty or None: []."""
    if text is None:
        return []
    out: list[Any] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        try:
            out.append(kind(part))
        except ValueError:
            raise JsgsError(f"{what}: {part!r} is not {'an integer' if kind is int else 'valid'}") from None
    return out


#: the spacing of the bench's default evaluations past step 10,000
EVAL_SPACING = 5_000


def default_eval_at(iterations: int) -> list[int]:
    """The bench's evaluation steps: 3000,7000,10000 cut at N, then every :data:`EVAL_SPACING` steps, and N
    (30,000 steps: 3000, 7000, 10000, 15000, 20000, 25000, 30000; enough points to read quality against
    training time)."""
    return (
        [s for s in (3000, 7000) if s < iterations]
        + list(range(10_000, iterations, EVAL_SPACING))
        + [iterations]
    )


def longer_run(eval_at: list[int], iterations: int, factor: float) -> tuple[int, list[int]]:
    """A run ``factor`` times as long as ``iterations`` steps (rounded up), and its evaluation steps:
    ``eval_at``, then on at the spacing of its last two steps (``iterations`` when it has only one), and the
    end."""
    total = math.ceil(factor * iterations)
    if total <= iterations:
        return iterations, list(eval_at)
    gap = eval_at[-1] - eval_at[-2] if len(eval_at) > 1 else iterations
    extra = list(range(iterations + gap, total, gap))
    return total, [*eval_at, *extra, total]


@dataclass(frozen=True)
class BenchSettings:
    """Everything a bench runs with, as ``jsgs bench`` gives it (built once by the command line, or by a
    library caller) and read by :func:`jsgs.bench.harness.bench` and :func:`build_plan`. Sequences are kept
    as tuples (lists given are converted). ``iterations``, ``eval_at``, ``device`` and ``lpips_weights``
    left None are filled by the harness: the strategy's preset length (mcmc: 30,000 steps; default: the
    paper's 10,000, :meth:`with_run_length`), :func:`default_eval_at`, the device there is, the weights
    found (``$JSGS_LPIPS_WEIGHTS``, else ``../shared/lpips``); mcmc without ``budgets``: the mcmc preset's
    budget, ``auto`` (:meth:`with_run_length`).

    ``time_limit`` (seconds from the call): no run starts after it (nor one that runs like it took longer
    than what is left) and runs still going are stopped (they resume on a rerun). ``compile_backend``:
    ``--compile`` of the JSGS runs. ``report_only``: train nothing, only collect the runs already in ``out``
    (copied back from GPU machines, say) into results.csv and report.md; runs without results are listed as
    not run. ``prepare_only``: build the datasets and stop. ``strategy`` mcmc: every run once per budget of
    ``budgets`` (budgets given as multiples are resolved from the clean DefaultStrategy runs, trained
    first). ``jsgs_config``: settings over ``config`` for the JSGS runs only. ``gsplat_steps``: the gsplat
    runs on JPEG datasets train that many times longer, evaluated past ``iterations`` (:func:`build_plan`),
    for the report's equal-time table. ``command``: the command line, recorded in bench.json and the
    report."""

    scenes: tuple[str | Path, ...]
    out: Path
    schedules: tuple[str, ...]
    fixed: tuple[int, ...]
    methods: tuple[str, ...]
    seeds: tuple[int, ...]
    ablation: str | None = None
    iterations: int | None = None
    eval_at: tuple[int, ...] | None = None
    strategy: str = "default"
    budgets: tuple[Budget, ...] = ()
    gsplat_steps: float = 1.0
    jobs_per_gpu: int = 1
    device: str | None = None
    config: str | Path | None = None
    jsgs_config: str | Path | None = None
    lpips_weights: str | None = None
    time_limit: float | None = None
    compile_backend: str = "off"
    prepare_only: bool = False
    report_only: bool = False
    progress: bool = True
    command: str | None = None

    def __post_init__(self) -> None:
        for name in ("scenes", "schedules", "fixed", "methods", "seeds", "budgets"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if self.eval_at is not None:
            object.__setattr__(self, "eval_at", tuple(self.eval_at))
        object.__setattr__(self, "out", Path(self.out))

    def with_run_length(self) -> BenchSettings:
        """These settings with ``iterations`` (the strategy's preset length) and ``eval_at``
        (:func:`default_eval_at`) filled in where they are None, and, with mcmc, ``budgets`` where none are
        given: the mcmc preset's, the budget sized to the scene (``auto``)."""
        iterations = self.iterations
        if iterations is None:
            from jsgs.train.config import preset_iterations

            iterations = preset_iterations("mcmc" if self.strategy == "mcmc" else "paper")
        budgets = self.budgets or ((preset_budget(),) if self.strategy == "mcmc" else ())
        return replace(
            self, iterations=iterations, eval_at=self.eval_at or default_eval_at(iterations), budgets=budgets
        )


def build_plan(settings: BenchSettings) -> BenchPlan:
    """Every dataset and run of the bench, in the order they are queued (longest-lived first is not
    attempted: runs of one scene and schedule stay together so partial results are usable early). Under
    ``strategy`` mcmc, one run per budget; a budget given as a multiple leaves its runs' ``cap`` None (see
    :func:`resolve_caps`) and adds the clean DefaultStrategy gsplat run of each scene and seed.
    ``gsplat_steps`` > 1: the gsplat runs on JPEG datasets train that many times ``iterations`` steps, their
    recipe laid out over ``iterations`` (``schedule_steps``; their evaluations up to it are those of a run
    of that length) and evaluated on past it (:func:`longer_run`), so that quality against training time
    can be read at JSGS's end without extrapolating."""
    s = settings.with_run_length()
    _check_plan_settings(s)
    names = _scene_folders(s.scenes, s.out)
    ablation = _ablation_scene(s.ablation, names)
    planner = _Planner(s, names)
    multiples = any(b.multiple is not None for b in s.budgets)
    for scene in names:
        if multiples:  # the reference counts come first
            for seed in s.seeds:
                planner.add(scene, "clean", "gsplat", seed)
        for label in s.schedules:
            for seed in s.seeds:
                for m in s.methods if label != "clean" else ["gsplat"]:
                    if s.strategy == "default":
                        planner.add(scene, label, m, seed)
                    for b in s.budgets:
                        planner.add(scene, label, m, seed, b)
        for q in s.fixed:
            for m in s.methods:
                planner.add(scene, f"fixed{q}", m, s.seeds[0])
        if scene == ablation:
            for variant in ABLATIONS:
                planner.add(scene, ABLATION_SCHEDULE, ABLATION_ALIAS.get(variant, variant), s.seeds[0])
    return BenchPlan(list(planner.datasets.values()), planner.runs)


def _check_plan_settings(s: BenchSettings) -> None:
    """JsgsError (one line) for a strategy, budget, schedule, method, quality, seed, length or evaluation
    step the plan cannot be made of."""
    if s.strategy not in STRATEGIES:
        raise JsgsError(f"--strategy: unknown strategy {s.strategy!r} (choose from {', '.join(STRATEGIES)})")
    if s.strategy == "default" and s.budgets:
        raise JsgsError("--budgets needs --strategy mcmc (DefaultStrategy has no Gaussian cap)")
    if s.strategy == "mcmc" and (s.fixed or s.ablation is not None):
        raise JsgsError("--fixed and --ablation are paper-protocol tables: they run with --strategy default")
    for sched in s.schedules:
        _check_schedule(sched)
    for m in s.methods:
        if m not in METHODS:
            raise JsgsError(f"--methods: unknown method {m!r} (choose from {', '.join(METHODS)})")
    for q in s.fixed:
        if not 1 <= q <= 100:
            raise JsgsError(f"--fixed: quality {q} is not in 1..100")
    if not s.seeds:
        raise JsgsError("--seeds: at least one seed is needed")
    if not (math.isfinite(s.gsplat_steps) and s.gsplat_steps >= 1.0):
        raise JsgsError(f"--gsplat-steps {s.gsplat_steps:g}: must be a factor of at least 1")
    _check_run_length(s.iterations, list(s.eval_at or []))


def _check_schedule(s: str) -> None:
    twice = _TWICE.fullmatch(s)
    if s not in SCHEDULES and not twice:
        raise JsgsError(
            f"--schedules: unknown schedule {s!r} (choose from {', '.join(SCHEDULES)}, or a mixed one "
            "saved twice such as gaussian+r90)"
        )
    if twice and not 1 <= int(twice["q"]) <= 100:
        raise JsgsError(f"--schedules: {s!r}: the second quality must be in 1..100")


def _check_run_length(iterations: int | None, eval_at: list[int]) -> None:
    assert iterations is not None  # BenchSettings.with_run_length
    if iterations < 1:
        raise JsgsError(f"--iterations {iterations}: must be at least 1")
    if not eval_at or eval_at[-1] != iterations or sorted(set(eval_at)) != eval_at or eval_at[0] < 1:
        raise JsgsError(
            f"--eval-at {','.join(map(str, eval_at))}: must be increasing steps ending at --iterations "
            f"{iterations}"
        )


def _scene_folders(scenes: tuple[str | Path, ...], out: Path) -> dict[str, Path]:
    """scene name -> its folder as given; JsgsError for one not found (without prepared datasets standing in
    for it) or two of one name."""
    names: dict[str, Path] = {}
    for s in scenes:
        p = Path(s)
        # A GPU machine has no source scenes: datasets prepared beforehand (--prepare-only) stand in for them.
        if not p.is_dir() and not (out / "data" / p.name).is_dir():
            raise JsgsError(f"{p}: scene folder not found (and no prepared datasets in {out}/data/{p.name})")
        name = p.resolve().name
        if name in names:
            raise JsgsError(f"{p}: two scenes are named {name!r} ({names[name]} and {p})")
        names[name] = p
    return names


def _ablation_scene(ablation: str | None, names: dict[str, Path]) -> str | None:
    """The name of the ablation's scene, given as a name or a path (JsgsError: not one of the scenes)."""
    if ablation is None:
        return None
    abl_name = Path(ablation).resolve().name if Path(ablation).is_dir() else ablation
    if abl_name not in names:
        raise JsgsError(f"--ablation {ablation}: not one of the scenes ({', '.join(names)})")
    return abl_name


class _Planner:
    """The datasets and runs of a plan as :func:`build_plan` adds them (each dataset once, each run once)."""

    def __init__(self, settings: BenchSettings, names: dict[str, Path]) -> None:
        assert settings.iterations is not None and settings.eval_at is not None
        self.s = settings
        self.iterations: int = settings.iterations
        self.eval_at: list[int] = list(settings.eval_at)
        self.names = names
        self.datasets: dict[str, Dataset] = {}
        self.runs: list[Run] = []

    def dataset(self, scene: str, label: str, seed: int) -> Dataset:
        """The dataset of ``scene`` under schedule ``label`` and ``seed`` (made once)."""
        again = None
        if label.startswith("fixed"):
            sched, q = "fixed", int(label[5:])
        elif m := _TWICE.fullmatch(label):
            sched, q, again = m["schedule"], None, int(m["q"])
        else:
            sched, q = label, None
        d = Dataset(
            scene, str(self.names[scene]), label, sched, q, seed,
            str(self.s.out / "data" / scene / f"{label}_s{seed}"), recompress=again,
        )  # fmt: skip
        return self.datasets.setdefault(d.key, d)

    def add(self, scene: str, label: str, method: str, seed: int, budget: Budget | None = None) -> None:
        """Queue ``method``'s run on the dataset (unless it is queued already)."""
        d = self.dataset(scene, label, seed)
        if method in ABLATIONS:
            train_method, flags = ABLATIONS[method]
        elif method in VARIANTS:
            train_method, flags = VARIANTS[method]
        else:
            train_method, flags = method, []
        steps, evals, recipe = self.iterations, list(self.eval_at), None
        if method == "gsplat" and label != "clean" and self.s.gsplat_steps > 1.0:
            steps, evals = longer_run(self.eval_at, self.iterations, self.s.gsplat_steps)
            recipe = self.iterations if steps > self.iterations else None
        r = Run(
            scene, label, method, seed, train_method, list(flags), d.key, d.manifest, "", "", steps, evals,
            strategy="default" if budget is None else "mcmc", budget=None if budget is None else budget.label,
            cap=None if budget is None else budget.count, schedule_steps=recipe,
        )  # fmt: skip
        if not r.unresolved:
            set_paths(r, self.s.out)
        if r.id not in {x.id for x in self.runs}:
            self.runs.append(r)


def set_paths(run: Run, out: str | Path) -> None:
    """The run's output folder and log under the results folder ``out`` (its cap must be known)."""
    run.out = str(Path(out) / "runs" / run.folder / f"s{run.seed}")
    run.log = str(Path(out) / "logs" / run.folder / f"s{run.seed}.log")


def resolve_caps(plan: BenchPlan, out: str | Path, counts: dict[str, float | None]) -> list[Run]:
    """Give the runs of budgets given as multiples their cap from ``counts`` (scene -> mean final
    #Gaussians of its clean DefaultStrategy runs; None where they failed) and their folders; returns the
    runs left without a cap (their scene has no count)."""
    budgets: dict[str, Budget] = {}
    missing = []
    for r in plan.runs:
        if not r.unresolved or r.budget is None:
            continue
        b = budgets.setdefault(r.budget, parse_budgets(r.budget)[0])
        count = counts.get(r.scene)
        if count is None:
            missing.append(r)
            continue
        r.cap = b.cap(count)
        set_paths(r, out)
    return missing


def train_argv(run: Run, device: str, config: str | None, resume: bool) -> list[str]:
    """The ``jsgs train`` subprocess for ``run`` (``--resume`` continues a stopped run, else ``--force``)."""
    head = [sys.executable, "-c", "from jsgs.cli import main; main(prog_name='jsgs')", "train"]
    if resume:  # the run's own settings (config.json); flags that would change them are refused
        return head + [run.manifest, "--out", run.out, "--resume", "--quiet"]
    argv = head + [
        run.manifest, "--out", run.out, "--method", run.train_method,
        "--iterations", str(run.iterations), "--eval-at", ",".join(map(str, run.eval_at)),
        "--seed", str(run.seed), "--device", device, "--quiet",
    ]  # fmt: skip
    if run.strategy == "mcmc":
        argv += ["--preset", "mcmc", "--cap-max", AUTO if run.auto else str(run.cap)]
    else:
        argv += ["--preset", "paper"]
    config = run.config if run.config is not None else config
    if config is not None:
        argv += ["--config", config]
    return argv + run.flags + ["--force"]
