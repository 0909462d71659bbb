"""``jsgs view RUN``: a thin wrapper over :class:`jsgs.apps.viewer.Viewer`."""

from __future__ import annotations

import time
from pathlib import Path

import click

from jsgs.base.commands import CONTEXT, EXAMPLE, PORT, user_errors


@click.command(
    "view",
    context_settings=CONTEXT,
    epilog=EXAMPLE.format("jsgs view runs/flower --port 8080 (then open http://localhost:8080)"),
)
@click.argument("run", type=click.Path(path_type=Path, file_okay=False))
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to serve on (0.0.0.0: all).")
@click.option("--port", type=PORT, default=8080, show_default=True, help="Port (the next free one if taken).")
@click.option(
    "--max-size",
    "max_size",
    type=click.IntRange(16, 4096),
    default=None,
    help="Longer side of the rendered image in pixels [default: 1024 on CUDA, 320 on the CPU].",
)
@click.option("--device", type=click.Choice(["auto", "cuda", "cpu"]), default="auto", show_default=True)
@user_errors
def view_command(run: Path, host: str, port: int, max_size: int | None, device: str) -> None:
    """Look at a trained RUN in the browser: the model rendered on this machine for the browser's camera,
    the training cameras as frustums, and a button that saves the current camera to RUN/viewer_cameras.json.
    Ctrl-C stops the server."""
    from jsgs.apps.viewer import Viewer, load_run_model

    model = load_run_model(run, device)
    size = max_size or (1024 if model.device.type == "cuda" else 320)
    viewer = Viewer(model, host=host, port=port, max_size=size)
    click.echo(
        f"viewing {run} ({model.splats['means'].shape[0]} Gaussians, {model.backend} on {model.device}, "
        f"{size} px) at http://{'localhost' if host in ('127.0.0.1', '0.0.0.0') else host}:{viewer.port}"
        " (Ctrl-C stops)"
    )
    try:
        while True:
            time.sleep(1.0)
    finally:
        viewer.stop()


def register(group: click.Group) -> None:
    """Add this module's commands to ``group``."""
    group.add_command(view_command)
