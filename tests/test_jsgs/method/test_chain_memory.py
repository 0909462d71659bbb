"""What the image terms' chain (JO, L_obs, DS and their gradient: what a CUDA graph records) keeps alive for
its backward. On CUDA its intermediates live in the graph's private pool for the run, so every image-sized
tensor kept for the backward is memory reserved beside the rest of the step (``docs/performance.md``, "Peak
memory"). These tests pin the cuts, each with the same values and gradients bit for bit."""

from __future__ import annotations

import weakref
from typing import Any

import torch

from jsgs.method import image_terms as image_terms_module
from jsgs.method.image_terms import terms_with_gradient
from jsgs.train.data import image_target

SETTINGS = dict(
    mode="paper", ssim_lambda=0.2, ssim_padding="valid", ds=True, gc=True, eps_sm=1e-3, eps_loss=1e-6,
    eps_block=1e-6,
)  # fmt: skip


def _bits(t: torch.Tensor) -> torch.Tensor:
    return t.detach().contiguous().view(-1).view(torch.uint8)


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
