"""The reference rasterizer against the per-pixel brute force (values and gradients, float64), gsplat's own
torch formulas, its generic extra channels, and the Gaussian Controller's pooled sums made through them."""

from __future__ import annotations

import math

import pytest
import torch

from jsgs.method.pooling import new_probe, pool_direct, pool_from_grad, pool_now, probe_objective
from jsgs.render import project_gaussians, rasterize, spherical_harmonics
from jsgs.render import reference as ref
from jsgs.render.bruteforce import _sh_rgb, render_bruteforce

F64 = torch.float64
W, H = 40, 28  # 3 x 2 tiles, the last column and row partial


def _cameras(dtype: torch.dtype = F64) -> tuple[torch.Tensor, torch.Tensor]:
    """Two cameras: identity, and one turned 0.15 rad about y and shifted; f = 30 px, centred."""
    vm = torch.eye(4, dtype=dtype).repeat(2, 1, 1)
    a = 0.15
    vm[1, :3, :3] = torch.tensor(
        [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=dtype
    )
    vm[1, :3, 3] = torch.tensor([-0.3, 0.1, 0.2], dtype=dtype)
    K = torch.tensor([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]], dtype=dtype).repeat(2, 1, 1)
    return vm, K


def _scene(dtype: torch.dtype = F64, seed: int = 0) -> dict[str, torch.Tensor]:
    """A dozen Gaussians that exercise every rule of the rasterizer in camera 0:

    0-3 an opaque stack on one line of sight (the pixel stops after the 2nd: T = 0.01² <= 1e-4);
    4 opacity 0.9999 centred on a pixel centre (α hits the 0.999 clamp); 5 faint (α < 1/255 skipped at its
    rim); 6 behind the camera, 7 opacity < 1/255, 8 off-screen, 9 nearer than the near plane (all culled);
    10 beyond the FOV clamp yet overlapping the image (J evaluated at the clamped direction); 11-13 random.
    """
    g = torch.Generator().manual_seed(seed)
    z4 = 3.0
    means = torch.tensor(
        [
            [0.1, 0.05, 2.0], [0.1, 0.05, 2.2], [0.12, 0.04, 2.4], [0.1, 0.06, 2.6],
            [(10.5 - W / 2) / 30 * z4, (7.5 - H / 2) / 30 * z4, z4],
            [-0.4, 0.3, 2.5], [0.0, 0.0, -1.0], [0.2, 0.2, 2.0], [5.0, 0.0, 2.0], [0.0, 0.0, 0.005],
            [3.0, 0.2, 3.0],
            [-0.5, -0.3, 3.5], [0.4, 0.4, 4.0], [0.0, -0.2, 1.5],
        ],
        dtype=dtype,
    )  # fmt: skip
    N = means.shape[0]
    quats = torch.randn(N, 4, generator=g, dtype=dtype)
    scales = torch.rand(N, 3, generator=g, dtype=dtype) * 0.15 + 0.05
    scales[4] = torch.tensor([0.02, 0.03, 0.02])
    scales[10] = torch.tensor([0.8, 0.6, 0.5])
    opac = torch.rand(N, generator=g, dtype=dtype) * 0.6 + 0.3
    opac[:4] = 0.99
    opac[4] = 0.9999
    opac[5] = 0.02
    opac[7] = 0.003
    colors = torch.rand(N, 3, generator=g, dtype=dtype)
    sh = torch.randn(N, 16, 3, generator=g, dtype=dtype) * 0.3
    vm, K = _cameras(dtype)
    bg = torch.rand(2, 3, generator=g, dtype=dtype)
    return dict(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opac,
        colors=colors,
        sh=sh,
        viewmats=vm,
        Ks=K,
        bg=bg,
    )


def _leaf(s: dict[str, torch.Tensor], keys: tuple[str, ...]) -> dict[str, torch.Tensor]:
    return {k: s[k].clone().requires_grad_(True) for k in keys}


def _grads(out: tuple[torch.Tensor, torch.Tensor], leaves: dict[str, torch.Tensor], seed: int = 1) -> dict:
    img, alpha = out
    g = torch.Generator().manual_seed(seed)
    wi = torch.randn(img.shape, generator=g, dtype=img.dtype)
    wa = torch.randn(alpha.shape, generator=g, dtype=img.dtype)
    grads = torch.autograd.grad(
        (img * wi).sum() + (alpha * wa).sum(), list(leaves.values()), allow_unused=True
    )
    return {
        k: (torch.zeros_like(v) if gr is None else gr)
        for (k, v), gr in zip(leaves.items(), grads, strict=True)
    }


def _close(a: torch.Tensor, b: torch.Tensor, rtol: float, what: str) -> None:
    err = (a - b).abs().max().item()
    scale = max(b.abs().max().item(), 1e-12)
    assert err <= rtol * scale, f"{what}: max |diff| {err:.3e} vs max |ref| {scale:.3e}"


@pytest.fixture(scope="module")
def scene() -> dict[str, torch.Tensor]:
    return _scene()


def test_scene_exercises_every_rule(scene: dict[str, torch.Tensor]) -> None:
    proj = project_gaussians(
        scene["means"],
        scene["quats"],
        scene["scales"],
        scene["opacities"],
        scene["viewmats"],
        scene["Ks"],
        W,
        H,
    )
    vis0 = proj.visible[0]
    assert not vis0[6:10].any(), "the culled Gaussians must be culled"
    assert vis0[:6].all() and vis0[10:].all()
    # Gaussian 10 is beyond the FOV clamp: its Jacobian differs from the unclamped one
    x, _, z = proj.means_cam[0, 10]
    assert x / z > (W - W / 2) / 30 * 1.3
    assert torch.isclose(proj.jacobians[0, 10, 0, 2], -30 * (W / 2 / 30 * 1.3) / z)
    # the clamp: o·exp(−σ) > 0.999 at Gaussian 4's centre pixel
    assert torch.allclose(proj.means2d[0, 4], torch.tensor([10.5, 7.5], dtype=F64))
    # the stop: after Gaussians 0 and 1 at the stack's centre pixel, T <= 1e-4
    bins = ref.bin_tiles(proj.means2d, proj.radii, proj.depths, W, H)
    c = proj.means2d[0, 0]
    px = torch.floor(c)
    w = ref.block_weights(
        proj.means2d[0, :4][None],
        proj.conics[0, :4][None],
        scene["opacities"][:4][None],
        (torch.div(px, 16, rounding_mode="floor") * 16 + 0.5)[None],
    )
    iy, ix = int(px[1]) % 16, int(px[0]) % 16
    assert w.alpha[0, iy, ix, 0] > 0 and w.alpha[0, iy, ix, 2:].eq(0).all()
    assert bins.counts.sum() > 0


def test_projection_matches_gsplat_torch_formulas(scene: dict[str, torch.Tensor]) -> None:
    from gsplat.cuda import _torch_impl as gt

    s = scene
    proj = project_gaussians(
        s["means"], s["quats"], s["scales"], s["opacities"], s["viewmats"], s["Ks"], W, H
    )
    covars, _ = gt._quat_scale_to_covar_preci(s["quats"], s["scales"], True, False, triu=False)
    _, means2d, depths, conics, _ = gt._fully_fused_projection(
        s["means"], covars, s["viewmats"], s["Ks"], W, H
    )
    means_c, covars_c = gt._world_to_cam(s["means"], covars, s["viewmats"])
    _, cov2d = gt._persp_proj(means_c, covars_c, s["Ks"], W, H)
    vis = proj.visible
    assert torch.allclose(proj.means2d[vis], means2d[vis], rtol=1e-12, atol=1e-10)
    assert torch.allclose(proj.depths, depths, rtol=1e-12)
    assert torch.allclose(proj.conics[vis], conics[vis], rtol=1e-10, atol=1e-12)
    assert torch.allclose(proj.covars2d[vis], cov2d[vis], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_sh_matches_gsplat_torch_impl(degree: int) -> None:
    from gsplat.cuda._torch_impl import _spherical_harmonics

    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(50, 3, generator=g, dtype=F64) * 3
    coeffs = torch.randn(50, 25, 3, generator=g, dtype=F64)
    ours = spherical_harmonics(degree, dirs, coeffs)
    theirs = _spherical_harmonics(degree, dirs, coeffs)
    assert torch.allclose(ours, theirs, rtol=1e-12, atol=1e-12)
    if degree <= 3:  # and the textbook formula of the brute force
        bf = torch.stack([_sh_rgb(coeffs[i], dirs[i], degree) for i in range(50)])
        assert torch.allclose(torch.clamp_min(ours + 0.5, 0.0), bf, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("mode", ["rgb_bg", "sh3", "per_camera_2ch"])
def test_reference_matches_bruteforce(scene: dict[str, torch.Tensor], mode: str) -> None:
    s = scene
    keys = ("means", "quats", "scales", "opacities")
    sh_degree, bg = None, None
    if mode == "rgb_bg":
        keys += ("colors", "bg")
        col_key = "colors"
    elif mode == "sh3":
        keys += ("sh",)
        col_key, sh_degree = "sh", 3
    else:
        g = torch.Generator().manual_seed(5)
        s = dict(s, pc=torch.rand(2, s["means"].shape[0], 2, generator=g, dtype=F64))
        keys += ("pc",)
        col_key = "pc"
    a, b = _leaf(s, keys), _leaf(s, keys)
    bg_a = a.get("bg")
    bg_b = b.get("bg")
    out = rasterize(
        a["means"], a["quats"], a["scales"], a["opacities"], a[col_key], s["viewmats"], s["Ks"], W, H,
        sh_degree=sh_degree, backgrounds=bg_a, backend="torch",
    )  # fmt: skip
    img, alpha, info = out
    bf_img, bf_alpha, bf_radii, _ = render_bruteforce(
        b["means"], b["quats"], b["scales"], b["opacities"], b[col_key], s["viewmats"], s["Ks"], W, H,
        sh_degree=sh_degree, backgrounds=bg_b if bg is None else bg,
    )  # fmt: skip
    assert torch.equal(info["radii"], bf_radii)
    _close(img, bf_img, 1e-12, "image")
    _close(alpha, bf_alpha, 1e-12, "alpha")
    assert alpha.max() > 0.99 and alpha.min() < 0.01  # opaque and empty regions both present
    ga = _grads((img, alpha), a)
    gb = _grads((bf_img, bf_alpha), b)
    for k in keys:
        assert torch.isfinite(ga[k]).all(), k
        _close(ga[k], gb[k], 1e-9, f"d/d{k}")
    # Gaussians culled in both cameras get exactly zero gradient
    for k in keys[:4]:
        assert ga[k][6:9].abs().max() == 0, k


def test_float32_close_to_float64(scene: dict[str, torch.Tensor]) -> None:
    s = scene
    args64 = [s[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")]
    args32 = [t.float() for t in args64]
    i64, a64, _ = rasterize(*args64, W, H, backend="torch")
    i32, a32, _ = rasterize(*args32, W, H, backend="torch")
    assert (i64 - i32.double()).abs().max() < 1e-4
    assert (a64 - a32.double()).abs().max() < 1e-4


def test_chunking_and_recompute_paths_agree(scene: dict[str, torch.Tensor]) -> None:
    """Tiny blocks and the recompute-in-backward path give the same values and gradients."""
    s = scene
    keys = ("means", "quats", "scales", "opacities", "colors")
    outs = []
    for chunk, save in ((ref.CHUNK_PAIRS, ref.SAVE_PAIRS), (256 * 3, 0), (256 * 7, 256 * 20)):
        lv = _leaf(s, keys)
        img, alpha, _ = ref.rasterize_torch(
            *lv.values(),
            s["viewmats"],
            s["Ks"],
            W,
            H,
            backgrounds=s["bg"],
            chunk_pairs=chunk,
            save_pairs=save,
        )
        outs.append((img.detach(), _grads((img, alpha), lv)))
    for img, gr in outs[1:]:
        _close(img, outs[0][0], 1e-14, "image")
        for k in keys:
            _close(gr[k], outs[0][1][k], 1e-12, k)


def test_render_modes(scene: dict[str, torch.Tensor]) -> None:
    s = scene
    args = [s[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")]
    rgb, alpha, info = rasterize(*args, W, H, backend="torch")
    depth_feat = info["depths"][..., None]
    d_ref, _, _ = rasterize(*args[:4], depth_feat, *args[5:], W, H, backend="torch")
    d, _, _ = rasterize(*args, W, H, backend="torch", render_mode="D")
    ed, _, _ = rasterize(*args, W, H, backend="torch", render_mode="ED")
    rgbd, _, _ = rasterize(*args, W, H, backend="torch", render_mode="RGB+ED")
    assert torch.allclose(d, d_ref, atol=1e-12)
    assert torch.allclose(ed, d_ref / alpha.clamp(min=1e-10), atol=1e-10)
    assert torch.allclose(rgbd[..., :3], rgb) and torch.allclose(rgbd[..., 3:], ed)
    feats = torch.rand(args[0].shape[0], 2, dtype=F64)
    with_extra, _, xinfo = rasterize(*args, W, H, backend="torch", render_mode="RGB+ED", extra=feats)
    assert torch.equal(with_extra, rgbd) and xinfo["extra"].shape == (2, H, W, 2)
    assert xinfo["extra_features"] is feats
    with pytest.raises(ValueError, match="colour render_mode"):
        rasterize(*args, W, H, backend="torch", render_mode="D", extra=feats)
    with pytest.raises(ValueError, match="extra must be"):
        rasterize(*args, W, H, backend="torch", extra=feats[:-1])


def test_split_modules_match_bruteforce(scene: dict[str, torch.Tensor]) -> None:
    """projection → SH colours → tile binning → compositing, called one module at a time, equal the
    per-pixel brute force (SH degree 3, a background)."""
    from jsgs.render.reference import projection, sh, tiles
    from jsgs.render.reference.composite import composite

    s = scene
    args = (s["means"], s["quats"], s["scales"], s["opacities"])
    proj = projection.project_gaussians(*args, s["viewmats"], s["Ks"], W, H)
    colors = sh.prepare_colors(s["means"], s["sh"], s["viewmats"], 3)
    bins = tiles.bin_tiles(proj.means2d, proj.radii, proj.depths, W, H)
    img, alpha = composite(proj, bins, s["opacities"], colors, s["bg"], W, H)
    bf_img, bf_alpha, bf_radii, _ = render_bruteforce(
        *args, s["sh"], s["viewmats"], s["Ks"], W, H, sh_degree=3, backgrounds=s["bg"]
    )
    assert torch.equal(proj.radii, bf_radii)
    _close(img, bf_img, 1e-12, "image")
    _close(alpha, bf_alpha, 1e-12, "alpha")


@pytest.mark.parametrize("shape", ["per_gaussian", "per_camera"])
def test_extra_channels(scene: dict[str, torch.Tensor], shape: str) -> None:
    """Extra channels of ones render the alpha; other features render as they would as colours (over a
    zero background), whatever the colours and background are; their gradient is Σ_p t·α·g(p)."""
    s = scene
    N = s["means"].shape[0]
    g = torch.Generator().manual_seed(11)
    feats = torch.rand(N, 3, generator=g, dtype=F64)
    feats[:, 0] = 1.0
    if shape == "per_camera":
        feats = torch.stack([feats, torch.rand(N, 3, generator=g, dtype=F64)])
        feats[:, :, 0] = 1.0
    feats.requires_grad_(True)
    geo = (s["means"], s["quats"], s["scales"], s["opacities"])
    cams = (s["viewmats"], s["Ks"], W, H)
    img, alpha, info = rasterize(*geo, s["sh"], *cams, sh_degree=3, backgrounds=s["bg"], backend="torch",
                                 extra=feats)  # fmt: skip
    ones = info["extra"][..., :1]
    _close(ones, alpha, 1e-14, "ones vs alpha")
    assert alpha.amax() > 0.5 and (alpha == 0).any()  # covered and empty pixels both present
    plain, _, _ = rasterize(*geo, s["sh"], *cams, sh_degree=3, backgrounds=s["bg"], backend="torch")
    _close(img, plain, 1e-14, "colours with and without extra channels")
    as_colours, _, _ = rasterize(*geo, feats.detach(), *cams, backend="torch")
    _close(info["extra"], as_colours, 1e-14, "extra vs colours")
    up = torch.rand(info["extra"].shape, generator=g, dtype=F64)
    (info["extra"] * up).sum().backward()
    # against the brute force's pooled sums: Σ_p t·α·g(p) = o·S_g for every channel
    bf_args = (*geo, s["sh"], *cams)
    for c in range(3):
        _, _, _, bf = render_bruteforce(*bf_args, sh_degree=3, r=up[..., c])
        want = bf["s_r"] * s["opacities"][None]
        got = feats.grad[..., c] if shape == "per_camera" else feats.grad[None, :, c]
        if shape == "per_gaussian":
            want = want.sum(0, keepdim=True)
        _close(got, want, 1e-12, f"gradient of channel {c}")


def test_absgrad_is_sum_of_per_pixel_magnitudes(scene: dict[str, torch.Tensor]) -> None:
    s = scene
    lv = _leaf(s, ("means",))
    args = (s["quats"], s["scales"], s["opacities"], s["colors"], s["viewmats"], s["Ks"])
    # a loss on one pixel: the sum over pixels has one term, so absgrad == |grad|
    img, _, info = rasterize(lv["means"], *args, W, H, backend="torch", absgrad=True)
    info["means2d"].retain_grad()
    img[0, 10, 12].sum().backward()
    g = info["means2d"].grad
    assert g.abs().max() > 0
    assert torch.allclose(info["means2d"].absgrad, g.abs(), atol=1e-14)
    # over the whole image: |Σ| <= Σ|.|, with strict inequality somewhere
    img, _, info = rasterize(lv["means"], *args, W, H, backend="torch", absgrad=True)
    info["means2d"].retain_grad()
    (img * torch.randn_like(img)).sum().backward()
    g, ag = info["means2d"].grad, info["means2d"].absgrad
    assert (ag >= g.abs() - 1e-12).all() and (ag > g.abs() + 1e-9).any()


def test_pooled_sums_match_bruteforce(scene: dict[str, torch.Tensor]) -> None:
    s = scene
    args = [s[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")]
    r = torch.rand(2, H, W, dtype=F64, generator=torch.Generator().manual_seed(3))
    _, _, _, bf = render_bruteforce(*args, W, H, r=r)
    direct = pool_direct(*args[:4], *args[5:], W, H, r)
    for name in ("s_r", "s_1", "nu"):
        _close(getattr(direct, name), bf[name], 1e-12, f"direct {name}")
    assert torch.equal(direct.contributors, bf["nu"] > 0)
    assert direct.contributors[0, :6].all() and not direct.contributors[0, 6:10].any()
    # the clamped Gaussian: κ = t·α/o, not exp(−σ), at its centre pixel; ν = o·S_1 everywhere
    assert torch.allclose(direct.nu, direct.s_1 * s["opacities"][None], rtol=1e-12)

    # the probe, through an immediate backward, and through the loss's own backward
    lv = _leaf(s, ("means", "quats", "scales", "opacities", "colors"))
    probe = new_probe(s["means"].shape[0], s["means"], n_cameras=2)
    img, alpha, info = rasterize(*lv.values(), *args[5:], W, H, backend="torch", extra=probe)
    now = pool_now(info, r)
    (img.sum() + probe_objective(info, r)).backward()
    later = pool_from_grad(info)
    for name in ("s_r", "s_1", "nu"):
        _close(getattr(now, name), bf[name], 1e-12, f"pool_now {name}")
        _close(getattr(later, name), bf[name], 1e-12, f"pool_from_grad {name}")
    rbar = direct.rbar()
    assert torch.allclose(rbar, bf["s_r"] / (bf["s_1"] + 1e-6))


def test_probe_changes_neither_image_nor_gradients(scene: dict[str, torch.Tensor]) -> None:
    s = scene
    keys = ("means", "quats", "scales", "opacities", "colors")
    r = torch.rand(2, H, W, dtype=F64)
    res = []
    for probe in (False, True):
        lv = _leaf(s, keys)
        extra = new_probe(s["means"].shape[0], s["means"], n_cameras=2) if probe else None
        img, alpha, info = rasterize(*lv.values(), s["viewmats"], s["Ks"], W, H, backend="torch",
                                     backgrounds=s["bg"], extra=extra)  # fmt: skip
        info["means2d"].retain_grad()
        loss = (img * img).sum() + alpha.sum()
        if probe:
            assert info["extra"].abs().max() == 0
            loss = loss + probe_objective(info, r)
        loss.backward()
        res.append((img.detach(), info["means2d"].grad, {k: v.grad for k, v in lv.items()}))
    assert torch.equal(res[0][0], res[1][0])
    _close(res[1][1], res[0][1], 1e-14, "means2d.grad")
    for k in keys:
        _close(res[1][2][k], res[0][2][k], 1e-14, k)


def test_culling_and_finite_gradients() -> None:
    vm, K = _cameras()
    means = torch.tensor(
        [[0.0, 0.0, 0.0], [0.0, 0.0, -2.0], [0.0, 0.0, 2e10], [100.0, 0.0, 1.0], [0.0, 0.0, 2.0]], dtype=F64
    )
    N = len(means)
    lv = {
        "means": means.clone().requires_grad_(True),
        "quats": torch.tensor([[1.0, 0, 0, 0]] * N, dtype=F64, requires_grad=True),
        "scales": torch.full((N, 3), 0.1, dtype=F64, requires_grad=True),
        "opacities": torch.full((N,), 0.5, dtype=F64, requires_grad=True),
        "colors": torch.rand(N, 3, dtype=F64, requires_grad=True),
    }
    img, alpha, info = rasterize(*lv.values(), vm[:1], K[:1], W, H, backend="torch")
    assert info["radii"][0, :4].eq(0).all() and info["radii"][0, 4].gt(0).all()
    (img.sum() + alpha.sum()).backward()
    for k, v in lv.items():
        assert torch.isfinite(v.grad).all(), k
        assert v.grad[:4].abs().max() == 0, k
    # radius_clip culls small Gaussians; everything culled renders the background
    bg = torch.tensor([[0.2, 0.3, 0.4]], dtype=F64)
    img, alpha, info = rasterize(*[v.detach() for v in lv.values()], vm[:1], K[:1], W, H, backend="torch",
                                 radius_clip=100.0, backgrounds=bg)  # fmt: skip
    assert info["radii"].eq(0).all() and alpha.eq(0).all()
    assert torch.equal(img, bg[:, None, None, :].expand_as(img))


def test_info_has_what_gsplat_meta_has(scene: dict[str, torch.Tensor]) -> None:
    s = scene
    args = [s[k].float() for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")]
    args[0].requires_grad_(True)
    _, _, info = rasterize(*args, W, H, backend="torch")
    C, N = 2, args[0].shape[0]
    assert info["radii"].shape == (C, N, 2) and info["radii"].dtype == torch.int32
    assert info["means2d"].shape == (C, N, 2) and info["means2d"].requires_grad
    assert info["depths"].shape == (C, N) and info["conics"].shape == (C, N, 3)
    assert info["opacities"].shape == (C, N)
    assert (info["width"], info["height"], info["n_cameras"], info["tile_size"]) == (W, H, C, 16)
    assert info["gaussian_ids"] is None and info["backend"] == "torch"
    assert info["isect_offsets"].shape == (C, 2, 3)
    assert int(info["tiles_per_gauss"].sum()) == info["flatten_ids"].numel()


def test_backend_selection_and_errors(scene: dict[str, torch.Tensor]) -> None:
    s = scene
    args = [s[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")]
    with pytest.raises(ValueError, match="CUDA"):
        rasterize(*args, W, H, backend="gsplat")
    with pytest.raises(ValueError, match="packed"):
        rasterize(*args, W, H, backend="torch", packed=True)
    with pytest.raises(ValueError, match="colors"):
        rasterize(*args[:4], s["sh"], *args[5:], W, H)
    with pytest.raises(ValueError, match="SH"):
        rasterize(*args, W, H, sh_degree=1)
    with pytest.raises(ValueError, match="render_mode"):
        rasterize(*args, W, H, render_mode="X")  # type: ignore[arg-type]
    _, _, info = rasterize(*args, W, H)
    assert info["backend"] == "torch"
