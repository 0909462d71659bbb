"""The JPEG building blocks against literal transcriptions of libjpeg-turbo's C code (plain Python integers)
and against float64; rounding semantics; gradcheck of the smooth parts."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from jsgs.jpeg import color, dct, rounding, sampling

pytestmark = pytest.mark.usefixtures("one_torch_thread")


# ----------------------------------------------------------------------------------------------------------
# Literal C transcriptions (jfdctint.c, jidctint.c, jccolor.c, jdcolor.c, jcsample.c, jdsample.c).
# ----------------------------------------------------------------------------------------------------------


def _descale(x: int, n: int) -> int:
    return (x + (1 << (n - 1))) >> n


def c_fdct_islow(block: list[list[int]]) -> list[list[int]]:
    data = [row[:] for row in block]

    def one_pass(get, put, first: bool) -> None:
        for i in range(8):
            d = [get(i, k) for k in range(8)]
            tmp0, tmp7 = d[0] + d[7], d[0] - d[7]
            tmp1, tmp6 = d[1] + d[6], d[1] - d[6]
            tmp2, tmp5 = d[2] + d[5], d[2] - d[5]
            tmp3, tmp4 = d[3] + d[4], d[3] - d[4]
            tmp10, tmp13, tmp11, tmp12 = tmp0 + tmp3, tmp0 - tmp3, tmp1 + tmp2, tmp1 - tmp2
            sh = 13 - 2 if first else 13 + 2
            if first:
                put(i, 0, (tmp10 + tmp11) << 2)
                put(i, 4, (tmp10 - tmp11) << 2)
            else:
                put(i, 0, _descale(tmp10 + tmp11, 2))
                put(i, 4, _descale(tmp10 - tmp11, 2))
            z1 = (tmp12 + tmp13) * 4433
            put(i, 2, _descale(z1 + tmp13 * 6270, sh))
            put(i, 6, _descale(z1 + tmp12 * -15137, sh))
            z1, z2, z3, z4 = tmp4 + tmp7, tmp5 + tmp6, tmp4 + tmp6, tmp5 + tmp7
            z5 = (z3 + z4) * 9633
            tmp4, tmp5, tmp6, tmp7 = tmp4 * 2446, tmp5 * 16819, tmp6 * 25172, tmp7 * 12299
            z1, z2, z3, z4 = z1 * -7373, z2 * -20995, z3 * -16069, z4 * -3196
            z3 += z5
            z4 += z5
            put(i, 7, _descale(tmp4 + z1 + z3, sh))
            put(i, 5, _descale(tmp5 + z2 + z4, sh))
            put(i, 3, _descale(tmp6 + z2 + z3, sh))
            put(i, 1, _descale(tmp7 + z1 + z4, sh))

    def put_row(i, k, v):
        data[i][k] = v

    def put_col(i, k, v):
        data[k][i] = v

    one_pass(lambda i, k: data[i][k], put_row, True)
    one_pass(lambda i, k: data[k][i], put_col, False)
    return data


def c_idct_islow(coef: list[list[int]]) -> list[list[int]]:
    """jpeg_idct_islow on dequantized coefficients, output before range limiting (pre +128)."""
    ws = [[0] * 8 for _ in range(8)]
    out = [[0] * 8 for _ in range(8)]

    def one_pass(c: list[int], sh: int) -> list[int]:
        z2, z3 = c[2], c[6]
        z1 = (z2 + z3) * 4433
        tmp2 = z1 + z3 * -15137
        tmp3 = z1 + z2 * 6270
        tmp0 = (c[0] + c[4]) << 13
        tmp1 = (c[0] - c[4]) << 13
        tmp10, tmp13, tmp11, tmp12 = tmp0 + tmp3, tmp0 - tmp3, tmp1 + tmp2, tmp1 - tmp2
        tmp0, tmp1, tmp2, tmp3 = c[7], c[5], c[3], c[1]
        z1, z2, z3, z4 = tmp0 + tmp3, tmp1 + tmp2, tmp0 + tmp2, tmp1 + tmp3
        z5 = (z3 + z4) * 9633
        tmp0, tmp1, tmp2, tmp3 = tmp0 * 2446, tmp1 * 16819, tmp2 * 25172, tmp3 * 12299
        z1, z2, z3, z4 = z1 * -7373, z2 * -20995, z3 * -16069, z4 * -3196
        z3 += z5
        z4 += z5
        tmp0 += z1 + z3
        tmp1 += z2 + z4
        tmp2 += z2 + z3
        tmp3 += z1 + z4
        r = [tmp10 + tmp3, tmp11 + tmp2, tmp12 + tmp1, tmp13 + tmp0, tmp13 - tmp0, tmp12 - tmp1, tmp11 - tmp2,
             tmp10 - tmp3]
        return [_descale(v, sh) for v in r]

    for col in range(8):
        res = one_pass([coef[r][col] for r in range(8)], 11)
        for r in range(8):
            ws[r][col] = res[r]
    for row in range(8):
        out[row] = one_pass(ws[row], 18)
    return out


def c_range_limit(x: int) -> int:
    table = [min(i, 255) for i in range(128, 512)]  # x & 1023 in [0, 384) -> x + 128, saturating
    i = x & 1023
    if i < 384:
        return table[i] if i >= 0 else 0
    if i < 896:
        return 255 if i < 512 else 0
    return i - 896


# ----------------------------------------------------------------------------------------------------------


def _random_blocks(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    blocks = rng.integers(-128, 128, (n, 8, 8))
    blocks[0] = -128
    blocks[1] = 127
    blocks[2] = np.where((np.add.outer(np.arange(8), np.arange(8)) % 2) == 0, 127, -128)  # Nyquist
    blocks[3] = np.arange(64).reshape(8, 8) * 4 - 128
    return blocks


def test_fdct_islow_matches_c_transcription() -> None:
    blocks = _random_blocks(60, 0)
    got = dct.fdct_islow(torch.tensor(blocks, dtype=torch.float64)).numpy()
    for b, g in zip(blocks, got, strict=True):
        assert np.array_equal(g, np.array(c_fdct_islow(b.tolist()))), b
    # float32 emulation (mode "float") agrees on these blocks too
    got32 = dct.fdct_islow(torch.tensor(blocks, dtype=torch.float32), torch.float32).numpy()
    assert np.mean(got32 == got) > 0.999


def test_fdct_islow_is_eight_times_orthonormal_dct() -> None:
    blocks = torch.tensor(_random_blocks(20, 1), dtype=torch.float64)
    diff = dct.fdct_islow(blocks) - 8 * dct.block_dct(blocks)
    assert diff.abs().max() < 4  # fixed-point rounding only (units of 1/8 orthonormal)


def test_idct_islow_and_range_limit_match_c_transcription() -> None:
    rng = np.random.default_rng(2)
    coefs = rng.integers(-60, 61, (40, 8, 8)) * rng.integers(1, 256, (40, 8, 8)) // 8
    coefs[0] = 0
    coefs[1, 0, 0] = 1024 * 3  # saturates high
    coefs[2, 0, 0] = -1024 * 3  # wraps in libjpeg's table
    got = dct.idct_islow(torch.tensor(coefs, dtype=torch.float64))
    lim = dct.range_limit(got).numpy()
    for c, g, li in zip(coefs, got.numpy(), lim, strict=True):
        ref = np.array(c_idct_islow(c.tolist()))
        assert np.array_equal(g, ref)
        assert np.array_equal(li, np.vectorize(c_range_limit)(ref))


def test_range_limit_table() -> None:
    x = torch.arange(-2048, 2048, dtype=torch.float64)
    got = dct.range_limit(x).numpy()
    assert np.array_equal(got, [c_range_limit(int(v)) for v in x])
    assert got[2048 - 128] == 0 and got[2048 + 127] == 255 and got[2048 + 500] == 255 and got[2048 - 500] == 0


def test_orthonormal_dct_roundtrip_and_blocks() -> None:
    d = dct.dct_matrix(torch.float64)
    assert torch.allclose(d @ d.T, torch.eye(8, dtype=torch.float64), atol=1e-14)
    x = torch.rand(2, 3, 16, 24, dtype=torch.float64)
    b = dct.blockify(x)
    assert b.shape == (2, 3, 2, 3, 8, 8)
    assert torch.equal(b[1, 2, 1, 2], x[1, 2, 8:16, 16:24])
    assert torch.equal(dct.unblockify(b), x)
    assert torch.allclose(dct.block_idct(dct.block_dct(b)), b, atol=1e-12)
    const = torch.full((8, 8), 3.0, dtype=torch.float64)
    assert dct.block_dct(const)[0, 0].item() == pytest.approx(24.0)


def test_colour_conversion_matches_c() -> None:
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (3, 4000))
    rgb[:, :8] = np.array([[0, 0, 0], [255, 255, 255], [255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0],
                           [0, 255, 255], [1, 254, 128]]).T
    r, g, b = (v.astype(np.int64) for v in rgb)
    y = (19595 * r + 38470 * g + 7471 * b + 32768) >> 16
    cb = (-11059 * r - 21709 * g + 32768 * b + (128 << 16) + 32767) >> 16
    cr = (32768 * r - 27439 * g - 5329 * b + (128 << 16) + 32767) >> 16
    t = torch.tensor(rgb, dtype=torch.float32).reshape(3, 40, 100)
    got = color.rgb_to_ycbcr_libjpeg(t).reshape(3, -1).numpy()
    assert np.array_equal(got, np.stack([y, cb, cr]))

    ycc = rng.integers(0, 256, (3, 4000))
    yy, cb, cr = (v.astype(np.int64) - np.array([0, 128, 128])[i] for i, v in enumerate(ycc))
    rr = np.clip(yy + ((91881 * cr + 32768) >> 16), 0, 255)
    gg = np.clip(yy + ((-22554 * cb - 46802 * cr + 32768) >> 16), 0, 255)
    bb = np.clip(yy + ((116130 * cb + 32768) >> 16), 0, 255)
    got = color.ycbcr_to_rgb_libjpeg(torch.tensor(ycc, dtype=torch.float32).reshape(3, 40, 100))
    assert np.array_equal(got.reshape(3, -1).numpy(), np.stack([rr, gg, bb]))


def test_float_colour_is_the_unrounded_integer_one() -> None:
    rgb = torch.randint(0, 256, (2, 3, 9, 7)).double()
    f = color.rgb_to_ycbcr(rgb)
    i = color.rgb_to_ycbcr_libjpeg(rgb)
    assert (f - i).abs().max() <= 0.5 + 1e-9
    assert torch.allclose(color.ycbcr_to_rgb(f), rgb, atol=0.05)  # inverse up to the 16-bit constants


def c_downsample(plane: np.ndarray, h: int, v: int) -> np.ndarray:
    """h2v1 / h2v2_downsample, and int_downsample (jcsample.c) for the other factors."""
    rows, cols = plane.shape[0] // v, plane.shape[1] // h
    out = np.zeros((rows, cols), np.int64)
    if (h, v) not in ((2, 1), (2, 2)):
        numpix = h * v
        for r in range(rows):
            for c in range(cols):
                out[r, c] = (int(plane[v * r : v * r + v, h * c : h * c + h].sum()) + numpix // 2) // numpix
        return out
    for r in range(rows):
        bias = 1 if v == 2 else 0
        for c in range(cols):
            s = int(plane[v * r : v * r + v, h * c : h * c + h].sum())
            out[r, c] = (s + bias) >> (1 if v == 1 else 2)
            bias = (bias ^ 3) if v == 2 else (bias ^ 1)
    return out


def c_upsample(plane: np.ndarray, h: int, v: int) -> np.ndarray:
    """h2v1 / h2v2 fancy up-sampling (jdsample.c) with libjpeg's edge context, replication if width <= 2;
    h1v2_fancy_upsample (any width); int_upsample (replication) for h4v1."""
    rows, w = plane.shape
    p = plane.astype(np.int64)
    if (h, v) == (4, 1):
        return np.repeat(p, 4, 1)
    if (h, v) == (1, 2):
        out = np.zeros((2 * rows, w), np.int64)
        for r in range(rows):
            for k, (other, bias) in enumerate(((max(r - 1, 0), 1), (min(r + 1, rows - 1), 2))):
                out[2 * r + k] = (3 * p[r] + p[other] + bias) >> 2
        return out
    if w <= 2:
        return np.repeat(np.repeat(p, v, 0), h, 1)
    if v == 1:
        out = np.zeros((rows, 2 * w), np.int64)
        for r in range(rows):
            x = p[r]
            out[r, 0] = x[0]
            out[r, 1] = (x[0] * 3 + x[1] + 2) >> 2
            for c in range(1, w - 1):
                out[r, 2 * c] = (3 * x[c] + x[c - 1] + 1) >> 2
                out[r, 2 * c + 1] = (3 * x[c] + x[c + 1] + 2) >> 2
            out[r, 2 * w - 2] = (x[w - 1] * 3 + x[w - 2] + 1) >> 2
            out[r, 2 * w - 1] = x[w - 1]
        return out
    out = np.zeros((2 * rows, 2 * w), np.int64)
    for r in range(rows):
        for k, other in enumerate((max(r - 1, 0), min(r + 1, rows - 1))):
            cs = 3 * p[r] + p[other]
            o = out[2 * r + k]
            o[0] = (cs[0] * 4 + 8) >> 4
            o[1] = (cs[0] * 3 + cs[1] + 7) >> 4
            for c in range(1, w - 1):
                o[2 * c] = (cs[c] * 3 + cs[c - 1] + 8) >> 4
                o[2 * c + 1] = (cs[c] * 3 + cs[c + 1] + 7) >> 4
            o[2 * w - 2] = (cs[w - 1] * 3 + cs[w - 2] + 8) >> 4
            o[2 * w - 1] = (cs[w - 1] * 4 + 7) >> 4
    return out


@pytest.mark.parametrize("h,v", [(2, 1), (2, 2), (1, 2), (4, 1)])
@pytest.mark.parametrize("shape", [(2, 2), (4, 6), (6, 10), (1, 2), (2, 4)])
def test_resampling_matches_c(h: int, v: int, shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(shape[0] * 31 + shape[1])
    full = rng.integers(0, 256, (shape[0] * v, shape[1] * h))
    t = torch.tensor(full, dtype=torch.float32)[None, None]
    assert np.array_equal(sampling.downsample_libjpeg(t, h, v)[0, 0].numpy(), c_downsample(full, h, v))
    small = rng.integers(0, 256, shape)
    for width in (shape[1], 1, 2, 3):
        s = small[:, :width]
        got = sampling.upsample_libjpeg(torch.tensor(s, dtype=torch.float32)[None, None], h, v)[0, 0]
        assert np.array_equal(got.numpy(), c_upsample(s, h, v)), (s, got)
        flt = sampling.upsample(torch.tensor(s, dtype=torch.float64)[None, None], h, v)[0, 0].numpy()
        assert np.abs(flt - got.numpy()).max() <= 1.0


def test_float_upsampling_is_bilinear_align_corners_false() -> None:
    x = torch.rand(1, 2, 5, 7, dtype=torch.float64)
    ref = torch.nn.functional.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
    assert torch.allclose(sampling.upsample(x, 2, 2), ref, atol=1e-12)
    assert torch.allclose(sampling.downsample(ref, 2, 2), torch.nn.functional.avg_pool2d(ref, 2))


def test_pad_replicate() -> None:
    x = torch.arange(6.0).reshape(1, 1, 2, 3)
    p = sampling.pad_replicate(x, 4, 5)
    assert p.shape == (1, 1, 4, 5)
    assert torch.equal(p[0, 0, 3], torch.tensor([3.0, 4, 5, 5, 5]))


# ----------------------------------------------------------------------------------------------------------
# Rounding
# ----------------------------------------------------------------------------------------------------------


def test_round_half_away_and_quantizer_on_half_boundaries() -> None:
    z = torch.tensor([-2.5, -1.5, -0.5, 0.5, 1.5, 2.5, 0.49999, -0.49999])
    assert rounding.round_half_away(z).tolist() == [-3, -2, -1, 1, 2, 3, 0, -0]
    q = torch.tensor(16.0)
    # t = 8 Q (k + 1/2) exactly: libjpeg rounds away from zero
    t = torch.tensor([64.0, -64.0, 192.0, -192.0, 63.0, -63.0], dtype=torch.float64)
    assert rounding.quantize_libjpeg(t, q).tolist() == [1, -1, 2, -2, 0, 0]


def test_soft_round_value_and_gradient() -> None:
    z = torch.tensor([-1.3, -0.5, 0.0, 0.2, 0.5, 0.75, 2.0, 3.4], dtype=torch.float64, requires_grad=True)
    r = torch.sign(z.detach()) * torch.floor(z.detach().abs() + 0.5)
    d = z.detach() - r
    y = rounding.soft_round(z)
    assert torch.allclose(y, r + d**3)
    (g,) = torch.autograd.grad(y.sum(), z)
    assert torch.allclose(g, 3 * d**2)
    # The derivative vanishes at integers (eq. soft_round with round treated as zero-gradient).
    assert g[2].item() == 0.0 and g[6].item() == 0.0
    assert g[4].item() == pytest.approx(0.75)

    y2 = rounding.round_soft_grad(z)
    assert torch.equal(y2.detach(), r)  # hard rounding, exactly
    (g2,) = torch.autograd.grad(y2.sum(), z)
    assert torch.allclose(g2, 3 * d**2)

    x = torch.tensor([0.4, 0.5, 254.7], requires_grad=True)
    s = rounding.round_ste(x)
    assert s.tolist() == [0.0, 1.0, 255.0]
    (g3,) = torch.autograd.grad(s.sum(), x)
    assert g3.tolist() == [1.0, 1.0, 1.0]


# ----------------------------------------------------------------------------------------------------------
# gradcheck of the smooth parts and float32 vs float64
# ----------------------------------------------------------------------------------------------------------


def test_gradcheck_smooth_parts() -> None:
    gc = torch.autograd.gradcheck
    b = torch.rand(2, 8, 8, dtype=torch.float64, requires_grad=True)
    assert gc(dct.block_dct, (b,))
    assert gc(dct.block_idct, (b,))
    rgb = (255 * torch.rand(1, 3, 4, 6, dtype=torch.float64)).requires_grad_()
    assert gc(color.rgb_to_ycbcr, (rgb,))
    assert gc(color.ycbcr_to_rgb, (rgb,))
    assert gc(lambda x: sampling.downsample(x, 2, 2), (rgb,))
    assert gc(lambda x: sampling.upsample(x, 2, 2), (rgb,))
    assert gc(lambda x: sampling.upsample(x, 2, 1), (rgb,))
    assert gc(lambda x: sampling.pad_replicate(x, 8, 8), (rgb,))


def test_float32_within_1e5_of_float64() -> None:
    x64 = torch.rand(2, 3, 16, 24, dtype=torch.float64)
    x32 = x64.float()
    cases = [
        (lambda x: dct.block_dct(dct.blockify(x - 0.5)), 1e-5),
        (lambda x: dct.block_idct(dct.blockify(x - 0.5)), 1e-5),
        (lambda x: color.rgb_to_ycbcr(x) / 255, 1e-5),
        (lambda x: color.ycbcr_to_rgb(x) / 255, 1e-5),
        (lambda x: sampling.upsample(sampling.downsample(x, 2, 2), 2, 2), 1e-5),
    ]
    for f, tol in cases:
        assert (f(x32).double() - f(x64)).abs().max() < tol
