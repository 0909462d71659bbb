"""What a bench consists of: datasets (one ``jstools compress`` output per scene x schedule x seed) and
training runs (one ``jsgs train`` per dataset x method), with their folders and command lines.

Layout under RESULTS::

    data/<scene>/<schedule>_s<seed>/            compress output (images/, reference/, sparse/, manifest.json)
    runs/<scene>/<schedule>/<method>/s<seed>/   jsgs train output (metrics.json, config.json, ...)
    logs/<scene>/<schedule>/<method>/s<seed>.log   the run's stdout + stderr

``schedule`` is uniform / gaussian / descending / clean / fixed<Q>; ``method`` is gsplat / jsgs or an
ablation name (jo, jo_ds, jo_gc). Both methods of one scene x schedule x seed train on the same files.
"""

from __future__ import annotations

import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from jsgs.errors import JsgsError

MIXED_SCHEDULES = ("uniform", "gaussian", "descending")
SCHEDULES = (*MIXED_SCHEDULES, "clean")
METHODS = ("gsplat", "jsgs")
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
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def id(self) -> str:
        return f"{self.scene}/{self.schedule}/{self.method}/s{self.seed}"

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["id"] = self.id
        d.pop("extra")
        return d


@dataclass
class BenchPlan:
    datasets: list[Dataset]
    runs: list[Run]


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


def default_eval_at(iterations: int) -> list[int]:
    """``jsgs train``'s rule: 3000,7000,10000 cut at N, and N."""
    return [s for s in (3000, 7000, 10000) if s < iterations] + [iterations]


def build_plan(
    scenes: list[str | Path],
    out: str | Path,
    schedules: list[str],
    fixed: list[int],
    methods: list[str],
    ablation: str | None,
    seeds: list[int],
    iterations: int,
    eval_at: list[int],
) -> BenchPlan:
    """Every dataset and run of the bench, in the order they are queued (longest-lived first is not
    attempted: runs of one scene and schedule stay together so partial results are usable early)."""
    out = Path(out)
    for s in schedules:
        if s not in SCHEDULES:
            raise JsgsError(f"--schedules: unknown schedule {s!r} (choose from {', '.join(SCHEDULES)})")
    for m in methods:
        if m not in METHODS:
            raise JsgsError(f"--methods: unknown method {m!r} (choose from {', '.join(METHODS)})")
    for q in fixed:
        if not 1 <= q <= 100:
            raise JsgsError(f"--fixed: quality {q} is not in 1..100")
    if not seeds:
        raise JsgsError("--seeds: at least one seed is needed")
    if iterations < 1:
        raise JsgsError(f"--iterations {iterations}: must be at least 1")
    if not eval_at or eval_at[-1] != iterations or sorted(set(eval_at)) != eval_at or eval_at[0] < 1:
        raise JsgsError(
            f"--eval-at {','.join(map(str, eval_at))}: must be increasing steps ending at --iterations "
            f"{iterations}"
        )
    names: dict[str, Path] = {}
    for s in scenes:
        p = Path(s)
        # A GPU machine has no source scenes: datasets prepared beforehand (--prepare-only) stand in for them.
        if not p.is_dir() and not (Path(out) / "data" / p.name).is_dir():
            raise JsgsError(f"{p}: scene folder not found (and no prepared datasets in {out}/data/{p.name})")
        name = p.resolve().name
        if name in names:
            raise JsgsError(f"{p}: two scenes are named {name!r} ({names[name]} and {p})")
        names[name] = p
    if ablation is not None:
        abl_name = Path(ablation).resolve().name if Path(ablation).is_dir() else ablation
        if abl_name not in names:
            raise JsgsError(f"--ablation {ablation}: not one of the scenes ({', '.join(names)})")
        ablation = abl_name

    datasets: dict[str, Dataset] = {}
    runs: list[Run] = []

    def dataset(scene: str, label: str, seed: int) -> Dataset:
        if label.startswith("fixed"):
            sched, q = "fixed", int(label[5:])
        else:
            sched, q = label, None
        d = Dataset(
            scene, str(names[scene]), label, sched, q, seed, str(out / "data" / scene / f"{label}_s{seed}")
        )
        return datasets.setdefault(d.key, d)

    def add(scene: str, label: str, method: str, seed: int) -> None:
        d = dataset(scene, label, seed)
        if method in ABLATIONS:
            train_method, flags = ABLATIONS[method]
        else:
            train_method, flags = method, []
        rel = Path(scene) / label / method / f"s{seed}"
        r = Run(
            scene, label, method, seed, train_method, list(flags), d.key, d.manifest,
            str(out / "runs" / rel), str(out / "logs" / rel.parent / f"s{seed}.log"), iterations,
            list(eval_at),
        )  # fmt: skip
        if r.id not in {x.id for x in runs}:
            runs.append(r)

    for scene in names:
        for label in schedules:
            for seed in seeds:
                for m in methods if label != "clean" else ["gsplat"]:
                    add(scene, label, m, seed)
        for q in fixed:
            for m in methods:
                add(scene, f"fixed{q}", m, seeds[0])
        if scene == ablation:
            for variant in ABLATIONS:
                add(scene, ABLATION_SCHEDULE, ABLATION_ALIAS.get(variant, variant), seeds[0])
    return BenchPlan(list(datasets.values()), runs)


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
    if config is not None:
        argv += ["--config", config]
    return argv + run.flags + ["--force"]
