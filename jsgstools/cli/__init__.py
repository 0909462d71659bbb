"""``jsgstools``: dataset preparation. Each command lives in its own module of this package."""

from __future__ import annotations

import click

from jsgs import __version__
from jsgs.cli._common import CONTEXT


@click.group(context_settings=CONTEXT)
@click.version_option(__version__, prog_name="jsgstools")
def main() -> None:
    """Prepare JPEG datasets for JSGS: inspect quantization tables, build mixed-quality scenes,
    validate COLMAP models and write training manifests."""


def _register() -> None:
    # Each module adds its commands to ``main``; kept apart so each command's wrapper stays small.
    from jsgstools.cli import dataset, inspect_dqt

    inspect_dqt.register(main)
    dataset.register(main)


_register()
