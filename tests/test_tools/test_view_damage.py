"""benchmarks/view_damage.py: per-view JPEG damage of the training views of compressed datasets."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import load_benchmark, shared_scene

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "view_damage.py"


vd = load_benchmark("view_damage")


@pytest.fixture(scope="module")
def synth_doc(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    """Uniform and descending datasets of a 16-view 64x48 synthetic scene (14 training views), kept."""
    from jsgstools.synth import synth

    root = tmp_path_factory.mktemp("view_damage")
    synth(root / "scene", views=16, size=(64, 48), seed=0)
    doc = vd.analyse([root / "scene"], ["uniform", "descending"], [0], work=root / "work", jobs=1)
    return doc, root / "work"


def test_shares_and_counts(synth_doc: tuple[dict[str, Any], Path]) -> None:
    doc, work = synth_doc
    assert [(d["scene"], d["schedule"], d["seed"]) for d in doc["datasets"]] == [
        ("scene", "uniform", 0),
        ("scene", "descending", 0),
    ]
    for d in doc["datasets"]:
        rec = json.loads((work / "scene" / f"{d['schedule']}_s0" / "compress.json").read_text())
        train = [v for v in rec["views"] if v["split"] == "train"]
        assert d["train_views"] == len(train) == 14
        views = [v for v in doc["views"] if v["schedule"] == d["schedule"]]
        # the qualities are compress's own, view by view
        assert {v["name"]: v["quality"] for v in views} == {v["name"]: v["quality"] for v in train}
        low = [v for v in views if v["quality"] <= 30]
        assert d["low_views"] == len(low)
        assert 0 <= d["low_view_share"] <= 1 and 0 <= d["low_sse_share"] <= 1
        assert d["low_view_share"] == pytest.approx(len(low) / 14)
        assert d["low_sse_share"] == pytest.approx(sum(v["mse"] for v in low) / sum(v["mse"] for v in views))
        # the low views are the most damaged: they carry more than their head count of the error
        assert d["low_sse_share"] > d["low_view_share"] > 0
    uni, desc = doc["datasets"]
    assert desc["low_view_share"] < uni["low_view_share"]  # descending puts few views at low quality
    for lv in doc["levels"]:
        n = sum(1 for v in doc["views"] if v["schedule"] == lv["schedule"] and v["quality"] == lv["quality"])
        assert lv["count"] == n
    assert sum(lv["count"] for lv in doc["levels"]) == len(doc["views"]) == 28


def test_psnr_matches_numpy(synth_doc: tuple[dict[str, Any], Path]) -> None:
    from PIL import Image

    doc, work = synth_doc
    v = min((v for v in doc["views"] if v["schedule"] == "uniform"), key=lambda v: v["quality"])
    data = work / "scene" / "uniform_s0"
    jpg = np.array(Image.open(data / "images" / v["name"]).convert("RGB")).astype(np.float64) / 255
    ref = np.array(Image.open(data / "reference" / (Path(v["name"]).stem + ".png"))).astype(np.float64) / 255
    assert ref.shape == jpg.shape == (48, 64, 3)
    mse = ((jpg - ref) ** 2).sum() / jpg.size
    assert v["mse"] == pytest.approx(mse, rel=1e-12)
    assert v["psnr"] == pytest.approx(-10 * np.log10(mse), rel=1e-12)


def test_lower_quality_lower_psnr(synth_doc: tuple[dict[str, Any], Path]) -> None:
    doc, _ = synth_doc
    q = np.array([v["quality"] for v in doc["views"]], dtype=float)
    p = np.array([v["psnr"] for v in doc["views"]], dtype=float)
    assert np.corrcoef(q, p)[0, 1] > 0.8
    levels = [lv for lv in doc["levels"] if lv["schedule"] == "uniform"]
    assert all(lv["count"] >= 1 for lv in levels)  # 14 views over 9 levels: every level is used
    psnr = [lv["mean_psnr"] for lv in levels]
    assert np.mean(psnr[:3]) < np.mean(psnr[3:6]) < np.mean(psnr[6:])
    assert psnr[0] < psnr[-1] - 5


def test_json_validates_and_markdown(synth_doc: tuple[dict[str, Any], Path]) -> None:
    from jsgs.base.errors import JsgsError
    from jsgs.base.schema import validate

    doc, _ = synth_doc
    validate(json.loads(json.dumps(doc)), "view_damage", "doc")
    bad = json.loads(json.dumps(doc))
    bad["datasets"][0]["low_sse_share"] = 1.5
    with pytest.raises(JsgsError, match="low_sse_share"):
        validate(bad, "view_damage", "doc")
    md = vd.markdown(doc).splitlines()
    assert "| scene | uniform | 0 | 14 |" in "\n".join(md)
    assert sum(1 for line in md if line.startswith("| ") and line[2:4].strip().isdigit()) == 9  # q rows


def test_bad_scene_is_one_line_error(tmp_path: Path) -> None:
    r = subprocess.run(
        [sys.executable, str(SCRIPT), str(tmp_path), "--no-progress"], capture_output=True, text=True
    )
    assert r.returncode == 1
    assert r.stderr.startswith("error: ") and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert r.stdout == ""


def test_real_scene_fern(tmp_path: Path) -> None:
    """llff_fern (20 views, 17 training JPEGs), gaussian schedule: real photographs behave the same way."""
    fern = shared_scene("llff_fern")
    doc = vd.analyse([fern], ["gaussian"], [0], work=tmp_path)
    (d,) = doc["datasets"]
    assert d["scene"] == "llff_fern" and d["train_views"] == 17
    rec = json.loads((tmp_path / "llff_fern" / "gaussian_s0" / "compress.json").read_text())
    counts = {int(q): c for q, c in rec["settings"]["counts"].items()}
    assert {lv["quality"]: lv["count"] for lv in doc["levels"] if lv["count"]} == {
        q: c for q, c in counts.items() if c
    }
    assert 0 <= d["low_view_share"] < d["low_sse_share"] <= 1
    by_q = sorted(doc["views"], key=lambda v: v["quality"])
    assert by_q[0]["psnr"] < by_q[-1]["psnr"]
    assert 20 < d["mean_psnr"] < 45
    vd_json = json.loads(json.dumps(doc))
    from jsgs.base.schema import validate

    validate(vd_json, "view_damage", "fern")
