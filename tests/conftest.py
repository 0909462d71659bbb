"""Shared fixtures. Dataset side: a small synthetic scene and its compressed dataset, built once per session
(read-only: tests that modify a scene copy it first), and access to ``../shared/scenes``."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

#: ``../shared`` beside the checkout (real scenes, the paper, LPIPS weights); tests that need it skip without.
SHARED = Path(__file__).resolve().parents[1].parent / "shared"


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
    """``<folder>/<name>.py`` (``benchmarks/`` or ``tools/diagnostics/``) imported as a module (these are
    scripts, not a package)."""
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
