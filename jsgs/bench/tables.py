"""Markdown pieces shared by the bench's report sections (:mod:`jsgs.bench.markdown`,
:mod:`jsgs.bench.budget`)."""

from __future__ import annotations


def number(v: float | None, digits: int, signed: bool = False) -> str:
    """``v`` with ``digits`` decimals (``signed``: with its sign); "n/a" for None."""
    if v is None:
        return "n/a"
    return f"{v:+.{digits}f}" if signed else f"{v:.{digits}f}"


def md_table(header: list[str], rows: list[list[str]], align: str | None = None) -> list[str]:
    """A markdown table's lines; ``align`` one letter per column, ``l`` or ``r`` (default: the first left,
    the rest right)."""
    align = align or "l" + "r" * (len(header) - 1)
    sep = ["---:" if a == "r" else "---" for a in align]
    return ["| " + " | ".join(header) + " |", "| " + " | ".join(sep) + " |"] + [
        "| " + " | ".join(r) + " |" for r in rows
    ]
