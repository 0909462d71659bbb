"""Every test that runs only with CUDA carries the ``gpu`` mark: the GPU sessions select their tests with
``pytest -m gpu`` (``scripts/gpu_run.sh``, the campaign scripts), so a CUDA-only test without it never runs
anywhere. Read with ``ast``, not run."""

from __future__ import annotations

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def unmarked_cuda_tests(source: str, path: str) -> list[str]:
    """``path:line name`` of each test (function or class) in ``source`` skipped where CUDA is missing
    (``skipif(not ...cuda.is_available()...)``) without the ``gpu`` mark (its own or the module's
    ``pytestmark``), and of each ``gpu`` mark on something that is not a test (it selects nothing)."""
    tree = ast.parse(source, path)
    module_marked = any(
        isinstance(n, ast.Assign) and any(getattr(t, "id", "") == "pytestmark" for t in n.targets)
        and "pytest.mark.gpu" in ast.unparse(n.value)
        for n in tree.body
    )  # fmt: skip
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            continue
        decorators = [ast.unparse(d) for d in node.decorator_list]
        marked = any(d.startswith("pytest.mark.gpu") for d in decorators)
        is_test = node.name.startswith(("test", "Test"))
        cuda_only = any(
            d.startswith("pytest.mark.skipif(not ") and "cuda.is_available()" in d for d in decorators
        )
        if (is_test and cuda_only and not (marked or module_marked)) or (marked and not is_test):
            found.append(f"{path}:{node.lineno} {node.name}")
    return found


def test_every_cuda_only_test_is_marked_gpu() -> None:
    files = sorted(TESTS.rglob("*.py"))
    assert len(files) > 50
    found = [hit for p in files for hit in unmarked_cuda_tests(p.read_text(), str(p.relative_to(TESTS)))]
    assert not found, found


def test_the_check_finds_an_unmarked_test_and_a_stray_mark() -> None:
    source = (
        "import pytest, torch\n"
        "@pytest.mark.skipif(not torch.cuda.is_available(), reason='cuda')\n"
        "def test_a(): pass\n"
        "@pytest.mark.gpu\n"
        "class _Helper: pass\n"
        "@pytest.mark.gpu\n"
        "@pytest.mark.skipif(not torch.cuda.is_available(), reason='cuda')\n"
        "def test_b(): pass\n"
        "@pytest.mark.skipif(torch.cuda.is_available(), reason='a CPU-only refusal')\n"
        "def test_c(): pass\n"
    )
    assert unmarked_cuda_tests(source, "x.py") == ["x.py:3 test_a", "x.py:5 _Helper"]
    module = "import pytest\npytestmark = pytest.mark.gpu\n" + source.split("\n", 1)[1]
    assert unmarked_cuda_tests(module, "x.py") == ["x.py:6 _Helper"]
