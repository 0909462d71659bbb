"""``jsgstools.derive``: JPEG datasets made from a clean dataset's references with Pillow only are the same,
bit for bit, as ``jsgstools compress`` makes from the scene; the manifest differs only in paths and
provenance."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from jsgs.base.errors import JsgsError

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def clean_base(synth_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``synth_scene`` compressed with schedule clean, carried as a GPU machine gets it (no images/)."""
    from jsgstools.compress import compress

    out = tmp_path_factory.mktemp("derive") / "clean_s0"
    compress(synth_scene, out, "clean", seed=0, jobs=1)
    shutil.rmtree(out / "images")
    return out


@pytest.mark.parametrize(("schedule", "quality"), [("gaussian", None), ("fixed", 30)])
def test_derive_matches_compress(
    synth_scene: Path, clean_base: Path, tmp_path: Path, schedule: str, quality: int | None
) -> None:
    from jsgstools.compress import compress
    from jsgstools.derive import derive

    ref = compress(synth_scene, tmp_path / "compressed", schedule, quality=quality, seed=0, jobs=1).manifest
    doc = derive(clean_base / "manifest.json", tmp_path / "derived", schedule, quality=quality, seed=0)
    assert doc == json.loads((tmp_path / "derived" / "manifest.json").read_text())
    assert [v["name"] for v in doc["views"]] == [v["name"] for v in ref["views"]]
    n_jpeg = 0
    for a, b in zip(ref["views"], doc["views"], strict=True):
        for key in ("split", "camera", "R", "t", "jpeg"):
            assert a[key] == b[key], (a["name"], key)
        if a["jpeg"] is not None:
            n_jpeg += 1
            assert b["image"] == a["image"] == f"images/{a['name']}"
            assert (tmp_path / "derived" / b["image"]).read_bytes() == (
                tmp_path / "compressed" / a["image"]
            ).read_bytes()
        else:
            assert b["image"] == b["reference"]
        target = (tmp_path / "derived" / b["reference"]).resolve()
        assert target == (clean_base / "reference" / f"{Path(a['name']).stem}.png").resolve()
    assert n_jpeg == sum(v["split"] == "train" for v in ref["views"]) > 0
    assert doc["points"] == ref["points"]
    for key in ("schedule", "quality", "seed", "test_every", "subsampling", "name"):
        assert doc["scene"][key] == ref["scene"][key], key
    st = doc["producer"]["settings"]
    assert doc["producer"]["tool"] == "jsgstools derive" and st["derive"] is True
    assert st["base"] == str(clean_base / "manifest.json") and (st["schedule"], st["seed"]) == (schedule, 0)
    assert st["per_view_quality"] == ref["producer"]["settings"]["per_view_quality"]
    assert st["counts"] == ref["producer"]["settings"]["counts"]
    names = sorted(p.name for p in (tmp_path / "derived").iterdir())
    assert names == [".jsgstools.json", "images", "manifest.json"]


def test_derived_manifest_loads(clean_base: Path, tmp_path: Path) -> None:
    from jsgs.base.manifest import load_manifest
    from jsgstools.derive import derive

    derive(clean_base, tmp_path / "d", "gaussian", seed=1)
    m = load_manifest(tmp_path / "d" / "manifest.json")
    assert all(v.reference is not None and v.reference.is_file() for v in m.views)
    assert all(v.reference.resolve().parent == (clean_base / "reference").resolve() for v in m.views)
    assert all(v.image.is_file() and (v.jpeg is None) == (v.split == "test") for v in m.views)


def test_import_without_pycolmap_or_opencv() -> None:
    code = (
        "import sys; import jsgstools.derive; "
        "assert 'pycolmap' not in sys.modules and 'cv2' not in sys.modules, sorted(sys.modules)"
    )
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr


def test_bad_inputs(synth_scene: Path, clean_base: Path, compressed_scene: Path, tmp_path: Path) -> None:
    from jsgstools.derive import derive

    base = clean_base / "manifest.json"
    with pytest.raises(JsgsError, match="not a clean dataset"):
        derive(compressed_scene / "manifest.json", tmp_path / "a", "gaussian")
    with pytest.raises(JsgsError, match="cannot read the base manifest"):
        derive(tmp_path / "nope" / "manifest.json", tmp_path / "a", "gaussian")
    with pytest.raises(JsgsError, match="choose one of"):
        derive(base, tmp_path / "a", "mixed")
    with pytest.raises(JsgsError, match="needs --quality"):
        derive(base, tmp_path / "a", "fixed")
    with pytest.raises(JsgsError, match="--subsampling"):
        derive(base, tmp_path / "a", "gaussian", subsampling="411")
    derive(base, tmp_path / "a", "uniform")
    with pytest.raises(JsgsError, match="not empty"):
        derive(base, tmp_path / "a", "gaussian")
    derive(base, tmp_path / "a", "gaussian", force=True)
    assert json.loads((tmp_path / "a" / "manifest.json").read_text())["scene"]["schedule"] == "gaussian"
    with pytest.raises(JsgsError, match="inside the input scene"):
        derive(base, clean_base / "x", "gaussian")
    broken = tmp_path / "broken"
    shutil.copytree(clean_base, broken)
    (broken / "reference" / "view_003.png").unlink()
    with pytest.raises(JsgsError, match=r"view_003\.png: reference file of view .* is missing") as e:
        derive(broken / "manifest.json", tmp_path / "b", "gaussian")
    assert "\n" not in str(e.value)
    assert not (tmp_path / "b").exists()
    (broken / "manifest.json").write_text("{")
    with pytest.raises(JsgsError, match="not a JSON file"):
        derive(broken, tmp_path / "b", "gaussian")


def test_derive_recompress_matches_compress_and_records_the_analysis(
    synth_scene: Path, clean_base: Path, tmp_path: Path
) -> None:
    """A schedule saved twice (``recompress``): the same bytes as ``compress --recompress``, and with
    ``analyze`` each JPEG view's compression analysis in the manifest, as ``jsgstools manifest --analyze``
    writes it."""
    from jsgstools.compress import compress
    from jsgstools.derive import derive

    twice = {"quality": 30, "seed": 0, "recompress": 90, "analyze": True}
    ref = compress(synth_scene, tmp_path / "c", "fixed", jobs=1, **twice)
    doc = derive(clean_base, tmp_path / "d", "fixed", **twice)
    assert doc["producer"]["settings"]["recompress"] == 90
    assert ref.manifest["producer"]["settings"]["recompress"] == 90
    jpegs = [(a, b) for a, b in zip(ref.manifest["views"], doc["views"], strict=True) if a["jpeg"]]
    assert jpegs
    for a, b in jpegs:
        assert (tmp_path / "d" / b["image"]).read_bytes() == (tmp_path / "c" / a["image"]).read_bytes()
        assert b["jpeg"] == a["jpeg"]
        assert b["jpeg"]["analysis"]["double_compressed"] is True
        assert b["jpeg"]["quality"] == 90
        assert abs(b["jpeg"]["analysis"]["primary_quality"] - 30) <= 5
    with pytest.raises(JsgsError, match="--recompress 0"):
        derive(clean_base, tmp_path / "e", "fixed", quality=30, recompress=0)
