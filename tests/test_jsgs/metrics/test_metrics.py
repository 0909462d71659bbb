"""PSNR, and ``evaluate_images`` (PSNR + SSIM + LPIPS per view, averaged) as the trainer calls it."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import pytest
import torch

import jsgs.kernels
from jsgs.metrics import ImageMetrics, evaluate_images, psnr
from jsgs.metrics import lpips as L

SHARED_WEIGHTS = Path(__file__).resolve().parents[4] / "shared" / "lpips" / "alexnet_features.pth"


@pytest.fixture(autouse=True)
def _fresh_state(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(L.ENV_VAR, raising=False)
    monkeypatch.setattr(L, "_warned", set())
    monkeypatch.setattr(L, "_download_failure", None)


@pytest.fixture
def stub_ssim(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, ...]]:
    """Replace ``jsgs.kernels.ssim`` by a stub returning 1 - mean |x - y| and recording the shapes it was
    given, so that the plumbing of ``evaluate_images`` is tested apart from SSIM."""
    calls: list[tuple[int, ...]] = []

    def ssim(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        calls.append(tuple(x.shape))
        return 1 - (x - y).abs().mean()

    monkeypatch.setattr(jsgs.kernels, "ssim", ssim)
    return calls


def test_psnr_known_values() -> None:
    ref = torch.full((2, 3, 4, 5), 0.5, dtype=torch.float64)
    pred = ref.clone()
    pred[0] += 0.1  # MSE 0.01 -> 20 dB
    pred[1, :, :2] += 0.01  # 1e-4 on 2 of 4 rows -> MSE 5e-5 -> 43.01 dB
    v = psnr(pred, ref)
    assert v.dtype == torch.float64 and v.shape == (2,)
    assert v[0].item() == pytest.approx(20.0, abs=1e-9)
    assert v[1].item() == pytest.approx(-10 * math.log10(1e-4 * 2 / 4), abs=1e-6)
    assert psnr(ref[0], ref[0]).item() == math.inf
    with pytest.raises(ValueError, match="differ"):
        psnr(ref, ref[:1])


def test_evaluate_plumbing_without_lpips_weights(
    stub_ssim: list[tuple[int, ...]], capsys: pytest.CaptureFixture[str]
) -> None:
    g = torch.Generator().manual_seed(0)
    ref = torch.rand(3, 3, 32, 40, generator=g)
    pred = (ref + 0.05 * torch.randn(3, 3, 32, 40, generator=g)).clamp(0, 1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        m = evaluate_images(pred, ref)
        m2 = evaluate_images(pred, ref)
    assert caught == []
    assert capsys.readouterr().err == f"note: {L.UNAVAILABLE_MESSAGE}\n"  # once, not per call
    assert isinstance(m, ImageMetrics) and m == m2
    assert m.lpips is None and m.lpips_note == L.UNAVAILABLE_MESSAGE
    assert len(m.per_view) == 3 and all(v["lpips"] is None for v in m.per_view)
    per = psnr(pred, ref)
    assert [v["psnr"] for v in m.per_view] == pytest.approx(per.tolist())
    assert m.psnr == pytest.approx(per.mean().item())
    assert m.ssim == pytest.approx(sum(1 - (pred[i] - ref[i]).abs().mean().item() for i in range(3)) / 3)
    assert stub_ssim[:3] == [(1, 3, 32, 40)] * 3  # one view at a time, batch of one
    assert m.as_dict() == {"psnr": m.psnr, "ssim": m.ssim, "lpips": None}


def test_evaluate_views_of_different_sizes_and_clamping(stub_ssim: list[tuple[int, ...]]) -> None:
    refs = [torch.full((3, 8, 8), 0.5), torch.full((3, 6, 10), 0.25)]
    preds = [refs[0] + 0.1, torch.full((3, 6, 10), -1.0)]  # second is clamped to 0 first
    m = evaluate_images(preds, refs, with_lpips=False)
    assert m.lpips is None and m.lpips_note == "LPIPS not requested"
    assert m.per_view[0]["psnr"] == pytest.approx(20.0)
    assert m.per_view[1]["psnr"] == pytest.approx(-10 * math.log10(0.25**2))
    assert m.psnr == pytest.approx((20.0 - 10 * math.log10(0.0625)) / 2)


def test_evaluate_input_errors(stub_ssim: list[tuple[int, ...]]) -> None:
    x = torch.rand(2, 3, 8, 8)
    with pytest.raises(ValueError, match="2 predictions for 1 references"):
        evaluate_images(x, x[:1], with_lpips=False)
    with pytest.raises(ValueError, match="view 0"):
        evaluate_images([x[0]], [x[0, :, :4]], with_lpips=False)
    with pytest.raises(ValueError, match="outside"):
        evaluate_images(x, x + 1.5, with_lpips=False)


@pytest.mark.skipif(not SHARED_WEIGHTS.is_file(), reason=f"LPIPS weights not available ({SHARED_WEIGHTS})")
def test_evaluate_with_lpips(
    stub_ssim: list[tuple[int, ...]], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv(L.ENV_VAR, str(SHARED_WEIGHTS))
    g = torch.Generator().manual_seed(1)
    ref = torch.rand(2, 3, 48, 64, generator=g)
    pred = (ref + 0.1 * torch.randn(2, 3, 48, 64, generator=g)).clamp(0, 1)
    m = evaluate_images(pred, ref)
    direct = L.lpips(pred, ref)
    assert m.lpips is not None and direct is not None and m.lpips_note is None
    assert [v["lpips"] for v in m.per_view] == pytest.approx(direct.tolist(), abs=1e-6)
    assert m.lpips == pytest.approx(direct.mean().item(), abs=1e-6)
    # views too small for AlexNet: LPIPS is null with a reason, the other metrics are still there
    capsys.readouterr()
    small = evaluate_images(pred[..., :30, :30], ref[..., :30, :30])
    assert small.lpips is None and "31 px" in (small.lpips_note or "")
    assert "31 px" in capsys.readouterr().err and math.isfinite(small.psnr)


def test_evaluate_with_real_ssim() -> None:
    g = torch.Generator().manual_seed(2)
    ref = torch.rand(2, 3, 24, 24, generator=g)
    same = evaluate_images(ref, ref, with_lpips=False)
    assert same.ssim == pytest.approx(1.0, abs=1e-6) and same.psnr == math.inf
    pred = (ref + 0.2 * torch.randn(2, 3, 24, 24, generator=g)).clamp(0, 1)
    noisy = evaluate_images(pred, ref, with_lpips=False)
    assert 0.0 < noisy.ssim < 0.99 and 5.0 < noisy.psnr < 30.0
