"""No function or method in ``jsgs`` or ``jsgstools`` longer than :data:`MAX_LINES` lines (its ``def`` line
to its last, decorators excluded, docstring included): a long one is split into helpers that each do one
thing. Read with ``ast``, not run."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("jsgs", "jsgstools")
MAX_LINES = 100


def long_functions(source: str, path: str, limit: int = MAX_LINES) -> dict[str, int]:
    """``path:name`` -> lines of every function (nested and methods too) in ``source`` over ``limit``."""
    out = {}
    for node in ast.walk(ast.parse(source, path)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            n = (node.end_lineno or node.lineno) - node.lineno + 1
            if n > limit:
                out[f"{path}:{node.name}"] = n
    return out


def test_no_function_is_over_the_limit() -> None:
    found: dict[str, int] = {}
    files = [p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))]
    assert len(files) > 100
    for p in files:
        found |= long_functions(p.read_text(), p.relative_to(ROOT).as_posix())
    assert found == {}


def test_the_check_sees_a_long_function() -> None:
    body = "".join(f"        x{i} = {i}\n" for i in range(MAX_LINES))
    code = f"def short():\n    pass\n\nclass A:\n    def long(self):\n{body}"
    assert long_functions(code, "m.py") == {"m.py:long": MAX_LINES + 1}
    assert long_functions(code, "m.py", limit=MAX_LINES + 1) == {}
