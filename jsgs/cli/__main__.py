"""``python -m jsgs.cli``: the same program as the ``jsgs`` console script (for machines where it is
not installed)."""

from jsgs.cli import main

main(prog_name="jsgs")
