"""``method_options.gc_attribution: footprint`` against the exact probe (the reference, the default).

The footprint estimate (``jsgs.method.pooling.footprint_sums``) renders no probe: r̄ from each Gaussian's
analytic footprint over the 8x8 blocks around its mean, V_i from the RGB backward's conic gradients. On a
synthetic scene of 1,500 Gaussians (float64, the reference rasteriser) its contributor set is the probe's
exactly, its r̄ ranks the Gaussians as the probe's does, and it is exact for unoccluded Gaussians inside one
block; in the trainer's hook it renders three channels, leaves every gradient but L_fro's as the probe route
has it, and is deterministic; the default stays the probe."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest
import torch
from test_gc_every import step_at
from test_jsgs_method import make_view, new_hook

from jsgs.base.errors import JsgsError
from jsgs.kernels import PooledSums, controller_matrix, fro_loss
from jsgs.method.options import parse_options
from jsgs.method.pooling import footprint_sums, new_probe, pool_now, probe_grad_from_sums
from jsgs.train.config import TrainConfig
from jsgs.train.render_view import render_view

pytestmark = pytest.mark.usefixtures("one_torch_thread")

D = torch.float64
W, H, F = 96, 64, 80.0


def scene(n: int, seed: int = 0) -> torch.nn.ParameterDict:
    """``n`` Gaussians in front of the camera, projected RMS sizes log-uniform in ~0.3-7.5 px, overlapping."""
    g = torch.Generator().manual_seed(seed)
    z = 3.0 + 3.0 * torch.rand(n, generator=g, dtype=D)
    half = torch.tensor([W, H], dtype=D) * 1.1 / F
    xy = (torch.rand(n, 2, generator=g, dtype=D) - 0.5) * half * z[:, None]
    px = torch.exp(torch.rand(n, 3, generator=g, dtype=D) * math.log(25.0)) * 0.3
    return torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter(torch.cat([xy, z[:, None]], 1)),
            "scales": torch.nn.Parameter(torch.log(z[:, None] / F * px)),
            "quats": torch.nn.Parameter(torch.randn(n, 4, generator=g, dtype=D)),
            "opacities": torch.nn.Parameter(torch.randn(n, generator=g, dtype=D) + 0.5),
            "sh0": torch.nn.Parameter(torch.randn(n, 1, 3, generator=g, dtype=D)),
            "shN": torch.nn.Parameter(torch.zeros(n, 0, 3, dtype=D)),
        }
    )


def camera() -> tuple[torch.Tensor, torch.Tensor]:
    return torch.eye(4, dtype=D), torch.tensor([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]], dtype=D)


def block_map(seed: int = 0, width: int = W, height: int = H) -> torch.Tensor:
    """[1, H, W] block-constant scores (skewed, as real ones are), 0 on the rows/columns without a block."""
    g = torch.Generator().manual_seed(100 + seed)
    nby, nbx = height // 8, width // 8
    b = torch.rand(1, nby, nbx, generator=g, dtype=D) ** 3
    pix = b[:, :, None, :, None].expand(1, nby, 8, nbx, 8).reshape(1, nby * 8, nbx * 8)
    return torch.nn.functional.pad(pix, (0, width - nbx * 8, 0, height - nby * 8))


def both(splats: torch.nn.ParameterDict, r: torch.Tensor) -> tuple[PooledSums, PooledSums, dict[str, Any]]:
    """The exact probe's pooled sums and the footprint's (V_i from an RGB loss's conic gradient)."""
    viewmat, K = camera()
    probe = new_probe(splats["means"].shape[0], splats["means"])
    cfg = TrainConfig.from_preset("paper")
    out = render_view(splats, viewmat[None], K[None], W, H, 0, cfg, "torch", probe)
    exact = pool_now(out.info, r)
    info = out.info
    info["conics"].retain_grad()
    (out.rgb - 0.3).abs().sum().backward()
    contributes = (info["conics"].grad != 0).any(-1)
    est = footprint_sums(r, info["means2d"].detach(), info["conics"], info["opacities"], contributes)
    return exact, est, info


def ranks(x: torch.Tensor) -> torch.Tensor:
    return x.argsort().argsort().to(D)


def corr(a: torch.Tensor, b: torch.Tensor) -> float:
    return torch.corrcoef(torch.stack([a, b]))[0, 1].item()


def test_footprint_agrees_with_the_probe_on_a_synthetic_scene() -> None:
    splats = scene(1500)
    exact, est, _ = both(splats, block_map())
    vis = exact.contributors[0]
    assert 1300 < int(vis.sum()) < 1500  # some Gaussians occluded or off-screen
    assert torch.equal(est.contributors[0], vis)  # V_i: the same set
    r_exact, r_est = exact.rbar()[0][vis], est.rbar()[0][vis]
    # measured 0.950 / 0.949 (0.85 / 0.79 for r at the mean's pixel alone)
    assert corr(r_est, r_exact) > 0.92 and corr(ranks(r_est), ranks(r_exact)) > 0.92
    # the Gaussians L_fro acts on (s̄ <= τ_s: exp(−s̄/τ_s) >= 1/e): measured 0.992
    viewmat, K = camera()
    A = controller_matrix(splats["means"], splats["quats"], viewmat, K, W, H)
    ft = {
        k: fro_loss(s.rbar()[0], vis, splats["opacities"], splats["scales"], A)
        for k, s in (("exact", exact), ("est", est))
    }
    small = vis & (ft["exact"].sbar <= 1.0)
    assert int(small.sum()) > 100 and corr(est.rbar()[0][small], exact.rbar()[0][small]) > 0.97
    # the per-Gaussian L_fro terms: the 10 % largest mostly the same Gaussians (measured 93 %); L_fro
    # within 5 % (measured −2.4 %)
    k = int(vis.sum()) // 10
    top = {n: set(f.weight.topk(k).indices.tolist()) for n, f in ft.items()}
    assert len(top["exact"] & top["est"]) > 0.85 * k
    assert ft["est"].loss.item() == pytest.approx(ft["exact"].loss.item(), rel=0.05)
    assert ft["est"].stats.visible == ft["exact"].stats.visible


def test_footprint_is_exact_for_an_unoccluded_gaussian_inside_one_block() -> None:
    """Small separate Gaussians (projected σ ~ 0.5-0.8 px) at block centres: every contributing pixel lies in
    the block, so the probe pools that block's score; the footprint too, but for its Gaussian tail beyond the
    block (< 1e-4 of its mass at 4 px; the rasteriser cuts it where α < 1/255)."""
    viewmat, K = camera()
    n = 12
    bx, by = torch.arange(n) % 6 * 2 + 1, torch.arange(n) // 6 * 3 + 2  # blocks apart from each other
    z = torch.full((n,), 4.0, dtype=D)
    u = (bx.to(D) * 8 + 4 - W / 2) / F * z
    v = (by.to(D) * 8 + 4 - H / 2) / F * z
    g = torch.Generator().manual_seed(1)
    splats = scene(n)
    with torch.no_grad():
        splats["means"].copy_(torch.stack([u, v, z], 1))
        px = 0.4 + 0.4 * torch.rand(n, 3, generator=g, dtype=D)
        splats["scales"].copy_(torch.log(z[:, None] / F * px))
    r = block_map(3)
    exact, est, _ = both(splats, r)
    assert bool(exact.contributors.all()) and torch.equal(est.contributors, exact.contributors)
    want = r[0, by * 8, bx * 8]
    torch.testing.assert_close(exact.rbar()[0], want, rtol=1e-5, atol=0.0)
    torch.testing.assert_close(est.rbar()[0], want, rtol=0.0, atol=1e-4 * r.max().item())


def test_probe_grad_from_sums_is_the_inverse_of_reading_a_probe() -> None:
    from jsgs.kernels import sums_from_probe_grad

    exact, est, info = both(scene(300), block_map())
    o = info["opacities"].detach()
    for s in (exact, est):
        back = sums_from_probe_grad(probe_grad_from_sums(s, o, 0.05), o, 0.05)
        for name in ("s_r", "s_1", "nu"):
            torch.testing.assert_close(getattr(back, name), getattr(s, name), rtol=1e-12, atol=1e-12)


def test_in_the_hook_footprint_renders_no_probe_and_changes_only_the_controllers_gradient() -> None:
    view = make_view(50, "4:2:0")
    probe = step_at(new_hook(view), 0)
    foot = step_at(new_hook(view, gc_attribution="footprint"), 0)
    off = step_at(new_hook(view, gc=False), 0)
    assert probe["probe"] and not foot["probe"]
    assert foot["stats"]["gc_visible"] == probe["stats"]["gc_visible"]  # V_i: the same set
    assert foot["terms"]["fro"] > 0 and foot["stats"]["gc_damped"] > 0
    assert foot["terms"]["fro"] == pytest.approx(probe["terms"]["fro"], rel=0.5)
    for name, g in foot["grads"].items():
        if name in ("opacities", "scales"):  # L_fro's: where the two attributions differ
            assert not torch.equal(g, off["grads"][name])
            # the controller's own part, footprint against probe
            d_foot, d_probe = g - off["grads"][name], probe["grads"][name] - off["grads"][name]
            assert corr(d_foot.flatten(), d_probe.flatten()) > 0.9
        else:  # the same rasterisation of RGB, without the probe's two (zero) channels
            torch.testing.assert_close(g, off["grads"][name], rtol=0, atol=0)
            torch.testing.assert_close(g, probe["grads"][name], rtol=1e-12, atol=1e-14)


def test_footprint_is_deterministic_and_the_default_is_the_probe() -> None:
    view = make_view(50, "4:2:0")
    a = step_at(new_hook(view, gc_attribution="footprint"), 0)
    b = step_at(new_hook(view, gc_attribution="footprint"), 0)
    assert a["terms"] == b["terms"] and a["stats"] == b["stats"]
    assert all(torch.equal(a["grads"][n], b["grads"][n]) for n in a["grads"])
    assert parse_options({}).gc_attribution == "probe"
    default, probe = step_at(new_hook(view), 0), step_at(new_hook(view, gc_attribution="probe"), 0)
    assert default["probe"] and default["terms"] == probe["terms"] and default["stats"] == probe["stats"]
    assert all(torch.equal(default["grads"][n], probe["grads"][n]) for n in default["grads"])


def test_footprint_with_lambda_fro_zero_logs_the_term_only() -> None:
    view = make_view(50, "4:2:0")
    hook = new_hook(view, gc_attribution="footprint", lambda_fro=0.0)
    assert hook.describe()["gc_route"] == "deferred"
    foot = step_at(hook, 0)
    off = step_at(new_hook(view, gc=False), 0)
    assert foot["terms"]["fro"] > 0 and foot["stats"]["gc_visible"] > 0
    assert all(torch.equal(foot["grads"][n], off["grads"][n]) for n in off["grads"])


def test_gc_attribution_is_validated() -> None:
    assert parse_options({"gc_attribution": "footprint"}).gc_attribution == "footprint"
    with pytest.raises(JsgsError, match="method_options.gc_attribution") as e:
        parse_options({"gc_attribution": "tiles"})
    assert "\n" not in str(e.value)
    with pytest.raises(JsgsError, match='gc_attribution footprint .* needs gc_pooling "deferred"') as e:
        parse_options({"gc_attribution": "footprint", "gc_pooling": "now"})
    assert "\n" not in str(e.value)


def test_a_short_run_keeps_most_of_the_controllers_effect(tmp_path: Path) -> None:
    """30 steps on the synthetic JPEG scene without densification (the Gaussians stay matched one to one),
    λ_fro = 1 so that the controller's effect is well above rounding: with the footprint the opacities end
    within 0.1 and the scales within 0.5 of the distance from the probe's that the run without the controller
    ends at (measured 0.03 and 0.33), and the run's config.json records the attribution."""
    from _train_scene import short_jsgs_runs

    variants = {"probe": {}, "footprint": {"gc_attribution": "footprint"}, "off": {"gc": False}}
    runs = short_jsgs_runs(tmp_path, variants)
    exact, cheap, off = (runs[n][1] for n in ("probe", "footprint", "off"))
    for n, bound in (("opacities", 0.1), ("scales", 0.5)):
        d_off = (off[n] - exact[n]).norm().item()
        assert d_off > 1e-3, n  # the controller did something
        assert (cheap[n] - exact[n]).norm().item() < bound * d_off, n
    stats = {n: runs[n][0]["train"]["stats"] for n in ("probe", "footprint")}
    assert stats["footprint"]["gc_visible"] == pytest.approx(stats["probe"]["gc_visible"], rel=0.02)
    assert stats["footprint"]["gc_damped"] == pytest.approx(stats["probe"]["gc_damped"], rel=0.1)
    for name in ("probe", "footprint"):
        config = json.loads((tmp_path / name / "config.json").read_text())
        assert config["derived"]["method"]["gc_attribution"] == name  # the resolved value


def test_footprint_with_gc_every_runs_on_the_controllers_steps_only() -> None:
    view = make_view(50, "4:2:0")
    on = step_at(new_hook(view, gc_attribution="footprint", gc_every=4), 4)
    exact = step_at(new_hook(view, gc_attribution="footprint", lambda_fro=0.05 * 4), 4)
    assert not on["probe"] and on["weights"]["fro"] == 0.2 and on["stats"]["gc_damped"] > 0
    assert on["terms"] == exact["terms"] and on["stats"] == exact["stats"]
    assert all(torch.equal(on["grads"][n], exact["grads"][n]) for n in on["grads"])
    between = step_at(new_hook(view, gc_attribution="footprint", gc_every=4), 5)
    off = step_at(new_hook(view, gc=False), 5)
    assert between["terms"]["fro"] == 0.0
    assert all(torch.equal(between["grads"][n], off["grads"][n]) for n in off["grads"])
