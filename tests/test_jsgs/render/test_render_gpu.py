"""Parity of the reference rasterizer with gsplat's CUDA rasterizer (images, meta, gradients, pooled sums).

Needs CUDA (gsplat JIT-compiles its kernels on first use, which takes minutes); skipped without it.
"""

from __future__ import annotations

import math

import pytest
import torch

from jsgs.method.pooling import (
    DeferredProbeMap,
    footprint_sums,
    new_probe,
    pool_direct,
    pool_from_grad,
    pool_now,
    probe_objective,
)
from jsgs.render import rasterize

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(
        not torch.cuda.is_available(), reason="needs CUDA (gsplat's kernels do not run on CPU)"
    ),
]

W, H = 150, 100  # partial tiles on both axes


def _scene(n: int = 3000, seed: int = 0, opacity: tuple[float, float] = (0.05, 0.95)) -> dict:
    g = torch.Generator().manual_seed(seed)
    dev = torch.device("cuda")
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([4.0, 3.0, 2.0]) + torch.tensor([0, 0, 4.0])
    lo, hi = opacity
    s = dict(
        means=means,
        quats=torch.randn(n, 4, generator=g),
        scales=torch.exp(torch.randn(n, 3, generator=g) * 0.5 - 3.2),
        opacities=torch.rand(n, generator=g) * (hi - lo) + lo,
        sh=torch.randn(n, 16, 3, generator=g) * 0.3,
        bg=torch.rand(2, 3, generator=g),
    )
    vm = torch.eye(4).repeat(2, 1, 1)
    a = 0.1
    vm[1, :3, :3] = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    vm[1, :3, 3] = torch.tensor([0.2, -0.1, 0.3])
    K = torch.tensor([[120.0, 0, W / 2], [0, 120.0, H / 2], [0, 0, 1]]).repeat(2, 1, 1)
    s.update(viewmats=vm, Ks=K)
    return {k: v.to(dev) for k, v in s.items()}


_KEYS = ("means", "quats", "scales", "opacities", "sh")


def _run(
    s: dict, backend: str, seed: int = 1, probe: bool = False, r: torch.Tensor | None = None, mode: str = "",
    distortion: torch.Tensor | None = None, deferred: bool = False, unit: bool = False,
):
    """Render with ``backend`` (absgrad on), back-propagate a fixed random loss; images, info, gradients.
    With ``probe``, the loss has the probe objective of ``r`` (``deferred``: its map made in the backward,
    ``rasterize(..., extra_upstream=DeferredProbeMap)``, as the trainer's deferred controller does; ``unit``:
    the map handed on as made, the loss's backward starting from 1 as the trainer's does)."""
    lv = {k: s[k].clone().requires_grad_(True) for k in _KEYS}
    extra = new_probe(s["means"].shape[0], s["means"], n_cameras=s["viewmats"].shape[0]) if probe else None
    make = DeferredProbeMap(1.0) if deferred else None
    img, alpha, info = rasterize(
        lv["means"], lv["quats"], lv["scales"], lv["opacities"], lv["sh"], s["viewmats"], s["Ks"], W, H,
        sh_degree=3, backgrounds=s["bg"], backend=backend, extra=extra, absgrad=True,
        render_mode=mode or "RGB", distortion=distortion, extra_upstream=make,
    )  # fmt: skip
    info["means2d"].retain_grad()
    info["conics"].retain_grad()  # the footprint attribution's V_i
    g = torch.Generator(device="cuda").manual_seed(seed)
    wi = torch.randn(img.shape, generator=g, device="cuda")
    wa = torch.randn(alpha.shape, generator=g, device="cuda")
    loss = (img * wi).sum() + (alpha * wa).sum()
    if make is not None:
        make.r, make.unit_upstream = r, unit
        loss = loss + info["extra_objective"]
    elif probe:
        loss = loss + probe_objective(info, r)
    loss.backward()
    grads = {k: v.grad for k, v in lv.items()}
    grads["means2d"] = info["means2d"].grad
    grads["means2d.absgrad"] = info["means2d"].absgrad
    return img.detach(), alpha.detach(), info, grads


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return ((a - b).norm() / b.norm().clamp_min(1e-30)).item()


SCENES = {
    "mixed": dict(opacity=(0.05, 0.95)),
    "init": dict(opacity=(0.1, 0.1)),  # gsplat's initial opacity: deep stacks before saturation
    "opaque": dict(opacity=(0.9, 1.0)),  # early stops and the 0.999 clamp
}


@pytest.mark.parametrize("kind", list(SCENES))
def test_reference_matches_gsplat(kind: str) -> None:
    s = _scene(**SCENES[kind])
    mode = "RGB+ED" if kind == "mixed" else "RGB"
    ri, ra, rinfo, rg = _run(s, "torch", mode=mode)
    gi, ga, ginfo, gg = _run(s, "gsplat", mode=mode)
    report = {}
    mismatch = (rinfo["radii"] != ginfo["radii"]).any(-1).float().mean().item()
    report["radii mismatch fraction"] = mismatch
    vis = (ginfo["radii"] > 0).all(-1) & (rinfo["radii"] > 0).all(-1)
    for k in ("means2d", "depths", "conics"):
        report[k] = _rel(rinfo[k][vis].detach(), ginfo[k][vis].detach())
    report["image max abs"] = (ri - gi).abs().max().item()
    report["image mean abs"] = (ri - gi).abs().mean().item()
    report["alpha max abs"] = (ra - ga).abs().max().item()
    for k, v in gg.items():
        report[f"grad {k} rel L2"] = _rel(rg[k], v)
    print(f"\nreference vs gsplat ({kind}, {mode}):", {k: f"{v:.2e}" for k, v in report.items()})
    assert mismatch < 1e-3
    for k in ("means2d", "depths", "conics"):
        assert report[k] < 1e-5, k
    assert report["image mean abs"] < 1e-4 and report["image max abs"] < 5e-3
    assert report["alpha max abs"] < 5e-3
    for k in gg:
        assert report[f"grad {k} rel L2"] < 1e-3, k


@pytest.mark.parametrize("mode", ["RGB", "RGB+ED"])
def test_distorted_cameras_on_gsplat_match_the_reference(mode: str) -> None:
    """A distorted camera on CUDA (the reference's projection, gsplat's compositing) renders the reference's
    image with its gradients; with the GC probe channels too."""
    s = _scene(seed=5)
    dist = torch.tensor([[-0.12, 0.03, 0.002, -0.001], [0.08, 0.0, 0.0, 0.0]], device="cuda")
    r = torch.rand(2, H, W, device="cuda", generator=torch.Generator(device="cuda").manual_seed(1))
    ri, ra, rinfo, rg = _run(s, "torch", mode=mode, distortion=dist, probe=True, r=r)
    gi, ga, ginfo, gg = _run(s, "gsplat", mode=mode, distortion=dist, probe=True, r=r)
    pinhole = _run(s, "gsplat", mode=mode)[0]
    report = {"image max abs": (ri - gi).abs().max().item(), "alpha max abs": (ra - ga).abs().max().item(),
              "extra rel L2": _rel(ginfo["extra"], rinfo["extra"]),
              "distortion moved the image": (pinhole - gi).abs().mean().item()}  # fmt: skip
    for k, v in gg.items():
        report[f"grad {k} rel L2"] = _rel(rg[k], v)
    print(f"\ndistorted reference vs gsplat ({mode}):", {k: f"{v:.2e}" for k, v in report.items()})
    assert torch.equal(rinfo["radii"], ginfo["radii"])
    assert report["distortion moved the image"] > 1e-2
    assert report["image max abs"] < 5e-3 and report["alpha max abs"] < 5e-3 and report["extra rel L2"] < 1e-4
    for k in gg:
        assert report[f"grad {k} rel L2"] < 1e-3, k


def test_pooled_sums_gsplat_probe_match_reference() -> None:
    s = _scene(seed=2)
    r = torch.rand(2, H, W, device="cuda", generator=torch.Generator(device="cuda").manual_seed(0))
    _, _, ginfo, _ = _run(s, "gsplat", probe=True, r=r)
    via_grad = pool_from_grad(ginfo)
    probe = new_probe(s["means"].shape[0], s["means"], n_cameras=2)
    ginfo_now = rasterize(
        s["means"], s["quats"], s["scales"], s["opacities"], s["sh"], s["viewmats"], s["Ks"], W, H,
        sh_degree=3, backgrounds=s["bg"], backend="gsplat", extra=probe,
    )[2]  # fmt: skip
    now = pool_now(ginfo_now, r)
    direct = pool_direct(s["means"], s["quats"], s["scales"], s["opacities"], s["viewmats"], s["Ks"], W, H, r)
    both = direct.contributors & via_grad.contributors
    mass = direct.nu[both]
    report = {
        "contributor sets differ": (direct.contributors != via_grad.contributors).float().mean().item(),
        "nu rel L2": _rel(via_grad.nu[both], direct.nu[both]),
        "rbar rel L2": _rel(via_grad.rbar()[both], direct.rbar()[both]),
        "rbar median rel": ((via_grad.rbar() - direct.rbar()).abs()[both] / direct.rbar()[both])
        .median()
        .item(),
        "rbar max abs (nu>1)": (via_grad.rbar() - direct.rbar())[both & (direct.nu > 1)].abs().max().item(),
        "pool_now vs grad rbar rel L2": _rel(now.rbar()[both], via_grad.rbar()[both]),
    }
    print("\ngsplat probe vs reference direct:", {k: f"{v:.2e}" for k, v in report.items()})
    assert mass.numel() > 100
    assert report["contributor sets differ"] < 1e-3
    assert report["nu rel L2"] < 1e-4 and report["rbar rel L2"] < 1e-4
    assert report["pool_now vs grad rbar rel L2"] < 1e-6


def _block_scores(n_cameras: int, seed: int = 0) -> torch.Tensor:
    """[C, H, W] block-constant scores, 0 on the rows and columns without a block (as DS makes them)."""
    nby, nbx = H // 8, W // 8
    g = torch.Generator(device="cuda").manual_seed(seed)
    b = torch.rand(n_cameras, nby, nbx, generator=g, device="cuda") ** 3
    pix = b.repeat_interleave(8, dim=1).repeat_interleave(8, dim=2)
    return torch.nn.functional.pad(pix, (0, W - nbx * 8, 0, H - nby * 8))


def test_footprint_attribution_on_gsplat_matches_its_probe() -> None:
    """``gc_attribution: footprint`` on gsplat, the same code as on the CPU: V_i from the conic gradients of
    gsplat's backward is the probe's contributor set, and r̄ ranks the Gaussians as the probe's does (the CPU
    reference's figures: tests/test_jsgs/method/test_gc_attribution.py)."""
    s = _scene(seed=4)
    r = _block_scores(2)
    _, _, info, _ = _run(s, "gsplat", probe=True, r=r)
    exact = pool_from_grad(info)
    on = (info["conics"].grad != 0).any(-1)
    est = footprint_sums(r, info["means2d"].detach(), info["conics"], info["opacities"], on)
    vis = exact.contributors
    assert int(vis.sum()) > 1000
    assert (est.contributors != vis).float().mean().item() < 1e-3
    both = vis & est.contributors
    a, b = est.rbar()[both].double(), exact.rbar()[both].double()
    ranks = [x.argsort().argsort().double() for x in (a, b)]
    print(
        "\nfootprint vs probe on gsplat: pearson", torch.corrcoef(torch.stack([a, b]))[0, 1].item(),
        "spearman", torch.corrcoef(torch.stack(ranks))[0, 1].item(),
    )  # fmt: skip
    assert torch.corrcoef(torch.stack([a, b]))[0, 1].item() > 0.9  # the reference: 0.987
    assert torch.corrcoef(torch.stack(ranks))[0, 1].item() > 0.9


def test_gsplat_probe_leaves_gradients_alone() -> None:
    s = _scene(seed=3)
    r = torch.rand(2, H, W, device="cuda")
    base = [_run(s, "gsplat") for _ in range(2)]
    with_probe = _run(s, "gsplat", probe=True, r=r)
    assert torch.equal(base[0][0], with_probe[0])
    for k, v in base[0][3].items():
        noise = (base[1][3][k] - v).abs().max().item()  # atomics make gsplat's backward order-dependent
        diff = (with_probe[3][k] - v).abs().max().item()
        assert diff <= max(4 * noise, 1e-6 * v.abs().max().item()), (k, diff, noise)


def _assert_gradients_within_noise(base: list, info: dict, grads: dict) -> None:
    """Every parameter's and the probe's gradient of a run (``info``, ``grads``) within 4x the difference of
    two baseline runs (``base``, each ``_run``'s output): atomics make gsplat's backward order-dependent."""
    for k, v in {**base[0][3], "probe": base[0][2]["extra_features"].grad}.items():
        other = base[1][3][k] if k != "probe" else base[1][2]["extra_features"].grad
        got = grads[k] if k != "probe" else info["extra_features"].grad
        noise = (other - v).abs().max().item()
        diff = (got - v).abs().max().item()
        assert diff <= max(4 * noise, 1e-6 * v.abs().max().item()), (k, diff, noise)


def test_gsplat_probe_map_made_in_the_backward_matches_the_objective(monkeypatch: pytest.MonkeyPatch) -> None:
    """The probe's map made in the backward on gsplat (``extra_upstream``, as the trainer's deferred
    controller renders): the same image, its colours a contiguous copy; gsplat's five-channel image freed
    after the render (no ``info["extra"]``), where the probe objective's render keeps it; the probe's and
    every parameter's gradient within gsplat's run-to-run noise of the probe objective's."""
    import weakref

    import gsplat

    s = _scene(seed=5)
    r = torch.rand(2, H, W, device="cuda")
    made: list = []
    real = gsplat.rasterization

    def recording(*args: object, **kwargs: object) -> object:
        out = real(*args, **kwargs)
        made.append(weakref.ref(out[0]))
        return out

    monkeypatch.setattr(gsplat, "rasterization", recording)
    base = [_run(s, "gsplat", probe=True, r=r) for _ in range(2)]
    assert made[-1]() is not None and base[1][2]["extra"].shape == (2, H, W, 2)
    img, _, info, grads = _run(s, "gsplat", probe=True, r=r, deferred=True)
    assert made[-1]() is None and "extra" not in info and img.is_contiguous()
    assert torch.equal(img, base[0][0])
    _assert_gradients_within_noise(base, info, grads)


def test_gsplat_probe_map_handed_on_as_made_and_the_objective_a_view_of_a_kept_zero() -> None:
    """The deferred probe as the trainer runs it on gsplat: the objective a view of one zero kept from render
    to render (no new zero, no copy), which stays 0 through the backwards; with the upstream 1 the map is
    handed on as made (``DeferredProbeMap.unit_upstream``): the probe's and every parameter's gradient within
    gsplat's run-to-run noise of the map multiplied by the upstream."""
    from jsgs.base.kept_zeros import kept_zeros

    s = _scene(seed=6)
    r = torch.rand(2, H, W, device="cuda")
    base = [_run(s, "gsplat", probe=True, r=r, deferred=True) for _ in range(2)]
    img, _, info, grads = _run(s, "gsplat", probe=True, r=r, deferred=True, unit=True)
    objectives = [i["extra_objective"] for i in (base[0][2], base[1][2], info)]
    zero = kept_zeros(objectives[0])
    assert all(o.data_ptr() == zero.data_ptr() and o.item() == 0.0 for o in objectives)
    assert zero.item() == 0.0 and torch.equal(img, base[0][0])
    _assert_gradients_within_noise(base, info, grads)


def test_gsplat_extra_channels_match_reference() -> None:
    """Generic extra channels on gsplat: ones render the alpha, and the channels equal the reference's."""
    s = _scene(seed=4)
    N = s["means"].shape[0]
    feats = torch.rand(N, 3, device="cuda", generator=torch.Generator(device="cuda").manual_seed(2))
    feats[:, 0] = 1.0
    outs = {}
    for backend in ("gsplat", "torch"):
        outs[backend] = rasterize(
            s["means"], s["quats"], s["scales"], s["opacities"], s["sh"], s["viewmats"], s["Ks"], W, H,
            sh_degree=3, backgrounds=s["bg"], backend=backend, extra=feats,
        )  # fmt: skip
    _, alpha, info = outs["gsplat"]
    assert info["extra"].shape == (2, H, W, 3)
    assert (info["extra"][..., :1] - alpha).abs().max().item() < 1e-5
    assert _rel(info["extra"], outs["torch"][2]["extra"]) < 1e-4
