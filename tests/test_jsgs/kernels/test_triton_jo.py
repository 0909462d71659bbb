"""The fused Triton kernels of ``jsgs/kernels/_triton_jo.py`` against their torch twins and float64: JO's
coding pass (``jsgs.jpeg.observe._code_blocks``, mode "paper") and DS's Delta
(``jsgs.jpeg.supervision.dct_supervision``), and how ``method_options.speed.fused_jo`` resolves.

On the CPU the kernels run under Triton's interpreter: these tests need Triton and ``TRITON_INTERPRET=1``
(``PYTHONPATH=$PWD:/path/to/triton TRITON_INTERPRET=1 pytest tests/test_jsgs/kernels/test_triton_jo.py``)
and skip otherwise. On CUDA (``-m gpu``, without ``TRITON_INTERPRET``) the kernels are compiled for float32
(what training runs) and compared with the twin on CUDA in float32 and float64, eagerly and inside a CUDA
graph; they print the largest differences.

Tolerances: float64 against the float64 twin, 1e-9 (8-bit units; the two sum the 64-term products in
different orders). float32: the soft rounding ``round(z) + (z - round z)^3`` jumps by 3/4 of a step where
``z`` crosses a half-integer, so a float32 rounding difference in ``z`` (~1e-6 relative) flips a
coefficient now and then; blocks that hold no such flip agree within 2e-3 (8-bit units), and at most 1 % of
the blocks may hold one. DS's Delta has no rounding: float64 within 1e-12, float32 within 1e-4 (Delta is in
8-bit levels / 255, up to ~8).

Mode float (integer samples in and out) agrees exactly under the interpreter. On CUDA the fused kernels and
the float32 twin are two float32 computations that differ only at float32 rounding ties: a decoded sample
within float32 rounding of a half-integer at the final rounding, or an islow coefficient whose float32 sums
pass 2^24 (off by one unit, now and then across a quantizer step). Each flips one level of one sample,
which the colour conversion turns into at most about 2 8-bit units of RGB: on an H100 (triton 3.6, q50)
JO differed by at most 2.00 on 0.0019 % / 0.0026 % of the values at 1920x1440 / 504x378 (benchmark:
0.0024 % / 0.0026 %), none at 53x37; its gradient by at most 7e-7 in the test and 0.125 (of 1.99) in the
benchmark's run at 1920x1440. The CUDA test allows 0.1 % of the values beyond 0.01 (8-bit units) and 0.1 %
of the gradient beyond 1e-3 of its largest value, in both modes.
"""

from __future__ import annotations

import re
from typing import Any

import pytest
import torch
from _fused_graph import check_graph_replay, observe_with_gradients

from jsgs.base.errors import JsgsError
from jsgs.jpeg.dct import blockify, dct_matrix, unblockify
from jsgs.jpeg.observe import _code_blocks, jpeg_observe
from jsgs.jpeg.supervision import dct_supervision
from jsgs.jpeg.tables import ijg_tables
from jsgs.kernels import _triton_jo
from jsgs.kernels._triton_jo import (
    dct_kron,
    ds_delta,
    float_code,
    interpreting,
    paper_code,
    triton_available,
)
from jsgs.method.options import parse_options, use_fused_jo

needs_interpreter = pytest.mark.skipif(
    not (triton_available() and interpreting()),
    reason="needs Triton and TRITON_INTERPRET=1 (the fused JO kernels on CPU tensors)",
)
cuda_triton = pytest.mark.skipif(
    not (torch.cuda.is_available() and triton_available() and not interpreting()),
    reason="needs CUDA and Triton, without TRITON_INTERPRET",
)


def twin(planes: torch.Tensor, tables: torch.Tensor, mode: str = "paper") -> torch.Tensor:
    """A mode's coding pass of ``(B, C, H, W)`` planes through the torch code JO runs."""
    b = planes.shape[0]
    blocks = blockify(planes)
    n = blocks.shape[1] * blocks.shape[2] * blocks.shape[3]
    q = tables[:, None].expand(b, n, 8, 8)
    return unblockify(_code_blocks(blocks.reshape(b, n, 8, 8), q, mode).reshape(blocks.shape))


def twin_float(planes: torch.Tensor, tables: torch.Tensor) -> torch.Tensor:
    return twin(planes, tables, "float")


def _tables(kind: str, views: int, gen: torch.Generator) -> torch.Tensor:
    if kind == "random":  # each view its own, steps 1..255
        return torch.randint(1, 256, (views, 8, 8), generator=gen).double()
    if kind == "16bit":  # extreme steps: most coefficients quantize to 0
        return torch.randint(1, 65536, (views, 8, 8), generator=gen).double()
    q = int(kind.removeprefix("q"))
    return torch.as_tensor(ijg_tables(q)[0], dtype=torch.float64).reshape(1, 8, 8).expand(views, 8, 8)


def _planes(shape: tuple[int, ...], seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(*shape, generator=g, dtype=torch.float64) * 300.0 - 20.0  # clamps hit at both ends
    return x, torch.randn(*shape, generator=g, dtype=torch.float64)


def _value_and_grad(fn, x: torch.Tensor, tables: torch.Tensor, g: torch.Tensor):  # type: ignore[no-untyped-def]
    xa = x.clone().requires_grad_()
    out = fn(xa, tables)
    (grad,) = torch.autograd.grad(out, xa, g)
    return out.detach(), grad


def _block_agreement(a: torch.Tensor, b: torch.Tensor, tol: float) -> tuple[float, float, float]:
    """(max |a - b| over all, max over the blocks within ``tol``, share of blocks beyond ``tol``)."""
    err = blockify((a - b).abs().double()).flatten(-2).amax(-1).flatten()
    ok = err <= tol
    return float(err.max()), float(err[ok].max()) if ok.any() else 0.0, float((~ok).double().mean())


def test_kron_is_the_dct_of_jo() -> None:
    d = dct_matrix(torch.float64)
    assert torch.equal(dct_kron(torch.float64), torch.kron(d, d))


@needs_interpreter
@pytest.mark.parametrize("kind", ["q10", "q50", "q95", "random", "16bit"])
@pytest.mark.parametrize("shape", [(2, 1, 16, 24), (2, 2, 8, 40), (1, 2, 24, 8)])
def test_matches_twin_float64(kind: str, shape: tuple[int, ...]) -> None:
    x, g = _planes(shape, 1)
    tables = _tables(kind, shape[0], torch.Generator().manual_seed(2))
    v1, g1 = _value_and_grad(paper_code, x, tables, g)
    v2, g2 = _value_and_grad(twin, x, tables, g)
    torch.testing.assert_close(v1, v2, rtol=0, atol=1e-9)
    torch.testing.assert_close(g1, g2, rtol=0, atol=1e-9)
    assert g2.abs().max() > 0.01  # the comparison has something to compare


@needs_interpreter
def test_strided_planes_and_views_with_their_own_tables() -> None:
    # a plane of a channels-last tensor (as JO's luma is when the image needs no padding), two views whose
    # tables differ: each block must use its own view's
    base, g = _planes((2, 3, 16, 32), 3)
    cl = base.contiguous(memory_format=torch.channels_last)[:, 1:]
    assert not cl.is_contiguous()
    tables = _tables("random", 2, torch.Generator().manual_seed(4))
    v1, g1 = _value_and_grad(paper_code, cl, tables, g[:, 1:])
    v2, g2 = _value_and_grad(twin, cl.contiguous(), tables, g[:, 1:])
    torch.testing.assert_close(v1, v2, rtol=0, atol=1e-9)
    torch.testing.assert_close(g1, g2, rtol=0, atol=1e-9)
    swapped = paper_code(cl, tables.flip(0))
    assert (swapped - v1).abs().max() > 1.0


@needs_interpreter
def test_float32_against_twin_and_float64() -> None:
    x, g = _planes((2, 2, 32, 48), 5)
    tables = _tables("q50", 2, torch.Generator())
    v32, g32 = _value_and_grad(paper_code, x.float(), tables.float(), g.float())
    t32, tg32 = _value_and_grad(twin, x.float(), tables.float(), g.float())
    t64, tg64 = _value_and_grad(twin, x, tables, g)
    for ref in (t32, t64):
        _, within, flipped = _block_agreement(v32, ref, 2e-3)
        assert within <= 2e-3 and flipped <= 0.01
    for ref in (tg32, tg64):
        _, within, flipped = _block_agreement(g32, ref, 2e-3)
        assert within <= 2e-3 and flipped <= 0.01


@needs_interpreter
@pytest.mark.parametrize("kind", ["q10", "q50", "q95", "random", "16bit"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_float_mode_matches_twin(kind: str, dtype: torch.dtype) -> None:
    # mode "float": integer samples in, integer samples out; the islow sums of these blocks stay below 2^24,
    # where float32 is exact, so the values agree exactly in both dtypes
    g = torch.Generator().manual_seed(17)
    x = torch.randint(0, 256, (2, 2, 16, 24), generator=g).to(dtype)
    grad_out = torch.randn(x.shape, generator=g, dtype=torch.float64).to(dtype)
    tables = _tables(kind, 2, torch.Generator().manual_seed(18)).to(dtype)
    v1, g1 = _value_and_grad(float_code, x, tables, grad_out)
    v2, g2 = _value_and_grad(twin_float, x, tables, grad_out)
    assert torch.equal(v1, v2) and torch.equal(v1, v1.round())
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(g1, g2, rtol=0, atol=tol)
    assert g2.abs().max() > 0.01


@needs_interpreter
def test_float_mode_survives_approximate_division(monkeypatch: pytest.MonkeyPatch) -> None:
    """On CUDA Triton's ``/`` on float32 is approximate (``div.full.f32``); ``tl.math.div_rn`` is not. Under
    the interpreter with ``/`` made approximate (``x * (1 / y)``, each rounded to float32), mode float's
    kernels still give the twin's samples exactly; with every division approximate (the kernels as they
    were when the H200 measured them disagreeing) they do not, and mode paper's kernels (which use ``/``)
    show that the patch reaches the kernels."""
    import numpy as np
    from triton.runtime.interpreter import InterpreterBuilder

    def approx(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.multiply(a, np.divide(np.ones_like(b), b))

    def approximate(name: str) -> None:
        monkeypatch.setattr(InterpreterBuilder, name, lambda self, lhs, rhs: self.binary_op(lhs, rhs, approx))

    g = torch.Generator().manual_seed(17)
    x = torch.randint(0, 256, (2, 2, 16, 24), generator=g).float()
    tables = _tables("q50", 2, torch.Generator().manual_seed(18)).float()
    reference, paper = twin_float(x, tables), paper_code(x, tables)
    assert torch.equal(float_code(x, tables), reference)
    approximate("create_fdiv")  # as on CUDA
    assert not torch.equal(paper_code(x, tables), paper)
    assert torch.equal(float_code(x, tables), reference)
    approximate("create_precise_divf")  # every division approximate: levels drop at the quantizer's ties
    assert int((float_code(x, tables) != reference).sum()) > 10


def _near_ties(shape: tuple[int, ...], seed: int, table: torch.Tensor) -> torch.Tensor:
    """float32 planes with, in every block, one coefficient ``z = c / Q`` within about 2 float32 ulps of a
    half-integer (``c`` moved there along its DCT basis image, which moves no other coefficient)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(*shape, generator=g, dtype=torch.float64) * 200.0 + 28.0
    blocks = blockify(x).contiguous()
    flat = blocks.view(-1, 64)
    k = dct_kron(torch.float64)
    e = torch.randint(0, 64, (flat.shape[0],), generator=g)
    q = table.double().reshape(64)[e]
    c = (flat * k[e]).sum(-1)
    flat += (((c / q).floor() + 0.5) * q - c)[:, None] * k[e]
    return unblockify(blocks).float()


@needs_interpreter
def test_benchmark_counts_tie_flips_apart(monkeypatch: pytest.MonkeyPatch) -> None:
    """``benchmarks/bench_jpeg_ops.py --fused-jo`` times mode paper's coding-pass kernels alone and compares
    them with the twin. It printed the largest difference over all pixels: 3.4 / 1.5 8-bit units on an H100
    at 1920x1440 / 504x378 at every launch setting, while the whole JO agreed within 2.4e-4. Those planes
    (uniform noise, seed 0) hold a coefficient with ``z`` 4.4999993 (step 19) / -1.5000006 (step 16, a DC),
    a few float32 ulps from a half-integer, where the soft rounding jumps by 3/4 of a step: 3.43 / 1.50
    units in the block. One tie flip, not a disagreement: the interpreter shows the same 1.50 at 504x378,
    in that block. The benchmark now counts such blocks apart (``tie_flip_agreement``); here with flips
    forced by a division 4 ulps high (a kernel whose ``z`` differs from the twin's by a few ulps), and a
    real disagreement still shows."""
    import numpy as np
    from conftest import load_benchmark
    from triton.runtime.interpreter import InterpreterBuilder

    bench = load_benchmark("bench_jpeg_ops")
    table = torch.as_tensor(ijg_tables(50)[0], dtype=torch.float32).reshape(1, 8, 8)
    planes = _near_ties((1, 3, 32, 64), 21, table)
    q = table.reshape(1, 64).contiguous()
    reference = twin(planes, table)
    fair = bench.tie_flip_agreement(_triton_jo.paper_code_forward(planes, q), reference, planes, table)
    assert fair.blocks == 96 and fair.other == 0 and fair.within <= 2e-3

    high = np.float32(1.0 + 4.0 * np.finfo(np.float32).eps)
    monkeypatch.setattr(InterpreterBuilder, "create_fdiv", lambda self, a, b: self.binary_op(
        a, b, lambda x, y: np.multiply(np.divide(x, y), high.astype(x.dtype))))  # fmt: skip
    out = _triton_jo.paper_code_forward(planes, q)
    flips = bench.tie_flip_agreement(out, reference, planes, table)
    assert flips.flipped >= 10 and flips.other == 0 and flips.within <= 2e-3 and flips.largest > 0.5
    assert f"{flips.flipped} of 96 blocks off by one quantizer tie flip, 0 otherwise" in flips.describe()
    broken = out.clone()
    broken[0, 1, 8:16, :8] += 0.01  # one block off everywhere by a little: no tie flip explains it
    assert bench.tie_flip_agreement(broken, reference, planes, table).other == 1


@needs_interpreter
def test_benchmark_times_the_steps_own_launches(capsys: pytest.CaptureFixture[str]) -> None:
    """``bench_jpeg_ops.py --fused-jo --coding-launches`` times mode paper's coding-pass kernels on the
    launches JO makes in a step (recorded from its backward: the padded luma plane, the two chroma planes,
    the saved output and the incoming gradient as the chain passes them) beside the benchmark's own
    three-plane launch, and names how Triton specialises each (one binary each; ptxas allocates registers
    per binary). At 53 x 37, 4:2:0: luma padded to 40 x 56, chroma (19 x 27 samples) to 24 x 32."""
    import argparse

    from conftest import load_benchmark

    bench = load_benchmark("bench_jpeg_ops")
    args = argparse.Namespace(quality=50, sampling="4:2:0", repeats=1, warmup=0)
    bench.coding_launches(53, 37, args, torch.device("cpu"))
    rows = [r for r in capsys.readouterr().out.splitlines() if r.startswith("| 16/4 |")]
    assert len(rows) == 3, rows
    cells = [[c.strip() for c in r.split("|")[1:-1]] for r in rows]
    assert [c[1:4] for c in cells] == [
        ["step, luma", "(1, 1, 40, 56)", "(2240, 2240, 56, 1); alike"],
        ["step, chroma", "(1, 2, 24, 32)", "(1536, 768, 32, 1); alike"],
        ["bench, 3 planes", "(1, 3, 32, 48)", "(4608, 1536, 48, 1); alike"],
    ]
    assert cells[0][4] == "=1: planes; not /16: n_blocks, nb, nbx, xs_h, os_h, gs_h"  # 35 blocks, 7 a row
    assert [int(c[5]) for c in cells] == [35, 24, 72]
    assert all(float(c[7]) > 0 for c in cells)


@needs_interpreter
def test_gradcheck_float64() -> None:
    g = torch.Generator().manual_seed(6)
    x = (torch.rand(2, 1, 8, 16, generator=g, dtype=torch.float64) * 200.0 + 20.0).requires_grad_()
    tables = torch.randint(2, 60, (2, 8, 8), generator=g).double()
    # fast_mode: directional derivatives along random vectors (each full Jacobian column is a forward pass
    # through the interpreter)
    ok = torch.autograd.gradcheck(lambda t: paper_code(t, tables), (x,), eps=1e-6, atol=1e-6, fast_mode=True)
    assert ok


@needs_interpreter
@pytest.mark.parametrize("mode", ["paper", "float"])
@pytest.mark.parametrize("sampling", ["4:2:0", "4:2:2", "4:4:4", "4:4:0", "4:1:1"])
@pytest.mark.parametrize(("height", "width"), [(37, 53), (13, 9), (16, 32)])
def test_jpeg_observe_triton_matches_torch(mode: str, sampling: str, height: int, width: int) -> None:
    # the padding and cropping around the kernels: odd sizes, every sampling, two views with own tables
    variants = [{"kernel": "triton"}, {"kernel": "torch"}]
    out = observe_with_gradients(7, height, width, sampling, mode, variants)
    torch.testing.assert_close(out[0][0], out[1][0], rtol=0, atol=1e-11)
    torch.testing.assert_close(out[0][1], out[1][1], rtol=0, atol=1e-11)


def _ds_both(obs: torch.Tensor, target: torch.Tensor, tables: torch.Tensor):  # type: ignore[no-untyped-def]
    """DS's delta, losses, block scores and the gradient of a mix of its terms, fused and torch."""
    out = []
    for kernel in ("triton", "torch"):
        x = obs.clone().requires_grad_()
        s = dct_supervision(x, target, tables, kernel=kernel)
        loss = s.loss_low.sum() + 2.0 * s.loss_mid.sum() + (s.block_score**2).sum()
        (grad,) = torch.autograd.grad(loss, x)
        out.append((s.delta.detach(), torch.stack([s.loss_low, s.loss_mid]).detach(), s.pixel_score, grad))
    return out


@needs_interpreter
@pytest.mark.parametrize(("height", "width"), [(37, 53), (16, 8), (8, 31)])
def test_ds_delta_matches_torch_float64(height: int, width: int) -> None:
    g = torch.Generator().manual_seed(9)
    obs = torch.rand(2, 3, height, width, generator=g, dtype=torch.float64)
    target = torch.rand(2, 3, height, width, generator=g, dtype=torch.float64)
    tables = torch.randint(1, 80, (2, 8, 8), generator=g).double()
    fused, twin_ = _ds_both(obs, target, tables)
    for a, b in zip(fused, twin_, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    assert twin_[3].abs().max() > 1e-3 and twin_[0].abs().max() > 0.1


@needs_interpreter
def test_ds_delta_float32_and_gradcheck() -> None:
    g = torch.Generator().manual_seed(10)
    obs = torch.rand(1, 3, 24, 40, generator=g, dtype=torch.float64)
    target = torch.rand(1, 3, 24, 40, generator=g, dtype=torch.float64)
    d64 = ds_delta(obs, target)
    torch.testing.assert_close(ds_delta(obs.float(), target.float()).double(), d64, rtol=0, atol=1e-4)
    x = obs[..., :16, :16].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda t: ds_delta(t, target[..., :16, :16]), (x,), fast_mode=True)


def test_ds_falls_back_where_the_kernel_cannot_run(monkeypatch: pytest.MonkeyPatch) -> None:
    g = torch.Generator().manual_seed(11)
    table = torch.randint(1, 80, (8, 8), generator=g).float()
    with pytest.raises(ValueError, match="kernel must be"):
        dct_supervision(torch.rand(1, 3, 16, 16), torch.rand(1, 3, 16, 16), table, kernel="cuda")
    # no valid block, or a target that needs a gradient: the torch code, whatever the kernel
    for obs, target in (
        (torch.rand(1, 3, 7, 30, generator=g), torch.rand(1, 3, 7, 30, generator=g)),
        (torch.rand(1, 3, 16, 16, generator=g), torch.rand(1, 3, 16, 16, generator=g).requires_grad_()),
    ):
        a = dct_supervision(obs, target, table, kernel="triton")
        b = dct_supervision(obs, target, table)
        assert torch.equal(a.delta, b.delta) and torch.equal(a.loss_mid, b.loss_mid)
    monkeypatch.setattr(_triton_jo, "fused_jo_runs", lambda x: False)
    obs, target = torch.rand(1, 3, 16, 16, generator=g), torch.rand(1, 3, 16, 16, generator=g)
    assert torch.equal(dct_supervision(obs, target, table, kernel="triton").delta,
                       dct_supervision(obs, target, table).delta)  # fmt: skip


@needs_interpreter
@pytest.mark.parametrize("twice", [False, True])
def test_jpeg_terms_with_triton_match_torch(twice: bool) -> None:
    # the method's chain (JO, L_obs, DS; a view compressed twice runs JO twice) with jo_kernel "triton"
    from jsgs.method.image_terms import terms_with_gradient

    g = torch.Generator().manual_seed(19)
    x = torch.rand(1, 3, 29, 43, generator=g, dtype=torch.float64).requires_grad_()
    y = torch.rand(1, 3, 29, 43, generator=g, dtype=torch.float64)
    tables = torch.randint(1, 90, (2, 8, 8), generator=g).double()
    first = torch.randint(20, 120, (2, 8, 8), generator=g).double() if twice else None
    settings = dict(
        mode="paper", ssim_lambda=0.2, ssim_padding="valid", ds=True, gc=True, eps_sm=1e-3, eps_loss=1e-6,
        eps_block=1e-6, first=first,
    )  # fmt: skip
    w = (0.2, 0.02, 0.03)
    out = [
        terms_with_gradient(x, y, tables, weights=w, sampling="4:2:0", jo_kernel=k, **settings)
        for k in ("triton", "torch")
    ]
    for a, b in zip(*out, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)
    assert out[1][1].abs().max() > 0


@pytest.mark.skipif(not triton_available(), reason="needs Triton")
def test_kernels_refuse_tensors_they_cannot_run_on() -> None:
    # a CPU tensor outside the interpreter (or float16, or tables on another device) is one ValueError
    # naming the function, not Triton's pointer error at the CUDA launch
    from jsgs.jpeg.color import kernel_coefficients
    from jsgs.kernels._triton_jo import color_convert

    image = torch.rand(1, 3, 16, 16)

    def coefficients(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        return kernel_coefficients("rgb2ycc", dtype, image.device)

    calls = {  # name: (function, its second tensor)
        "paper_code": (paper_code, torch.full((1, 8, 8), 16.0)),
        "float_code": (float_code, torch.full((1, 8, 8), 16.0)),
        "ds_delta": (ds_delta, torch.rand(1, 3, 16, 16)),
        "color_convert": (lambda x, _: color_convert(x, *coefficients(x.dtype)), None),
    }
    for name, (fn, other) in calls.items():
        with pytest.raises(ValueError, match=f"{name} needs float32 CUDA tensors"):
            fn(image.half(), None if other is None else other.half())
        if other is not None:  # the second tensor on another device
            with pytest.raises(ValueError, match=f"{name} needs .* on one device, got .* cpu, meta"):
                fn(image, other.to("meta"))
        if not interpreting():
            with pytest.raises(ValueError, match=f"{name} needs float32 CUDA tensors"):
                fn(image, other)


def test_mode_exact_ignores_the_kernel() -> None:
    g = torch.Generator().manual_seed(8)
    rgb = torch.rand(1, 3, 19, 21, generator=g)
    luma, chroma = (torch.as_tensor(t).float() for t in ijg_tables(75))
    a = jpeg_observe(rgb, luma, chroma, "4:2:0", "exact", kernel="triton")
    assert torch.equal(a, jpeg_observe(rgb, luma, chroma, "4:2:0", "exact"))


def test_kernel_choice_is_checked(monkeypatch: pytest.MonkeyPatch) -> None:
    rgb = torch.rand(1, 3, 16, 16)
    luma, chroma = (torch.as_tensor(t).float() for t in ijg_tables(75))
    with pytest.raises(ValueError, match="kernel must be one of"):
        jpeg_observe(rgb, luma, chroma, kernel="cuda")
    # where the kernels cannot run (no Triton, a CPU tensor, float64 on CUDA): the torch code
    monkeypatch.setattr(_triton_jo, "fused_jo_runs", lambda x: False)
    a = jpeg_observe(rgb, luma, chroma, "4:2:0", "paper", kernel="triton")
    assert torch.equal(a, jpeg_observe(rgb, luma, chroma, "4:2:0", "paper"))


def test_fused_jo_setting() -> None:
    cpu = torch.device("cpu")
    assert parse_options({}).speed.fused_jo == "auto"
    assert not use_fused_jo(parse_options({}), cpu)  # the CPU runs the torch code, whatever is installed
    assert not use_fused_jo(parse_options({"speed": {"fused_jo": False}}), cpu)
    with pytest.raises(JsgsError, match="fused_jo needs a CUDA device"):
        use_fused_jo(parse_options({"speed": {"fused_jo": True}}), cpu)
    for other in ({"jpeg_mode": "exact"}, {"speed": {"compile": "inductor"}}):
        raw = {**other, "speed": {**other.get("speed", {}), "fused_jo": True}}
        with pytest.raises(JsgsError, match="fused_jo covers jpeg_mode paper and float without compile"):
            parse_options(raw)
    cuda = torch.device("cuda")
    # modes paper and float: the kernels by default (auto) and with true, on a GPU with Triton
    for mode in ("paper", "float"):
        assert use_fused_jo(parse_options({"jpeg_mode": mode}), cuda) == triton_available(), mode
        on = parse_options({"jpeg_mode": mode, "speed": {"fused_jo": True}})
        if triton_available():
            assert use_fused_jo(on, cuda), mode
        else:
            with pytest.raises(JsgsError, match="fused_jo needs Triton"):
                use_fused_jo(on, cuda)
        with pytest.raises(JsgsError, match="fused_jo needs a CUDA device"):
            use_fused_jo(on, cpu)
    # auto: the torch code where the kernels do not apply
    for raw in ({"jpeg_mode": "exact"}, {"speed": {"compile": "inductor"}}, {"speed": {"fused_jo": False}}):
        assert not use_fused_jo(parse_options(raw), cuda), raw


@pytest.mark.slow
@pytest.mark.skipif(
    not triton_available() or interpreting(), reason="needs Triton, without TRITON_INTERPRET (compiles only)"
)
@pytest.mark.parametrize(
    "name",
    ["_paper_forward", "_paper_backward", "_float_forward", "_float_backward", "_ds_delta_forward",
     "_ds_delta_backward", "_color_affine", "_color_affine:strided"],
)  # fmt: skip
def test_kernels_compile_for_sm90(name: str) -> None:
    """Each kernel compiles to a cubin for an H100 (sm_90) with the launch settings it runs with (e.g.
    ``BLOCKS_PER_PROGRAM`` / ``WARPS``), on any machine (Triton ships ptxas): what the interpreter cannot
    check (layouts, dot lowering, shared memory). Its products are float32 (no TF32), the colour maps divide
    nowhere, and it keeps its work in registers: ptxas reports at most 256 bytes of spill stores per thread
    (mode paper's backward about 100, the others none), every integer argument a plain ``i32`` here
    (:func:`test_coding_pass_spills_little_as_the_step_launches_it` compiles the coding pass as the step
    specialises it). At 32 blocks and 4 warps mode paper's backward kernel spilled about 10 KB per thread
    (an 8 KB stack frame, 32 registers) and timed slower than at 16 and 4."""
    kernel = _compile_sm90(name)
    assert kernel.asm["cubin"] and "tf32" not in kernel.asm["ptx"]  # float32 products, no TF32
    if name.startswith("_color_"):  # an affine map: products and sums, no float division at all
        assert not re.search(r"\b(div|rcp)\.[a-z.]*f32", kernel.asm["ptx"])
    spills = _ptxas_spills(kernel)
    assert max(spills) <= 256, spills


def _ptxas_spills(kernel: Any) -> list[int]:
    """The spill stores per thread (bytes) that Triton's ptxas reports for ``kernel``'s PTX on sm_90."""
    import subprocess
    import tempfile

    from triton.backends.nvidia.compiler import get_ptxas

    with tempfile.NamedTemporaryFile("w", suffix=".ptx") as f:
        f.write(kernel.asm["ptx"])
        f.flush()
        run = subprocess.run(
            [get_ptxas(90).path, "-v", "--gpu-name", "sm_90a", f.name, "-o", "/dev/null"],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
    spills = [int(b) for b in re.findall(r"(\d+) bytes spill stores", run.stderr)]
    assert spills, run.stderr
    return spills


def _step_planes(width: int, height: int, sampling: str = "4:2:0") -> list[torch.Tensor]:
    """The planes JO hands mode paper's coding pass for one ``width`` x ``height`` view (the luma plane,
    then the two chroma planes; padded, contiguous as :func:`paper_code` makes them): ``jpeg_observe``'s
    own padding and sampling, recorded with the kernels stood in by the identity."""
    seen: list[torch.Tensor] = []

    def record(planes: torch.Tensor, tables: torch.Tensor) -> torch.Tensor:
        seen.append(planes.detach().contiguous())
        return planes

    luma, chroma = (torch.tensor(t, dtype=torch.float32) for t in ijg_tables(50))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_triton_jo, "fused_jo_runs", lambda x: True)
        mp.setattr(_triton_jo, "paper_code", record)
        jpeg_observe(torch.rand(1, 3, height, width), luma, chroma, sampling, "paper", kernel="triton")
    return seen


@pytest.mark.slow
@pytest.mark.skipif(
    not triton_available() or interpreting(), reason="needs Triton, without TRITON_INTERPRET (compiles only)"
)
@pytest.mark.parametrize("name", ["_paper_forward", "_paper_backward"])
@pytest.mark.parametrize(("width", "height"), [(504, 378), (1440, 1920)])
def test_coding_pass_spills_little_as_the_step_launches_it(name: str, width: int, height: int) -> None:
    """Mode paper's coding-pass kernels compiled as a training step launches them, for sm_90: Triton
    compiles one binary per specialisation of the integer arguments (those equal to 1 become constants,
    those divisible by 16 carry the hint), and ptxas allocates registers per binary. At 32 blocks and 4
    warps the backward's binary for llff_flower's luma plane ((1, 1, 384, 504): one plane, 63 blocks a
    row) kept 32 registers and spilled 11.7 KB per thread, while those of the chroma planes, of jpeg_mouse's
    planes and of the benchmark's three-plane launch kept 255 and spilled about 1 KB: in flower's step that
    backward ran ~8x slower per block than the benchmark timed it. Each launch of the step (luma, chroma;
    llff_flower's 504 x 378 and jpeg_mouse's 1440 x 1920, 4:2:0) spills at most 256 bytes at the launch
    settings."""
    planes = _step_planes(width, height)
    assert [p.shape[1] for p in planes] == [1, 2]  # one launch for luma, one for both chroma planes
    fails = []
    for p in planes:
        _, launch = _triton_jo._grid_args(p, _triton_jo.BLOCKS_PER_PROGRAM)
        strides = p.stride() * (3 if name == "_paper_backward" else 2)  # contiguous out and gradient alike
        spills = _ptxas_spills(_compile_sm90(name, (*launch, *strides)))
        if max(spills) > 256:
            fails.append(f"{tuple(p.shape)}: {max(spills)} bytes")
    assert not fails, f"{name} spills per thread on sm_90 at {width}x{height}: {fails}"


def _compile_sm90(name: str, ints: tuple[int, ...] | None = None) -> Any:
    """Kernel ``name`` compiled for sm_90 with the launch settings it runs with (Triton ships ptxas);
    ``_color_affine`` as the forward on contiguous planes runs it, ``_color_affine:strided`` as the backward
    on a strided gradient. ``ints``: the integer arguments' values at one launch, in order, specialised as
    Triton's launcher specialises them (1: a constant; divisible by 16: that hint; pointers 16-byte aligned,
    as torch allocates); without them every integer is a plain ``i32``."""
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    name, _, variant = name.partition(":")
    fn = getattr(_triton_jo, name)
    signature = {a: "*fp32" if a.endswith("_ptr") else "i32" for a in fn.arg_names}
    constants: dict[str, Any] = {}
    attrs: dict[tuple[int, ...], list[list[Any]]] = {}
    if ints is not None:
        names = [a for a in fn.arg_names if a in signature and not a.endswith("_ptr") and a.upper() != a]
        assert len(names) == len(ints), (names, ints)
        for a in fn.arg_names:
            if a.endswith("_ptr"):
                attrs[(fn.arg_names.index(a),)] = [["tt.divisibility", 16]]
        for a, v in zip(names, ints, strict=True):
            if v == 1:
                signature[a] = "constexpr"
                constants[a] = 1
            elif v % 16 == 0:
                attrs[(fn.arg_names.index(a),)] = [["tt.divisibility", 16]]
    if name == "_color_affine":
        flat = variant != "strided"
        constexprs = {"BLOCK": _triton_jo.COLOR_BLOCK, "FLAT": flat, "OFFSET": flat}
        warps = _triton_jo.COLOR_WARPS
    else:
        prefix = "DS_" if "_ds_" in name else "FLOAT_" if "_float_" in name else ""
        bn, warps = (getattr(_triton_jo, prefix + k) for k in ("BLOCKS_PER_PROGRAM", "WARPS"))
        constexprs = {"BN": bn}
    signature |= dict.fromkeys(constexprs, "constexpr")
    src = ASTSource(fn=fn, signature=signature, constexprs=constexprs | constants, attrs=attrs)
    return _triton_jo.triton.compile(src, target=GPUTarget("cuda", 90, 32), options={"num_warps": warps})


@pytest.mark.skipif(
    not triton_available() or interpreting(), reason="needs Triton, without TRITON_INTERPRET (compiles only)"
)
@pytest.mark.parametrize("name", ["_float_forward", "_float_backward"])
def test_float_kernels_divide_as_torch_on_cuda(name: str) -> None:
    """Mode float floors quotients that sit exactly on integers (the islow shifts, the quantizer's ties
    ``(|t| + 4Q) / 8Q``): the interpreter divides as numpy (correctly rounded) and cannot show it, but
    Triton's ``/`` compiles float32 to ``div.full.f32`` (within 2 ulp), which drops a level below such a tie.
    On an H200 those kernels disagreed with the twin by up to 29 / 28 8-bit units on 2.08 % / 2.44 % of the
    pixels (1920x1440 / 504x378, q50), none at 53x37; the twin with ``x * (1 / y)`` at the quantizer
    instead of ``x / y`` reproduces that (29 / 28 units, 1.5 % / 1.9 %, none at 53x37). The kernels'
    PTX for sm_90 holds only correctly rounded float divisions."""
    ptx = _compile_sm90(name).asm["ptx"]
    assert "div.rn.f32" in ptx
    assert not re.search(r"\b(div\.full|div\.approx|rcp\.approx)\.", ptx)


# --- CUDA -----------------------------------------------------------------------------------------------


@cuda_triton
@pytest.mark.gpu
@pytest.mark.parametrize("kind", ["q10", "q50", "q95", "random", "16bit"])
def test_cuda_matches_twin(kind: str) -> None:
    x, g = _planes((2, 2, 120, 168), 11)
    tables = _tables(kind, 2, torch.Generator().manual_seed(12))
    x, g, tables = (t.cuda() for t in (x, g, tables))
    v1, g1 = _value_and_grad(paper_code, x.float(), tables.float(), g.float())
    print()
    for name, dtype in (("twin float32", torch.float32), ("twin float64", torch.float64)):
        v2, g2 = _value_and_grad(twin, x.to(dtype), tables.to(dtype), g.to(dtype))
        value, grad = _block_agreement(v1, v2, 2e-3), _block_agreement(g1, g2, 2e-3)
        print(f"fused float32 vs {name}, tables {kind}: value max {value[0]:.2e} (8-bit units), within-"
              f"tolerance blocks max {value[1]:.2e}, flipped blocks {100 * value[2]:.3f} %; gradient "
              f"{grad[0]:.2e} / {grad[1]:.2e} / {100 * grad[2]:.3f} %")  # fmt: skip
        assert value[1] <= 2e-3 and value[2] <= 0.01 and grad[1] <= 2e-3 and grad[2] <= 0.01


@cuda_triton
@pytest.mark.gpu
@pytest.mark.parametrize(
    ("mode", "height", "width", "sampling"),
    [(mode, h, w, "4:2:0") for mode in ("paper", "float") for h, w in ((1440, 1920), (378, 504), (37, 53))]
    + [
        (mode, h, w, s)
        for mode in ("paper", "float")
        for h, w in ((378, 504), (37, 53))
        for s in ("4:4:0", "4:1:1")
    ],
)
def test_cuda_jpeg_observe_matches_twin(mode: str, height: int, width: int, sampling: str) -> None:
    g = torch.Generator().manual_seed(13)
    rgb = torch.rand(1, 3, height, width, generator=g).cuda()
    w = torch.randn(1, 3, height, width, generator=g).cuda()
    luma, chroma = (torch.as_tensor(t, device="cuda").float() for t in ijg_tables(50))
    out = []
    for kernel in ("triton", "torch"):
        x = rgb.clone().requires_grad_()
        o = jpeg_observe(x, luma, chroma, sampling, mode, kernel=kernel)
        (grad,) = torch.autograd.grad((o * w).sum(), x)
        out.append((o.detach(), grad))
    d_val = 255 * (out[0][0] - out[1][0]).abs()
    d_grad = (out[0][1] - out[1][1]).abs()
    print(f"\nmode {mode}, {sampling}, {width}x{height} float32: max |fused - twin| "
          f"{float(d_val.max()):.2e} (8-bit units), pixels > 0.01: "
          f"{100 * float((d_val > 0.01).double().mean()):.4f} %; gradient max "
          f"{float(d_grad.max()):.2e} of {float(out[1][1].abs().max()):.2e}")  # fmt: skip
    assert float((d_val > 0.01).double().mean()) < 1e-3
    assert float((d_grad > 1e-3 * out[1][1].abs().max()).double().mean()) < 1e-3


@cuda_triton
@pytest.mark.gpu
@pytest.mark.parametrize(("height", "width"), [(1440, 1920), (378, 504), (37, 53)])
def test_cuda_ds_matches_twin(height: int, width: int) -> None:
    g = torch.Generator().manual_seed(16)
    obs = torch.rand(1, 3, height, width, generator=g).cuda()
    target = torch.rand(1, 3, height, width, generator=g).cuda()
    tables = torch.randint(1, 80, (1, 8, 8), generator=g).float().cuda()
    fused, twin_ = _ds_both(obs, target, tables)
    errs = [float((a - b).abs().max()) for a, b in zip(fused, twin_, strict=True)]
    print(f"\nDS {width}x{height} float32: max |fused - twin| delta {errs[0]:.2e}, losses {errs[1]:.2e}, "
          f"pixel score {errs[2]:.2e}, gradient {errs[3]:.2e} of {float(twin_[3].abs().max()):.2e}")
    torch.testing.assert_close(fused[0], twin_[0], rtol=0, atol=1e-4)
    torch.testing.assert_close(fused[1], twin_[1], rtol=1e-4, atol=1e-7)
    # psi's derivative delta / sqrt(delta^2 + eps_sm^2) amplifies float32 rounding of a Delta near 0 (1/eps_sm
    # = 1000): a bound on the largest difference and on the share of larger ones, not on every element
    diff, largest = (fused[3] - twin_[3]).abs(), float(twin_[3].abs().max())
    assert float(diff.max()) <= 1e-2 * largest
    assert float((diff > 1e-3 * largest).double().mean()) < 1e-3


@cuda_triton
@pytest.mark.gpu
def test_cuda_graph_replays_the_fused_chain() -> None:
    check_graph_replay({"jo_kernel": "triton"}, {"jo_kernel": "torch"}, "graph (fused) vs eager (twin)")
