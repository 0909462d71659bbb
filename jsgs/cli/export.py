"""``jsgs export RUN --out FILE``: a thin wrapper over :func:`jsgs.train.export.export_run`."""

from __future__ import annotations

from pathlib import Path

import click

from jsgs.base.commands import CONTEXT, EXAMPLE, user_errors


@click.command(
    "export",
    context_settings=CONTEXT,
    epilog=EXAMPLE.format("jsgs export runs/jsgs --out flower.ply"),
)
@click.argument("run", type=click.Path(path_type=Path, file_okay=False))
@click.option(
    "--out", "out", required=True, type=click.Path(path_type=Path, dir_okay=False), help="File to write."
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["ply", "splat", "ply-compressed"]),
    default="ply",
    show_default=True,
    help="gsplat's exporter: ply (the 3DGS layout), splat (antimatter15's viewer), ply-compressed "
    "(SuperSplat).",
)
@click.option(
    "--frame",
    type=click.Choice(["colmap", "training"]),
    default="colmap",
    show_default=True,
    help="colmap: the scene's own frame (the trainer's normalisation undone); training: as trained.",
)
@click.option(
    "--force", is_flag=True, help="Replace an existing FILE (never one of the run's own files)."
)
@user_errors
def export_command(run: Path, out: Path, fmt: str, frame: str, force: bool) -> None:
    """Write a finished RUN's Gaussians to FILE (and FILE.json, what it holds), in the scene's COLMAP frame by
    default, for other 3DGS viewers and tools."""
    from jsgs.train.export import export_run

    rec = export_run(run, out, fmt, frame, force=force)
    what = f"{rec['gaussians']} Gaussians, {fmt}, {frame} frame, {rec['bytes']} bytes"
    if rec["dropped"]:
        what += f"; {rec['dropped']} nearly transparent ones left out by {fmt}"
    click.echo(f"wrote {out} ({what}) and {out}.json")


def register(group: click.Group) -> None:
    """Add this module's commands to ``group``."""
    group.add_command(export_command)
