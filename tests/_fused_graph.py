"""What the fused Triton kernels' tests (``tests/test_jsgs/kernels/test_triton_jo.py`` and
``test_triton_color.py``) share: JO's value and gradient on one random batch under several kernel settings
(:func:`observe_with_gradients`), and the CUDA-graph check of their GPU tests (:func:`check_graph_replay`):
JO → L_obs → DS and the gradient of their weighted sum, recorded as one graph with the kernels under test
and replayed for a second view, against the same kernels run eagerly (the replay computes what they
compute) and against the reference kernels run eagerly (within float32 rounding). Prints the largest
differences."""

from __future__ import annotations

from typing import Any

import torch

#: the chain's settings (mode paper, DS and GC on) and weights (λ_obs, λ_low, λ_mid)
SETTINGS: dict[str, Any] = dict(
    mode="paper", ssim_lambda=0.2, ssim_padding="valid", ds=True, gc=True, eps_sm=1e-3, eps_loss=1e-6,
    eps_block=1e-6,
)  # fmt: skip
WEIGHTS = (0.2, 0.02, 0.03)


def observe_with_gradients(
    seed: int, height: int, width: int, sampling: str, mode: str, variants: list[dict[str, str]]
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """``jpeg_observe`` of one random float64 batch of two views (values slightly outside [0, 1], each view
    with its own tables) and the gradient of a random weighting of it, once per ``variants`` entry (its
    ``kernel`` / ``color_kernel`` keywords): ``(observation, gradient)`` each."""
    from jsgs.jpeg.observe import jpeg_observe

    g = torch.Generator().manual_seed(seed)
    rgb = torch.rand(2, 3, height, width, generator=g, dtype=torch.float64) * 1.1 - 0.05
    w = torch.randn(2, 3, height, width, generator=g, dtype=torch.float64)
    luma = torch.randint(1, 80, (2, 8, 8), generator=g).double()
    chroma = torch.randint(1, 120, (2, 8, 8), generator=g).double()
    out = []
    for kernels in variants:
        x = rgb.clone().requires_grad_()
        o = jpeg_observe(x, luma, chroma, sampling, mode, **kernels)  # type: ignore[arg-type]
        (grad,) = torch.autograd.grad((o * w).sum(), x)
        out.append((o.detach(), grad))
    return out


def check_graph_replay(kernels: dict[str, str], reference: dict[str, str], label: str) -> None:
    """Record the chain with ``kernels`` (``jsgs.method.image_terms``'s ``jo_kernel`` / ``color_kernel``) in
    a :class:`jsgs.method.graphed.GraphedImageTerms` and replay it: equal to the same kernels run eagerly
    (values 1e-6 relative, the observation within 1e-6, the gradient 1e-5 relative), and to the
    ``reference`` kernels run eagerly (values 1e-4 relative; under 0.1 % of the observation's values more
    than 0.01 8-bit units apart, and of the gradient's more than 1e-3 of its largest value). ``label``
    names the comparison in the printed line. Needs CUDA."""
    from jsgs.method.graphed import GraphedImageTerms
    from jsgs.method.image_terms import terms_with_gradient

    graphed = GraphedImageTerms(weights=WEIGHTS, **SETTINGS, **kernels)
    for seed in (14, 15):  # the second view replays the graph recorded for the first
        g = torch.Generator().manual_seed(seed)
        x = torch.rand(1, 3, 378, 504, generator=g).cuda().requires_grad_()
        y = torch.rand(1, 3, 378, 504, generator=g).cuda()
        tables = torch.randint(1, 100, (2, 8, 8), generator=g).float().cuda()
        got = graphed(x, y, tables, "4:2:0", observation=True)
        (grad_graph,) = torch.autograd.grad(got.weighted, x)
        # the same kernels eagerly: the replay computes what they compute
        same, grad_same, _, obs_same = terms_with_gradient(
            x, y, tables, weights=WEIGHTS, sampling="4:2:0", **SETTINGS, **kernels
        )
        torch.testing.assert_close(got.values, same[1:], rtol=1e-6, atol=1e-7)
        torch.testing.assert_close(got.obs, obs_same, rtol=0, atol=1e-6)
        torch.testing.assert_close(grad_graph, grad_same, rtol=1e-5, atol=1e-8)
        values, grad_ref, _, obs = terms_with_gradient(
            x, y, tables, weights=WEIGHTS, sampling="4:2:0", **SETTINGS, **reference
        )
        print(f"\n{label}, view {seed}: terms {got.values.tolist()} vs {values[1:].tolist()}; max |obs diff| "
              f"{float((got.obs - obs).abs().max()) * 255:.2e} (8-bit units), max |grad diff| "
              f"{float((grad_graph - grad_ref).abs().max()):.2e}")  # fmt: skip
        torch.testing.assert_close(got.values, values[1:], rtol=1e-4, atol=1e-6)
        assert float(((got.obs - obs).abs() * 255 > 0.01).double().mean()) < 1e-3
        off = (grad_graph - grad_ref).abs() > 1e-3 * grad_ref.abs().max()
        assert float(off.double().mean()) < 1e-3
