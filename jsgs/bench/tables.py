"""Markdown pieces and number formats shared by the bench's report sections and plots
(:mod:`jsgs.bench.markdown`, :mod:`jsgs.bench.budget`, :mod:`jsgs.bench.plots`)."""

from __future__ import annotations


def number(v: float | None, digits: int, signed: bool = False) -> str:
    """``v`` with ``digits`` decimals (``signed``: with its sign); "n/a" for None."""
    if v is None:
        return "n/a"
    return f"{v:+.{digits}f}" if signed else f"{v:.{digits}f}"


def count_label(v: float) -> str:
    """A Gaussian count for a plot's axis, to three significant digits: 0, 950, 100k, 101k (100,682), 1.5M
    (six-digit tick labels run into each other)."""
    if abs(v) >= 1e6:
        return f"{v / 1e6:.3g}M"
    if abs(v) >= 1e3:
        return f"{v / 1e3:.3g}k"
    return f"{v:.3g}"


def md_table(header: list[str], rows: list[list[str]], align: str | None = None) -> list[str]:
    """A markdown table's lines; ``align`` one letter per column, ``l`` or ``r`` (default: the first left,
    the rest right)."""
    align = align or "l" + "r" * (len(header) - 1)
    sep = ["---:" if a == "r" else "---" for a in align]
    return ["| " + " | ".join(header) + " |", "| " + " | ".join(sep) + " |"] + [
        "| " + " | ".join(r) + " |" for r in rows
    ]
