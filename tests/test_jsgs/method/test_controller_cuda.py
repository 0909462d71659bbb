"""The fused Gaussian Controller (``jsgs/kernels/csrc/controller.cu``) against its torch twin
(``jsgs.kernels.fro_from_probe_grad``), and ``method_options.speed.gc_kernel``.

On CPU: the option's resolution and refusals. On CUDA: gradients and statistics equal to the twin's in
float64 (tight) and float32, with hard cases (Gaussians behind the near plane and far outside the image,
tiny and huge scales, an empty V_i, N = 0), and a short training run with the kernel against one with the
twin.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import torch
from test_graphed import assert_same_training, train_jsgs_variants
from test_jsgs_method import jsgs_options, make_view, new_hook

from jsgs.base.errors import JsgsError
from jsgs.kernels import fro_from_probe_grad, fro_from_probe_grad_fused, packed_fro_stats
from jsgs.method.hook import JsgsHook
from jsgs.method.options import parse_options

SETTINGS = dict(weight=0.05, near_plane=0.01, eps_proj=1e-6, tau_s=1.0)
cuda = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs CUDA (the fused controller is CUDA-only)"
)


def test_gc_kernel_option_on_cpu() -> None:
    view = make_view(30, "4:2:0")
    tables = {view.index: new_hook(view).tables[view.index]}
    cpu = torch.device("cpu")
    assert JsgsHook(parse_options({}), tables, device=cpu).describe()["gc_kernel"] == "torch"
    with pytest.raises(JsgsError, match="gc_kernel cuda needs a CUDA device"):
        JsgsHook(parse_options(jsgs_options(gc_kernel="cuda")), tables, device=cpu)
    with pytest.raises(JsgsError, match="gc_kernel must be one of"):
        parse_options(jsgs_options(gc_kernel="fast"))


def test_fused_controller_refusal_words() -> None:
    """The words of a refusal (the C++ side answers only yes or no): each check, on the CPU."""
    from jsgs.kernels._wrapper import _fused_arguments_error

    n = 10
    good = (torch.zeros(1, n, 2), torch.zeros(n), torch.zeros(n, 3), torch.zeros(n, 3), torch.zeros(n, 4),
            torch.eye(4), torch.eye(3))  # fmt: skip
    assert _fused_arguments_error(good, 0.05) == (
        "the fused controller: probe_grad is torch.float32 on cpu; every tensor must be torch.float32 on one "
        "CUDA device"
    )
    assert "weight must be > 0, got -1.0" in _fused_arguments_error(good, -1.0)
    ints = (good[0], torch.zeros(n, dtype=torch.long), *good[2:])
    assert "got torch.int64" in _fused_arguments_error(ints, 1.0)
    assert "opacity_logits must be [N], got shape (1, 10)" in _fused_arguments_error(
        (good[0], good[1][None], *good[2:]), 1.0
    )


def _inputs(n: int, seed: int, dtype: torch.dtype, hard: bool = False) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    nu = torch.rand(n, generator=g, dtype=torch.float64) * (torch.rand(n, generator=g) > 0.3)
    probe = torch.stack([torch.rand(n, generator=g, dtype=torch.float64) * nu, nu], dim=-1)[None] * 0.05
    logits = torch.randn(n, generator=g, dtype=torch.float64) * 2
    log_scales = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.5 - 4.0
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) + torch.tensor([0.0, 0.0, 4.0])
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    if hard and n >= 8:
        means[0] = torch.tensor([0.0, 0.0, -1.0])  # behind the camera (J at z = 1)
        means[1] = torch.tensor([0.0, 0.0, 0.005])  # nearer than the near plane
        means[2] = torch.tensor([50.0, -40.0, 2.0])  # far outside the image: clamped x/z, y/z
        log_scales[3] = -15.0  # s̄ far below τ_s: damped
        log_scales[4] = 3.0  # huge: exp(-s̄/τ) underflows to 0
        logits[5] = 30.0  # α = 1 to rounding
        logits[6] = -6.0  # α small but contributing
        probe[0, 7] = 0.0  # not in V
    a = math.radians(20)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = torch.tensor(
        [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=torch.float64
    )
    viewmat[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    K = torch.tensor([[300.0, 0.0, 83.0], [0.0, 310.0, 58.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return tuple(t.to("cuda", dtype) for t in (probe, logits, log_scales, means, quats, viewmat, K))


def _both(inputs: tuple[torch.Tensor, ...]) -> tuple[tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]:
    got = fro_from_probe_grad_fused(*inputs, 160, 120, **SETTINGS)
    ref = fro_from_probe_grad(*inputs, 160, 120, **SETTINGS)
    return got, (ref.grad_logit, ref.grad_log_scale, packed_fro_stats(ref.terms))


@cuda
@pytest.mark.gpu
@pytest.mark.parametrize("hard", [False, True])
def test_fused_controller_matches_twin_float64(hard: bool) -> None:
    got, want = _both(_inputs(20000, 1, torch.float64, hard))
    assert want[2][1] > 1000 and want[2][3] > 0  # many in V, some damped
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-11, atol=1e-15)
    assert torch.isfinite(got[0]).all() and torch.isfinite(got[1]).all()


@cuda
@pytest.mark.gpu
def test_fused_controller_matches_twin_float32_at_training_size() -> None:
    inputs = _inputs(600_000, 2, torch.float32, hard=True)
    got, want = _both(inputs)
    exact, _ = _both(tuple(t.double() for t in inputs))
    torch.testing.assert_close(got[0], want[0], rtol=1e-4, atol=1e-12)
    torch.testing.assert_close(got[1], want[1], rtol=1e-4, atol=1e-12)
    assert got[2][1] == want[2][1] and got[2][3] == want[2][3]  # |V| and #damped are counts
    torch.testing.assert_close(got[2], want[2], rtol=1e-5, atol=0)
    torch.testing.assert_close(got[2].double(), exact[2], rtol=1e-5, atol=0)
    # reproducible: fixed-order sums, no atomics
    again = fro_from_probe_grad_fused(*inputs, 160, 120, **SETTINGS)
    assert all(torch.equal(a, b) for a, b in zip(got, again, strict=True))


@cuda
@pytest.mark.gpu
@pytest.mark.parametrize("n", [0, 1, 300])
def test_fused_controller_empty_view(n: int) -> None:
    inputs = list(_inputs(n, 3, torch.float32))
    inputs[0] = torch.zeros_like(inputs[0])  # no Gaussian contributes: L_fro = 0, zero gradients
    got, want = _both(tuple(inputs))
    for a, b in zip(got, want, strict=True):
        assert torch.equal(a, b) and not a.any()


_REFUSALS = """
import torch
from jsgs.kernels import fro_from_probe_grad_fused

n = 100
good = [torch.zeros(1, n, 2), torch.zeros(n), torch.zeros(n, 3), torch.zeros(n, 3), torch.zeros(n, 4),
        torch.eye(4), torch.eye(3)]
good = [t.cuda() for t in good]
cases = [
    [good[0][:, :50], *good[1:]],
    [good[0].double(), *good[1:]],
    [t.half() for t in good],
    [good[0], good[1][None], *good[2:]],
]
for i, args in enumerate([*cases, good]):
    print("case", i, flush=True)
    try:
        fro_from_probe_grad_fused(*args, 160, 120, weight=0.05 if i < len(cases) else 0.0)
    except ValueError as e:
        print(str(e).splitlines()[0], flush=True)
    else:
        print("accepted", flush=True)
print("alive")
"""


@cuda
@pytest.mark.gpu
def test_fused_controller_refuses_bad_input() -> None:
    """Bad arguments raise a ValueError naming the tensor (checked in C++, jsgs/kernels/csrc/bindings.cpp,
    which refuses with an empty result; the words are Python's). Run in a child process: an exception or a
    message built in the extension crashed the process on the GPU machine, and a crash must fail this test,
    not end the test session."""
    repo = Path(__file__).resolve().parents[3]
    path = os.pathsep.join([str(repo), os.environ.get("PYTHONPATH", "")])
    r = subprocess.run(
        [sys.executable, "-X", "faulthandler", "-c", _REFUSALS], capture_output=True, text=True, timeout=600,
        cwd=repo, env={**os.environ, "PYTHONPATH": path},
    )  # fmt: skip
    assert r.returncode == 0, f"exit {r.returncode} after {r.stdout[-500:]!r}: {r.stderr[-3000:]}"
    assert [s for s in r.stdout.splitlines() if not s.startswith("case ")] == [
        "the fused controller: probe_grad has shape (1, 50, 2), expected (1, 100, 2)",
        "the fused controller: probe_grad is torch.float64 on cuda:0; every tensor must be torch.float32 on "
        "one CUDA device",
        "the fused controller needs float32 or float64, got torch.float16",
        "the fused controller: opacity_logits must be [N], got shape (1, 100)",
        "the fused controller: weight must be > 0, got 0.0",
        "alive",
    ]


@cuda
@pytest.mark.gpu
def test_training_with_the_fused_controller_matches_the_twin(tmp_path: Path, capsys: Any) -> None:
    evals = train_jsgs_variants(tmp_path, {"cuda": {"gc_kernel": "cuda"}, "torch": {"gc_kernel": "torch"}})
    assert "warning" not in capsys.readouterr().err
    assert_same_training(evals["cuda"], evals["torch"])
