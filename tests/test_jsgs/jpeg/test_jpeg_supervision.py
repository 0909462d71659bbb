"""DCT supervision (DS) against an independent float64 computation written straight from the paper's equations
(explicit loops over blocks and coordinates), on hand-checkable tables: all 1s, all 255s, IJG q = 50."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from jsgs.jpeg import supervision as S
from jsgs.jpeg.tables import ijg_tables

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def paper_reference(obs: np.ndarray, tgt: np.ndarray, table: np.ndarray, eps_sm=1e-3, eps=1e-6) -> dict:
    """Eqs. omega .. jsgs_block_score for one view, float64, loops. obs/tgt: H x W x 3 in [0, 1];
    table[v][u] natural order."""
    h, w, _ = obs.shape

    def y8(x: np.ndarray) -> np.ndarray:  # eq. jsgs_luminance
        return 255.0 * (0.299 * x[..., 0] + 0.587 * x[..., 1] + 0.114 * x[..., 2])

    def dct2(block: np.ndarray) -> np.ndarray:  # orthonormal DCT-II, C[v, u]
        out = np.zeros((8, 8))
        for v in range(8):
            for u in range(8):
                cu = math.sqrt(1 / 8) if u == 0 else math.sqrt(2 / 8)
                cv = math.sqrt(1 / 8) if v == 0 else math.sqrt(2 / 8)
                s = 0.0
                for y in range(8):
                    for x in range(8):
                        s += block[y, x] * math.cos((2 * x + 1) * u * math.pi / 16) * math.cos(
                            (2 * y + 1) * v * math.pi / 16)
                out[v, u] = cu * cv * s
        return out

    yi, yj = y8(tgt) - 128, y8(obs) - 128  # eq. jsgs_level_shift
    nby, nbx = h // 8, w // 8
    omega = np.zeros((8, 8))
    m_low = np.zeros((8, 8))
    m_mid = np.zeros((8, 8))
    for v in range(8):
        for u in range(8):
            f = u + v
            omega[v, u] = math.exp(-2 * (table[v, u] - 1) / 254 - f / 14)
            m_low[v, u] = 1.0 if f <= 3 else 0.0
            m_mid[v, u] = 1.0 if 3 < f <= 5 else 0.0
    w_mid = m_mid * omega
    e = np.zeros((nby, nbx))
    low_num = 0.0
    deltas = np.zeros((nby, nbx, 8, 8))
    for by in range(nby):
        for bx in range(nbx):
            ci = dct2(yi[8 * by : 8 * by + 8, 8 * bx : 8 * bx + 8])
            cj = dct2(yj[8 * by : 8 * by + 8, 8 * bx : 8 * bx + 8])
            delta = (cj - ci) / 255
            deltas[by, bx] = delta
            pen = np.sqrt(delta**2 + eps_sm**2) - eps_sm
            e[by, bx] = float((w_mid * pen).sum())
            low_num += float((m_low * pen).sum())
    nb = nby * nbx
    l_low = low_num / (nb * m_low.sum() + eps)
    l_mid = e.sum() / (nb * w_mid.sum() + eps)
    r_b = e / (w_mid.sum() + eps)
    r_p = np.zeros((h, w))
    for y in range(nby * 8):
        for x in range(nbx * 8):
            r_p[y, x] = r_b[y // 8, x // 8]
    return {"omega": omega, "w_mid": w_mid, "delta": deltas, "e": e, "l_low": l_low, "l_mid": l_mid,
            "r_b": r_b, "r_p": r_p}


TABLES = {
    "ones": np.ones((8, 8)),
    "all255": np.full((8, 8), 255.0),
    "ijg50": ijg_tables(50)[0].astype(np.float64),
}


@pytest.mark.parametrize("name", list(TABLES))
def test_matches_paper_reference(name: str) -> None:
    rng = np.random.default_rng(len(name))
    h, w = 17, 26  # 2 x 3 valid blocks, partial blocks at the bottom / right
    obs = rng.random((h, w, 3))
    tgt = np.clip(obs + rng.normal(0, 0.05, obs.shape), 0, 1)
    table = TABLES[name]
    ref = paper_reference(obs, tgt, table)
    to_t = lambda a: torch.tensor(a).permute(2, 0, 1)[None]  # noqa: E731
    out = S.dct_supervision(to_t(obs), to_t(tgt), torch.tensor(table)[None])
    assert np.allclose(out.omega[0].numpy(), ref["omega"], rtol=1e-12)
    assert np.allclose(out.w_mid[0].numpy(), ref["w_mid"], rtol=1e-12)
    assert np.allclose(out.delta[0].numpy(), ref["delta"], atol=1e-12)
    assert np.allclose(out.block_error[0].numpy(), ref["e"], rtol=1e-10)
    assert out.loss_low[0].item() == pytest.approx(ref["l_low"], rel=1e-10)
    assert out.loss_mid[0].item() == pytest.approx(ref["l_mid"], rel=1e-10)
    assert np.allclose(out.block_score[0].numpy(), ref["r_b"], rtol=1e-10)
    assert np.allclose(out.pixel_score[0].numpy(), ref["r_p"], rtol=1e-10)
    assert out.pixel_score.shape == (1, h, w) and out.pixel_score[0, 16:].abs().sum() == 0


def test_hand_checked_values() -> None:
    # omega: all-1 table -> exp(-F/14); all-255 -> exp(-2 - F/14); IJG q=50 at (v, u) = (0, 0): T = 16.
    f = S.frequency_index(torch.float64)
    assert torch.allclose(S.omega(torch.ones(8, 8, dtype=torch.float64)), torch.exp(-f / 14))
    assert torch.allclose(S.omega(torch.full((8, 8), 255.0, dtype=torch.float64)), torch.exp(-2 - f / 14))
    o50 = S.omega(torch.tensor(ijg_tables(50)[0], dtype=torch.float64))
    assert o50[0, 0].item() == pytest.approx(math.exp(-2 * 15 / 254))
    assert o50[2, 3].item() == pytest.approx(math.exp(-2 * 23 / 254 - 5 / 14))  # T[2][3] = 24, F = 5
    assert S.low_mask().sum() == 10 and S.mid_mask().sum() == 11
    assert S.mid_mask()[0, 4] == 1 and S.mid_mask()[5, 0] == 1 and S.mid_mask()[3, 3] == 0
    assert S.psi(torch.tensor(0.0)).item() == 0.0
    assert S.psi(torch.tensor(1.0), 1e-3).item() == pytest.approx(math.sqrt(1 + 1e-6) - 1e-3)
    # Identical images: every term is 0.
    x = torch.rand(1, 3, 16, 16)
    out = S.dct_supervision(x, x, torch.ones(8, 8))
    assert out.loss_low.abs().max() < 1e-7 and out.loss_mid.abs().max() < 1e-7
    # A pure DC offset of d levels in every pixel: Delta_DC = 8 d / 255, all other Delta 0.
    y = torch.zeros(1, 3, 8, 8, dtype=torch.float64)
    out = S.dct_supervision(y + 10 / 255, y, torch.ones(8, 8, dtype=torch.float64))
    assert out.delta[0, 0, 0, 0, 0].item() == pytest.approx(80 / 255)
    assert out.loss_low.item() == pytest.approx((math.sqrt((80 / 255) ** 2 + 1e-6) - 1e-3) / (10 + 1e-6))
    assert out.loss_mid.item() == pytest.approx(0.0, abs=1e-9)


def test_small_images_and_16bit_tables_are_finite() -> None:
    tables = torch.tensor(np.stack([np.ones((8, 8)), np.full((8, 8), 255), np.full((8, 8), 1000),
                                    np.full((8, 8), 30000), np.full((8, 8), 65535)]), dtype=torch.float32)
    for h, w in ((1, 1), (7, 9), (17, 33), (1, 1000), (8, 8)):
        obs = torch.rand(5, 3, h, w, requires_grad=True)
        out = S.dct_supervision(obs, torch.rand(5, 3, h, w), tables)
        for t in out:
            assert torch.isfinite(t).all()
        (g,) = torch.autograd.grad((out.loss_low + out.loss_mid + out.block_score.sum((1, 2))).sum(), obs)
        assert torch.isfinite(g).all()
        if h < 8 or w < 8:
            assert out.loss_low.abs().sum() == 0 and out.pixel_score.abs().sum() == 0
    # 16-bit tables: omega keeps decreasing past 255 (no clamp), underflows to 0 in float32, stays finite.
    om = S.omega(tables)
    assert (om[1] > om[2]).all() and (om[2] > om[3]).all() and (om[4] == 0).all()


def test_batch_equals_views_one_by_one_and_float32() -> None:
    obs = torch.rand(3, 3, 24, 17, dtype=torch.float64)
    tgt = torch.rand(3, 3, 24, 17, dtype=torch.float64)
    tables = torch.tensor(np.stack(list(TABLES.values())))
    out = S.dct_supervision(obs, tgt, tables)
    for i in range(3):
        one = S.dct_supervision(obs[i : i + 1], tgt[i : i + 1], tables[i])
        for a, b in zip(one, out, strict=True):
            assert torch.allclose(a[0], b[i], rtol=1e-12, atol=1e-15)
    out32 = S.dct_supervision(obs.float(), tgt.float(), tables.float())
    for a, b in zip(out32, out, strict=True):
        assert (a.double() - b).abs().max() < 1e-5


def test_weights_made_beforehand_are_bit_identical() -> None:
    # a view's DS weights are made once (table_weights) and passed to every step: the same bits as DS's own,
    # for an integer table, a float one and a batch, in float32 and float64, with the same gradient
    for dtype in (torch.float32, torch.float64):
        obs = torch.rand(2, 3, 24, 17, dtype=dtype, requires_grad=True)
        tgt = torch.rand(2, 3, 24, 17, dtype=dtype)
        for table in (torch.tensor(TABLES["ijg50"]), torch.tensor(ijg_tables(90)[0]).float(),
                      torch.tensor(np.stack([ijg_tables(10)[0], ijg_tables(90)[0]]))):  # fmt: skip
            own = S.dct_supervision(obs, tgt, table)
            given = S.dct_supervision(obs, tgt, table, weights=S.table_weights(table, 2, dtype))
            for a, b in zip(own, given, strict=True):
                assert a.dtype == b.dtype and torch.equal(a, b)
            g_own = torch.autograd.grad(own.loss_mid.sum() + own.loss_low.sum(), obs)[0]
            g_given = torch.autograd.grad(given.loss_mid.sum() + given.loss_low.sum(), obs)[0]
            assert torch.equal(g_own, g_given)


def test_gradcheck() -> None:
    obs = torch.rand(1, 3, 8, 16, dtype=torch.float64, requires_grad=True)
    tgt = torch.rand(1, 3, 8, 16, dtype=torch.float64)
    table = torch.tensor(TABLES["ijg50"])

    def f(x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = S.dct_supervision(x, tgt, table)
        return out.loss_low, out.loss_mid, out.block_score

    assert torch.autograd.gradcheck(f, (obs,))
    assert torch.autograd.gradcheck(S.psi, (torch.randn(20, dtype=torch.float64, requires_grad=True) * 1e-3,))


def test_host_tables_must_hold_quantization_steps() -> None:
    """DS's weights from a table given as an array: integers 1..65535, else a ValueError naming it (a 0 or a
    negative step gave weights above 1, NaN a NaN loss)."""
    obs, target = torch.rand(1, 3, 16, 16), torch.rand(1, 3, 16, 16)
    for bad in (np.zeros((8, 8)), -np.ones((8, 8)), np.full((8, 8), np.nan), np.full((8, 8), 0.5)):
        with pytest.raises(ValueError, match=r"^luma_table: entry .* is not a quantization step"):
            S.dct_supervision(obs, target, bad)
    ok = S.dct_supervision(obs, target, np.full((8, 8), 65535))
    assert torch.isfinite(ok.loss_low).all() and torch.isfinite(ok.loss_mid).all()
