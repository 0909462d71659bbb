"""jsgstools.dqt.analysis and ``inspect-dqt --analyze``: double compression found on small synthetic photos
made with Pillow, the primary quality near the truth, the block DCT against OpenCV, the JSON against the
schema, and one-line errors."""

from __future__ import annotations

import io
import json
from pathlib import Path

import cv2
import jsonschema
import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from jsgs.base.errors import JsgsError
from jsgs.base.schema import load_schema
from jsgs.jpeg.tables import ijg_tables
from jsgstools.cli.inspect_dqt import inspect_dqt
from jsgstools.dqt import read_header_from
from jsgstools.dqt import report as report_module
from jsgstools.dqt.analysis import Analysis, analyze_bytes, block_dct

KEYS = {
    "double_compressed",
    "confidence",
    "evidence",
    "primary_quality",
    "primary_luma_table",
    "effective_luma_table",
    "effective_chroma_table",
    "noise_variance",
    "blockiness",
}


def photo(seed: int = 0, size: tuple[int, int] = (320, 240)) -> Image.Image:
    """A photo-like RGB image: smooth random fields at several scales (bicubic-upsampled noise), a few hard
    edges and fine grain, so its DCT coefficients have the peaked, heavy-tailed spread of real photos."""
    rng = np.random.default_rng(seed)
    w, h = size
    acc = np.zeros((h, w, 3))
    for scale, amp in ((64, 60.0), (16, 30.0), (4, 12.0)):
        small = rng.normal(size=(h // scale + 2, w // scale + 2, 3)).astype(np.float32)
        acc += (
            amp
            * cv2.resize(small, (w + 2 * scale, h + 2 * scale), interpolation=cv2.INTER_CUBIC)[
                scale : scale + h, scale : scale + w
            ]
        )
    yy, xx = np.mgrid[0:h, 0:w]
    acc += 40.0 * ((xx * 0.7 + yy * 0.3) % 90 < 45)[:, :, None]
    acc += rng.normal(scale=2.0, size=acc.shape)
    return Image.fromarray(np.clip(acc + 128, 0, 255).astype(np.uint8))


def jpeg(im: Image.Image, quality: int, subsampling: int = 2) -> bytes:
    buf = io.BytesIO()
    im.save(buf, format="JPEG", quality=quality, subsampling=subsampling)
    return buf.getvalue()


def twice(im: Image.Image, q1: int, q2: int, subsampling: int = 2) -> bytes:
    """Saved at q1, decoded (to its own mode), saved again at q2 (same size: aligned grids)."""
    with Image.open(io.BytesIO(jpeg(im, q1, subsampling))) as first:
        return jpeg(first.convert(im.mode), q2, subsampling)


def analyse(data: bytes) -> Analysis:
    return analyze_bytes(data, read_header_from(io.BytesIO(data), "t.jpg", len(data)))


def test_block_dct_matches_opencv() -> None:
    rng = np.random.default_rng(3)
    plane = rng.integers(0, 256, size=(20, 27)).astype(np.uint8)  # 2x3 whole blocks, partial ones dropped
    got = block_dct(plane)
    assert got.shape == (6, 64)
    for k, (by, bx) in enumerate((by, bx) for by in range(2) for bx in range(3)):
        block = plane[8 * by : 8 * by + 8, 8 * bx : 8 * bx + 8].astype(np.float64) - 128
        np.testing.assert_allclose(got[k], cv2.dct(block).reshape(64), atol=2e-3)


@pytest.mark.parametrize("quality", [30, 75, 95])
def test_single_compression_is_not_flagged(quality: int) -> None:
    im = photo(1)
    a = analyse(jpeg(im, quality))
    assert not a.double_compressed
    assert a.primary_quality is None and a.primary_luma_table is None
    luma, chroma = ijg_tables(quality)
    np.testing.assert_array_equal(a.effective_luma_table, luma)  # effective = the header when single
    np.testing.assert_array_equal(a.effective_chroma_table, chroma)
    assert 0.5 <= a.confidence <= 1.0


@pytest.mark.parametrize(("q1", "q2", "subsampling"), [(50, 90, 2), (30, 60, 0), (70, 90, 2)])
def test_double_compression_is_found_with_its_primary_quality(q1: int, q2: int, subsampling: int) -> None:
    a = analyse(twice(photo(2), q1, q2, subsampling))
    assert a.double_compressed and a.confidence > 0.9
    assert a.primary_quality is not None and abs(a.primary_quality - q1) <= 3
    header = ijg_tables(q2)[0]
    primary = ijg_tables(q1)[0]
    assert np.all(a.effective_luma_table >= header)
    # Effective = the coarser of the two steps: the low frequencies, where the comb is plain, agree exactly.
    np.testing.assert_array_equal(a.effective_luma_table[:3, :3], np.maximum(primary, header)[:3, :3])
    assert np.all(a.effective_chroma_table >= ijg_tables(q2)[1])


def test_coarser_second_compression_leaves_nothing_to_find() -> None:
    a = analyse(twice(photo(4), 90, 60))
    assert not a.double_compressed
    np.testing.assert_array_equal(a.effective_luma_table, ijg_tables(60)[0])


def test_gray_double_compression() -> None:
    gray = photo(5).convert("L")
    a = analyse(twice(gray, 40, 85))
    assert a.double_compressed and abs(a.primary_quality - 40) <= 3
    assert a.effective_chroma_table is None
    assert not analyse(jpeg(gray, 85)).double_compressed


def test_cmyk_is_refused_in_one_line() -> None:
    data = jpeg(photo(6).convert("CMYK"), 90)
    with pytest.raises(JsgsError, match=r"^t\.jpg: --analyze supports 8-bit YCbCr and gray JPEGs"):
        analyse(data)


# ---------------------------------------------------------------------------------------------------------
# The CLI


def run(args: list[str]) -> tuple[int, str, str]:
    result = CliRunner().invoke(inspect_dqt, args, catch_exceptions=False)
    return result.exit_code, result.stdout, result.stderr


@pytest.fixture
def files(tmp_path: Path) -> tuple[Path, Path]:
    single, double = tmp_path / "single.jpg", tmp_path / "double.jpg"
    single.write_bytes(jpeg(photo(7), 80))
    double.write_bytes(twice(photo(7), 50, 90))
    return single, double


def test_cli_json_analysis_validates(files: tuple[Path, Path]) -> None:
    code, out, _ = run(["--json", "--analyze", *map(str, files)])
    assert code == 0
    doc = json.loads(out)
    jsonschema.Draft202012Validator(load_schema("dqt_report")).validate(doc)
    single, double = (f["analysis"] for f in doc["files"])
    assert set(single) == KEYS and set(double) == KEYS
    assert single["double_compressed"] is False and single["primary_quality"] is None
    assert double["double_compressed"] is True and abs(double["primary_quality"] - 50) <= 3
    assert np.array(double["effective_luma_table"]).shape == (8, 8)
    assert doc["summary"]["double_compressed"] == 1
    # the noise estimate follows what the file went through (with the effective tables): saved at 50 then
    # 90 carries more damage than saved once at 80, close to the true error against the original
    for f, a in zip(files, (single, double), strict=True):
        with Image.open(f) as im:
            im.draft("YCbCr", im.size)
            dec = np.asarray(im, dtype=np.float64)
        truth = float(((dec - np.asarray(photo(7).convert("YCbCr"), dtype=np.float64)) ** 2).mean())
        assert 0.4 * truth < a["noise_variance"] < 1.5 * truth, (f.name, a["noise_variance"], truth)
    assert double["noise_variance"] > single["noise_variance"]
    # the blockiness is the decoded luma's (jsgs.jpeg.noise.blockiness), as the trainer would measure it
    from jsgs.base.images import read_ycbcr8
    from jsgs.jpeg.noise import blockiness

    for f, a in zip(files, (single, double), strict=True):
        assert a["blockiness"] == pytest.approx(blockiness(read_ycbcr8(f)[..., 0]), abs=1e-4)
        assert a["blockiness"] > 0.5


def test_cli_table_column(files: tuple[Path, Path]) -> None:
    code, out, _ = run(["--analyze", *map(str, files)])
    assert code == 0
    lines = out.splitlines()
    assert lines[0].split()[-5:] == ["DOUBLE", "(confidence)", "EST.", "PSNR", "BLOCKS"]
    single, double = lines[1].split(), lines[2].split()
    assert single[-5] == "no" and double[-6] == "yes"
    assert abs(int(double[-5].removeprefix("q")) - 50) <= 3
    # the estimated PSNR: the file saved at 50 then 90 is further from the original than the one saved at 80
    assert single[-2] == double[-2] == "dB" and 25 < float(double[-3]) < float(single[-3]) < 50
    # and its block grid shows more, although its header is the finer one
    assert 1.0 < float(single[-1]) < float(double[-1])
    assert "double       1 of 2 double-compressed" in out


def test_without_analyze_nothing_is_decoded(
    files: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    def boom(*_: object) -> None:
        raise AssertionError("decoded without --analyze")

    monkeypatch.setattr(report_module, "analyze_bytes", boom)
    code, out, _ = run(["--json", *map(str, files)])
    assert code == 0
    doc = json.loads(out)
    assert all("analysis" not in f for f in doc["files"]) and "double_compressed" not in doc["summary"]


def test_cli_non_jpeg_is_one_line(tmp_path: Path, files: tuple[Path, Path]) -> None:
    bad = tmp_path / "notes.jpg"
    bad.write_text("not a picture")
    code, out, err = run(["--analyze", str(bad), str(files[0])])
    assert code == 1
    expected = f"error: {bad}: not a JPEG file: starts with 6E 6F 74 20, a JPEG starts with FF D8 (SOI)"
    assert err.strip().splitlines() == [expected]
    assert "single.jpg" in out


@pytest.mark.parametrize("size", [(1, 1), (9, 7), (1000, 1), (1, 1000)])
def test_no_full_block_is_undecided(size: tuple[int, int]) -> None:
    """Images with no full 8x8 block (and a flat one) give the test nothing to count: "no" at confidence 0.5
    (undecided), not the confidence of a photo with no trace; the noise estimate falls back on the tables'
    uniform bound, finite."""
    rng = np.random.default_rng(0)
    tiny = Image.fromarray(rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8))
    flat = Image.fromarray(np.full((32, 32, 3), 128, np.uint8))
    for im in (tiny, flat):
        for data in (jpeg(im, 50), twice(im, 30, 90)):
            a = analyse(data)
            assert not a.double_compressed and a.confidence == 0.5, (im.size, a)
            assert a.noise_variance is not None and np.isfinite(a.noise_variance)
    a = analyse(jpeg(photo(), 50))  # a photo without a trace stays a confident "no"
    assert not a.double_compressed and a.confidence > 0.9
