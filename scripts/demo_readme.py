"""Writes the demo's output into README.md between its ``<!-- demo-output -->`` and ``<!-- /demo-output -->``
markers (as a fenced block, lines over 110 characters shortened), so the README shows what the demo printed.
Output that lacks a line of :data:`SHAPE` (a run that stopped early, or one without LPIPS) is refused with
one line and the README is left as it is.

    python scripts/demo_readme.py demo_out/demo_output.txt README.md
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

BEGIN, END = "<!-- demo-output -->", "<!-- /demo-output -->"
WIDTH = 110
_N = r"[+-]?\d+\.\d+"
#: the lines the demo's output has, in this order (other lines may come between them)
SHAPE = (
    r"== 1\. synthetic scene \(\d+x\d+, texture scale [\d.]+, seed \d+\)",
    r"== 2\. .*(quality|schedule).*",
    r"== 3\. validate",
    r"ok",
    r"== 4\. JPEG state of the training views",
    r"== 5\. manifest",
    r"== 6\. train gsplat and JSGS \(\d+ steps each on \w+, at most \d+ Gaussians; .*\)",
    r"JSGS's recipe: .*",
    r"gsplat: complete: (\d+)/\1 steps, .*PSNR .*LPIPS .*",
    r"jsgs: complete: (\d+)/\1 steps, .*PSNR .*LPIPS .*",
    r"== 7\. metrics \(test views against their uncompressed references\)",
    r"method +PSNR +SSIM +LPIPS +#Gauss +s/step",
    rf"gsplat +{_N} +{_N} +{_N} +\d+ +{_N}",
    rf"jsgs +{_N} +{_N} +{_N} +\d+ +{_N}",
    rf"JSGS against gsplat: LPIPS {_N} %, PSNR {_N} dB, SSIM {_N}",
    r"target \(LPIPS at least 5 % lower, PSNR not lower\): (met|NOT met)",
    r"== 8\. a test view side by side",
    r"wrote \S+side_by_side\.png .*",
    r"== done in \d+ min \d+ s on \w+ \(\d+ cores, load \S+ at the start\): outputs in \S+",
)


def block(output: str) -> str:
    """The fenced block of ``output``: one line per line printed, each at most :data:`WIDTH` characters."""
    lines = [line if len(line) <= WIDTH else line[: WIDTH - 1] + "…" for line in output.rstrip().splitlines()]
    return "```\n" + "\n".join(lines) + "\n```"


def missing(output: str) -> str | None:
    """The first line of :data:`SHAPE` that ``output`` lacks (in order; ``None``: it has them all)."""
    lines = iter(output.splitlines())
    for shape in SHAPE:
        if not any(re.fullmatch(shape, line.rstrip("…")) for line in lines):
            return shape
    return None


def replace(readme: str, output: str) -> str:
    """``readme`` with the text between the markers replaced by :func:`block` of ``output``."""
    pattern = re.compile(re.escape(BEGIN) + r"\n.*?" + re.escape(END), re.DOTALL)
    if len(pattern.findall(readme)) != 1:
        raise SystemExit(f"error: README: expected one {BEGIN} ... {END} section")
    return pattern.sub(lambda _: f"{BEGIN}\n{block(output)}\n{END}", readme)


def main() -> None:
    output, readme = Path(sys.argv[1]), Path(sys.argv[2])
    gap = missing(output.read_text())
    if gap is not None:
        raise SystemExit(f"error: {output}: no line like {gap!r}; {readme} left as it is")
    text = replace(readme.read_text(), output.read_text())
    tmp = readme.with_name(readme.name + ".part")
    tmp.write_text(text)
    os.replace(tmp, readme)


if __name__ == "__main__":
    main()
