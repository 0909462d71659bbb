"""``--method jsgs`` (jsgs.method): every term against a float64 evaluation of its equation written
here from the paper (independent of jsgs.jpeg / jsgs.render / jsgs.kernels), r̄ from the training
path against the brute-force rasteriser, L_fro's gradients, the ablation switches, the options, and a short
``jsgs train --method jsgs`` run on the compressed synthetic scene.

The tiny scene: 10 Gaussians (one behind the camera, one off-screen) seen by one 27 x 19 px camera, so that
the last 3 rows and columns lie outside the valid 8x8 blocks. Everything is float64 except the end-to-end run.
"""

from __future__ import annotations

import io
import json
import math
import os
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from PIL import Image

from jsgs.base.camera import Camera
from jsgs.base.errors import JsgsError
from jsgs.base.manifest import JpegState
from jsgs.jpeg.losses import photometric_loss
from jsgs.jpeg.tables import ijg_tables
from jsgs.method.hook import JsgsHook, make_jsgs_hook
from jsgs.method.image_terms import view_tables
from jsgs.method.options import parse_options
from jsgs.render.bruteforce import render_bruteforce
from jsgs.train.config import TrainConfig
from jsgs.train.data import TrainingView, image_target
from jsgs.train.hook import StepContext, make_hook
from jsgs.train.render_view import render_view
from jsgs.train.trainer import weighted_loss

D = torch.float64
WIDTH, HEIGHT, FOCAL = 27, 19, 30.0


pytestmark = pytest.mark.usefixtures("one_torch_thread")


SUBSAMPLING = {"4:4:4": 0, "4:2:2": 1, "4:2:0": 2}

# ---------------------------------------------------------------------------------------------------------
# float64 references, straight from the paper's equations (numpy)


def _fix(c: float) -> float:
    """libjpeg's 16-bit fixed-point colour constants, FIX(c) = round(c·2^16) / 2^16 (the JPEG convention
    the observation operator follows)."""
    return round(c * 65536) / 65536


def ref_dct_matrix() -> np.ndarray:
    """Orthonormal 8-point DCT-II: C = D X Dᵀ, D[k, n] = c_k cos((2n + 1) k π / 16)."""
    k, n = np.meshgrid(np.arange(8), np.arange(8), indexing="ij")
    d = np.sqrt(2 / 8) * np.cos((2 * n + 1) * k * np.pi / 16)
    d[0] /= np.sqrt(2)
    return d


def ref_blocks(plane: np.ndarray) -> np.ndarray:
    """[H, W] (multiples of 8) -> [H/8, W/8, 8, 8]."""
    h, w = plane.shape
    return plane.reshape(h // 8, 8, w // 8, 8).transpose(0, 2, 1, 3)


def ref_unblocks(b: np.ndarray) -> np.ndarray:
    nby, nbx = b.shape[:2]
    return b.transpose(0, 2, 1, 3).reshape(nby * 8, nbx * 8)


def ref_jo_paper_444(rgb: np.ndarray, luma: np.ndarray, chroma: np.ndarray) -> np.ndarray:
    """Eq. jpeg_operator with eq. soft_round, 4:4:4: [H, W, 3] in [0, 1] -> [H, W, 3]."""
    x = 255 * np.clip(rgb, 0, 1)
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    y = _fix(0.299) * r + _fix(0.587) * g + _fix(0.114) * b
    cb = -_fix(0.16874) * r - _fix(0.33126) * g + _fix(0.5) * b + 128
    cr = _fix(0.5) * r - _fix(0.41869) * g - _fix(0.08131) * b + 128
    h, w = y.shape
    hp, wp = 8 * math.ceil(h / 8), 8 * math.ceil(w / 8)
    dm = ref_dct_matrix()
    out = []
    for plane, table in ((y, luma), (cb, chroma), (cr, chroma)):
        p = np.pad(plane, ((0, hp - h), (0, wp - w)), mode="edge") - 128
        c = dm @ ref_blocks(p) @ dm.T
        z = c / table
        zr = np.round(z)
        deq = table * (zr + (z - zr) ** 3)
        rec = np.clip(dm.T @ deq @ dm + 128, 0, 255)
        out.append(ref_unblocks(rec)[:h, :w])
    y, cb, cr = out[0], out[1] - 128, out[2] - 128
    rr = y + _fix(1.402) * cr
    gg = y - _fix(0.34414) * cb - _fix(0.71414) * cr
    bb = y + _fix(1.772) * cb
    return np.clip(np.stack([rr, gg, bb], -1), 0, 255) / 255


def ref_pillow_jpeg(rgb: np.ndarray, luma: np.ndarray, chroma: np.ndarray, sampling: str) -> np.ndarray:
    """Real JPEG (Pillow / libjpeg-turbo) encode + decode of the 8-bit image: [H, W, 3] -> same, in [0, 1]."""
    arr = np.floor(255 * np.clip(rgb, 0, 1) + 0.5).astype(np.uint8)
    buf = io.BytesIO()
    # Pillow's qtables take natural-order tables
    Image.fromarray(arr).save(
        buf, "JPEG", qtables=[luma.astype(int).ravel().tolist(), chroma.astype(int).ravel().tolist()],
        subsampling=SUBSAMPLING[sampling],
    )  # fmt: skip
    with Image.open(io.BytesIO(buf.getvalue())) as im:
        return np.asarray(im.convert("RGB"), dtype=np.float64) / 255


def ref_ssim_valid(x: np.ndarray, y: np.ndarray) -> float:
    """Mean SSIM, 11 x 11 Gaussian window (σ 1.5) as a 2-D kernel, valid positions only; [H, W, 3]."""
    t = np.arange(11) - 5
    g = np.exp(-(t**2) / (2 * 1.5**2))
    g /= g.sum()
    win = np.outer(g, g)
    h, w = x.shape[:2]
    vals = []
    for c in range(3):
        for i in range(h - 10):
            for j in range(w - 10):
                a, b = x[i : i + 11, j : j + 11, c], y[i : i + 11, j : j + 11, c]
                ma, mb = (win * a).sum(), (win * b).sum()
                va, vb = (win * a * a).sum() - ma**2, (win * b * b).sum() - mb**2
                cov = (win * a * b).sum() - ma * mb
                c1, c2 = 0.01**2, 0.03**2
                vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


def ref_photometric(x: np.ndarray, y: np.ndarray, lam: float = 0.2) -> float:
    """Eq. photometric: (1 − λ) ‖X − Y‖₁ / (3HW) + λ (1 − SSIM)."""
    return (1 - lam) * np.abs(x - y).mean() + lam * (1 - ref_ssim_valid(x, y))


def ref_ds(obs: np.ndarray, target: np.ndarray, luma: np.ndarray, eps_sm: float = 1e-3) -> dict[str, Any]:
    """Eqs. omega, jsgs_luminance … jsgs_dct_losses, jsgs_block_score; r(p) (0 outside the valid blocks)."""
    dm = ref_dct_matrix()

    def coeffs(img: np.ndarray) -> np.ndarray:
        y8 = 255 * (0.299 * img[..., 0] + 0.587 * img[..., 1] + 0.114 * img[..., 2]) - 128
        hb, wb = (y8.shape[0] // 8) * 8, (y8.shape[1] // 8) * 8
        return dm @ ref_blocks(y8[:hb, :wb]) @ dm.T

    delta = (coeffs(obs) - coeffs(target)) / 255
    psi = np.sqrt(delta**2 + eps_sm**2) - eps_sm
    v, u = np.meshgrid(np.arange(8), np.arange(8), indexing="ij")
    f = u + v
    omega = np.exp(-2 * (luma - 1) / 254 - f / 14)
    m_low = (f <= 3).astype(float)
    w_mid = ((f > 3) & (f <= 5)) * omega
    nby, nbx = delta.shape[:2]
    e = (w_mid * psi).sum(axis=(-1, -2))
    low = (m_low * psi).sum() / (nby * nbx * m_low.sum() + 1e-6)
    mid = e.sum() / (nby * nbx * w_mid.sum() + 1e-6)
    rb = e / (w_mid.sum() + 1e-6)
    r_pix = np.zeros(obs.shape[:2])
    r_pix[: nby * 8, : nbx * 8] = np.kron(rb, np.ones((8, 8)))
    return {"low": low, "mid": mid, "r_block": rb, "r": r_pix}


def ref_sbar(mean: np.ndarray, q: np.ndarray, s: np.ndarray, viewmat: np.ndarray, K: np.ndarray) -> float:
    """Eq. controller_scale: sqrt(½ tr(A diag(s)² Aᵀ)), A = J W R(q); J at the camera-space mean with gsplat's
    FOV clamp of x/z, y/z (30 % margin)."""
    W = viewmat[:3, :3]
    x, y, z = W @ mean + viewmat[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = np.clip(x / z, -(cx / fx + 0.15 * WIDTH / fx), (WIDTH - cx) / fx + 0.15 * WIDTH / fx)
    v = np.clip(y / z, -(cy / fy + 0.15 * HEIGHT / fy), (HEIGHT - cy) / fy + 0.15 * HEIGHT / fy)
    J = np.array([[fx / z, 0, -fx * u / z], [0, fy / z, -fy * v / z]])
    a, b, c, d = q / np.linalg.norm(q)
    R = np.array(
        [
            [1 - 2 * (c * c + d * d), 2 * (b * c - a * d), 2 * (b * d + a * c)],
            [2 * (b * c + a * d), 1 - 2 * (b * b + d * d), 2 * (c * d - a * b)],
            [2 * (b * d - a * c), 2 * (c * d + a * b), 1 - 2 * (b * b + c * c)],
        ]
    )
    A = J @ W @ R
    return math.sqrt(0.5 * np.trace(A @ np.diag(s**2) @ A.T))


# ---------------------------------------------------------------------------------------------------------
# the tiny scene


def make_splats(seed: int = 0) -> torch.nn.ParameterDict:
    g = torch.Generator().manual_seed(seed)
    n = 10
    z = 3.0 + 3.0 * torch.rand(n, generator=g, dtype=D)
    xy = (
        (torch.rand(n, 2, generator=g, dtype=D) - 0.5)
        * torch.tensor([WIDTH, HEIGHT], dtype=D)
        / FOCAL
        * z[:, None]
    )
    means = torch.cat([xy, z[:, None]], 1)
    means[8] = torch.tensor([0.2, 0.1, -2.0], dtype=D)  # behind the camera: never in V
    means[9] = torch.tensor([40.0, 0.0, 4.0], dtype=D)  # off-screen: never in V
    means[7] = torch.tensor([1.53, 1.0, 4.0], dtype=D)  # over the bottom-right pixels without a block score
    # projected RMS scales from ~0.5 px to ~3 px: the exponential matters, some are "damped"
    scales = torch.log(z[:, None] / FOCAL * (0.1 + 2.0 * torch.rand(n, 3, generator=g, dtype=D)))
    return torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter(means),
            "scales": torch.nn.Parameter(scales),
            "quats": torch.nn.Parameter(torch.randn(n, 4, generator=g, dtype=D)),
            "opacities": torch.nn.Parameter(torch.randn(n, generator=g, dtype=D) + 1.0),
            "sh0": torch.nn.Parameter(torch.randn(n, 1, 3, generator=g, dtype=D)),
            "shN": torch.nn.Parameter(torch.zeros(n, 0, 3, dtype=D)),
        }
    )


def camera() -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1]])
    viewmat = np.eye(4)
    return viewmat, K


def make_view(quality: int | None, sampling: str = "4:2:0", index: int = 0) -> TrainingView:
    viewmat, K = camera()
    cam = Camera("PINHOLE", WIDTH, HEIGHT, FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2)
    assert np.array_equal(cam.K, K)
    jpeg = None
    if quality is not None:
        luma, chroma = ijg_tables(quality)
        jpeg = JpegState(
            np.asarray(luma, dtype=np.int32).reshape(8, 8), np.asarray(chroma, dtype=np.int32).reshape(8, 8),
            sampling, quality, True, 8, "baseline",
        )  # fmt: skip
    c2w = np.linalg.inv(viewmat)
    return TrainingView(index, f"v{index}", "train", Path("x.jpg"), None, jpeg, cam, c2w, viewmat)


def render(
    splats: torch.nn.ParameterDict, extra: torch.Tensor | None, extra_kwargs: dict[str, Any] | None = None
) -> Any:
    viewmat, K = camera()
    return render_view(
        splats, torch.tensor(viewmat, dtype=D)[None], torch.tensor(K, dtype=D)[None], WIDTH, HEIGHT, 0,
        TrainConfig.from_preset("paper"), "torch", extra, extra_kwargs,
    )  # fmt: skip


def target_for(view: TrainingView) -> torch.Tensor:
    """The decoded training JPEG: a different scene (shifted colours and centres) through Pillow with the
    view's own tables and sampling; [1, H, W, 3] float64."""
    sp = make_splats(seed=0)
    with torch.no_grad():
        sp["sh0"].add_(
            0.4 * torch.randn(sp["sh0"].shape, generator=torch.Generator().manual_seed(3), dtype=D)
        )
        sp["means"][:, 0] += 0.05
        img = render(sp, None).rgb[0].numpy() + 0.3
    j = view.jpeg
    if j is None:
        return torch.tensor(np.clip(img, 0, 1), dtype=D)[None]
    return torch.tensor(ref_pillow_jpeg(img, j.luma_table, j.chroma_table, j.sampling), dtype=D)[None]


SPEED_KEYS = (
    "compile", "cuda_graph", "cuda_graph_free_warmup", "cuda_graph_gc", "gc_kernel", "fused_jo", "fused_color"
)


def jsgs_options(**options: Any) -> dict[str, Any]:
    """``method_options`` from keyword arguments, the speed settings (``SPEED_KEYS``) put in ``speed``."""
    speed = {k: options.pop(k) for k in SPEED_KEYS if k in options}
    return {**options, "speed": speed} if speed else options


def new_hook(view: TrainingView, **options: Any) -> JsgsHook:
    hook = JsgsHook(parse_options(jsgs_options(**options)), view_tables([view], torch.device("cpu"), "test"))
    hook.keep_last = True
    return hook


def train_step(
    hook: JsgsHook, view: TrainingView, splats: torch.nn.ParameterDict | None = None,
    image: torch.Tensor | None = None, context_image: bool = True, render_kwargs: bool = False,
) -> dict[str, Any]:  # fmt: skip
    """One step as the trainer takes it: render (training path), base ℓ_ph, the hook's terms, backward.
    ``image``: a uint8 [H, W, 3] training image, the target made from it as the trainer makes it, the image
    in the step's context too with ``context_image`` (else :func:`target_for`'s target alone);
    ``render_kwargs``: the render also takes the hook's ``render_kwargs`` (as the trainer's does). Returns
    term values (read after the backward, as the trainer does), stats, parameter gradients and the
    screen-space means' gradient."""
    splats = splats if splats is not None else make_splats()
    target = target_for(view) if image is None else image_target(image)
    extra = hook.extra_channels(0, view, splats)
    out = render(splats, extra, hook.render_kwargs(0, view) if render_kwargs else None)
    out.info["means2d"].retain_grad()
    ctx = StepContext(
        0, view, out.rgb, out.alpha, target, out.info, splats, None, {}, 0, image if context_image else None,
        folded_upstream_one=True,  # added unweighted below, backward from 1
    )  # fmt: skip
    h = hook.losses(ctx)
    h.check("jsgs")
    x, y = out.rgb.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2)
    terms = {"photometric": photometric_loss(x, y, 0.2, padding="valid"), **h.terms}
    loss = weighted_loss(terms, {"photometric": 1.0, **h.weights}, h.folded, h.folded_loss)
    loss.backward()
    return {
        "terms": {k: v.item() for k, v in h.terms.items()},
        "weights": dict(h.weights),
        "stats": {k: float(v) for k, v in h.stats.items()},
        "grads": {k: p.grad.clone() for k, p in splats.items() if p.grad is not None},
        "means2d": out.info["means2d"].grad.clone(),
        "render": out.rgb.detach()[0].numpy(),
        "target": target[0].numpy(),
        "hook": hook,
    }


# ---------------------------------------------------------------------------------------------------------
# every term against its equation


@pytest.mark.parametrize("route", ["deferred", "now"])
def test_terms_equal_float64_evaluation_of_the_equations(route: str) -> None:
    view = make_view(50, "4:4:4")
    res = train_step(new_hook(view, gc_pooling=route), view)
    last = res["hook"].last
    luma, chroma = view.jpeg.luma_table.astype(float), view.jpeg.chroma_table.astype(float)
    # JO (eq. jpeg_operator, paper mode) and L_obs (eq. obs_loss)
    obs_ref = ref_jo_paper_444(res["render"], luma, chroma)
    obs = last["observation"][0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(obs, obs_ref, rtol=0, atol=1e-10)
    assert math.isclose(res["terms"]["obs"], ref_photometric(obs_ref, res["target"]), rel_tol=1e-9)
    # DS (eqs. jsgs_dct_losses) on (Î^J, I)
    ds = ref_ds(obs, res["target"], luma)
    assert math.isclose(res["terms"]["low"], ds["low"], rel_tol=1e-10)
    assert math.isclose(res["terms"]["mid"], ds["mid"], rel_tol=1e-10)
    np.testing.assert_allclose(last["ds"].block_score[0].detach().numpy(), ds["r_block"], rtol=1e-10)
    np.testing.assert_allclose(last["ds"].pixel_score[0].numpy(), ds["r"], rtol=1e-10, atol=0)
    # GC (eqs. gaussian_risk, controller_scale, fro): pooled by the brute-force per-pixel definition
    sp = make_splats()
    viewmat, K = camera()
    with torch.no_grad():
        _, _, _, pooled = render_bruteforce(
            sp["means"], sp["quats"], torch.exp(sp["scales"]), torch.sigmoid(sp["opacities"]), sp["sh0"],
            torch.tensor(viewmat, dtype=D)[None], torch.tensor(K, dtype=D)[None], WIDTH, HEIGHT, sh_degree=0,
            r=torch.tensor(ds["r"], dtype=D)[None],
        )  # fmt: skip
    nu = pooled["nu"][0].numpy()
    vis = nu > 0
    rbar = pooled["s_r"][0].numpy() / (pooled["s_1"][0].numpy() + 1e-6)
    assert not vis[8] and not vis[9] and vis[:8].all()
    np.testing.assert_array_equal(last["visible"].numpy(), vis)
    np.testing.assert_allclose(last["rbar"].numpy(), rbar, rtol=1e-9, atol=1e-15)
    alpha = 1 / (1 + np.exp(-sp["opacities"].detach().numpy()))
    s = np.exp(sp["scales"].detach().numpy())
    means, quats = sp["means"].detach().numpy(), sp["quats"].detach().numpy()
    sbar = np.array([ref_sbar(means[j], quats[j], s[j], viewmat, K) if vis[j] else 0.0 for j in range(10)])
    per = rbar * alpha**2 * np.exp(-sbar / 1.0)
    fro_ref = per[vis].sum() / vis.sum()
    assert fro_ref > 1e-4  # the scene exercises the term
    assert math.isclose(res["terms"]["fro"], fro_ref, rel_tol=1e-9)
    np.testing.assert_allclose(last["fro"].sbar.numpy()[vis], sbar[vis], rtol=1e-12)
    # statistics (definitions in jsgs.kernels.ControllerStats)
    assert res["stats"]["gc_visible"] == vis.sum()
    assert math.isclose(res["stats"]["gc_rbar"], rbar[vis].mean(), rel_tol=1e-9)
    assert res["stats"]["gc_damped"] == ((rbar > 0) & vis & (sbar <= 1.0)).sum()
    # eq. overall: the paper's weights
    assert res["weights"] == {"obs": 0.2, "low": 0.02, "mid": 0.03, "fro": 0.05}


def test_obs_exact_mode_is_a_real_jpeg_of_the_render_with_the_views_tables() -> None:
    view = make_view(30, "4:2:0")  # its own tables and sampling (not the other test's)
    res = train_step(new_hook(view, jpeg_mode="exact"), view)
    j = view.jpeg
    ref = ref_pillow_jpeg(res["render"], j.luma_table, j.chroma_table, j.sampling)
    obs = res["hook"].last["observation"][0].permute(1, 2, 0).numpy()
    np.testing.assert_array_equal(np.round(obs * 255), np.round(ref * 255))
    assert math.isclose(res["terms"]["obs"], ref_photometric(ref, res["target"]), rel_tol=1e-9)


def test_rbar_of_the_training_path_equals_the_brute_force() -> None:
    """r̄ and V from the probe inside the training render (both routes) against the per-pixel, per-Gaussian
    brute force with the same r(p) (the library's own block scores here)."""
    view = make_view(50, "4:2:0")
    for route in ("deferred", "now"):
        res = train_step(new_hook(view, gc_pooling=route), view)
        last = res["hook"].last
        sp = make_splats()
        viewmat, K = camera()
        with torch.no_grad():
            _, _, _, pooled = render_bruteforce(
                sp["means"], sp["quats"], torch.exp(sp["scales"]), torch.sigmoid(sp["opacities"]), sp["sh0"],
                torch.tensor(viewmat, dtype=D)[None], torch.tensor(K, dtype=D)[None], WIDTH, HEIGHT,
                sh_degree=0, r=last["ds"].pixel_score,
            )  # fmt: skip
        rbar = pooled["s_r"] / (pooled["s_1"] + 1e-6)
        torch.testing.assert_close(last["rbar"], rbar[0], rtol=1e-10, atol=1e-16)
        assert torch.equal(last["visible"], pooled["nu"][0] > 0)
        torch.testing.assert_close(last["sums"].nu[0], pooled["nu"][0], rtol=1e-10, atol=1e-16)


# ---------------------------------------------------------------------------------------------------------
# gradients


def test_fro_gradients_reach_only_opacity_and_scale() -> None:
    view = make_view(50, "4:2:0")
    # the term alone, by autograd (route "now")
    hook = new_hook(view, gc_pooling="now")
    sp = make_splats()
    out = render(sp, hook.extra_channels(0, view, sp))
    ctx = StepContext(0, view, out.rgb, out.alpha, target_for(view), out.info, sp, None, {}, 0)
    fro = hook.losses(ctx).terms["fro"]
    names = list(sp.keys())
    grads = dict(zip(names, torch.autograd.grad(fro, [sp[n] for n in names], allow_unused=True), strict=True))
    for n in ("means", "quats", "sh0", "shN"):
        assert grads[n] is None or not grads[n].any(), n
    # the opacity gradient is L_fro's closed form, d/dlogit [(1/|V|) sum_V rbar alpha^2 exp(-sbar/tau_s)] =
    # (1/|V|) rbar exp(-sbar/tau_s) 2 alpha^2 (1 - alpha) on V and 0 elsewhere, with
    # sbar = sqrt(tr(A diag(s)^2 A^T) / 2) (paper eqs. controller_scale, fro)
    last = hook.last
    vis, rbar, A = last["visible"], last["rbar"], last["A"]
    alpha = torch.sigmoid(sp["opacities"].detach())
    s2 = torch.exp(2 * sp["scales"].detach())
    sbar = torch.sqrt(0.5 * torch.einsum("nij,nj,nij->n", A, s2, A))
    tau = hook.opts.tau_s
    expect = torch.where(vis, rbar * torch.exp(-sbar / tau) * 2 * alpha**2 * (1 - alpha), 0.0) / vis.sum()
    assert int(vis.sum()) > 0 and bool((expect != 0).any())
    torch.testing.assert_close(grads["opacities"], expect, rtol=1e-9, atol=1e-15)
    assert not grads["scales"][~vis].any() and grads["scales"][vis].abs().sum() > 0
    # and inside a full step, both routes: the whole difference λ_fro·∇L_fro sits in opacity and scale,
    # equals that autograd gradient, and the densification signal (means2d) does not move
    base = train_step(new_hook(view, gc=False), view)
    for route in ("deferred", "now"):
        full = train_step(new_hook(view, gc_pooling=route), view)
        for n in ("means", "quats", "sh0"):
            torch.testing.assert_close(full["grads"][n], base["grads"][n], rtol=0, atol=1e-15)
        torch.testing.assert_close(full["means2d"], base["means2d"], rtol=0, atol=1e-15)
        for n in ("opacities", "scales"):
            torch.testing.assert_close(
                full["grads"][n] - base["grads"][n], 0.05 * grads[n], rtol=1e-9, atol=1e-17
            )


@pytest.mark.parametrize("backward", [True, False])
def test_a_step_leaves_nothing_alive_for_the_cycle_collector(backward: bool) -> None:
    """With Python's cycle collector off, a step's rasterisation outputs are freed by reference counting
    alone once the step is over (a reference cycle through the deferred GC hook kept every step's outputs on
    the GPU and ran a 140 GB card out of memory within 2000 steps)."""
    import gc
    import weakref

    view = make_view(50, "4:2:0")
    hook = new_hook(view, gc_pooling="deferred")
    hook.keep_last = False
    gc.collect()
    gc.disable()
    try:
        refs = []
        for _ in range(2):
            sp = make_splats()
            out = render(sp, hook.extra_channels(0, view, sp))
            ctx = StepContext(0, view, out.rgb, out.alpha, target_for(view), out.info, sp, None, {}, 0)
            h = hook.losses(ctx)
            if backward:
                (out.rgb.sum() + weighted_loss(h.terms, h.weights, h.folded, h.folded_loss)).backward()
            refs.append(weakref.ref(out.info["extra_features"]))
            del out, ctx, h, sp
        # the second step's outputs may wait for its backward (or the next step); the first's are gone
        assert refs[0]() is None
        if backward:
            assert refs[1]() is None
    finally:
        gc.enable()


def test_the_two_pooling_routes_agree() -> None:
    view = make_view(50, "4:2:0")
    a = train_step(new_hook(view, gc_pooling="deferred"), view)
    b = train_step(new_hook(view, gc_pooling="now"), view)
    assert a["terms"].keys() == b["terms"].keys()
    for k in a["terms"]:
        assert math.isclose(a["terms"][k], b["terms"][k], rel_tol=1e-12), k
    assert a["stats"] == pytest.approx(b["stats"], rel=1e-12)
    for n in a["grads"]:
        torch.testing.assert_close(a["grads"][n], b["grads"][n], rtol=1e-10, atol=1e-16)


# ---------------------------------------------------------------------------------------------------------
# ablations and options


def test_ablation_switches_change_exactly_their_terms() -> None:
    view = make_view(50, "4:2:0")
    full = train_step(new_hook(view), view)
    cases = {
        "no_ds": ({"ds": False}, {"obs", "fro"}),
        "no_gc": ({"gc": False}, {"obs", "low", "mid"}),
        "jo_only": ({"ds": False, "gc": False}, {"obs"}),
    }
    for name, (opts, expected) in cases.items():
        res = train_step(new_hook(view, **opts), view)
        assert set(res["terms"]) == expected, name
        assert set(res["weights"]) == expected, name
        for k in expected:
            assert math.isclose(res["terms"][k], full["terms"][k], rel_tol=1e-12), (name, k)
            assert res["weights"][k] == full["weights"][k], (name, k)
        assert bool(res["stats"]) == ("fro" in expected), name
        if "fro" in expected:
            assert res["stats"] == pytest.approx(full["stats"], rel=1e-12), name
    # GC only touches opacity and scale (above); dropping DS changes the image-domain gradients
    no_ds = train_step(new_hook(view, ds=False), view)
    assert not torch.allclose(no_ds["grads"]["sh0"], full["grads"]["sh0"])


def test_all_switches_off_is_the_baseline_and_no_jo_alone_is_refused(tmp_path: Path) -> None:
    scene = SimpleNamespace(train_views=[make_view(50)], manifest_path=tmp_path / "m.json")
    off = {"jo": False, "ds": False, "gc": False}
    cfg = TrainConfig.from_preset("paper", method="jsgs", method_options=off)
    assert make_hook(cfg, scene, torch.device("cpu")) is None
    for opts in ({"jo": False}, {"jo": False, "ds": False}, {"jo": False, "gc": False}):
        with pytest.raises(JsgsError, match="need JO"):
            parse_options(opts)


def test_lossless_views_get_the_photometric_loss_only() -> None:
    view = make_view(None)
    hook = new_hook(view)
    assert hook.extra_channels(0, view, make_splats()) is None
    res = train_step(hook, view)
    assert res["terms"] == {"obs": 0.0, "low": 0.0, "mid": 0.0, "fro": 0.0}
    assert res["stats"] == {"gc_visible": 0.0, "gc_rbar": 0.0, "gc_damped": 0.0}


def test_options_are_validated() -> None:
    o = parse_options({})
    assert (o.lambda_obs, o.lambda_low, o.lambda_mid, o.lambda_fro) == (0.2, 0.02, 0.03, 0.05)
    assert (o.tau_s, o.eps_sm, o.eps_dct_loss, o.eps_dct_block, o.eps_proj) == (1.0, 1e-3, 1e-6, 1e-6, 1e-6)
    assert (o.jpeg_mode, o.jo, o.ds, o.gc, o.gc_pooling) == ("paper", True, True, True, "deferred")
    bad = [
        ({"lambda_obz": 1}, "unknown setting method_options.lambda_obz"),
        ({"cuda_graph": True}, "unknown setting method_options.cuda_graph .known: .*speed"),
        ({"speed": {"gc_kernel": "fast"}}, "method_options.speed.gc_kernel must be one of"),
        ({"lambda_base": 2}, "loss.base_weight"),
        ({"lambda_fro": -1}, "must be >= 0"),
        ({"lambda_fro": "x"}, "finite number"),
        ({"tau_s": 0}, "must be > 0"),
        ({"jo": 1}, "true or false"),
        ({"jpeg_mode": "fast"}, "one of"),
        ({"gc_pooling": "later"}, "one of"),
    ]
    for opts, msg in bad:
        with pytest.raises(JsgsError, match=msg):
            parse_options(opts)


@pytest.mark.parametrize(("sampling", "gray"), [("other", False), ("gray", True)])
def test_unsupported_jpeg_states_are_refused_naming_the_view(
    sampling: str, gray: bool, tmp_path: Path
) -> None:
    v = make_view(50, sampling, index=3)
    if gray:
        v.jpeg = JpegState(v.jpeg.luma_table, None, "gray", 50, True, 8, "baseline")
    scene = SimpleNamespace(train_views=[make_view(50), v], manifest_path=tmp_path / "m.json")
    with pytest.raises(JsgsError, match="'v3'"):
        make_jsgs_hook(TrainConfig.from_preset("paper", method="jsgs"), scene, torch.device("cpu"))


# ---------------------------------------------------------------------------------------------------------
# end to end


def test_cli_train_method_jsgs_end_to_end(compressed_scene: Path, tmp_path: Path) -> None:
    from jsgs.cli import main

    cfg = {
        "init": {"type": "random", "num_points": 300, "scale": 0.3},
        "eval": {"fps_passes": 1, "fps_warmup": 0, "save_renders": False},
        "log_every": 4,
    }
    cfg_path = tmp_path / "cfg.json"
    cfg_path.write_text(json.dumps(cfg))
    run = tmp_path / "run"
    manifest = compressed_scene / "manifest.json"
    args = [
        "train", str(manifest), "--out", str(run), "--method", "jsgs", "--iterations", "24",
        "--eval-at", "12,24", "--device", "cpu", "--config", str(cfg_path), "--quiet", "--jpeg-mode", "float",
        "--preset", "paper",
    ]  # fmt: skip
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    doc = json.loads((run / "metrics.json").read_text())
    assert doc["status"] == "complete" and doc["method"] == "jsgs"
    for e in doc["evals"]:
        terms, stats = e["train"]["terms"], e["train"]["stats"]
        assert {"obs", "low", "mid", "fro", "photometric"} <= set(terms)
        assert set(stats) == {"gc_visible", "gc_rbar", "gc_damped"}
        assert all(math.isfinite(v) for v in [*terms.values(), *stats.values(), e["train"]["loss"]])
        assert terms["obs"] > 0 and terms["mid"] > 0 and stats["gc_visible"] > 0
        # the logged total includes L_fro, whose value is only known inside the backward (deferred pooling)
        w = {"photometric": 1.0, "obs": 0.2, "low": 0.02, "mid": 0.03, "fro": 0.05}
        assert e["train"]["loss"] == pytest.approx(sum(w[k] * terms[k] for k in w), rel=1e-5)
        # per-view sums partition the interval: step counts add up, step-weighted means give the totals back
        pv = e["train"]["per_view"]
        assert len(pv) > 1 and sum(v["steps"] for v in pv.values()) == e["train"]["steps"] == 12
        n = e["train"]["steps"]
        got = sum(v["steps"] * v["loss"] for v in pv.values()) / n
        assert got == pytest.approx(e["train"]["loss"], rel=1e-9)
        for k in terms:
            got = sum(v["steps"] * v["terms"][k] for v in pv.values()) / n
            assert got == pytest.approx(terms[k], rel=1e-9), k
    run_config = json.loads((run / "config.json").read_text())
    settings = run_config["settings"]
    assert settings["method_options"] == {"jpeg_mode": "float"}
    # what "auto" and the routes resolved to on this device
    resolved = {
        "color_kernel": "torch", "cuda_graph": False, "cuda_graph_gc": False, "gc_attribution": "probe",
        "gc_kernel": "torch", "gc_route": "deferred", "jo_kernel": "torch", "jpeg_mode": "float",
    }  # fmt: skip
    assert run_config["derived"]["method"] == resolved
    assert "--jpeg-mode float" in json.loads((run / "config.json").read_text())["command"]
    # the switches are refused where they do not apply, and --no-jo alone is refused
    gsplat = ["train", str(manifest), "--out", str(tmp_path / "x"), "--method", "gsplat"]
    r = CliRunner().invoke(main, [*gsplat, "--no-gc"])
    assert r.exit_code == 1 and "apply to --method jsgs" in r.output
    r = CliRunner().invoke(main, [*gsplat, "--compile", "inductor"])
    assert r.exit_code == 1 and "apply to --method jsgs" in r.output
    r = CliRunner().invoke(
        main,
        [
            "train",
            str(manifest),
            "--out",
            str(tmp_path / "y"),
            "--method",
            "jsgs",
            "--no-jo",
            "--device",
            "cpu",
        ],
    )
    assert r.exit_code == 1 and "need JO" in r.output


# ---------------------------------------------------------------------------------------------------------
# r̄ of the training path against the reference rasteriser on real data (CPU: torch backend on the synthetic
# compressed scene; GPU: the gsplat backend on a real scene — the number the README quotes)


def rbar_parity(manifest: Path, backend: str, device: torch.device, n_views: int) -> dict[str, float]:
    """r̄ and V of the JSGS training path (``render_view`` with the hook's probe, both GC routes, float32) on
    the first training views at SfM initialisation, against the reference rasteriser's direct pooling
    (``pool_direct``, float64) with the same r(p). Returns the worst figures over views and routes."""
    from jsgs.method.pooling import pool_direct
    from jsgs.train.data import load_image, load_training_scene
    from jsgs.train.model import activated, init_splats

    cfg = TrainConfig.from_preset("paper", method="jsgs", device=device.type)
    scene = load_training_scene(manifest, cfg)
    torch.manual_seed(0)
    splats = init_splats(
        torch.from_numpy(scene.points), torch.from_numpy(scene.points_rgb).float() / 255.0, cfg,
        scene.scene_scale, device,
    )  # fmt: skip
    tables = view_tables(scene.train_views, device, str(manifest))
    worst = {"contributor sets differ": 0.0, "rbar rel L2": 0.0, "rbar median rel": 0.0, "nu rel L2": 0.0}
    sizes = []
    for view in scene.train_views[:n_views]:
        target = load_image(view.image, view.width, view.height, "image").to(device).float()[None] / 255.0
        for route in ("deferred", "now"):
            hook = JsgsHook(parse_options({"gc_pooling": route}), tables)
            hook.keep_last = True
            out = render_view(
                splats, view.viewmat_tensor(device), view.K_tensor(device), view.width, view.height, 0, cfg,
                backend, hook.extra_channels(0, view, splats),
            )  # fmt: skip
            ctx = StepContext(0, view, out.rgb, out.alpha, target, out.info, splats, None, {}, 0)
            h = hook.losses(ctx)
            weighted_loss(h.terms, h.weights, h.folded, h.folded_loss).backward()
            for p in splats.values():
                p.grad = None
            last = hook.last
            p64 = {k: v.detach().double() for k, v in activated(splats).items()}
            direct = pool_direct(
                p64["means"], p64["quats"], p64["scales"], p64["opacities"],
                view.viewmat_tensor(device).double(), view.K_tensor(device).double(), view.width, view.height,
                last["ds"].pixel_score.double(),
            )  # fmt: skip
            vis_ref = direct.contributors[0]
            both = vis_ref & last["visible"]
            rb, rr = last["rbar"][both].double(), direct.rbar()[0][both]
            nu, nr = last["sums"].nu[0][both].double(), direct.nu[0][both]
            sizes.append(int(both.sum()))
            figures = {
                "contributor sets differ": (vis_ref != last["visible"]).double().mean().item(),
                "rbar rel L2": ((rb - rr).norm() / rr.norm()).item(),
                "rbar median rel": ((rb - rr).abs() / rr.clamp_min(1e-30)).median().item(),
                "nu rel L2": ((nu - nr).norm() / nr.norm()).item(),
            }
            worst = {k: max(worst[k], figures[k]) for k in worst}
    worst["min |V|"] = float(min(sizes))
    return worst


def test_rbar_parity_helper_on_the_synthetic_scene(compressed_scene: Path) -> None:
    rep = rbar_parity(compressed_scene / "manifest.json", "torch", torch.device("cpu"), n_views=1)
    assert rep["min |V|"] > 100
    assert rep["contributor sets differ"] < 1e-3 and rep["rbar rel L2"] < 1e-5 and rep["nu rel L2"] < 1e-5


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (gsplat's kernels do not run on CPU)")
def test_gpu_rbar_of_the_gsplat_path_matches_the_reference_on_a_real_scene(tmp_path: Path) -> None:
    # A lent GPU machine has neither ../shared nor pycolmap: a GPU run points this at a dataset
    # derived there from a carried clean base (JSGS_GPU_MANIFEST).
    env = os.environ.get("JSGS_GPU_MANIFEST")
    if env:
        manifest, name = Path(env), Path(env).parent.name
    else:
        from conftest import shared_scene

        from jsgstools.compress import compress

        src = shared_scene("custom_kwrous_cup")
        compress(src, tmp_path / "data", "gaussian", seed=0)
        manifest, name = tmp_path / "data" / "manifest.json", src.name
    rep = rbar_parity(manifest, "gsplat", torch.device("cuda"), n_views=3)
    print(f"\nJSGS r̄, gsplat training path vs reference rasteriser ({name}, first 3 training views):", rep)
    assert rep["min |V|"] > 100
    assert rep["contributor sets differ"] < 1e-3
    assert rep["rbar rel L2"] < 1e-4 and rep["nu rel L2"] < 1e-4


def test_jsgs_runs_resume_bit_exactly_with_densification(tmp_path: Path) -> None:
    """The deferred GC gradient, densification (which swaps the parameters after a backward) and resuming:
    a run split at step 4 equals the uninterrupted one exactly."""
    from _train_scene import make_scene

    from jsgs.train import checkpoint as ckpt
    from jsgs.train.trainer import train

    manifest = make_scene(tmp_path / "scene", jpeg_train=True)

    def cfg() -> TrainConfig:
        c = TrainConfig.from_preset("paper", method="jsgs", iterations=8, eval_at=[4, 8], device="cpu")
        c.strategy.refine_start_iter, c.strategy.refine_every = 1, 3
        c.eval.fps_passes, c.eval.fps_warmup, c.eval.save_renders = 1, 0, False
        return c

    a = train(manifest, tmp_path / "a", cfg(), progress=False)
    train(manifest, tmp_path / "b", cfg(), stop_at=4, progress=False)
    train(manifest, tmp_path / "b", None, resume=True, progress=False)
    ca = ckpt.load_checkpoint(tmp_path / "a" / "checkpoints" / "step_000008.pt")
    cb = ckpt.load_checkpoint(tmp_path / "b" / "checkpoints" / "step_000008.pt")
    n4 = ckpt.load_checkpoint(tmp_path / "a" / "checkpoints" / "step_000004.pt")["splats"]["means"].shape[0]
    assert 80 != n4 != ca["splats"]["means"].shape[0], "densification should act before and after the cut"
    for name, t in ca["splats"].items():
        assert torch.equal(t, cb["splats"][name]), name
    train_a = a["evals"][-1]["train"]
    assert train_a["stats"]["gc_visible"] > 0 and train_a["terms"]["fro"] > 0
    assert train_a == json.loads((tmp_path / "b" / "metrics.json").read_text())["evals"][-1]["train"]


def test_packed_rendering_is_refused_with_gc(tmp_path: Path) -> None:
    scene = SimpleNamespace(train_views=[make_view(50)], manifest_path=tmp_path / "m.json")
    cfg = TrainConfig.from_preset("paper", method="jsgs")
    cfg.render.packed = True
    with pytest.raises(JsgsError, match="packed"):
        make_jsgs_hook(cfg, scene, torch.device("cpu"))
    cfg.method_options = {"gc": False}
    assert make_jsgs_hook(cfg, scene, torch.device("cpu")) is not None


@pytest.mark.parametrize("mode", ["paper", "exact"])
def test_compiled_jpeg_terms_equal_eager(mode: str) -> None:
    """method_options.speed.compile traces JO, L_obs's ℓ_ph and DS with torch.compile; "aot_eager" checks on
    the CPU that the traced graphs (straight-through rounding included) give the eager values and
    gradients."""
    view = make_view(50, "4:2:0")
    eager = train_step(new_hook(view, jpeg_mode=mode), view)
    traced = train_step(new_hook(view, jpeg_mode=mode, compile="aot_eager"), view)
    assert set(traced["terms"]) == set(eager["terms"])
    for k, v in eager["terms"].items():
        assert traced["terms"][k] == pytest.approx(v, rel=1e-9, abs=1e-12), k
    for k, g in eager["grads"].items():
        assert torch.allclose(traced["grads"][k], g, rtol=1e-7, atol=1e-12), k


@pytest.mark.slow
def test_inductor_compiled_jpeg_terms_equal_eager() -> None:
    """The same with inductor itself (CPU code generation): its tracing of replication padding's backward on
    the colour transform's strided planes failed before jsgs.jpeg.sampling.pad_replicate made them
    contiguous under compile (aot_eager does not reach that check). A size that needs edge padding."""
    view = make_view(50, "4:2:0")
    eager = train_step(new_hook(view), view)
    compiled = train_step(new_hook(view, compile="inductor"), view)
    for k, v in eager["terms"].items():
        assert compiled["terms"][k] == pytest.approx(v, rel=1e-5, abs=1e-8), k
    for k, g in eager["grads"].items():
        torch.testing.assert_close(compiled["grads"][k], g, rtol=1e-4, atol=1e-7, msg=k)


def test_compile_failure_falls_back_to_eager(monkeypatch: pytest.MonkeyPatch, capsys: Any) -> None:
    """An internal compiler error (as torch 2.11's inductor raises on CUDA) runs the step eagerly instead
    of stopping the training: the same values and gradients as eager, one warning line, once."""
    from torch._dynamo.exc import TorchDynamoException

    calls = []

    def broken_compile(fn: Any, **kw: Any) -> Any:
        def run(*a: Any, **k: Any) -> Any:
            calls.append(fn.__name__)
            raise TorchDynamoException("internal compiler error\nsecond line")

        return run

    monkeypatch.setattr(torch, "compile", broken_compile)
    view = make_view(50, "4:2:0")
    eager = train_step(new_hook(view), view)
    hook = new_hook(view, compile="inductor")
    first = train_step(hook, view)
    second = train_step(hook, view)
    for k, v in eager["terms"].items():
        assert first["terms"][k] == v == second["terms"][k], k
    for k, g in eager["grads"].items():
        assert torch.equal(first["grads"][k], g), k
    assert sorted(calls) == ["dct_supervision", "jpeg_observe", "photometric_loss"]  # tried once each
    err = capsys.readouterr().err
    assert err.count("warning: torch.compile (inductor) of jpeg_observe failed") == 1
    assert "running it eagerly" in err and "second line" not in err


def test_quantization_noise_variance_of_ijg_tables() -> None:
    """Q²/12 per coefficient, averaged over Y and twice the chroma table, /3 channels: against Pillow's
    own tables, and monotone in the quality."""
    import io

    from PIL import Image

    from jsgs.method.image_terms import quantization_noise_variance

    values = []
    for q in (95, 90, 75, 50, 30, 10):
        buf = io.BytesIO()
        Image.new("RGB", (16, 16)).save(buf, "JPEG", quality=q)
        t = Image.open(buf).quantization
        qy, qc = np.array(t[0], dtype=np.float64), np.array(t[1], dtype=np.float64)
        v = quantization_noise_variance(qy, qc)
        assert v == pytest.approx((np.mean(qy**2) / 12 + 2 * np.mean(qc**2) / 12) / 3, rel=1e-12)
        values.append(v)
    assert values == sorted(values)
    assert 20 < values[1] < 26 and 500 < values[3] < 650  # q = 90, q = 50


@pytest.mark.parametrize(
    ("base_noise", "k", "b"),
    [("tables", 1.0, 0.0), ("pixels", 1.0, 0.0), ("pixels", 2.0, 0.0), ("pixels", 2.0, 0.1)],
)
def test_base_by_view_scales_the_photometric_weight(
    tmp_path: Path, base_noise: str, k: float, b: float
) -> None:
    """With base_by_view, each JPEG view's step loss carries λ_base·w·ℓ_ph, w = 1 / (1 + (σ²/σ_ref²)^k)
    (k = 1: σ_ref²/(σ_ref²+σ²)): recomputed from the logged terms of every step; σ² the tables' bound or the
    estimate from the file. With base_block_ref b, w is also divided by 1 + ((B − 1)/b)^k, B the blockiness
    of the view's decoded luma."""
    from _train_scene import make_scene

    from jsgs.base.images import read_ycbcr8
    from jsgs.jpeg.noise import blockiness, jpeg_noise_variance
    from jsgs.method.image_terms import quantization_noise_variance
    from jsgs.train.callbacks import Callback
    from jsgs.train.config import TrainConfig
    from jsgs.train.trainer import train

    manifest = make_scene(tmp_path / "scene", jpeg_train=True)
    doc = json.loads(manifest.read_text())
    noise, bound, grid = {}, {}, {}
    for v in doc["views"]:
        if v.get("jpeg"):
            qy, qc = np.array(v["jpeg"]["luma_table"]), np.array(v["jpeg"]["chroma_table"])
            bound[v["name"]] = quantization_noise_variance(qy, qc)
            dec = read_ycbcr8(manifest.parent / v["image"])
            noise[v["name"]] = jpeg_noise_variance(dec, qy, qc, v["jpeg"]["sampling"])
            grid[v["name"]] = blockiness(dec[..., 0])
            assert 0.0 < noise[v["name"]] < bound[v["name"]]
    if base_noise == "tables":
        noise = bound
    seen: list[tuple[str, float, dict[str, float]]] = []

    class Spy(Callback):
        def on_step_end(self, trainer: Any, result: Any) -> None:
            seen.append((result.view, result.loss, dict(result.terms)))

    cfg = TrainConfig.from_preset("paper", iterations=4, eval_at=[], device="cpu", method="jsgs")
    cfg.method_options = {"base_by_view": True, "base_noise_ref": 6.0, "base_noise": base_noise, "gc": False}
    if k != 1.0:
        cfg.method_options["base_noise_exponent"] = k
    if b:
        cfg.method_options["base_block_ref"] = b
        assert max(grid.values()) > 1.05  # the factor bites on these views

    def weight(name: str) -> float:
        var = noise[name]
        w = 36.0 / (36.0 + var) if k == 1.0 else 1.0 / (1.0 + (var / 36.0) ** k)
        return w / (1.0 + (max(grid[name] - 1.0, 0.0) / b) ** k) if b else w

    cfg.strategy.refine_start_iter = 10_000
    said: list[str] = []
    train(manifest, tmp_path / "run", cfg, progress=False, callbacks=[Spy()], log=said.append)
    assert len(seen) == 4
    for view, loss, terms in seen:
        w = weight(view)
        assert 0.0 < w < 1.0
        expect = w * terms["photometric"] + 0.2 * terms["obs"] + 0.02 * terms["low"] + 0.03 * terms["mid"]
        assert loss == pytest.approx(expect, rel=1e-6)
    # config.json records every JPEG view's σ² and weight; the start says how they spread
    derived = json.loads((tmp_path / "run" / "config.json").read_text())["derived"]
    by_view = derived["method"]["base_by_view"]
    assert set(by_view) == set(noise)
    for name, rec in by_view.items():
        assert rec["noise_variance"] == pytest.approx(noise[name], abs=1e-5)
        assert rec["weight"] == pytest.approx(weight(name), abs=1e-5)
        assert ("blockiness" in rec) == bool(b)
        if b:
            assert rec["blockiness"] == pytest.approx(grid[name], abs=1e-5)
    w = sorted(r["weight"] for r in by_view.values())
    note = [n for n in said if "base_by_view:" in n]
    assert len(note) == 1 and f"keep {w[0]:.2f}–{w[-1]:.2f} of ℓ_ph" in note[0]
    assert ("k = 2" in note[0]) == (k == 2.0)
    assert ("blockiness factor, b = 0.1" in note[0]) == bool(b)
    assert any("base_by_view:" in n for n in derived["notes"])
    assert any("measured the noise of" in n for n in said) == (base_noise == "pixels")
    assert any("blockiness of" in n and "from their files" in n for n in said) == bool(b)


def test_base_ramp_steps_lowers_each_views_weight_from_one(tmp_path: Path) -> None:
    """base_ramp_steps T: at 0-based step t < T a JPEG view's ℓ_ph weight is w + (1 − w)(1 − t/T) (1 at the
    first step), from T on its w; recomputed from the logged terms. Without base_by_view the setting is
    refused in one line."""
    from _train_scene import make_scene

    from jsgs.base.errors import JsgsError
    from jsgs.method.options import parse_options
    from jsgs.train.callbacks import Callback
    from jsgs.train.config import TrainConfig
    from jsgs.train.trainer import train

    manifest = make_scene(tmp_path / "scene", jpeg_train=True)
    seen: list[tuple[int, str, float, dict[str, float]]] = []

    class Spy(Callback):
        def on_step_end(self, trainer: Any, result: Any) -> None:
            seen.append((result.step, result.view, result.loss, dict(result.terms)))

    cfg = TrainConfig.from_preset("paper", iterations=6, eval_at=[], device="cpu", method="jsgs")
    cfg.method_options = {"base_by_view": True, "base_noise_ref": 6.0, "base_noise": "tables",
                          "base_noise_exponent": 2.0, "base_ramp_steps": 4, "gc": False}  # fmt: skip
    cfg.strategy.refine_start_iter = 10_000
    said: list[str] = []
    train(manifest, tmp_path / "run", cfg, progress=False, callbacks=[Spy()], log=said.append)
    final = {n: r["weight"] for n, r in json.loads((tmp_path / "run" / "config.json").read_text())["derived"][
        "method"]["base_by_view"].items()}  # fmt: skip
    assert [s for s, *_ in seen] == list(range(6))
    for step, view, loss, terms in seen:
        w = final[view]
        assert 0.0 < w < 1.0
        scale = w + (1.0 - w) * (1.0 - step / 4) if step < 4 else w
        expect = scale * terms["photometric"] + 0.2 * terms["obs"] + 0.02 * terms["low"] + 0.03 * terms["mid"]
        assert loss == pytest.approx(expect, rel=1e-5)
        # the ramp is not the final weight: at step 0 the loss is off by (1 − w)·ℓ_ph from the final weight's
        if step == 0:
            assert abs(loss - (expect - (1.0 - w) * terms["photometric"])) > 1e-3 * loss
    assert any("from 1 over the first 4 steps" in n for n in said)
    with pytest.raises(JsgsError, match=r"^cfg: method_options.base_ramp_steps \(10\).*base_by_view"):
        parse_options({"base_ramp_steps": 10}, "cfg")
    with pytest.raises(JsgsError, match=r"^cfg: method_options.base_block_ref \(0.5\).*base_by_view"):
        parse_options({"base_block_ref": 0.5}, "cfg")


def test_base_noise_pixels_takes_the_manifests_estimate(tmp_path: Path) -> None:
    """A manifest written with --analyze records each view's noise estimate and blockiness: base_noise
    pixels and base_block_ref use them (no second decode); without them the view's file is read, and tables
    keep the bound."""
    from _train_scene import make_scene

    from jsgs.method.image_terms import quantization_noise_variance, view_tables
    from jsgs.train.config import TrainConfig
    from jsgs.train.data import load_training_scene

    manifest = make_scene(tmp_path / "scene", jpeg_train=True)
    doc = json.loads(manifest.read_text())
    jpeg_views = [v for v in doc["views"] if v.get("jpeg")]
    first = jpeg_views[0]
    j = first["jpeg"]
    j["analysis"] = {"double_compressed": False, "confidence": 0.9, "evidence": 1.0, "primary_quality": None,
                     "primary_luma_table": None, "effective_luma_table": j["luma_table"],
                     "effective_chroma_table": j["chroma_table"], "noise_variance": 7.5,
                     "blockiness": 1.7}  # fmt: skip
    manifest.write_text(json.dumps(doc))
    views = load_training_scene(manifest, TrainConfig.from_preset("paper", device="cpu")).train_views
    cpu = torch.device("cpu")
    px = view_tables(views, cpu, "m", noise="pixels")
    tb = view_tables(views, cpu, "m", noise="tables")
    by_name = {v.name: v.index for v in views}
    assert px[by_name[first["name"]]].noise_variance == 7.5
    other = by_name[jpeg_views[1]["name"]]
    bound = quantization_noise_variance(np.array(jpeg_views[1]["jpeg"]["luma_table"]),
                                        np.array(jpeg_views[1]["jpeg"]["chroma_table"]))  # fmt: skip
    assert 0 < px[other].noise_variance < bound == tb[other].noise_variance
    # blockiness likewise: the recorded value, else measured from the file; 1 when not asked for
    from jsgs.base.images import read_ycbcr8
    from jsgs.jpeg.noise import blockiness

    bk = view_tables(views, cpu, "m", noise="pixels", blocks=True)
    assert bk[by_name[first["name"]]].blockiness == 1.7
    other_view = next(v for v in views if v.index == other)
    assert bk[other].blockiness == blockiness(read_ycbcr8(other_view.image)[..., 0]) != 1.0
    assert px[other].blockiness == 1.0


def test_many_estimates_are_announced_and_match_one_by_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Estimating many views' noise from their files says so first on stderr (it takes seconds per dozen
    photos) and runs several files at once: the values are those of one file at a time."""
    from _train_scene import make_scene

    import jsgs.method.image_terms as it
    from jsgs.base.images import read_ycbcr8
    from jsgs.jpeg.noise import jpeg_noise_variance
    from jsgs.train.config import TrainConfig
    from jsgs.train.data import load_training_scene

    manifest = make_scene(tmp_path / "scene", jpeg_train=True)
    views = load_training_scene(manifest, TrainConfig.from_preset("paper", device="cpu")).train_views
    jpeg_views = [v for v in views if v.jpeg is not None]
    monkeypatch.setattr(it, "ANNOUNCE_ESTIMATES", len(jpeg_views) - 1)
    got = it.view_tables(views, torch.device("cpu"), "m", noise="pixels")
    assert f"estimating the quantisation noise of {len(jpeg_views)} JPEG views" in capsys.readouterr().err
    for v in jpeg_views:
        j = v.jpeg
        qy, qc = (np.array(t, dtype=np.float64).reshape(8, 8) for t in (j.luma_table, j.chroma_table))
        one = jpeg_noise_variance(read_ycbcr8(v.image), qy, qc, j.sampling)
        assert got[v.index].noise_variance == one
    monkeypatch.setattr(it, "ANNOUNCE_ESTIMATES", len(jpeg_views))
    it.view_tables(views, torch.device("cpu"), "m", noise="pixels")
    assert capsys.readouterr().err == ""


def test_views_with_equal_tables_share_one_tensor_of_them(tmp_path: Path) -> None:
    """``view_tables``: JPEG views saved with the same tables hold one tensor of them (the graph then copies
    it into its input once, not view after view); a view with other tables holds its own, with its values."""
    from _train_scene import make_scene

    from jsgs.train.config import TrainConfig
    from jsgs.train.data import load_training_scene

    manifest = make_scene(tmp_path / "scene", jpeg_train=True)  # every training view at quality 75
    doc = json.loads(manifest.read_text())
    odd = next(v for v in doc["views"] if v.get("jpeg"))
    odd["jpeg"]["luma_table"] = np.minimum(np.array(odd["jpeg"]["luma_table"]) + 1, 255).tolist()
    manifest.write_text(json.dumps(doc))
    views = load_training_scene(manifest, TrainConfig.from_preset("paper", device="cpu")).train_views
    tabs = view_tables(views, torch.device("cpu"), "m")
    by_name = {v.name: tabs[v.index] for v in views if v.index in tabs}
    mine = by_name.pop(odd["name"])
    rest = list(by_name.values())
    assert len(rest) >= 2 and all(t.tables is rest[0].tables for t in rest)
    assert mine.tables is not rest[0].tables
    assert mine.tables[0].flatten().tolist() == np.array(odd["jpeg"]["luma_table"], float).ravel().tolist()
    assert torch.equal(mine.tables[1], rest[0].tables[1])
    assert not torch.equal(mine.tables[0], rest[0].tables[0])

