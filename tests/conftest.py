"""Shared fixtures. Dataset side: a small synthetic scene and its compressed dataset, built once per session
(read-only: tests that modify a scene copy it first), and access to ``../shared/scenes``."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

#: ``../shared`` beside the checkout (real scenes, the paper, LPIPS weights); tests that need it skip without.
SHARED = Path(__file__).resolve().parents[1].parent / "shared"


def pytest_configure(config: pytest.Config) -> None:
    """No test downloads anything: LPIPS's AlexNet download is off, and torch's hub cache is a fresh folder
    (so a backbone cached by an earlier, non-test run cannot change what the tests see). Set here, in the
    environment, so that the CLI subprocesses of the end-to-end tests inherit it."""
    import tempfile

    os.environ["JSGS_LPIPS_DOWNLOAD"] = "0"
    os.environ["TORCH_HOME"] = tempfile.mkdtemp(prefix="jsgs-test-torch-home-")


# A test needs ../shared when its body names one of these (the helpers below, the module constants that point
# into ../shared) or it uses a fixture built from it; such tests get the ``needs_data`` marker at collection,
# so ``-m needs_data`` / ``-m "not needs_data"`` select them, and the session's end counts how many ran.
_DATA_NAMES = ("shared_scene(", "shared_images(", "SHARED", "SCENES", "WEIGHTS", "needs_shared")
# tests/test_jsgs/metrics/test_lpips.py: the LPIPS model on the real backbone;
# tests/test_jsgstools/test_sfm.py: camera-like JPEGs made from the shared cup
_DATA_FIXTURES = {"model", "jpeg_scene"}
_data_outcomes: dict[str, int] = {"ran": 0, "skipped": 0}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    import inspect

    for item in items:
        fn = getattr(item, "function", None)
        try:
            src = inspect.getsource(fn) if fn is not None else ""
        except (OSError, TypeError):
            src = ""
        fixtures = set(getattr(item, "fixturenames", ()))
        if any(n in src for n in _DATA_NAMES) or fixtures & _DATA_FIXTURES:
            item.add_marker(pytest.mark.needs_data)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    # GPU tests that read ../shared skip on a CPU machine for lack of CUDA, not of data: not counted
    if "needs_data" not in report.keywords or "gpu" in report.keywords:
        return
    if report.when == "call":
        _data_outcomes["ran"] += 1
    elif report.skipped:
        _data_outcomes["skipped"] += 1


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int, config: pytest.Config) -> None:
    ran, skipped = _data_outcomes["ran"], _data_outcomes["skipped"]
    where = "present" if SHARED.is_dir() else "absent"
    terminalreporter.write_line(f"needs_data: {ran} ran, {skipped} skipped (../shared is {where}: {SHARED})")


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """With ../shared present, a run that selected data tests but ran none of them has not tested what it
    claims: fail it (a moved folder or a broken skip condition would otherwise pass silently)."""
    ran, skipped = _data_outcomes["ran"], _data_outcomes["skipped"]
    if SHARED.is_dir() and ran == 0 and skipped > 0:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
        print(f"\nneeds_data: ../shared is present ({SHARED}) but all {skipped} data tests skipped")


@pytest.fixture(scope="session")
def synth_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 12-view, 64x48 synthetic COLMAP scene (``jsgstools synth``, seed 0). Do not modify."""
    from jsgstools.synth import synth

    out = tmp_path_factory.mktemp("dataset") / "scene"
    synth(out, views=12, size=(64, 48), seed=0)
    return out


@pytest.fixture(scope="session")
def compressed_scene(synth_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``synth_scene`` compressed with the gaussian schedule, seed 0, default settings. Do not modify."""
    from jsgstools.compress import compress

    out = tmp_path_factory.mktemp("dataset") / "data"
    compress(synth_scene, out, "gaussian", seed=0, jobs=1)
    return out


@pytest.fixture
def one_torch_thread() -> Iterator[None]:
    """One torch thread for a test (``pytestmark = pytest.mark.usefixtures("one_torch_thread")``): the
    tensors of the JPEG and JSGS tests are tiny, and on a busy 2-core machine the intra-op thread pool's
    wake-ups cost 10-25x more than the work itself (measured)."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def load_benchmark(name: str, folder: str = "benchmarks") -> Any:
    """``<folder>/<name>.py`` (``benchmarks/``, ``tools/diagnostics/`` or ``tools/results/``) imported as a
    module (these are scripts, not a package)."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / folder / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"_benchmark_{name}", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    # registered before it runs, as an import would: @dataclass looks its module up in sys.modules
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def shared_scene(name: str) -> Path:
    """``../shared/scenes/<name>``, or skip the test with the reason."""
    path = SHARED / "scenes" / name
    if not (path / "sparse" / "0").is_dir():
        pytest.skip(f"needs the shared scene {path} (../shared beside the checkout), which is absent")
    return path
