""":func:`bench`: plan -> datasets (``jsgstools.compress``, or ``jsgstools.derive`` from a clean base) ->
worker pool (``jsgs train`` subprocesses) -> ``results.csv`` -> ``report.md`` + plots, recording everything in
``RESULTS/bench.json`` (``jsgs/schemas/bench.schema.json``)."""

from __future__ import annotations

import datetime as _dt
import functools
import json
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

from jsgs.base.errors import JsgsError
from jsgs.base.io import write_json_atomic
from jsgs.bench import markdown as report_mod
from jsgs.bench import results as results_mod
from jsgs.bench import workers as pool_mod
from jsgs.bench.plan import BenchPlan, Budget, Dataset, Run, build_plan, resolve_caps, train_argv

BENCH_FORMAT = "jsgs-bench"
BENCH_VERSION = 1
REPO = Path(__file__).resolve().parents[2]


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _cmd(args: list[str]) -> str | None:
    try:
        r = subprocess.run(args, capture_output=True, text=True, timeout=30, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def environment(device: str) -> dict[str, Any]:
    """Software and hardware versions (GPU names from nvidia-smi, so the parent holds no CUDA context)."""
    import torch

    import jsgs

    try:
        import gsplat

        gv: str | None = gsplat.__version__
    except Exception:
        gv = None
    gpus = []
    smi = _cmd(["nvidia-smi", "--query-gpu=name,memory.total,driver_version", "--format=csv,noheader"])
    for line in (smi or "").splitlines():
        parts = [p.strip() for p in line.split(",")]
        if len(parts) == 3:
            gpus.append({"name": parts[0], "memory": parts[1], "driver": parts[2]})
    commit = _cmd(["git", "-C", str(REPO), "rev-parse", "HEAD"])
    dirty = _cmd(["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=no"])
    return {
        "jsgs": jsgs.__version__,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_cuda": torch.version.cuda,
        "gsplat": gv,
        "platform": platform.platform(),
        "cpu_count": os.cpu_count() or 1,
        "device": device,
        "gpus": gpus,
        "git_commit": commit,
        "git_dirty": None if dirty is None else bool(dirty),
    }


def _dataset_ready(d: Dataset) -> bool:
    """The dataset's manifest exists and was made with ``d``'s settings (read from ``compress.json``, or from
    the manifest's ``scene`` for a dataset made by :func:`jsgstools.derive.derive`)."""
    try:
        manifest = json.loads((Path(d.out) / "manifest.json").read_text())
        if (Path(d.out) / "compress.json").is_file():
            s = json.loads((Path(d.out) / "compress.json").read_text()).get("settings", {})
        else:
            s = manifest.get("scene", {})
        made = manifest["producer"].get("settings", {})
    except (OSError, ValueError, AttributeError, KeyError, TypeError):
        return False
    return (
        s.get("schedule") == d.compress_schedule
        and s.get("seed") == d.seed
        and s.get("quality") == d.quality
        and made.get("recompress") == d.recompress
    )


def clean_base(d: Dataset) -> Path:
    """The scene's clean dataset ``RESULTS/data/<scene>/clean_s0/manifest.json``, the base that
    :func:`jsgstools.derive.derive` makes the other datasets from where the source scene is absent."""
    return Path(d.out).parent / "clean_s0" / "manifest.json"


def prepare_datasets(plan: BenchPlan, progress: bool = True) -> dict[str, dict[str, Any]]:
    """Build every dataset not already there; ``{key: {"status": ..., "error"?: ...}}``.

    With the source scene present: ``jsgstools.compress`` (pycolmap, OpenCV). Without it (a GPU machine) but
    with the scene's clean base ``data/<scene>/clean_s0/`` (its manifest.json, compress.json and reference/
    PNGs): ``jsgstools.derive`` (Pillow only), same files bit for bit. A carried clean base without its
    ``images/`` gets them back as copies of its references."""
    out: dict[str, dict[str, Any]] = {}
    for d in plan.datasets:
        base = clean_base(d)
        derived = not Path(d.source).is_dir() and base.is_file()
        try:
            if _dataset_ready(d):
                if d.compress_schedule == "clean" and Path(d.out) == base.parent and derived:
                    from jsgstools.derive import restore_clean_images

                    n = restore_clean_images(d.out)
                    if n and progress:
                        print(f"restored {n} lossless images of {d.out} from reference/", file=sys.stderr)
                out[d.key] = {"status": "skipped"}
                continue
            if derived:
                from jsgstools.derive import derive

                if progress:
                    print(f"derive: {base.parent} -> {d.out} ({d.schedule}, seed {d.seed})", file=sys.stderr)
                derive(base, d.out, d.compress_schedule, quality=d.quality, seed=d.seed, force=True,
                       recompress=d.recompress, analyze=d.recompress is not None)  # fmt: skip
            else:
                # imported only when needed: a GPU machine (no pycolmap/OpenCV) runs on prepared datasets
                from jsgstools.compress import compress

                if progress:
                    print(f"compress: {d.source} -> {d.out} ({d.schedule}, seed {d.seed})", file=sys.stderr)
                compress(d.source, d.out, d.compress_schedule, quality=d.quality, seed=d.seed, force=True,
                         recompress=d.recompress, analyze=d.recompress is not None)  # fmt: skip
            out[d.key] = {"status": "complete"}
        except Exception as e:  # noqa: BLE001 - reported per dataset; its runs fail, the others go on
            out[d.key] = {"status": "failed", "error": str(e)}
            print(f"failed: {'derive' if derived else 'compress'} {d.key}: {e}", file=sys.stderr)
    return out


def _default_lpips_weights() -> str | None:
    from jsgs.metrics.lpips import ENV_VAR

    if os.environ.get(ENV_VAR):
        return os.environ[ENV_VAR]
    p = REPO.parent / "shared" / "lpips" / "alexnet_features.pth"
    return str(p) if p.is_file() else None


def _read_config(path: str | Path | None) -> Any:
    if path is None:
        return None
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise JsgsError(f"{path}: cannot read the config: {e}") from None


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``over`` merged into ``base`` section by section (a nested dict merges; anything else replaces)."""
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _run_record(r: Run, device: str, config: str | None) -> dict[str, Any]:
    """A run's bench.json entry before it runs (no command while its budget is unresolved)."""
    return {
        **r.to_json(),
        "command": None if r.unresolved else " ".join(train_argv(r, device, config, False)),
        "status": "pending",
    }


def reference_counts(refs: list[Run]) -> dict[str, float | None]:
    """scene -> the mean final #Gaussians of its complete clean DefaultStrategy runs (None: none complete)."""
    counts: dict[str, list[int]] = {r.scene: [] for r in refs}
    for r in refs:
        state, m = pool_mod.run_state(r)
        if state == "complete" and m is not None:
            counts[r.scene].append(int(m["evals"][-1]["num_gaussians"]))
    return {sc: (sum(v) / len(v) if v else None) for sc, v in counts.items()}


def _resolve(
    plan: BenchPlan, out: Path, refs: list[Run], records: dict[str, dict[str, Any]]
) -> dict[str, dict[str, Any]]:
    """Resolve the budgets given as multiples; returns failure records for the runs that cannot be."""
    failed = {}
    why = [x.get("error") for x in records.values() if x.get("status") == "failed"]
    for r in resolve_caps(plan, out, reference_counts(refs)):
        failed[r.id] = {"id": r.id, "status": "failed", "stderr_tail": "",
                        "error": f"not run: no complete clean DefaultStrategy run of {r.scene} to take "
                        f"{r.budget} of" + (f" ({why[0]})" if why else "")}  # fmt: skip
    return failed


def write_bench_json(doc: dict[str, Any], path: Path) -> None:
    from jsgs.schemas import validate

    validate(doc, "bench", str(path))
    write_json_atomic(path, doc)


def _bench(
    scenes: list[str | Path],
    out: str | Path,
    schedules: list[str],
    fixed: list[int],
    methods: list[str],
    ablation: str | None,
    seeds: list[int],
    iterations: int | None = None,
    eval_at: list[int] | None = None,
    jobs_per_gpu: int = 1,
    device: str | None = None,
    config: str | Path | None = None,
    lpips_weights: str | None = None,
    progress: bool = True,
    command: str | None = None,
    time_limit: float | None = None,
    prepare_only: bool = False,
    compile_backend: str = "off",
    report_only: bool = False,
    strategy: str = "default",
    budgets: list[Budget] | None = None,
    jsgs_config: str | Path | None = None,
    gsplat_steps: float = 1.0,
) -> dict[str, Any]:
    """Run the whole bench into ``out``; returns the final bench.json document. ``time_limit`` (seconds
    from the call): no run starts after it (nor one that runs like it took longer than what is left) and runs
    still going are stopped (they resume on a rerun). ``compile_backend``: ``--compile`` of the JSGS runs.
    ``report_only``: train nothing, only collect the runs already in ``out`` (copied back from GPU machines,
    say) into results.csv and report.md; runs without results are listed as not run. ``strategy`` mcmc:
    every run once per budget of ``budgets`` (budgets given as multiples are resolved from the clean
    DefaultStrategy runs, trained first). ``jsgs_config``: settings over ``config`` for the JSGS runs only.
    ``iterations`` None: the length of the strategy's preset (mcmc: 30,000 steps; default: the paper's
    10,000).
    ``gsplat_steps``: the gsplat runs on JPEG datasets train that many times longer, evaluated past
    ``iterations`` (:func:`jsgs.bench.plan.build_plan`), for the report's equal-time table."""
    import time

    deadline = None if time_limit is None else time.time() + time_limit
    from jsgs.bench.plan import default_eval_at

    out = Path(out)
    if time_limit is not None and time_limit <= 0:
        raise JsgsError(f"--time-limit {time_limit:g}: must be a positive number of seconds")
    if jobs_per_gpu < 1:
        raise JsgsError(f"--jobs-per-gpu {jobs_per_gpu}: must be at least 1")
    from jsgs.method.options import COMPILE_BACKENDS

    if compile_backend not in COMPILE_BACKENDS:
        raise JsgsError(f"--compile {compile_backend!r}: choose one of {', '.join(COMPILE_BACKENDS)}")
    if report_only and prepare_only:
        raise JsgsError("--report-only and --prepare-only exclude each other")
    if report_only:
        device = "cpu" if device in (None, "auto") else device
    elif device in (None, "auto"):
        import torch

        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not report_only:
        import torch

        if not torch.cuda.is_available():
            raise JsgsError("--device cuda: no CUDA device is available")
    if iterations is None:
        from jsgs.train.config import preset_iterations

        iterations = preset_iterations("mcmc" if strategy == "mcmc" else "paper")
    eval_at = eval_at or default_eval_at(iterations)
    config_path = str(Path(config).resolve()) if config is not None else None
    config_doc = _read_config(config)
    jsgs_doc = _read_config(jsgs_config)
    plan = build_plan(
        scenes, out, schedules, fixed, methods, ablation, seeds, iterations, eval_at, strategy, budgets,
        gsplat_steps,
    )  # fmt: skip
    if compile_backend != "off":
        for r in plan.runs:
            if r.train_method == "jsgs":
                r.flags = [*r.flags, "--compile", compile_backend]
    out.mkdir(parents=True, exist_ok=True)
    if jsgs_doc is not None:
        merged = out / "configs" / "jsgs.json"
        merged.parent.mkdir(exist_ok=True)
        write_json_atomic(merged, _merge(config_doc or {}, jsgs_doc))
        for r in plan.runs:
            if r.train_method == "jsgs":
                r.config = str(merged.resolve())
    longer = {r.schedule_steps for r in plan.runs if r.schedule_steps is not None}
    for n in longer:  # gsplat past the recipe's length: its schedules laid out over the recipe's steps
        path = out / "configs" / f"gsplat_recipe{n}.json"
        path.parent.mkdir(exist_ok=True)
        write_json_atomic(path, _merge(config_doc or {}, {"optim": {"means_lr_decay_steps": n}}))
        for r in plan.runs:
            if r.schedule_steps == n:
                r.config = str(path.resolve())
    lpips_weights = lpips_weights or _default_lpips_weights()
    env_extra = {"JSGS_LPIPS_WEIGHTS": str(Path(lpips_weights).resolve())} if lpips_weights else {}
    # every training records how many shared its device (metrics.json runs_per_device)
    from jsgs.train.trainer import RUNS_PER_DEVICE_ENV

    env_extra[RUNS_PER_DEVICE_ENV] = str(jobs_per_gpu)
    slots = [None] if report_only else pool_mod.detect_slots(device, jobs_per_gpu)
    if not slots:
        raise JsgsError("--device cuda: torch.cuda.device_count() found no GPU")
    doc: dict[str, Any] = {
        "format": BENCH_FORMAT,
        "format_version": BENCH_VERSION,
        "status": "running",
        "started": _now(),
        "finished": None,
        "command": command,
        "settings": {
            "scenes": [str(s) for s in scenes],
            "schedules": schedules,
            "fixed": fixed,
            "methods": methods,
            "ablation": ablation,
            "seeds": seeds,
            "iterations": iterations,
            "eval_at": eval_at,
            "jobs_per_gpu": jobs_per_gpu,
            "device": device,
            "workers": len(slots),
            "compile": compile_backend,
            "report_only": report_only,
            "config": config_path,
            "config_content": config_doc,
            "jsgs_config": None if jsgs_config is None else str(Path(jsgs_config).resolve()),
            "jsgs_config_content": jsgs_doc,
            "strategy": strategy,
            "budgets": [b.label for b in budgets or []],
            "gsplat_steps": gsplat_steps,
            "lpips_weights": lpips_weights,
        },  # fmt: skip
        "environment": environment(device),
        "datasets": [
            {
                "key": d.key,
                "scene": d.scene,
                "source": d.source,
                "schedule": d.schedule,
                "compress_schedule": d.compress_schedule,
                "quality": d.quality,
                "recompress": d.recompress,
                "seed": d.seed,
                "out": d.out,
                "status": "pending",
            }
            for d in plan.datasets
        ],  # fmt: skip
        "runs": [_run_record(r, device, config_path) for r in plan.runs],
        "summary": None,
    }
    bench_json = out / "bench.json"
    write_bench_json(doc, bench_json)

    if report_only:
        ds_status = {d.key: {"status": "skipped"} for d in plan.datasets}
    else:
        ds_status = prepare_datasets(plan, progress)
    for d in doc["datasets"]:
        d.update(ds_status[d["key"]])
    if prepare_only:
        # The CPU half of a GPU session: compress here (pycolmap, OpenCV, ../shared), carry RESULTS/data.
        doc["status"] = "prepared"
        doc["finished"] = _now()
        write_bench_json(doc, bench_json)
        return doc
    bad = {k for k, v in ds_status.items() if v["status"] == "failed"}
    runnable = [r for r in plan.runs if r.data not in bad]
    if report_only:
        _resolve(plan, out, plan.references(), {})
        doc["runs"] = [_run_record(r, device, config_path) for r in plan.runs]
        records = {
            r.id: pool_mod.skipped_record(r)
            or {"id": r.id, "status": "failed", "stderr_tail": "",
                "error": f"not run: no complete metrics.json at step {r.iterations} in {r.out}"}
            for r in runnable
        }  # fmt: skip
    else:
        records = {}
        refs = [r for r in plan.references() if r in runnable]
        if refs:  # budgets given as multiples of these runs' counts: train them first
            records = pool_mod.run_pool(
                refs, slots, device, config_path, env_extra, progress=progress, deadline=deadline
            )
        left = _resolve(plan, out, refs, records)
        records.update(left)
        rest = [r for r in runnable if r.id not in records]
        records.update(
            pool_mod.run_pool(
                rest, slots, device, config_path, env_extra, progress=progress, deadline=deadline
            )
        )
        doc["runs"] = [_run_record(r, device, config_path) for r in plan.runs]
    for r in plan.runs:
        if r.data in bad:
            records[r.id] = {"id": r.id, "status": "failed", "error": f"dataset {r.data} could not be built: "
                             f"{ds_status[r.data].get('error')}", "stderr_tail": ""}  # fmt: skip
    for rj in doc["runs"]:
        if rj["id"] not in records:  # a budget without its reference count
            records[rj["id"]] = {"id": rj["id"], "status": "failed", "stderr_tail": "",
                                 "error": "not run: its budget's reference count is missing"}  # fmt: skip
        rec = dict(records[rj["id"]])
        rec.pop("id", None)
        rj.update(rec)

    rows = results_mod.collect(plan.runs)
    shared = sorted({int(r["runs_per_device"]) for r in rows if r.get("runs_per_device") is not None})
    header = results_mod.write_csv(rows, out / "results.csv")
    failures = [records[r.id] | {"id": r.id} for r in plan.runs if records[r.id]["status"] == "failed"]
    counts = {
        s: sum(1 for r in records.values() if r["status"] == s) for s in ("complete", "skipped", "failed")
    }
    env = doc["environment"]
    gpu_txt = ", ".join(g["name"] for g in env["gpus"]) or "none"
    if report_only:  # this machine only collected: the devices are those the runs themselves recorded
        devices = sorted({str(r.get("device_name")) for r in rows if r.get("device_name")}) or ["unknown"]
        where = f"collected (--report-only) from runs trained elsewhere, on: {', '.join(devices)}"
    else:
        where = f"device {device}, GPUs: {gpu_txt}"
    sharing = (
        "unstated"
        if not shared
        else "; ".join("one run per device" if n == 1 else f"{n} runs per device" for n in shared)
    )
    head = [
        f"Generated {_now()} by jsgs {env['jsgs']} (git {env['git_commit'] or 'unknown'}"
        f"{', uncommitted changes' if env['git_dirty'] else ''}); torch {env['torch']}, "
        f"gsplat {env['gsplat']}, python {env['python']}; {where}.",
        "",
        f"Command: `{command}`" if command else "Command: (library call)",
        "",
        f"{iterations} iterations, evaluations at {','.join(map(str, eval_at))}; seeds {seeds}; "
        f"{len(slots)} concurrent workers ({jobs_per_gpu} per GPU on cuda); device sharing of the runs "
        f"reported (their metrics.json): {sharing}."
        + (f" gsplat's runs on JPEG views train {gsplat_steps:g}x as long (evaluated past {iterations})."
           if gsplat_steps > 1 else "")
        + f" Runs: {len(plan.runs)} "
        f"({counts['complete']} trained now, {counts['skipped']} already complete, "
        f"{counts['failed']} failed). "
        "Metrics are on the test views against their uncompressed references; settings and versions in "
        "bench.json, every row in results.csv.",
    ]  # fmt: skip
    report_mod.write_report(rows, out, head, failures)
    doc["status"] = "complete" if not failures else "failed_runs"
    doc["finished"] = _now()
    doc["summary"] = {**counts, "runs": len(plan.runs), "rows": len(rows), "csv_header": header}
    write_bench_json(doc, bench_json)
    return doc


@functools.wraps(_bench)
def bench(scenes: list[str | Path], out: str | Path, *args: Any, **kwargs: Any) -> dict[str, Any]:
    """:func:`_bench` holding the results folder's output lock (one bench per folder; a second is refused
    naming the first's PID)."""
    from jsgs.base.io import OutputLock

    with OutputLock(Path(out), f"jsgs bench (into {out})"):
        return _bench(scenes, out, *args, **kwargs)
