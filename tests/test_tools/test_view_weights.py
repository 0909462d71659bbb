"""tools/diagnostics/view_weights.py: each JPEG training view's ℓ_ph weight under a recipe, by quality, on
the synthetic compressed scene, against the weights a training run records in its config.json."""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import pytest
from conftest import load_benchmark

vw = load_benchmark("view_weights", "tools/diagnostics")


def test_weights_are_the_trainers(compressed_scene: Path, tmp_path: Path) -> None:
    from jsgs.train.config import TrainConfig
    from jsgs.train.trainer import train

    manifest = compressed_scene / "manifest.json"
    preset = vw.RECIPES["mcmc"]
    raw = [("default", preset), vw.parse_recipe('b={"base_block_ref": 0.2}')]
    recipes = {n: vw.parse_options(o, n) for n, o in raw}
    rows = vw.view_table(manifest, recipes)
    assert rows and all(0.0 < r["b"] <= r["default"] <= 1.0 and r["blockiness"] > 0 for r in rows)
    assert any(r["b"] < 0.9 * r["default"] for r in rows)  # the blockiness factor bites somewhere
    # a one-step run of the same recipe records the same weights
    cfg = TrainConfig.from_preset("paper", iterations=1, eval_at=[], device="cpu", method="jsgs")
    cfg.method_options = {**vw.RECIPES["mcmc"], "base_block_ref": 0.2, "gc": False}
    train(manifest, tmp_path / "run", cfg, progress=False)
    by_view = json.loads((tmp_path / "run" / "config.json").read_text())["derived"]["method"]["base_by_view"]
    mine, trainers = sorted(r["b"] for r in rows), sorted(r["weight"] for r in by_view.values())
    assert mine == pytest.approx(trainers, abs=2e-6)  # config.json rounds to 6 places
    text = vw.markdown(manifest, rows, list(recipes))
    assert "| weight, b | " in text
    last = text.splitlines()[-1].split("|")
    assert float(last[-2]) == pytest.approx(statistics.median(r["b"] for r in rows), abs=0.005)


def test_bad_recipe_is_one_line(compressed_scene: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m = str(compressed_scene / "manifest.json")
    assert vw.main([m, "--recipe", "x"]) == 1
    err = capsys.readouterr().err
    assert err == "error: --recipe 'x': expected NAME=JSON, e.g. 'b0.5={\"base_block_ref\": 0.5}'\n"
    assert vw.main([m, "--recipe", "x={"]) == 1
    assert capsys.readouterr().err.startswith("error: --recipe x: not JSON")
    assert vw.main([m, "--recipe", 'x={"base_block_ref": -1}']) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "base_block_ref" in err
