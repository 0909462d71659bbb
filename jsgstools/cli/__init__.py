"""``jsgstools``: dataset preparation. Each command lives in its own module of this package."""

from __future__ import annotations

import click

from jsgs import __version__
from jsgs.base.commands import CONTEXT

#: the commands that use pycolmap (its import installs a native SIGTERM handler that prints a stack dump)
COLMAP_COMMANDS = frozenset({"synth", "compress", "validate", "manifest", "sfm"})


@click.group(context_settings=CONTEXT)
@click.version_option(__version__, prog_name="jsgstools")
@click.pass_context
def main(ctx: click.Context) -> None:
    """Prepare JPEG datasets for JSGS: inspect quantization tables, build mixed-quality scenes,
    validate COLMAP models and write training manifests."""
    if ctx.invoked_subcommand in COLMAP_COMMANDS:
        import pycolmap  # noqa: F401 - imported first so that our SIGTERM handler replaces its own

        from jsgs.base.commands import terminate_on_sigterm

        terminate_on_sigterm()


def _register() -> None:
    # Each module adds its commands to ``main``; kept apart so each command's wrapper stays small.
    from jsgstools.cli import dataset, inspect_dqt, sfm

    inspect_dqt.register(main)
    dataset.register(main)
    sfm.register(main)


_register()
