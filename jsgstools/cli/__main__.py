"""``python -m jsgstools.cli``: the same program as the ``jsgstools`` console script (for machines where it is
not installed)."""

from jsgstools.cli import main

main(prog_name="jsgstools")
