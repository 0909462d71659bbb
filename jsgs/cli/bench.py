"""``jsgs bench SCENES... --out RESULTS``: a thin wrapper over :func:`jsgs.bench.bench`."""

from __future__ import annotations

from pathlib import Path

import click

from jsgs.base.commands import CONTEXT, EXAMPLE, FINITE, WORKERS, invocation, user_errors


@click.command(
    "bench",
    context_settings=CONTEXT,
    epilog=EXAMPLE.format(
        "jsgs bench ../shared/scenes/llff_fern --out results --strategy mcmc --budgets 300k --seeds 0,1,2"
    ),
)
@click.argument("scenes", nargs=-1, required=True, type=click.Path(path_type=Path, file_okay=False))
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(path_type=Path, file_okay=False),
    help="Results folder (data/, runs/, logs/, results.csv, report.md, plots/, bench.json).",
)
@click.option(
    "--schedules",
    default="uniform,gaussian,descending,clean",
    show_default=True,
    help="Mixed-quality schedules (and clean: gsplat on the uncompressed views; gaussian+r90: the gaussian "
    "schedule's JPEGs saved once more at q = 90, analysed); '' for none.",
)
@click.option(
    "--fixed",
    default=None,
    help="Fixed JPEG qualities (seed 0 only); '' none [default: 30,50 with --strategy default, none with "
    "mcmc].",
)
@click.option(
    "--methods", default="gsplat,jsgs", show_default=True,
    help="gsplat, jsgs, jsgs_eff (JSGS with --tables effective).",
)  # fmt: skip
@click.option(
    "--ablation", default=None, help="Scene (name or path) for Table 2's ablation (gaussian, seed 0)."
)
@click.option(
    "--strategy",
    type=click.Choice(["default", "mcmc"]),
    default="default",
    show_default=True,
    help="Densification of every run: gsplat's DefaultStrategy (the paper's protocol) or MCMCStrategy at "
    "each of --budgets (jsgs train --preset mcmc --cap-max N or auto).",
)
@click.option(
    "--budgets",
    default=None,
    help="--strategy mcmc: Gaussian budgets, counts (300k, 1.5m, 250000), multiples of each scene's clean "
    "DefaultStrategy run's final count (0.5x, 1x; those runs train first), or auto (each run sizes it to its "
    "scene: jsgs train --cap-max auto) [default with --strategy mcmc: auto, the mcmc preset's].",
)
@click.option(
    "--jsgs-config",
    "jsgs_config",
    type=click.Path(path_type=Path, dir_okay=False),
    default=None,
    help="JSON settings over --config for the JSGS runs only (a recipe: method_options, loss weights).",
)
@click.option(
    "--iterations",
    type=int,
    default=None,
    help="Training steps per run [default: the strategy's preset: 10000 with --strategy default (the paper's "
    "protocol), 30000 with mcmc (gsplat simple_trainer's length)].",
)
@click.option(
    "--eval-at",
    "eval_at",
    default=None,
    help="Evaluation steps [default: 3000,7000 and from 10000 every 5000, cut at --iterations, and "
    "--iterations].",
)
@click.option(
    "--gsplat-steps",
    "gsplat_steps",
    type=float,
    default=1.0,
    show_default=True,
    help="gsplat's runs on the JPEG schedules train this many times --iterations steps: the recipe laid out "
    "over --iterations (its evaluations up to there are those of a run of that length), then on, evaluated "
    "past it at the same spacing, so that the report's equal-time table reads gsplat at JSGS's end without "
    "extrapolating (a JSGS step costs about 1.5 gsplat steps: 2 leaves room).",
)
@click.option(
    "--seeds",
    default="0,1",
    show_default=True,
    help="Seeds (compress and train); fixed-quality and ablation runs use the first.",
)
@click.option(
    "--jobs-per-gpu",
    "jobs_per_gpu",
    type=WORKERS,
    default=1,
    show_default=True,
    help="Concurrent trainings per GPU (on the CPU: in all).",
)
@click.option("--device", type=click.Choice(["auto", "cuda", "cpu"]), default="auto", show_default=True)
@click.option(
    "--config",
    "config",
    type=click.Path(path_type=Path, dir_okay=False),
    default=None,
    help="JSON settings given to every `jsgs train` (--config).",
)
@click.option(
    "--lpips-weights",
    "lpips_weights",
    default=None,
    help="AlexNet backbone for LPIPS [default: $JSGS_LPIPS_WEIGHTS, else "
    "../shared/lpips/alexnet_features.pth when present].",
)
@click.option(
    "--time-limit",
    "time_limit",
    type=FINITE,
    default=None,
    help="Seconds: start no run after this and stop those still going (a rerun resumes them).",
)
@click.option(
    "--prepare-only",
    is_flag=True,
    help="Only compress the datasets into OUT/data (on a CPU machine with ../shared, pycolmap and OpenCV); a "
    "GPU machine then runs the same command on them.",
)
@click.option(
    "--compile",
    "compile_backend",
    type=click.Choice(["off", "inductor", "aot_eager"]),
    default="off",
    show_default=True,
    help="--compile of every JSGS run (torch.compile of JO, L_obs and DS).",
)
@click.option(
    "--report-only",
    "report_only",
    is_flag=True,
    help="Train nothing: collect the runs already in OUT (e.g. copied back from GPU machines) into "
    "results.csv, report.md and plots; missing runs are listed as not run.",
)
@click.option("--quiet", is_flag=True, help="No progress bar.")
@user_errors
def bench_command(
    scenes: tuple[Path, ...], out: Path, schedules: str, fixed: str | None, methods: str,
    ablation: str | None, strategy: str, budgets: str | None, jsgs_config: Path | None,
    iterations: int | None, eval_at: str | None, gsplat_steps: float, seeds: str, jobs_per_gpu: int,
    device: str, config: Path | None,
    lpips_weights: str | None, time_limit: float | None, prepare_only: bool, compile_backend: str,
    report_only: bool, quiet: bool,
) -> None:  # fmt: skip
    """Reproduce the paper's tables: compress every scene per schedule and seed, train gsplat and JSGS on the
    same files (a pool of `jsgs train` subprocesses), then write results.csv, report.md and plots. With
    --strategy mcmc --budgets, every method and the clean ceiling train at each Gaussian budget and the report
    compares them at equal size."""
    import sys

    from jsgs.bench import bench
    from jsgs.bench.plan import BenchSettings, parse_budgets, parse_list

    if fixed is None:
        fixed = "30,50" if strategy == "default" else ""

    settings = BenchSettings(
        scenes=scenes, out=out, schedules=parse_list(schedules, "--schedules"),
        fixed=parse_list(fixed, "--fixed", int), methods=parse_list(methods, "--methods"),
        seeds=parse_list(seeds, "--seeds", int), ablation=ablation, iterations=iterations,
        eval_at=parse_list(eval_at, "--eval-at", int) if eval_at is not None else None, strategy=strategy,
        budgets=parse_budgets(budgets), gsplat_steps=gsplat_steps, jobs_per_gpu=jobs_per_gpu, device=device,
        config=config, jsgs_config=jsgs_config, lpips_weights=lpips_weights, time_limit=time_limit,
        compile_backend=compile_backend, prepare_only=prepare_only, report_only=report_only,
        progress=not quiet,
        command=invocation(click.get_current_context(), "jsgs"),
    )  # fmt: skip
    doc = bench(settings)
    if prepare_only:
        n = len(doc["datasets"])
        click.echo(f"bench: {n} datasets ready in {out}/data (runs not started: --prepare-only)")
        return
    s = doc["summary"]
    if report_only:
        n = f"collected {s['skipped']} of {s['runs']} runs ({s['failed']} not run)"
        click.echo(f"bench: {n}, {s['rows']} rows")
        click.echo(f"wrote {out}/results.csv, {out}/report.md, {out}/plots/, {out}/bench.json")
        return
    click.echo(
        f"bench: {s['runs']} runs ({s['complete']} trained, {s['skipped']} already complete, {s['failed']} "
        f"failed), {s['rows']} rows"
    )
    click.echo(f"wrote {out}/results.csv, {out}/report.md, {out}/plots/, {out}/bench.json")
    if s["failed"]:
        click.echo(
            f"error: {s['failed']} run(s) failed; see {out}/report.md (Failed runs) and the logs", err=True
        )
        sys.exit(1)


def register(group: click.Group) -> None:
    """Add this module's commands to ``group``."""
    group.add_command(bench_command)
