"""``jsgs``: the trainer (``jsgs train MANIFEST``) and its benchmarks."""

from __future__ import annotations

import click

from jsgs import __version__
from jsgs.base.commands import CONTEXT


@click.group(context_settings=CONTEXT)
@click.version_option(__version__, prog_name="jsgs")
def main() -> None:
    """Train 3D Gaussian Splatting from mixed-quality JPEG views (JSGS) or the gsplat baseline."""


def _register() -> None:
    from jsgs.cli import bench, export, render, train, view

    train.register(main)
    bench.register(main)
    view.register(main)
    export.register(main)
    render.register(main)


_register()
