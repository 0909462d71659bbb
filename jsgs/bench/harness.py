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
from dataclasses import replace
from pathlib import Path
from typing import Any

from jsgs.base.errors import JsgsError
from jsgs.base.io import write_json_atomic, write_json_checked
from jsgs.bench import markdown as report_mod
from jsgs.bench import results as results_mod
from jsgs.bench import workers as pool_mod
from jsgs.bench.plan import BenchPlan, BenchSettings, Dataset, Run, build_plan, resolve_caps, train_argv

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
    """The JSON of a settings file given to every run (``--config``, ``--jsgs-config``), read as
    ``jsgs train`` reads one (:func:`jsgs.base.limits.read_json`: a regular file, no NaN, bounded nesting;
    one line)."""
    from jsgs.base.limits import read_json

    return None if path is None else read_json(path, "a settings file")


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
    write_json_checked(path, doc, "bench")


def _bench(settings: BenchSettings) -> dict[str, Any]:
    """Run the whole bench into ``settings.out``; returns the final bench.json document (the settings'
    fields: :class:`jsgs.bench.plan.BenchSettings`)."""
    import time

    deadline = None if settings.time_limit is None else time.time() + settings.time_limit
    s = _settle(settings)
    out = s.out
    config_path = str(Path(s.config).resolve()) if s.config is not None else None
    config_doc = _read_config(s.config)
    jsgs_doc = _read_config(s.jsgs_config)
    plan = build_plan(s)
    _configure_runs(plan, s, config_doc, jsgs_doc)
    slots = [None] if s.report_only else pool_mod.detect_slots(s.device, s.jobs_per_gpu)
    if not slots:
        raise JsgsError("--device cuda: torch.cuda.device_count() found no GPU")
    doc: dict[str, Any] = {
        "format": BENCH_FORMAT,
        "format_version": BENCH_VERSION,
        "status": "running",
        "started": _now(),
        "finished": None,
        "command": s.command,
        "settings": _settings_record(s, len(slots), config_path, config_doc, jsgs_doc),
        "environment": environment(s.device),
        "datasets": [_dataset_record(d) for d in plan.datasets],
        "runs": [_run_record(r, s.device, config_path) for r in plan.runs],
        "summary": None,
    }
    bench_json = out / "bench.json"
    write_bench_json(doc, bench_json)

    if s.report_only:
        ds_status = {d.key: {"status": "skipped"} for d in plan.datasets}
    else:
        ds_status = prepare_datasets(plan, s.progress)
    for d in doc["datasets"]:
        d.update(ds_status[d["key"]])
    if s.prepare_only:
        # The CPU half of a GPU session: compress here (pycolmap, OpenCV, ../shared), carry RESULTS/data.
        doc["status"] = "prepared"
        doc["finished"] = _now()
        write_bench_json(doc, bench_json)
        return doc
    bad = {k for k, v in ds_status.items() if v["status"] == "failed"}
    runnable = [r for r in plan.runs if r.data not in bad]
    if s.report_only:
        records = _collect_records(plan, out, runnable)
    else:
        env_extra = _run_environment(s)
        records = _train(plan, s, runnable, slots, config_path, env_extra, deadline)
    doc["runs"] = [_run_record(r, s.device, config_path) for r in plan.runs]
    _settle_records(doc, plan, records, bad, ds_status)

    rows = results_mod.collect(plan.runs)
    header = results_mod.write_csv(rows, out / "results.csv")
    failures = [records[r.id] | {"id": r.id} for r in plan.runs if records[r.id]["status"] == "failed"]
    counts = {
        st: sum(1 for r in records.values() if r["status"] == st) for st in ("complete", "skipped", "failed")
    }
    head = _report_head(s, doc["environment"], rows, len(slots), len(plan.runs), counts)
    report_mod.write_report(rows, out, head, failures)
    doc["status"] = "complete" if not failures else "failed_runs"
    doc["finished"] = _now()
    doc["summary"] = {**counts, "runs": len(plan.runs), "rows": len(rows), "csv_header": header}
    write_bench_json(doc, bench_json)
    return doc


def _settle(s: BenchSettings) -> BenchSettings:
    """The settings checked (JsgsError, one line, naming the option) with the harness's defaults filled in:
    the device (``auto``: cuda when there is one; cpu for ``report_only``), the run length
    (:meth:`BenchSettings.with_run_length`) and the LPIPS weights."""
    if s.time_limit is not None and s.time_limit <= 0:
        raise JsgsError(f"--time-limit {s.time_limit:g}: must be a positive number of seconds")
    if s.jobs_per_gpu < 1:
        raise JsgsError(f"--jobs-per-gpu {s.jobs_per_gpu}: must be at least 1")
    from jsgs.method.options import COMPILE_BACKENDS

    if s.compile_backend not in COMPILE_BACKENDS:
        raise JsgsError(f"--compile {s.compile_backend!r}: choose one of {', '.join(COMPILE_BACKENDS)}")
    if s.report_only and s.prepare_only:
        raise JsgsError("--report-only and --prepare-only exclude each other")
    device = s.device
    if s.report_only:
        device = "cpu" if device in (None, "auto") else device
    elif device in (None, "auto"):
        import torch

        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not s.report_only:
        import torch

        if not torch.cuda.is_available():
            raise JsgsError("--device cuda: no CUDA device is available")
    s = replace(s, device=device, lpips_weights=s.lpips_weights or _default_lpips_weights())
    return s.with_run_length()


def _configure_runs(plan: BenchPlan, s: BenchSettings, config_doc: Any, jsgs_doc: Any) -> None:
    """The runs' flags and configs beyond the plan's: ``--compile`` of the JSGS runs, their settings with
    ``--jsgs-config`` over ``--config`` (``OUT/configs/jsgs.json``), and the recipe of gsplat runs trained
    past its length (``OUT/configs/gsplat_recipe<N>.json``). Makes the results folder."""
    if s.compile_backend != "off":
        for r in plan.runs:
            if r.train_method == "jsgs":
                r.flags = [*r.flags, "--compile", s.compile_backend]
    s.out.mkdir(parents=True, exist_ok=True)
    if jsgs_doc is not None:
        merged = s.out / "configs" / "jsgs.json"
        merged.parent.mkdir(exist_ok=True)
        write_json_atomic(merged, _merge(config_doc or {}, jsgs_doc))
        for r in plan.runs:
            if r.train_method == "jsgs":
                r.config = str(merged.resolve())
    longer = {r.schedule_steps for r in plan.runs if r.schedule_steps is not None}
    for n in longer:  # gsplat past the recipe's length: its schedules laid out over the recipe's steps
        path = s.out / "configs" / f"gsplat_recipe{n}.json"
        path.parent.mkdir(exist_ok=True)
        write_json_atomic(path, _merge(config_doc or {}, {"optim": {"means_lr_decay_steps": n}}))
        for r in plan.runs:
            if r.schedule_steps == n:
                r.config = str(path.resolve())


def _run_environment(s: BenchSettings) -> dict[str, str]:
    """The environment every ``jsgs train`` subprocess gets on top of the bench's: the LPIPS weights, and
    how many runs share a device (recorded in each run's metrics.json, ``runs_per_device``)."""
    env_extra = {"JSGS_LPIPS_WEIGHTS": str(Path(s.lpips_weights).resolve())} if s.lpips_weights else {}
    from jsgs.train.trainer import RUNS_PER_DEVICE_ENV

    env_extra[RUNS_PER_DEVICE_ENV] = str(s.jobs_per_gpu)
    return env_extra


def _settings_record(
    s: BenchSettings, workers: int, config_path: str | None, config_doc: Any, jsgs_doc: Any
) -> dict[str, Any]:
    """bench.json's ``settings``: the settled settings, the worker count and the configs' contents."""
    return {
        "scenes": [str(x) for x in s.scenes],
        "schedules": list(s.schedules),
        "fixed": list(s.fixed),
        "methods": list(s.methods),
        "ablation": s.ablation,
        "seeds": list(s.seeds),
        "iterations": s.iterations,
        "eval_at": list(s.eval_at or []),
        "jobs_per_gpu": s.jobs_per_gpu,
        "device": s.device,
        "workers": workers,
        "compile": s.compile_backend,
        "report_only": s.report_only,
        "config": config_path,
        "config_content": config_doc,
        "jsgs_config": None if s.jsgs_config is None else str(Path(s.jsgs_config).resolve()),
        "jsgs_config_content": jsgs_doc,
        "strategy": s.strategy,
        "budgets": [b.label for b in s.budgets],
        "gsplat_steps": s.gsplat_steps,
        "lpips_weights": s.lpips_weights,
    }


def _dataset_record(d: Dataset) -> dict[str, Any]:
    """A dataset's bench.json entry before it is built."""
    return {
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


def _collect_records(plan: BenchPlan, out: Path, runnable: list[Run]) -> dict[str, dict[str, Any]]:
    """``report_only``: the records of the runs already in ``out`` (the others: not run)."""
    _resolve(plan, out, plan.references(), {})
    return {
        r.id: pool_mod.skipped_record(r)
        or {"id": r.id, "status": "failed", "stderr_tail": "",
            "error": f"not run: no complete metrics.json at step {r.iterations} in {r.out}"}
        for r in runnable
    }  # fmt: skip


def _train(
    plan: BenchPlan, s: BenchSettings, runnable: list[Run], slots: list[Any], config_path: str | None,
    env_extra: dict[str, str], deadline: float | None,
) -> dict[str, dict[str, Any]]:  # fmt: skip
    """Train the runnable runs on the worker pool: the reference runs of budgets given as multiples first,
    then the rest; their records."""
    assert s.device is not None  # _settle
    records: dict[str, dict[str, Any]] = {}
    refs = [r for r in plan.references() if r in runnable]
    if refs:  # budgets given as multiples of these runs' counts: train them first
        records = pool_mod.run_pool(
            refs, slots, s.device, config_path, env_extra, progress=s.progress, deadline=deadline
        )
    left = _resolve(plan, s.out, refs, records)
    records.update(left)
    rest = [r for r in runnable if r.id not in records]
    records.update(
        pool_mod.run_pool(
            rest, slots, s.device, config_path, env_extra, progress=s.progress, deadline=deadline
        )
    )
    return records


def _settle_records(
    doc: dict[str, Any], plan: BenchPlan, records: dict[str, dict[str, Any]], bad: set[str],
    ds_status: dict[str, dict[str, Any]],
) -> None:  # fmt: skip
    """Give every run a record (those on a dataset that could not be built and those whose budget has no
    reference count fail) and copy the records into ``doc["runs"]``."""
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


def _report_head(
    s: BenchSettings, env: dict[str, Any], rows: list[dict[str, Any]], workers: int, runs: int,
    counts: dict[str, int],
) -> list[str]:  # fmt: skip
    """report.md's opening lines: versions, where the runs trained, the command and the settings."""
    assert s.eval_at is not None  # _settle
    shared = sorted({int(r["runs_per_device"]) for r in rows if r.get("runs_per_device") is not None})
    gpu_txt = ", ".join(g["name"] for g in env["gpus"]) or "none"
    if s.report_only:  # this machine only collected: the devices are those the runs themselves recorded
        devices = sorted({str(r.get("device_name")) for r in rows if r.get("device_name")}) or ["unknown"]
        where = f"collected (--report-only) from runs trained elsewhere, on: {', '.join(devices)}"
    else:
        where = f"device {s.device}, GPUs: {gpu_txt}"
    sharing = (
        "unstated"
        if not shared
        else "; ".join("one run per device" if n == 1 else f"{n} runs per device" for n in shared)
    )
    return [
        f"Generated {_now()} by jsgs {env['jsgs']} (git {env['git_commit'] or 'unknown'}"
        f"{', uncommitted changes' if env['git_dirty'] else ''}); torch {env['torch']}, "
        f"gsplat {env['gsplat']}, python {env['python']}; {where}.",
        "",
        f"Command: `{s.command}`" if s.command else "Command: (library call)",
        "",
        f"{s.iterations} iterations, evaluations at {','.join(map(str, s.eval_at))}; seeds {list(s.seeds)}; "
        f"{workers} concurrent workers ({s.jobs_per_gpu} per GPU on cuda); device sharing of the runs "
        f"reported (their metrics.json): {sharing}."
        + (f" gsplat's runs on JPEG views train {s.gsplat_steps:g}x as long (evaluated past {s.iterations})."
           if s.gsplat_steps > 1 else "")
        + f" Runs: {runs} "
        f"({counts['complete']} trained now, {counts['skipped']} already complete, "
        f"{counts['failed']} failed). "
        "Metrics are on the test views against their uncompressed references; settings and versions in "
        "bench.json, every row in results.csv.",
    ]  # fmt: skip


@functools.wraps(_bench)
def bench(settings: BenchSettings) -> dict[str, Any]:
    """:func:`_bench` holding the results folder's output lock (one bench per folder; a second is refused
    naming the first's PID)."""
    from jsgs.base.io import OutputLock

    with OutputLock(settings.out, f"jsgs bench (into {settings.out})"):
        return _bench(settings)
