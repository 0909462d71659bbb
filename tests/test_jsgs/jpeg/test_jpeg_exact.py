"""jpeg_observe against the real thing: Pillow (libjpeg-turbo) encode + decode.

Progressive, restart-interval and arithmetic-coded files carry the same quantized coefficients as baseline
ones, so "exact" must match their decode too, with the tables and sampling the header parser reads from them.

Mode "exact" must reproduce Pillow's decode of Pillow's encode bit for bit for q = 1..100 (every quality at
least once per sampling), 4:4:4 / 4:2:2 / 4:2:0, sizes from 1x1 to whole photographs that are not multiples of
16; mode "float" must stay >= 49 dB PSNR against the same decodes. Each image is run as one batch whose views
carry different tables (Pillow's own tables, as ``Image.quantization`` reports them, natural order).
"""

from __future__ import annotations

import base64
import io
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from jsgs.jpeg.observe import jpeg_observe
from jsgstools.dqt import parse_header

SHARED = Path(__file__).resolve().parents[3].parent / "shared"
SCENES = SHARED / "scenes"
SUBSAMPLING = {"4:4:4": 0, "4:2:2": 1, "4:2:0": 2}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def pillow_roundtrip(arr: np.ndarray, quality: int,
                     sampling: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(decoded HxWx3 uint8, luma table 8x8, chroma table 8x8) of Pillow's JPEG of ``arr``."""
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, "JPEG", quality=quality, subsampling=SUBSAMPLING[sampling])
    buf.seek(0)
    im = Image.open(buf)
    tables = im.quantization
    decoded = np.asarray(im.convert("RGB"))
    return decoded, np.array(tables[0]).reshape(8, 8), np.array(tables[1]).reshape(8, 8)


def to_tensor(arr: np.ndarray, batch: int) -> torch.Tensor:
    x = torch.from_numpy(np.array(arr, copy=True)).permute(2, 0, 1).float() / 255.0
    return x[None].expand(batch, -1, -1, -1).contiguous()


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(((a.astype(np.float64) - b.astype(np.float64)) ** 2).mean())
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


def synthetic_images() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1234)
    yy, xx = np.mgrid[0:29, 0:43]
    ramp = np.stack([(xx * 6) % 256, (yy * 9) % 256, ((xx + yy) * 4) % 256], -1).astype(np.uint8)
    checker = (((yy + xx) % 2) * 255).astype(np.uint8)
    return {
        "noise_1x1": rng.integers(0, 256, (1, 1, 3), dtype=np.uint8),
        "noise_7x9": rng.integers(0, 256, (7, 9, 3), dtype=np.uint8),
        "noise_17x33": rng.integers(0, 256, (17, 33, 3), dtype=np.uint8),
        "noise_1x1000": rng.integers(0, 256, (1, 1000, 3), dtype=np.uint8),
        "noise_1000x1": rng.integers(0, 256, (1000, 1, 3), dtype=np.uint8),
        "noise_5x4": rng.integers(0, 256, (5, 4, 3), dtype=np.uint8),
        "saturated_23x41": (rng.integers(0, 2, (23, 41, 3)) * 255).astype(np.uint8),
        "ramp_29x43": ramp,
        "checker_29x43": np.repeat(checker[..., None], 3, -1),
        "black_9x10": np.zeros((9, 10, 3), np.uint8),
        "white_10x9": np.full((10, 9, 3), 255, np.uint8),
        "constant_12x13": np.full((12, 13, 3), (200, 30, 90), np.uint8),
    }


def photo_images() -> dict[str, np.ndarray]:
    """Odd crops and one whole photograph from ../shared/scenes (empty when it is absent)."""
    files = sorted(SCENES.glob("*/images/*.png")) if SCENES.is_dir() else []
    if not files:
        return {}
    out: dict[str, np.ndarray] = {}
    rng = np.random.default_rng(7)
    for k, (h, w) in enumerate([(61, 83), (37, 129), (101, 77), (45, 45)]):
        f = files[(k * 37) % len(files)]
        img = np.asarray(Image.open(f).convert("RGB"))
        y = int(rng.integers(0, img.shape[0] - h))
        x = int(rng.integers(0, img.shape[1] - w))
        out[f"{f.parent.parent.name}_{f.stem}_{h}x{w}"] = img[y : y + h, x : x + w]
    whole = next((f for f in files if "fern" in str(f)), files[0])
    out[f"{whole.parent.parent.name}_{whole.stem}_whole"] = np.asarray(Image.open(whole).convert("RGB"))
    return out


def quality_plan(names: list[str], sampling: str) -> dict[str, list[int]]:
    """Spread q = 1..100 over the images (every q once per sampling) plus q = 1, 50, 100 for each image; whole
    photographs (the slow ones) get q = 1, 50, 100 only."""
    offset = sum(map(ord, sampling))
    plan: dict[str, list[int]] = {n: [1, 50, 100] for n in names}
    spread = [n for n in names if not n.endswith("_whole")]
    for q in range(1, 101):
        name = spread[(q * 7 + offset) % len(spread)]
        if q not in plan[name]:
            plan[name].append(q)
    return plan


def run_image(arr: np.ndarray, refs: list[tuple[np.ndarray, np.ndarray, np.ndarray]], sampling: str,
              mode: str) -> np.ndarray:
    """jpeg_observe of ``arr``, one batch, a view per Pillow reference (its tables): (B, H, W, 3) uint8."""
    luma = torch.tensor(np.stack([r[1] for r in refs]), dtype=torch.float32)
    chroma = torch.tensor(np.stack([r[2] for r in refs]), dtype=torch.float32)
    out = jpeg_observe(to_tensor(arr, len(refs)), luma, chroma, sampling, mode)
    return (out * 255).round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy()


def _images(kind: str) -> dict[str, np.ndarray]:
    if kind == "photo":
        photos = photo_images()
        if not photos:
            pytest.skip(f"no photographs: {SCENES} is absent (../shared not checked out beside the project)")
        return photos
    return synthetic_images()


@pytest.mark.parametrize("kind", ["synthetic", "photo"])
@pytest.mark.parametrize("sampling", ["4:4:4", "4:2:2", "4:2:0"])
def test_exact_is_bit_exact_and_float_reaches_49_db(kind: str, sampling: str) -> None:
    images = _images(kind)
    plan = quality_plan(sorted(images), sampling)
    failures = []
    worst = (float("inf"), "")
    for name, qualities in plan.items():
        refs = [pillow_roundtrip(images[name], q, sampling) for q in qualities]
        for mode in ("exact", "float"):
            outs = run_image(images[name], refs, sampling, mode)
            for q, got, ref in zip(qualities, outs, refs, strict=True):
                if mode == "float":
                    worst = min(worst, (psnr(got, ref[0]), f"{name} q={q}"))
                elif not np.array_equal(got, ref[0]):
                    diff = np.abs(got.astype(int) - ref[0].astype(int))
                    failures.append(f"{name} q={q}: {int((diff > 0).sum())} samples differ, max {diff.max()}")
    assert not failures, "exact mode:\n" + "\n".join(failures)
    assert worst[0] >= 49.0, f"float mode: {worst[0]:.2f} dB on {worst[1]}"


def test_every_quality_is_covered() -> None:
    names = sorted(synthetic_images()) + ["some_photo_whole"]
    for sampling in SUBSAMPLING:
        covered = set().union(*quality_plan(names, sampling).values())
        assert covered == set(range(1, 101))


def test_custom_and_16bit_tables_match_pillow() -> None:
    """Non-IJG tables, all-1 / all-255 tables and 16-bit tables (Pillow writes them with 16-bit precision)."""
    rng = np.random.default_rng(5)
    arr = rng.integers(0, 256, (19, 27, 3), dtype=np.uint8)
    tables = {
        "ones": (np.ones(64, int), np.ones(64, int)),
        "all255": (np.full(64, 255), np.full(64, 255)),
        "random": (rng.integers(1, 256, 64), rng.integers(1, 256, 64)),
        "16bit": (rng.integers(1, 2000, 64), rng.integers(200, 8000, 64)),
        # the largest step libjpeg-turbo's encoder represents (it keeps 8Q in 16 bits: 8192 wraps to 0)
        "16bit_8191": (np.full(64, 8191), np.where(np.arange(64) % 2, 8191, 1)),
    }
    for name, (luma, chroma) in tables.items():
        for sampling in SUBSAMPLING:
            buf = io.BytesIO()
            # Pillow's qtables take natural order lists and write them zigzagged.
            Image.fromarray(arr).save(buf, "JPEG", qtables=[list(luma), list(chroma)],
                                      subsampling=SUBSAMPLING[sampling])
            buf.seek(0)
            im = Image.open(buf)
            got_tables = im.quantization
            assert list(got_tables[0]) == list(luma)
            ref = np.asarray(im.convert("RGB"))
            lt, ct = np.array(luma).reshape(8, 8), np.array(chroma).reshape(8, 8)
            out = jpeg_observe(to_tensor(arr, 1), lt, ct, sampling, "exact")
            got = (out[0] * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
            assert np.array_equal(got, ref), f"{name} {sampling}: max {np.abs(got.astype(int) - ref).max()}"


@pytest.mark.slow
@pytest.mark.parametrize("sampling", ["4:4:4", "4:2:2", "4:2:0"])
def test_whole_photographs_every_quality(sampling: str) -> None:
    """A whole photograph per sampling (the 480x640 portrait for 4:2:0, a 504x378 landscape otherwise, when
    present), q = 1..100, exact."""
    files = sorted(SCENES.glob("*/images/*.png")) if SCENES.is_dir() else []
    if not files:
        pytest.skip(f"no photographs: {SCENES} is absent (../shared not checked out beside the project)")
    portrait = [f for f in files if Image.open(f).size[1] > Image.open(f).size[0]]
    landscape = next((f for f in files if "fern" in str(f)), files[0])
    picks = portrait[:1] if sampling == "4:2:0" and portrait else [landscape]
    failures = []
    for f in picks:
        arr = np.asarray(Image.open(f).convert("RGB"))
        for start in range(1, 101, 10):
            qualities = list(range(start, start + 10))
            refs = [pillow_roundtrip(arr, q, sampling) for q in qualities]
            outs = run_image(arr, refs, sampling, "exact")
            failures += [f"{f.name} q={q}" for q, got, ref in zip(qualities, outs, refs, strict=True)
                         if not np.array_equal(got, ref[0])]
    assert not failures, failures


#: ``_pattern()`` saved by Pillow (quality=60, 4:2:0), then transcoded losslessly by libjpeg-turbo 2.1's
#: ``jpegtran -arithmetic`` (SOF9) and ``jpegtran -progressive -arithmetic`` (SOF10): Pillow writes no
#: arithmetic coding, but decodes it.
ARITHMETIC = {
    "extended-arithmetic": (
        "/9j/4AAQSkZJRgABAQAAAQABAAD/2wBDAA0JCgsKCA0LCgsODg0PEyAVExISEyccHhcgLikxMC4pLSwzOko+MzZGNywtQFdBRkxO"
        "UlNSMj5aYVpQYEpRUk//2wBDAQ4ODhMREyYVFSZPNS01T09PT09PT09PT09PT09PT09PT09PT09PT09PT09PT09PT09PT09PT09P"
        "T09PT09PT0//yQARCAARACEDASIAAhEBAxEB/8wACgAQEAUBEBEF/9oADAMBAAIRAxEAPwCTKsphz63nX+5C1b/lJUeRrGHWBEY0"
        "xQOzqaSKth3E7SjTQcVPGrbMh5TbjcJHAWC7EbkZid56c3anSKCpYijL5ChOws+O0vQ0/wDAHEDw+ckGRdwjE3QDK/3OIKREdGul"
        "UBjvLzufYwwABESlnu3OZ6MxoYKh2xEeOTM0w3B3cnWbrUR75pwM0/DIZ1smQGgiIUuee0XAflXyaXGTd9aZlneSs24LHLtikvGb"
        "F/FekfT3ZSTzwvIG/bpiiHvFRs343hsVbNGlBb2SAcFbQkTNKIaR103u8jmnuULMWWB21EcWZ3bDMSJYi/SEKZLXxlpPlMQUH19Y"
        "tFVZi+/4ohWTc7NnpejoWEcf4167Ff2OpzWfHMSqWPErQoPjuDbkxJW2QuhciynZuT8BR0lNF+QC9zEx4HadrmUAKEkSRx2WCiSc"
        "/Pf2xq12GFgVKCBVoalFBjaH0q+zRA+kKOL0ixIImmHo/9k="
    ),
    "progressive-arithmetic": (
        "/9j/4AAQSkZJRgABAQAAAQABAAD/2wBDAA0JCgsKCA0LCgsODg0PEyAVExISEyccHhcgLikxMC4pLSwzOko+MzZGNywtQFdBRkxO"
        "UlNSMj5aYVpQYEpRUk//2wBDAQ4ODhMREyYVFSZPNS01T09PT09PT09PT09PT09PT09PT09PT09PT09PT09PT09PT09PT09PT09P"
        "T09PT09PT0//ygARCAARACEDASIAAhEBAxEB/8wABgAQARD/2gAMAwEAAhADEAAAASeJQkTIrXSpC0JSfXbBo6kez4D/zAAEEAX/"
        "2gAIAQEAAQUCcY9YhkeVOxcWggG/YmGX/kf9mgqw/8wABBEF/9oACAEDAQE/AVUUwGP6YwRcIMOJMctW5ZKZMP/MAAQRBf/aAAgB"
        "AgEBPwEk4OWhaXZQyMlcQjfutOvm70xD/8wABBAF/9oACAEBAAY/ApF4mhliAgFVB5lOrAHAlqzcjCl0tzTy3YVfarLXQP/MAAQQ"
        "Bf/aAAgBAQABPyEkI8/WgOWws1qREZghtLzrN3wC6y29Siy23Ym9/mpS436cIjPGbPn5avpa2NjFUOU2IrjaM/8AD6qjyf/aAAwD"
        "AQACAAMAAAAQOFizNv/MAAQRBf/aAAgBAwEBPxAJz00RIZFqV5hwyGVD2IqqEbF6sfR1pB2exh+SVI5vO5D/zAAEEQX/2gAIAQIB"
        "AT8QGolnoABE/wDMuQX1rX39HRMflEmYNiWgQc1IawX/zAAEEAX/2gAIAQEAAT8Q85zGQR6lKdJRGrPC6ccPYqpAQlSKHQ1KvuQV"
        "3jC9+o8BN+R57Bj1+spiAtMnQhkKIb356dxjMPgpcnlvUMqohXkAud4sQDSxKyDUoE+a0ShDiQMB6zQ/q3x2ZFeKiY+LF8/1s69e"
        "grz0Nxmw54pYaR5tNRdM54bkjMlCxtEWKpbgnnxDEP/Z"
    ),
}


def _pattern(h: int = 17, w: int = 33) -> np.ndarray:
    """h x w RGB texture from integer arithmetic alone (the source of ``ARITHMETIC``'s and
    ``CJPEG_SAMPLINGS``' files)."""
    yy, xx = np.mgrid[0:h, 0:w]
    planes = [(xx * 29 + yy * 47 + c * 83 + (xx * yy % 17) * 9) % 256 for c in range(3)]
    return np.stack(planes, -1).astype(np.uint8)


def _exact_from_header(arr: np.ndarray, data: bytes, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(JO "exact" of ``arr`` with the tables and sampling parsed from ``data``, Pillow's decode of it)."""
    state = parse_header(data, name).manifest_state()
    out = jpeg_observe(to_tensor(arr, 1), np.array(state["luma_table"]), np.array(state["chroma_table"]),
                       state["sampling"], "exact")
    got = (out[0] * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
    with Image.open(io.BytesIO(data)) as im:
        return got, np.asarray(im.convert("RGB"))


@pytest.mark.parametrize("sampling", sorted(SUBSAMPLING))
@pytest.mark.parametrize(
    "options",
    [{"progressive": True}, {"restart_marker_blocks": 1}, {"progressive": True, "restart_marker_rows": 1}],
    ids=["progressive", "dri", "progressive_dri"],
)
def test_progressive_and_restart_files_are_bit_exact(sampling: str, options: dict[str, object]) -> None:
    arr = _pattern()
    for q in (5, 60, 97):
        buf = io.BytesIO()
        Image.fromarray(arr).save(buf, "JPEG", quality=q, subsampling=SUBSAMPLING[sampling], **options)
        h = parse_header(buf.getvalue(), "f.jpg")
        assert (h.frame == "progressive") == bool(options.get("progressive"))
        assert (h.restart_interval > 0) == (options != {"progressive": True})
        got, decoded = _exact_from_header(arr, buf.getvalue(), "f.jpg")
        assert np.array_equal(got, decoded), (options, q)


def test_arithmetic_coded_files_are_bit_exact() -> None:
    arr = _pattern()
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, "JPEG", quality=60, subsampling=2)
    with Image.open(buf) as im:
        huffman = np.asarray(im.convert("RGB"))
    for frame, text in ARITHMETIC.items():
        data = base64.b64decode(text)
        assert parse_header(data, "a.jpg").frame_name == frame
        got, decoded = _exact_from_header(arr, data, "a.jpg")
        assert np.array_equal(decoded, huffman), frame  # the same coefficients as Pillow's Huffman file
        assert np.array_equal(got, decoded), frame


#: ``_pattern(h, w)`` encoded by libjpeg-turbo 2.1's ``cjpeg -quality q -sample 1x2`` (4:4:0) or ``4x1``
#: (4:1:1) ``-optimize``, which Pillow cannot write (it reads them): (sampling, h, w, q) -> the file, base64.
CJPEG_SAMPLINGS = {
    ('4:4:0', 17, 33, 50): (
        "/9j/4AAQSkZJRgABAQAAAQABAAD/2wBDABALDA4MChAODQ4SERATGCgaGBYWGDEjJR0oOjM9PDkzODdASFxOQERXRTc4UG1R"
        "V19iZ2hnPk1xeXBkeFxlZ2P/2wBDARESEhgVGC8aGi9jQjhCY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2Nj"
        "Y2NjY2NjY2NjY2NjY2P/wAARCAARACEDARIAAhEBAxEB/8QAGgAAAgIDAAAAAAAAAAAAAAAAAAIDBAEFBv/EADUQAAIBAgIE"
        "CQ0BAAAAAAAAAAECEQADEiExQVGBBAUTNFJxobHRFBUiMjM1YXJ0g5GSpLL/xAAaAQACAwEBAAAAAAAAAAAAAAAAAgMEBgUB"
        "/8QALxEAAQICBwUIAwAAAAAAAAAAAQACESEDBDFBUXGBMzRhobEFEhNSkaLB0YKy4f/aAAwDAQACEQMRAD8AA6CLT2mYQIso"
        "IzyInROgfnLYGUX2B5NYZicdxFLEg6xG/LtzpXEWk8/mZPLSKBAQEhl9CfqY5LNsAWgzm3IWGRMgw9KZ35HTqpLNs3MItKWG"
        "AguwzOUAidmW4RSuewSdLlhEziRyM4XAoeC0FzhfG4GMrhPGMwPRRm6LTW1cNbkySgwsTEHRpAM6Iy3VIQyPA5R70w7AEgEA"
        "iQc5O7SNudO6BtnrLhPDLWyfkWm2ZOkY8/jCSGt4HWYtKPUCyCwkTqGWzfTISvCUHIM2GZxKVABGqeufj20B5azvHhhO284c"
        "cEPBLCXYZZWzjHC7NL55udD+keFL5Fe6Kfq3jTeHVvP7v6jv1byj3far8O5xf+W1/laKlqdup6ldGt7m/M/stja938I+nbuN"
        "FU+0d8Zp1K4tT2rcwql3m3F33O8UU1FtqTTotHQ7xS/j0UnE/s06xRVjtjYDP4KydHaukorMqZf/2Q=="
    ),
    ('4:4:0', 2, 40, 75): (
        "/9j/4AAQSkZJRgABAQAAAQABAAD/2wBDAAgGBgcGBQgHBwcJCQgKDBQNDAsLDBkSEw8UHRofHh0aHBwgJC4nICIsIxwcKDcp"
        "LDAxNDQ0Hyc5PTgyPC4zNDL/2wBDAQkJCQwLDBgNDRgyIRwhMjIyMjIyMjIyMjIyMjIyMjIyMjIyMjIyMjIyMjIyMjIyMjIy"
        "MjIyMjIyMjIyMjIyMjL/wAARCAACACgDARIAAhEBAxEB/8QAFwABAQEBAAAAAAAAAAAAAAAAAAQBAv/EACMQAAICAgEDBQEA"
        "AAAAAAAAAAECAxEABAUSIUETIlFxkTH/xAAYAQEBAAMAAAAAAAAAAAAAAAADBAECBf/EACoRAAADBAcJAAAAAAAAAAAAAAAB"
        "AgMEMoEFNXKCscHCMTM0QUJxg7Lw/9oADAMBAAIRAxEAPwDrkUSLieNijVUjkvrRRQamiqx5xljzWhfdImoWBcsxRuxxw7Gl"
        "HEiok2uvqKooP1GS7Hm6F/WM5Ktwm9gkb8/KIOWY6ejsS6pMEg3HUPF7SAFloWPHYfgxjvkDCynMYVxTxZPAhm8BraPGPAPS"
        "dgQWj9pIBir+fZ/TjLGu1vdwIK/QL7J9jF8aKdnm3KjrSJ3Vq7qxhskfBJ7384wmlXTPUBaxu0tI/9k="
    ),
    ('4:1:1', 17, 33, 50): (
        "/9j/4AAQSkZJRgABAQAAAQABAAD/2wBDABALDA4MChAODQ4SERATGCgaGBYWGDEjJR0oOjM9PDkzODdASFxOQERXRTc4UG1R"
        "V19iZ2hnPk1xeXBkeFxlZ2P/2wBDARESEhgVGC8aGi9jQjhCY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2Nj"
        "Y2NjY2NjY2NjY2NjY2P/wAARCAARACEDAUEAAhEBAxEB/8QAGQABAAMBAQAAAAAAAAAAAAAAAAIDBAUG/8QANRAAAgECAgQJ"
        "DQEAAAAAAAAAAQIRAAMSITFBUYEEBRM0UnGhsdEUFSIyMzVhcnSDkZKksv/EABkBAQACAwAAAAAAAAAAAAAAAAMABAEFBv/E"
        "ACsRAAEBBQUHBQAAAAAAAAAAAAEAAxEUIfACMTJTgQQSYZGhwdFBcpKx4f/aAAwDAQACEQMRAD8AB0EWntMwgRZQRnkROidA"
        "/OWwTtgC0Gc25CwyJkGHpTO/I6dVUG6LTW1cNbkySgwsTEHRpAM6Iy3VY1vA6zFpR6gWQWEidQy2b6geC8zquZUIHpVXaFPP"
        "Nzof0jwpSlHBteHwHhJBMM4VqpKL7A8msMxOO4iliQdYjfl251GzbNzCLSlhgILsMzlAInZluEUIZHgco96YdgCQCARIOcnd"
        "pG3OpISvCUHIM2GZxKVABGqeufj21nfsGT3OnXXjdochJ4rveXFV+RXuin6t40pSrMbsuYevhFF2sqxy/Vn4dzi/8tr/ACtd"
        "G17v4R9O3cayXebcXfc7xVnE/s06xQnGfZ2KsNcLbT7C9JSlK51a9f/Z"
    ),
    ('4:1:1', 40, 2, 75): (
        "/9j/4AAQSkZJRgABAQAAAQABAAD/2wBDAAgGBgcGBQgHBwcJCQgKDBQNDAsLDBkSEw8UHRofHh0aHBwgJC4nICIsIxwcKDcp"
        "LDAxNDQ0Hyc5PTgyPC4zNDL/2wBDAQkJCQwLDBgNDRgyIRwhMjIyMjIyMjIyMjIyMjIyMjIyMjIyMjIyMjIyMjIyMjIyMjIy"
        "MjIyMjIyMjIyMjIyMjL/wAARCAAoAAIDAUEAAhEBAxEB/8QAFwABAQEBAAAAAAAAAAAAAAAAAAQFA//EACIQAAICAQQCAwEA"
        "AAAAAAAAAAECAAMRBAUSIRNBImFxFP/EABcBAQEBAQAAAAAAAAAAAAAAAAUEAgP/xAAtEQABAgMEBwkAAAAAAAAAAAABAAMC"
        "BBEFEiHRExRBYXFy0xVCUpKToaKj4v/aAAwDAQACEQMRAD8Aqp27VtTW1Wz0eMqCudKzHGOu+Qz+4H4IiJk2xAMDOGvKOmuG"
        "jsXwu/HNQMiWOz26MXWMctYmpdVc+yAFIAP11ERKBPECgcZ9uoq7zW2fjG67HmtyrV3ClPBt+5tTxHBv7OOV9HGDjr1ERDjJ"
        "Q1xmma8jeSIpJ7Y4/L+1k8dsf5216qyxu2evRIysfZBGMj7iIiIlrW7rbdOMWaY7YmRhrcI3XTh9a5+S1fjVoN1asdIw3DiC"
        "PRx3j8yYiISbMbJqZpoHhApdfZGBJ9FvNf/Z"
    ),
}


@pytest.mark.parametrize("key", sorted(CJPEG_SAMPLINGS), ids=lambda k: f"{k[0]}-{k[1]}x{k[2]}-q{k[3]}")
def test_440_and_411_files_are_bit_exact(key: tuple[str, int, int, int]) -> None:
    """4:4:0 (h1v2: libjpeg's int_downsample, then h1v2 fancy up-sampling at any width) and 4:1:1 (h4v1:
    int_downsample, replication): "exact" equals Pillow's decode of the cjpeg-made file, "float" >= 49 dB."""
    sampling, h, w, q = key
    data = base64.b64decode(CJPEG_SAMPLINGS[key])
    arr = _pattern(h, w)
    assert parse_header(data, "s.jpg").sampling == sampling
    got, decoded = _exact_from_header(arr, data, "s.jpg")
    assert np.array_equal(got, decoded), np.abs(got.astype(int) - decoded).max()
    state = parse_header(data, "s.jpg").manifest_state()
    out = jpeg_observe(to_tensor(arr, 1), np.array(state["luma_table"]), np.array(state["chroma_table"]),
                       sampling, "float")
    assert psnr((out[0] * 255).round().permute(1, 2, 0).numpy(), decoded) >= 49.0
