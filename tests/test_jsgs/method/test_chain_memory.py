"""What the image terms' chain (JO, L_obs, DS and their gradient: what a CUDA graph records) keeps alive for
its backward. On CUDA its intermediates live in the graph's private pool for the run, so every image-sized
tensor kept for the backward is memory reserved beside the rest of the step (``docs/performance.md``, "Peak
memory"). These tests pin the cuts, each with the same values and gradients bit for bit."""

from __future__ import annotations

import weakref
from typing import Any

import pytest
import torch
import torch.nn.functional as F

from jsgs.jpeg import losses as losses_module
from jsgs.jpeg.losses import _MeanAbsDifference, photometric_loss, photometric_terms
from jsgs.jpeg.observe import _Clamp255, jpeg_observe
from jsgs.jpeg.sampling import replicate_pad
from jsgs.kernels import ssim
from jsgs.kernels._triton_jo import interpreting, triton_available
from jsgs.method import image_terms as image_terms_module
from jsgs.method.image_terms import terms_with_gradient
from jsgs.train.data import image_target

needs_interpreter = pytest.mark.skipif(
    not (triton_available() and interpreting()),
    reason="needs Triton and TRITON_INTERPRET=1 (the fused JO kernels on CPU tensors)",
)

SETTINGS = dict(
    mode="paper", ssim_lambda=0.2, ssim_padding="valid", ds=True, gc=True, eps_sm=1e-3, eps_loss=1e-6,
    eps_block=1e-6,
)  # fmt: skip


def _bits(t: torch.Tensor) -> torch.Tensor:
    return t.detach().contiguous().view(-1).view(torch.uint8)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_clamp_keeps_a_mask_and_is_hardtanh_bit_for_bit(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 9, 11, generator=g, dtype=dtype) * 300 - 20
    edges = [0.0, 255.0, -0.0, float("nan"), float("inf"), -float("inf"), 1e-30, 254.99]
    x.view(-1)[:8] = torch.tensor(edges)
    up = torch.randn(x.shape, generator=g, dtype=dtype)
    a, b = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
    ref, out = F.hardtanh(a, 0.0, 255.0), _Clamp255.apply(b)
    assert torch.equal(_bits(ref), _bits(out))
    (ga,) = torch.autograd.grad(ref, a, up)
    (gb,) = torch.autograd.grad(out, b, up)
    # zeros of the same sign; at NaN 0, as the CPU's vectorised hardtanh (CUDA's passes it: test_cuda_cuts.py)
    assert torch.equal(_bits(ga), _bits(gb))
    (saved,) = _Clamp255.apply(x.clone().requires_grad_(True)).grad_fn.saved_tensors
    assert saved.dtype == torch.bool and saved.shape == x.shape


def _saved_storages(root: Any) -> dict[int, tuple[int, int]]:
    """storage address -> (its bytes, the largest saved tensor's bytes on it) over every tensor the autograd
    graph below ``root`` keeps for its backward."""
    out: dict[int, tuple[int, int]] = {}
    seen, todo = set(), [root]
    while todo:
        node = todo.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        saved = list(getattr(node, "saved_tensors", None) or ())
        saved += [getattr(node, a) for a in dir(node) if a.startswith("_saved_")]
        for t in saved:
            if torch.is_tensor(t) and t.numel():
                s = t.untyped_storage()
                own = out.get(s.data_ptr(), (0, 0))[1]
                out[s.data_ptr()] = (s.nbytes(), max(own, t.numel() * t.element_size()))
        todo += [n for n, _ in node.next_functions]
    return out


@needs_interpreter
def test_jo_keeps_no_whole_ycbcr_image_and_no_float_clamp_input_for_its_backward() -> None:
    # 64x48, 4:2:0: no plane is padded, so the luma plane JO codes is a view of the colour map's output
    h, w = 48, 64
    x = torch.rand(1, h, w, 3, generator=torch.Generator().manual_seed(1)).permute(0, 3, 1, 2)
    x.requires_grad_(True)
    q = torch.full((8, 8), 12.0)
    obs = jpeg_observe(x, q, q, "4:2:0", "paper", kernel="triton", color_kernel="triton")
    saved = _saved_storages(obs.grad_fn)
    render = x.untyped_storage().data_ptr()
    # no saved tensor is a view that keeps a larger storage alive (the YCbCr image behind the luma plane)
    assert all(nbytes == used for p, (nbytes, used) in saved.items() if p != render), saved
    # what stays: the luma plane and its coded plane (4 + 4 bytes a pixel), the chroma planes and their coded
    # planes (2 + 2), the vertically up-sampled chroma (4), the clamp's mask (3): 19 B a pixel, and the two
    # tables; the float input of the clamp (12) or the whole YCbCr image (12 for the luma plane's 4) is more
    kept = sum(nbytes for p, (nbytes, _) in saved.items() if p != render)
    assert kept <= 19 * h * w + 2 * 64 * 4, kept / (h * w)


def _chain(x: torch.Tensor, image: torch.Tensor, **kwargs: Any) -> tuple[torch.Tensor, ...]:
    tables = torch.stack([torch.full((8, 8), 9.0), torch.full((8, 8), 14.0)]).to(x.dtype)
    w = (1.0, 0.3, 0.7)
    return terms_with_gradient(x, image, tables, weights=w, sampling="4:2:0", **SETTINGS, **kwargs)


def test_block_scores_are_r_p_at_each_blocks_pixel_and_no_view_of_an_image_sized_map() -> None:
    g = torch.Generator().manual_seed(3)
    image = (torch.rand(43, 61, 3, generator=g) * 255).to(torch.uint8)
    x = torch.rand(1, 3, 43, 61, generator=g)
    values, grad, r_p, _ = _chain(x.clone().requires_grad_(True), image)
    values_b, grad_b, r_b, _ = _chain(x.clone().requires_grad_(True), image, r_blocks=True)
    assert torch.equal(_bits(values), _bits(values_b)) and torch.equal(_bits(grad), _bits(grad_b))
    assert torch.equal(r_b, r_p[:, :40:8, :56:8]) and r_b.shape == (1, 5, 7)
    assert r_b.untyped_storage().nbytes() == r_b.numel() * r_b.element_size()


def test_the_target_made_from_the_image_is_freed_before_the_backward(monkeypatch: Any) -> None:
    """The chain's functions keep what their backward needs (the fused SSIM a contiguous copy of the target,
    stood in here by a loss that keeps one); the target made from the uint8 image is not kept beside the
    backward's gradients."""
    alive_at_backward: list[bool] = []
    targets: list[list[bool]] = []

    def target(image: torch.Tensor) -> torch.Tensor:
        t = image_target(image)
        state = [True]
        weakref.finalize(t.untyped_storage(), state.__setitem__, 0, False)
        targets.append(state)
        return t

    def photometric(obs: torch.Tensor, y: torch.Tensor, lam: float, **_: Any) -> torch.Tensor:
        loss = (obs - y.contiguous()).square().mean()
        loss.grad_fn.register_prehook(lambda grad: alive_at_backward.append(targets[-1][0]))
        return loss

    monkeypatch.setattr(image_terms_module, "image_target", target)
    g = torch.Generator().manual_seed(4)
    image = (torch.rand(40, 48, 3, generator=g) * 255).to(torch.uint8)
    x = torch.rand(1, 3, 40, 48, generator=g, requires_grad=True)
    _chain(x, image, photometric=photometric)
    assert alive_at_backward == [False]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("grads", [(True, False), (True, True), (False, True)])
def test_the_l1_term_keeps_no_difference_and_is_autograds_bit_for_bit(
    dtype: torch.dtype, grads: tuple[bool, bool]
) -> None:
    g = torch.Generator().manual_seed(5)
    x = torch.rand(1, 29, 37, 3, generator=g, dtype=dtype).permute(0, 3, 1, 2)  # a render's layout
    y = torch.rand(1, 3, 29, 37, generator=g, dtype=dtype)
    y[0, 1, 2, :5] = x[0, 1, 2, :5]  # ties: sgn 0
    inputs = [(x.detach().clone().requires_grad_(grads[0]), y.clone().requires_grad_(grads[1])) for _ in "ab"]
    (xa, ya), (xb, yb) = inputs
    ref, out = (xa - ya).abs().mean(), _MeanAbsDifference.apply(xb, yb)
    assert torch.equal(_bits(ref), _bits(out))
    up = torch.tensor(-0.37, dtype=dtype)
    want = torch.autograd.grad(ref, [t for t in (xa, ya) if t.requires_grad], up)
    got = torch.autograd.grad(out, [t for t in (xb, yb) if t.requires_grad], up)
    for a, b in zip(want, got, strict=True):
        assert torch.equal(_bits(a), _bits(b))
    # what it keeps for the backward are its inputs themselves, no tensor of its own
    kept = {t.untyped_storage().data_ptr() for t in _MeanAbsDifference.apply(xb, yb).grad_fn.saved_tensors}
    assert kept <= {xb.untyped_storage().data_ptr(), yb.untyped_storage().data_ptr()}


def test_l1_and_the_fused_ssim_keep_one_contiguous_copy_of_the_target(monkeypatch: Any) -> None:
    """Where the fused SSIM runs (CUDA; stood in here by the torch twin) the loss hands it the target laid out
    contiguously, the copy the kernel would make and keep, and L1 keeps that same copy: one copy for both."""
    seen: list[torch.Tensor] = []

    def ssim_spy(x: torch.Tensor, y: torch.Tensor, **kwargs: Any) -> torch.Tensor:
        seen.append(y)
        return ssim(x, y, **{**kwargs, "kernel": "torch", "fused": False})

    g = torch.Generator().manual_seed(6)
    x = torch.rand(1, 3, 24, 32, generator=g, requires_grad=True)
    y = torch.rand(1, 24, 32, 3, generator=g).permute(0, 3, 1, 2)  # a target's layout
    plain = photometric_terms(x, y, 0.2, padding="valid", ssim_kernel="torch")
    monkeypatch.setattr(losses_module, "ssim_is_fused", lambda *a: True)
    monkeypatch.setattr(losses_module, "ssim", ssim_spy)
    lean = photometric_terms(x, y, 0.2, padding="valid", ssim_kernel="torch")
    assert torch.equal(_bits(plain.loss), _bits(lean.loss))
    (g_plain,), (g_lean,) = torch.autograd.grad(plain.loss, x), torch.autograd.grad(lean.loss, x)
    assert torch.equal(_bits(g_plain), _bits(g_lean))
    (given,) = seen
    assert given.is_contiguous() and not y.is_contiguous()
    again = photometric_terms(x, y, 0.2, padding="valid", ssim_kernel="torch")  # its graph not run yet
    kept = {t.untyped_storage().data_ptr() for t in again.l1.grad_fn.saved_tensors}
    assert seen[1].untyped_storage().data_ptr() in kept


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gpu_the_chains_peak_is_within_its_shape_budget() -> None:
    """The graph's function on CUDA at 960x720 as the hook records it (fused JO, colour and DS kernels where
    Triton runs, the fused SSIM): its peak of allocated memory above its inputs is what its pool needs. The
    shape budget (docs/performance.md, "Peak memory") is 98.2 B a pixel; 5 % for the allocator's rounding."""
    from jsgs.jpeg.supervision import table_weights
    from jsgs.kernels._triton_jo import fused_jo_runs

    h, w = 720, 960
    g = torch.Generator().manual_seed(7)
    x = torch.rand(1, h, w, 3, generator=g).permute(0, 3, 1, 2).cuda()
    image = (torch.rand(2, h, w, 3, generator=g) * 255).to(torch.uint8).cuda()
    tables = torch.stack([torch.full((8, 8), 9.0), torch.full((8, 8), 14.0)]).cuda()
    kern = "triton" if fused_jo_runs(x) else "torch"
    settings = {**SETTINGS, "jo_kernel": kern, "color_kernel": kern, "ssim_kernel": "auto",
                "ds_weights": table_weights(tables[0], 1, torch.float32, x.device)}  # fmt: skip
    buf = x.clone(memory_format=torch.preserve_format).requires_grad_(True)
    r_into = torch.empty(1, h // 8, w // 8, device="cuda")
    index = torch.tensor([1], device="cuda")

    def run() -> None:
        with torch.no_grad():
            buf.copy_(x)
        terms_with_gradient(
            buf, image, tables, weights=(1.0, 0.3, 0.7), sampling="4:2:0", observation=False,
            grad_into_x=True, r_into=r_into, r_blocks=True, y_index=index, **settings,
        )  # fmt: skip

    run()  # kernels compiled and loaded, constants made
    torch.cuda.synchronize()
    start = torch.cuda.memory_allocated()
    torch.cuda.reset_peak_memory_stats()
    run()
    torch.cuda.synchronize()
    per_pixel = (torch.cuda.max_memory_allocated() - start) / (h * w)
    print(f"the chain's peak at {w}x{h}: {per_pixel:.1f} B a pixel (kernels {kern})")
    if kern == "triton":
        assert per_pixel <= 98.2 * 1.05, per_pixel


def test_with_block_scores_ds_makes_no_score_map_and_the_fused_ssims_target_is_the_only_copy(
    monkeypatch: Any,
) -> None:
    """``r_blocks``: DS is asked for r_b alone (no r(p), 8 B a pixel of temporaries at the forward's end);
    where the fused SSIM runs (stood in: ``ssim_is_fused`` true) the target made from the image is laid out
    as that kernel keeps it, the one copy L1, the SSIM and DS read, and the pick is handed to L_obs. The same
    values and gradient."""
    asked: list[bool] = []
    layouts: list[bool] = []
    handed: list[bool | None] = []
    real_supervise = image_terms_module.dct_supervision

    def supervise(*args: Any, **kwargs: Any) -> Any:
        asked.append(kwargs.get("score_map", True))
        out = real_supervise(*args, **kwargs)
        assert (out.pixel_score is None) == (not asked[-1])
        return out

    def photometric(obs: torch.Tensor, y: torch.Tensor, lam: float, **kw: Any) -> torch.Tensor:
        layouts.append(y.is_contiguous())
        handed.append(kw.get("ssim_fused"))
        # the torch twin stands in for the fused SSIM (its values up to rounding, here bit for bit)
        return photometric_terms(obs, y, lam, **{**kw, "ssim_fused": False}).loss

    g = torch.Generator().manual_seed(8)
    image = (torch.rand(40, 56, 3, generator=g) * 255).to(torch.uint8)
    x = torch.rand(1, 3, 40, 56, generator=g)
    plain = _chain(x.clone().requires_grad_(True), image, r_blocks=True)
    monkeypatch.setattr(image_terms_module, "ssim_is_fused", lambda *a: True)
    lean = _chain(x.clone().requires_grad_(True), image, r_blocks=True, supervise=supervise,
                  photometric=photometric)  # fmt: skip
    for a, b in zip(plain[:3], lean[:3], strict=True):
        assert torch.equal(_bits(a), _bits(b))
    assert asked == [False] and layouts == [True] and handed == [True]


@pytest.mark.parametrize("ssim_kernel", ["auto", "torch"])
def test_a_uint8_targets_ssim_kernel_is_picked_once_and_handed_to_l_obs(
    monkeypatch: Any, ssim_kernel: str
) -> None:
    """For a uint8 target the chain picks the SSIM kernel once (where it lays the target out for the fused
    SSIM) and hands the pick to L_obs (``photometric_loss``'s ``ssim_fused``, then ``ssim``'s ``fused``):
    the pick the loss would make on the observation; the values, gradient, r_b and observation those of
    the same target given as floats (for which the loss picks), bit for bit."""
    from jsgs.kernels import _wrapper

    calls: list[tuple[int, ...]] = []
    real = _wrapper._use_fused
    monkeypatch.setattr(_wrapper, "_use_fused", lambda x, *a: calls.append(tuple(x.shape)) or real(x, *a))
    handed: list[tuple[bool | None, bool]] = []

    def photometric(obs: torch.Tensor, y: torch.Tensor, lam: float, **kw: Any) -> torch.Tensor:
        handed.append((kw.get("ssim_fused"), real(obs, y, kw["ssim_kernel"], 11)))
        return photometric_loss(obs, y, lam, **kw)

    g = torch.Generator().manual_seed(10)
    image = (torch.rand(40, 56, 3, generator=g) * 255).to(torch.uint8)
    x = torch.rand(1, 3, 40, 56, generator=g)
    got = _chain(x.clone().requires_grad_(True), image, r_blocks=True, ssim_kernel=ssim_kernel,
                 photometric=photometric)  # fmt: skip
    assert calls == [(1, 3, 40, 56)] and handed == [(False, False)]
    calls.clear()
    target = image_target(image).permute(0, 3, 1, 2)
    want = _chain(x.clone().requires_grad_(True), target, r_blocks=True, ssim_kernel=ssim_kernel)
    assert calls == [(1, 3, 40, 56)]  # the loss's own pick
    for a, b in zip(got, want, strict=True):
        assert torch.equal(_bits(a), _bits(b))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("pad", [(0, 5, 0, 3), (1, 1, 0, 0), (0, 0, 1, 1)])
def test_the_replicate_pad_keeps_only_a_shape_and_is_replication_pad_bit_for_bit(
    dtype: torch.dtype, pad: tuple[int, int, int, int]
) -> None:
    g = torch.Generator().manual_seed(9)
    image = torch.rand(2, 11, 13, 3, generator=g, dtype=dtype).permute(0, 3, 1, 2)  # channels-last planes
    a, b = image.clone().requires_grad_(True), image.clone().requires_grad_(True)
    ref, out = F.pad(a[:, :1], pad, mode="replicate"), replicate_pad(b[:, :1], pad)
    assert torch.equal(_bits(ref), _bits(out))
    up = torch.randn(ref.shape, generator=g, dtype=dtype)
    (ga,), (gb,) = torch.autograd.grad(ref, a, up), torch.autograd.grad(out, b, up)
    assert torch.equal(_bits(ga), _bits(gb))
    assert replicate_pad(b[:, :1], pad).grad_fn.saved_tensors == ()  # the image behind the plane is not kept
