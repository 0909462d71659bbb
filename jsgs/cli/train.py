"""``jsgs train MANIFEST --out RUN``: a thin wrapper over :func:`jsgs.train.trainer.train`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from jsgs.base.commands import CONTEXT, EXAMPLE, MAX_PROCESSES, PORT, invocation, user_errors
from jsgs.base.errors import JsgsError
from jsgs.train.config import MCMC_CAP_MAX, PRESETS
from jsgs.train.method import method_flags, method_names, method_recipe


def method_switches(command: Callable[..., Any]) -> Callable[..., Any]:
    """Add every registered method's ``jsgs train`` switches (:func:`jsgs.train.method.method_flags`)."""
    for name in reversed(method_names()):
        for f in reversed(method_flags(name)):
            text = f"--method {name}: {f.help}"
            if f.choices:
                command = click.option(f.flag, f.dest, type=click.Choice(f.choices), default=None, help=text)(
                    command
                )
            else:
                command = click.option(f.flag, f.dest, is_flag=True, help=text)(command)
    return command


def recipes_text(preset: str) -> str:
    """What preset ``preset`` gives each method, for the help (:func:`jsgs.train.method.method_recipe`)."""

    def word(key: str, value: Any) -> str:
        if isinstance(value, bool):
            return key if value else f"{key} false"
        return f"{key} {format(value, 'g') if isinstance(value, float) else value}"

    return "".join(
        f"; for --method {name}: method_options " + ", ".join(word(k, v) for k, v in recipe.items())
        for name in method_names()
        if (recipe := method_recipe(name, preset))
    )


def given_switches(values: dict[str, Any]) -> dict[str, Any]:
    """The method switches given on the command line: flag -> its value (True for an on/off flag)."""
    flags = {f.dest: f for name in method_names() for f in method_flags(name)}
    return {flags[k].flag: v for k, v in values.items() if v is not None and v is not False}


def _parse_steps(text: str) -> list[int]:
    text = text.strip()
    if not text:
        return []
    try:
        return [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise JsgsError(
            f"--eval-at: expected comma-separated step counts like 3000,7000,10000 (got {text!r})"
        ) from None


@click.command(
    "train",
    context_settings=CONTEXT,
    epilog=EXAMPLE.format("jsgs train flower_gaussian/manifest.json --out runs/jsgs"),
)
@click.argument("manifest", type=click.Path(path_type=Path))
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(path_type=Path, file_okay=False),
    help="Run folder (config.json, metrics.json, point_cloud.ply, renders/, checkpoints/).",
)
@click.option(
    "--method",
    default=None,
    help="jsgs (JPEG state-guided supervision) or gsplat (the baseline: no JPEG terms) [default: jsgs].",
)
@click.option(
    "--iterations",
    type=int,
    default=None,
    help="Training steps [default: the preset's: 30000 for mcmc (gsplat simple_trainer's length), 10000 for "
    "paper].",
)
@click.option(
    "--eval-at",
    "eval_at",
    default=None,
    help="Comma-separated steps to evaluate and checkpoint at [default: the preset's: 7000,30000 for mcmc, "
    "3000,7000,10000 for paper; with --iterations N: those below N, and N]. '' for none.",
)
@click.option(
    "--config",
    "config_file",
    type=click.Path(path_type=Path, dir_okay=False),
    default=None,
    help="JSON settings (partial, over the defaults) or an earlier RUN/config.json.",
)
@click.option(
    "--preset",
    type=click.Choice(list(PRESETS)),
    default=None,
    help="Starting settings under --config and the options. mcmc (the defaults): gsplat simple_trainer's "
    "mcmc recipe (30000 steps, evaluations at 7000 and 30000, MCMCStrategy refining until step 25000 with a "
    "Gaussian budget sized to the scene, --cap-max auto, init.opacity 0.5, init.scale 0.1, "
    f"loss.opacity_reg 0.01, loss.scale_reg 0.01{recipes_text('mcmc')}); "
    "paper: the paper's protocol (gsplat's DefaultStrategy and default recipe, JSGS at the paper's "
    "weights, 10000 steps); preview: a quick CPU look at photos downscaled by 2 (the baseline, --method "
    "gsplat, with DefaultStrategy, 1000 steps, one evaluation at the end; docs/training.md) [default: mcmc].",
)
@click.option(
    "--cap-max",
    "cap_max",
    default=None,
    help="The Gaussian budget of strategy.type mcmc: a fixed number (strategy.cap_max), or auto: chosen from "
    "the scene's SfM points and training pixels when the run starts (strategy.cap_max_auto; the choice and "
    f"its inputs in config.json derived.budget; a manifest without SfM points gets at most {MCMC_CAP_MAX}) "
    "[default: auto].",
)
@click.option(
    "--device",
    type=click.Choice(["auto", "cuda", "cpu"]),
    default=None,
    help="cuda renders with gsplat, cpu with the torch reference rasterizer [default: auto].",
)
@method_switches
@click.option("--resume", is_flag=True, help="Continue RUN from its last checkpoint, bit for bit.")
@click.option("--force", is_flag=True, help="Overwrite the outputs of an earlier run in RUN.")
@click.option("--seed", type=int, default=None, help="Random seed [default: 42].")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@click.option(
    "--profile",
    is_flag=True,
    help="Record per-phase times and, on CUDA, per-phase peak allocated memory (synchronises the device; "
    "slower).",
)
@click.option(
    "--viewer",
    "viewer_port",
    type=PORT,
    default=None,
    is_flag=False,
    flag_value=8080,
    help="Serve the browser viewer (jsgs view) on the model as it trains, on this port [flag alone: 8080].",
)
@click.option(
    "--gpus",
    type=click.IntRange(max=MAX_PROCESSES),
    default=None,
    help="Train on this many GPUs of this machine, one process each, the Gaussians sharded and every step's "
    "views split across them (starts the processes as torchrun would; on several machines use torchrun; "
    "docs/performance.md).",
)
@click.option(
    "--processes",
    type=click.IntRange(max=MAX_PROCESSES),
    default=None,
    help="As --gpus on whatever --device is (on the CPU: gloo and the reference rasterizer).",
)
@click.option(
    "--stop-at",
    "stop_at",
    type=int,
    default=None,
    hidden=True,
    help="Stop with a checkpoint after this many steps (as an interruption would).",
)
@user_errors
def train_command(
    manifest: Path,
    out: Path,
    method: str | None,
    iterations: int | None,
    eval_at: str | None,
    config_file: Path | None,
    preset: str | None,
    cap_max: str | None,
    device: str | None,
    resume: bool,
    force: bool,
    seed: int | None,
    quiet: bool,
    profile: bool,
    viewer_port: int | None,
    gpus: int | None,
    processes: int | None,
    stop_at: int | None,
    **switches: Any,
) -> None:
    """Train Gaussians on the views of MANIFEST (a jsgs manifest, or the folder holding its manifest.json;
    see `jsgstools manifest`; for a folder of photos, `jsgstools sfm` first)."""
    from jsgs.train.config import cap_max_settings, command_settings
    from jsgs.train.distributed import is_main_process
    from jsgs.train.trainer import load_run_settings, train

    if resume and force:
        raise JsgsError("--resume and --force exclude each other")
    ctx = click.get_current_context()
    if gpus is not None or processes is not None:
        from jsgs.train.launch import launch_command

        ctx.exit(launch_command(invocation(ctx, "jsgs"), gpus, processes, device))
    overrides = {
        k: v
        for k, v in (("method", method), ("iterations", iterations), ("device", device), ("seed", seed))
        if v is not None
    }
    if eval_at is not None:
        overrides["eval_at"] = _parse_steps(eval_at)
    if cap_max is not None:
        overrides["strategy"] = cap_max_settings(cap_max)
    cfg = command_settings(
        preset_name=preset,
        config_file=config_file,
        resume_settings=load_run_settings(out) if resume and config_file is None else None,
        overrides=overrides,
        switches=given_switches(switches),
        eval_at_given=eval_at is not None,
    )
    if cap_max is not None and cfg.strategy.type != "mcmc":
        kind = cfg.strategy.type
        raise JsgsError(
            f"--cap-max applies to strategy.type mcmc (not --preset paper or preview); it is {kind!r}"
        )
    callbacks = []
    if viewer_port is not None:
        from jsgs.apps.viewer import LiveViewer

        callbacks.append(LiveViewer(port=viewer_port))
    doc = train(
        manifest, out, cfg, resume=resume, force=force, stop_at=stop_at, progress=not quiet, profile=profile,
        command=invocation(ctx, "jsgs"), callbacks=callbacks,
    )  # fmt: skip
    if not is_main_process():  # under torchrun: rank 0 reports
        return
    last = doc["evals"][-1] if doc["evals"] else None
    summary = f"{doc['status']}: {doc['step']}/{doc['iterations']} steps, {doc['num_gaussians']} Gaussians"
    if last is not None:
        parts = [
            f"PSNR {last['psnr']:.3f}" if last["psnr"] is not None else "PSNR n/a",
            f"SSIM {last['ssim']:.4f}" if last["ssim"] is not None else "SSIM n/a",
            f"LPIPS {last['lpips']:.4f}" if last["lpips"] is not None else "LPIPS n/a",
        ]
        summary += f"; at step {last['step']}: " + ", ".join(parts)
        if doc.get("reference") in ("jpeg", "mixed"):
            summary += " (test views against their JPEGs: no lossless copy)"
    click.echo(summary)
    names = ("metrics.json", "config.json", "point_cloud.ply", "point_cloud_colmap.ply", "renders/",
             "checkpoints/")
    click.echo(f"outputs in {out}/ ({', '.join(n for n in names if (out / n.rstrip('/')).exists())})")


def register(group: click.Group) -> None:
    """Add this module's commands to ``group``."""
    group.add_command(train_command)
