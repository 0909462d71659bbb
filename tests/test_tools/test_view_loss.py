"""benchmarks/view_loss.py: shares of the training loss carried by the low-quality views, from the per-view
log of metrics.json."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from conftest import load_benchmark

from jsgs.base.errors import JsgsError

vl = load_benchmark("view_loss")

QUALITY = {"a": 10, "b": 30, "c": 80, "d": None}  # d: a lossless training view


def _train() -> dict[str, Any]:
    per_view = {
        "a": {"steps": 2, "loss": 0.5, "terms": {"photometric": 0.4, "obs": 1.0}},
        "b": {"steps": 1, "loss": 0.2, "terms": {"photometric": 0.2, "obs": 0.0}},
        "c": {"steps": 3, "loss": 0.1, "terms": {"photometric": 0.1, "obs": 0.5}},
        "d": {"steps": 4, "loss": 0.05, "terms": {"photometric": 0.05}},
    }
    return {"steps": 10, "loss": 0.0, "terms": {}, "stats": {}, "per_view": per_view}


def test_shares_by_hand() -> None:
    s = vl.interval_shares(_train(), QUALITY, 30)
    assert s["views"] == pytest.approx(2 / 4) and s["steps"] == pytest.approx(3 / 10)
    assert s["loss"] == pytest.approx((2 * 0.5 + 0.2) / (2 * 0.5 + 0.2 + 3 * 0.1 + 4 * 0.05))
    assert s["photometric"] == pytest.approx((0.8 + 0.2) / (0.8 + 0.2 + 0.3 + 0.2))
    assert s["obs"] == pytest.approx(2.0 / (2.0 + 1.5))  # the lossless view has no L_obs
    assert s["mid"] is None  # a term no view logged
    assert s["lph_low"] == pytest.approx(1.0 / 3) and s["lph_high"] == pytest.approx(0.5 / 7)
    # the threshold is inclusive and moves the split
    assert vl.interval_shares(_train(), QUALITY, 29)["steps"] == pytest.approx(2 / 10)


def test_a_term_some_steps_skipped_is_summed_over_the_steps_that_computed_it() -> None:
    train = _train()
    train["per_view"]["a"] |= {"steps": 4, "terms": {"photometric": 0.4, "fro": 0.3}, "skipped": {"fro": 3}}
    train["per_view"]["c"] |= {"terms": {"photometric": 0.1, "fro": 0.1}, "skipped": {"fro": 2}}
    s = vl.interval_shares(train, QUALITY, 30)
    assert s["fro"] == pytest.approx(0.3 / (0.3 + 0.1))  # one step of each computed it
    assert s["photometric"] == pytest.approx((1.6 + 0.2) / (1.6 + 0.2 + 0.3 + 0.2))


def test_missing_log_and_unknown_views() -> None:
    assert vl.interval_shares({"steps": 3, "per_view": {}}, QUALITY, 30) is None
    with pytest.raises(JsgsError, match="not training views"):
        vl.interval_shares(_train(), {"a": 10}, 30)


def test_cli(compressed_scene: Path, tmp_path: Path, capsys: Any) -> None:
    # a valid manifest (the shared compressed scene's) with four training views named and graded as QUALITY
    doc = json.loads((compressed_scene / "manifest.json").read_text())
    jpeg_view = next(v for v in doc["views"] if v["split"] == "train" and v["jpeg"] is not None)
    test_view = next(v for v in doc["views"] if v["split"] == "test")
    views = []
    for n, q in QUALITY.items():
        v = json.loads(json.dumps(jpeg_view))
        v["name"] = n
        if q is None:
            v["jpeg"] = None
        else:
            v["jpeg"]["quality"] = q
        views.append(v)
    manifest = tmp_path / "manifest.json"
    manifest.write_text(json.dumps({**doc, "views": [*views, test_view]}))
    run = tmp_path / "run"
    run.mkdir()
    old = {"steps": 1, "loss": 0.1, "terms": {}, "stats": {}}  # written before the per-view log existed
    (run / "metrics.json").write_text(
        json.dumps({"evals": [{"step": 5, "train": old}, {"step": 15, "train": _train()}]})
    )
    assert vl.main([str(run), "--manifest", str(manifest)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert "0–5 | no per-view log" in out[2]
    assert "| 5–15 | 50.0 % | 30.0 % |" in out[3]
    assert vl.main([str(run), "--manifest", str(tmp_path / "nope.json")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "nope.json" in err and err.count("\n") == 1
