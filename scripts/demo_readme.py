"""Writes the demo's output into README.md between its ``<!-- demo-output -->`` and ``<!-- /demo-output -->``
markers (as a fenced block, lines over 110 characters shortened), so the README shows what the demo printed.

    python scripts/demo_readme.py demo_out/demo_output.txt README.md
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

BEGIN, END = "<!-- demo-output -->", "<!-- /demo-output -->"
WIDTH = 110


def block(output: str) -> str:
    """The fenced block of ``output``: one line per line printed, each at most :data:`WIDTH` characters."""
    lines = [line if len(line) <= WIDTH else line[: WIDTH - 1] + "…" for line in output.rstrip().splitlines()]
    return "```\n" + "\n".join(lines) + "\n```"


def replace(readme: str, output: str) -> str:
    """``readme`` with the text between the markers replaced by :func:`block` of ``output``."""
    pattern = re.compile(re.escape(BEGIN) + r"\n.*?" + re.escape(END), re.DOTALL)
    if len(pattern.findall(readme)) != 1:
        raise SystemExit(f"error: README: expected one {BEGIN} ... {END} section")
    return pattern.sub(lambda _: f"{BEGIN}\n{block(output)}\n{END}", readme)


def main() -> None:
    output, readme = Path(sys.argv[1]), Path(sys.argv[2])
    text = replace(readme.read_text(), output.read_text())
    tmp = readme.with_name(readme.name + ".part")
    tmp.write_text(text)
    os.replace(tmp, readme)


if __name__ == "__main__":
    main()
