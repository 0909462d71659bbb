"""tools/diagnostics/damage_channels.py: a view's JPEG damage split into its luma and chroma planes, and the
subsampling's own share, on the synthetic compressed scene."""

from __future__ import annotations

import math
import statistics
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from _lpips_backbone import random_backbone
from conftest import load_benchmark

from jsgs.base.images import read_rgb8
from jsgs.base.manifest import load_manifest

dc = load_benchmark("damage_channels", "tools/diagnostics")


@pytest.fixture(scope="module")
def weights(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("lpips") / "alexnet_features.pth"
    torch.save(random_backbone(5), path)
    return str(path)


def test_luma_and_chroma_images_add_up_to_the_jpeg(compressed_scene: Path) -> None:
    # in RGB (a linear map of Y, Cb, Cr): luma + chroma - reference = jpeg, wherever nothing was clamped
    v = next(v for v in load_manifest(compressed_scene / "manifest.json").views if v.jpeg is not None)
    j, r = dc._planes(read_rgb8(v.image)), dc._planes(read_rgb8(v.reference))
    luma, chroma = dc._rgb01(torch.cat([j[:1], r[1:]])), dc._rgb01(torch.cat([r[:1], j[1:]]))
    jpeg, ref = dc._rgb01(j), dc._rgb01(r)
    inside = torch.ones_like(jpeg, dtype=torch.bool)
    for x in (luma, chroma, jpeg, ref):
        inside &= (x > 0) & (x < 1)
    assert inside.float().mean() > 0.5
    d = (luma.double() + chroma.double() - ref.double() - jpeg.double())[inside]
    assert d.abs().max() < 1e-6
    # each carries a part of the damage: neither is the reference nor the JPEG
    for part in (luma, chroma):
        assert float((part - ref).abs().max()) > 0 and float((part - jpeg).abs().max()) > 0


def test_rows_and_summary(compressed_scene: Path, weights: str) -> None:
    rows = dc.view_rows(compressed_scene / "manifest.json", weights)
    train_jpegs = [v for v in load_manifest(compressed_scene / "manifest.json").views if v.jpeg is not None]
    assert len(rows) == len(train_jpegs) > 0
    for r in rows:
        # quality 100 keeps far more than the view's own quality (10..90)
        assert r["psnr_sub"] > r["psnr_jpeg"]
        assert all(math.isfinite(r[f"lpips_{k}"]) and r[f"lpips_{k}"] >= 0 for k in dc.IMAGES)
        assert 0.0 <= r["zeroed"] <= 1.0 and r["noise"] > 0 and r["blockiness"] > 0
        assert math.isfinite(r["contrast"])
    s = dc.summary(rows)
    chroma = statistics.median(r["lpips_chroma"] / r["lpips_jpeg"] for r in rows)
    assert s["share_chroma"] == pytest.approx(chroma)
    assert s["psnr_sub"] == pytest.approx(statistics.median(r["psnr_sub"] for r in rows))


def test_zeroed_share_on_blocks_of_known_coefficients() -> None:
    # a flat 8x8 block at 128 + d has one coefficient, DC = 8 d (orthonormal DCT); with a DC step of 16:
    # d = 0.5 -> DC 4, quantised to 0 (error² 16); d = 3 -> DC 24, quantised to 2 steps (error² (24-32)² = 64)
    table = np.full((8, 8), 16)
    y = np.concatenate([np.full((8, 8), 128.5), np.full((8, 8), 131.0)], axis=1)
    assert dc.zeroed_share(y, table) == pytest.approx(16 / 80)
    assert dc.zeroed_share(np.full((8, 16), 128.0), table) == 0.0  # nothing to lose
    assert dc.zeroed_share(np.full((8, 8), 128.5), table) == pytest.approx(1.0)


def test_summary_on_hand_made_rows() -> None:
    rows: list[dict[str, Any]] = [
        {"psnr_jpeg": 30.0, "lpips_jpeg": 0.2, "lpips_luma": 0.1, "lpips_chroma": 0.05, "lpips_sub": 0.02},
        {"psnr_jpeg": 34.0, "lpips_jpeg": 0.1, "lpips_luma": 0.08, "lpips_chroma": 0.01, "lpips_sub": 0.001},
        {"psnr_jpeg": 32.0, "lpips_jpeg": 0.4, "lpips_luma": 0.1, "lpips_chroma": 0.3, "lpips_sub": 0.04},
    ]
    s = dc.summary(rows)
    assert s["psnr_jpeg"] == 32.0 and s["lpips_jpeg"] == 0.2
    assert s["share_luma"] == pytest.approx(0.5) and s["share_chroma"] == pytest.approx(0.25)
    assert s["share_sub"] == pytest.approx(0.1)


def test_main_prints_a_row_and_refuses_a_dataset_without_jpegs(
    compressed_scene: Path, synth_scene: Path, weights: str, tmp_path: Path, capsys: Any
) -> None:
    from jsgstools.compress import compress

    assert dc.main([str(compressed_scene / "manifest.json"), "--weights", weights]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[2].startswith(f"| {compressed_scene.name} | ")
    # the correlation table: one manifest, so no pooled row
    assert out[4].startswith("| views of |") and out[6].startswith(f"| {compressed_scene.name} | ")
    assert len(out) == 7
    clean = tmp_path / "clean"
    compress(synth_scene, clean, "clean", seed=0, jobs=1)
    assert dc.main([str(clean / "manifest.json"), "--weights", weights]) == 1
    assert "no JPEG view with a lossless reference" in capsys.readouterr().err


def test_block_contrast_grows_with_the_grid_not_the_texture() -> None:
    rng = np.random.default_rng(1)
    texture = rng.uniform(0, 20, (48, 64))
    assert abs(dc.block_contrast(texture)) < 0.5  # no grid: edge and inside steps alike
    grid = np.kron(rng.uniform(0, 30, (6, 8)), np.ones((8, 8)))
    assert dc.block_contrast(texture + grid) > dc.block_contrast(texture)
    # the same edge excess counts for less on busier texture (masking), more on smooth planes
    smooth = np.add.outer(np.arange(48.0), np.arange(64.0)) * 0.1
    assert dc.block_contrast(smooth + grid) > dc.block_contrast(texture + grid)
    assert dc.block_contrast(np.zeros((16, 16))) == 0.0


def test_spearman() -> None:
    assert dc.spearman([1.0, 2.0, 3.0, 4.0], [10.0, 20.0, 25.0, 100.0]) == pytest.approx(1.0)
    assert dc.spearman([1.0, 2.0, 3.0, 4.0], [4.0, 3.0, 2.0, 1.0]) == pytest.approx(-1.0)
    assert dc.spearman([1.0, 2.0, 3.0, 4.0, 5.0], [2.0, 1.0, 4.0, 3.0, 5.0]) == pytest.approx(0.8)
    assert math.isnan(dc.spearman([1.0, 2.0], [2.0, 1.0]))
