"""``jsgs render RUN --out FILE``: a thin wrapper over :func:`jsgs.apps.render_video.render_run`."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from jsgs.base.commands import CONTEXT, EXAMPLE, user_errors


@click.command(
    "render",
    context_settings=CONTEXT,
    epilog=EXAMPLE.format("jsgs render runs/jsgs --out flower.mp4 --path spiral --frames 120 --size 504x378"),
)
@click.argument("run", type=click.Path(path_type=Path, file_okay=False))
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(path_type=Path),
    help="A video (.mp4, .mov, .mkv, .avi) or a folder of PNG frames; the cameras go beside it as JSON.",
)
@click.option(
    "--path",
    "path",
    default="interpolate",
    show_default=True,
    help="interpolate (through the training cameras), spiral, ellipse, test (test views beside their "
    "references), or a JSON file: a path written by jsgs render, or RUN/viewer_cameras.json (key cameras).",
)
@click.option("--frames", type=click.IntRange(1, 100_000), default=120, show_default=True, help="Frames.")
@click.option(
    "--fps",
    type=float,
    default=30.0,
    show_default=True,
    help="Frames per second of the video (above 0, at most 1000).",
)
@click.option(
    "--size", default=None, help="WIDTHxHEIGHT, at most 8192 a side [default: the training images' size]."
)
@click.option("--device", type=click.Choice(["auto", "cuda", "cpu"]), default="auto", show_default=True)
@click.option(
    "--force",
    is_flag=True,
    help="Replace an existing video, or a folder of frames that jsgs render made, once the new render is "
    "complete (never one of the run's own files).",
)
@user_errors
def render_command(
    run: Path, out: Path, path: str, frames: int, fps: float, size: str | None, device: str, force: bool
) -> None:
    """Render a finished RUN along a camera path to a video or PNG frames (the run's own rasterizer: gsplat
    on CUDA, the torch reference on the CPU, where small sizes are advisable)."""
    from jsgs.apps.render_video import parse_size, render_run

    res = render_run(run, out, path, frames, fps, parse_size(size), device, sys.stderr.isatty(), force)
    what = f"{res['frames']} frames of {res['width']}x{res['height']}"
    click.echo(f"wrote {res['out']} ({what}) and {res['cameras']}")


def register(group: click.Group) -> None:
    """Add this module's commands to ``group``."""
    group.add_command(render_command)
