"""``method_options.tables: effective``: a training view saved twice (q 40, then q 90) is observed through
both quantizations, so the JPEG observation of the clean image reproduces the file far better than the
header's tables alone; manifests record the analysis with ``--analyze``; a view without one is refused."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from PIL import Image

from jsgs.base.errors import JsgsError
from jsgs.base.manifest import JpegState
from jsgs.method.image_terms import jpeg_terms, view_tables


def _texture(h: int = 192, w: int = 256) -> np.ndarray:
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:h, 0:w]
    base = 128 + 60 * np.sin(xx / 7.0) * np.cos(yy / 11.0)
    img = np.stack([base, base * 0.8 + 20, 255 - base], axis=-1) + rng.normal(0, 12, (h, w, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def _save(img: np.ndarray, q: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="JPEG", quality=q, subsampling=2)
    return buf.getvalue()


class _View:
    def __init__(self, jpeg: JpegState) -> None:
        self.index, self.name, self.jpeg = 0, "v.jpg", jpeg


def test_two_quantizations_reproduce_a_photo_saved_twice(tmp_path: Path) -> None:
    from jsgstools.dqt import parse_header
    from jsgstools.dqt.analysis import analyze_file

    clean = _texture()
    once = _save(clean, 40)
    twice = _save(np.asarray(Image.open(io.BytesIO(once)).convert("RGB")), 90)
    path = tmp_path / "twice.jpg"
    path.write_bytes(twice)
    a = analyze_file(path).to_json()
    assert a["double_compressed"] and abs(a["primary_quality"] - 40) <= 5
    st = parse_header(twice, "twice.jpg").manifest_state()
    ec = np.asarray(a["effective_chroma_table"]) if a["effective_chroma_table"] else None
    state = JpegState(
        np.asarray(st["luma_table"]), np.asarray(st["chroma_table"]), st["sampling"], st["quality"],
        st["quality_exact"], 8, st["frame"], "YCbCr", np.asarray(a["effective_luma_table"]), ec, True,
    )  # fmt: skip
    cpu = torch.device("cpu")
    header = view_tables([_View(state)], cpu, "m.json")[0]  # type: ignore[list-item]
    effective = view_tables([_View(state)], cpu, "m.json", "effective")[0]  # type: ignore[list-item]
    assert header.first is None and effective.first is not None
    assert effective.noise_variance > header.noise_variance
    x = torch.from_numpy(clean).permute(2, 0, 1)[None].double() / 255
    y = torch.from_numpy(np.asarray(Image.open(path).convert("RGB"))).permute(2, 0, 1)[None].double() / 255
    settings = dict(sampling="4:2:0", mode="exact", ssim_lambda=0.0, ssim_padding="valid", ds=False, gc=False,
                    eps_sm=1e-6, eps_loss=1e-6, eps_block=1e-6)  # fmt: skip
    _, l_header, _ = jpeg_terms(x, y, header.luma.double(), header.chroma.double(), **settings)
    _, l_eff, _ = jpeg_terms(x, y, header.luma.double(), header.chroma.double(),
                             first=effective.first.double(), **settings)  # fmt: skip
    assert float(l_eff) < 0.5 * float(l_header), (float(l_eff), float(l_header))


def test_manifest_analyze_and_training_with_effective_tables(compressed_scene: Path, tmp_path: Path) -> None:
    from jsgs.cli import main as jsgs_main
    from jsgstools.cli import main as tools

    man = tmp_path / "m.json"
    r = CliRunner().invoke(tools, ["manifest", str(compressed_scene), "--out", str(man), "--analyze"])
    assert r.exit_code == 0 and "compressed twice" in r.output, r.output
    doc = json.loads(man.read_text())
    jpegs = [v for v in doc["views"] if v["jpeg"]]
    assert jpegs and all("analysis" in v["jpeg"] for v in jpegs)
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"method_options": {"tables": "effective"}}))
    args = ["train", str(man), "--out", str(tmp_path / "run"), "--method", "jsgs", "--iterations", "3",
            "--eval-at", "3", "--device", "cpu", "--config", str(cfg), "--quiet"]  # fmt: skip
    r = CliRunner().invoke(jsgs_main, args)
    assert r.exit_code == 0, r.output
    settings = json.loads((tmp_path / "run" / "config.json").read_text())["settings"]
    assert settings["method_options"]["tables"] == "effective"
    # the same through `--tables effective` without --analyze: refused in one line naming a view
    plain = compressed_scene / "manifest.json"
    args = args[:-3] + ["--tables", "effective", "--quiet"]
    args[1], args[3] = str(plain), str(tmp_path / "run2")
    r = CliRunner().invoke(jsgs_main, args)
    assert r.exit_code == 1 and "has no compression analysis" in r.output and r.output.count("\n") == 1
    # and with gsplat, which has no tables, in one line too
    r = CliRunner().invoke(jsgs_main, [*args[:3], str(tmp_path / "run3"), "--method", "gsplat", *args[6:]])
    assert r.exit_code == 1 and "--tables" in r.output and r.output.count("\n") == 1, r.output


def test_view_without_analysis_is_refused() -> None:
    t = np.full((8, 8), 4, dtype=np.int32)
    state = JpegState(t, t, "4:2:0", 90, False, 8, "baseline", "YCbCr")
    with pytest.raises(JsgsError, match="manifest --analyze"):
        view_tables([_View(state)], torch.device("cpu"), "m.json", "effective")  # type: ignore[list-item]


def test_recompress_makes_double_compressed_views_that_validate_finds(
    synth_scene: Path, tmp_path: Path
) -> None:
    from jsgstools.cli import main as tools
    from jsgstools.dqt import read_header

    out = tmp_path / "twice"
    args = ["compress", str(synth_scene), "--out", str(out), "--schedule", "fixed", "--quality", "30",
            "--recompress", "95", "--jobs", "1"]  # fmt: skip
    r = CliRunner().invoke(tools, args)
    assert r.exit_code == 0, r.output
    rec = json.loads((out / "compress.json").read_text())
    assert rec["settings"]["recompress"] == 95
    jpgs = sorted((out / "images").glob("*.jpg"))
    assert jpgs and all(read_header(p).quality.quality == 95 for p in jpgs)  # the header says the last save
    r = CliRunner().invoke(tools, ["validate", str(out), "--analyze"])
    assert r.exit_code == 0 and "compressed twice" in r.output, r.output
