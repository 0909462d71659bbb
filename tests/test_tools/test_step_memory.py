"""tools/diagnostics/step_memory.py: the storage accounting on hand-made ops (sizes known exactly), and the
whole tool on a tiny synthetic scene on the CPU (gsplat, jsgs and the CUDA-graph layout), its JSON against
schemas/step_memory.schema.json."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import torch
from conftest import load_benchmark

sm = load_benchmark("step_memory", "tools/diagnostics")

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_live_storages_counts_each_storage_once_until_freed() -> None:
    """Made storages count from the op that makes them until torch frees them (a storage kept alive by
    autograd counts until the backward releases it); views, in-place ops and tensors made before the mode
    count nothing; the peak lists what was alive at it."""
    old = torch.ones(1000)
    mode = sm.LiveStorages(lambda shape: "other")
    with mode:
        old.add_(1.0)  # in place on a storage made before: not made here
        a = torch.empty(1000)  # 4000 B
        b = torch.empty(2000)  # 8000 B
        a2 = a.view(10, 100)  # a view: the same storage
        assert mode.bytes == 12000
        del a, a2
        assert mode.bytes == 8000  # a's storage freed with its last view
        c = torch.empty(500)
        x = torch.rand(300, requires_grad=True)  # 1200 B
        y = (x * 2.0).exp()  # x*2 is freed at once (nothing saves it); exp saves its output y
        assert mode.bytes == 8000 + 2000 + 1200 + 1200
        y.sum().backward()
        del y
    assert mode.peak["all"] >= 12400 and mode.peak["pool"] == 0
    peak = [mode.made[i] for i in mode.at_peak["all"]]
    assert {m.nbytes for m in peak} >= {8000, 2000, 1200}
    del b, c
    assert mode.bytes == 1200 + 1200  # x and its gradient
    assert all(m.op.startswith("aten.") and m.phase in ("forward", "backward") for m in mode.made)
    assert any(m.phase == "backward" for m in mode.made)


def test_scale_classes() -> None:
    scale_of = sm.scale_classifier(504, 378, 40000)
    assert scale_of((1, 3, 378, 504)) == "pixels"
    assert scale_of((1, 4560, 8, 8)) == "other"  # blocks flattened with channels: no image dimension
    assert scale_of((48, 64, 8, 8)) == "pixels"  # 384/8 x 512/8 blocks
    assert scale_of((190512, 3)) == "pixels"
    assert scale_of((40000, 3)) == "gaussians"
    assert scale_of((341, 16, 16, 13)) == "other"


def test_tiny_scene_three_layouts(tmp_path: Path, capsys: Any) -> None:
    from jsgs.base.schema import validate

    out = tmp_path / "memory.json"
    cfg = tmp_path / "few.json"  # few Gaussians: the image terms, not the rasteriser's pairs, make the peak
    cfg.write_text(json.dumps({"init": {"type": "random", "num_points": 100, "scale": 0.3}}))
    argv = ["--size", "64x48", "--views", "4", "--warmup", "1", "--top", "6", "--config", str(cfg),
            "--out", str(out)]  # fmt: skip
    assert sm.main(argv) == 0
    doc = json.loads(out.read_text())
    validate(doc, "step_memory", "test")
    res = doc["results"]
    g, j, gl = res["gsplat"], res["jsgs"], res["jsgs-graph-layout"]
    h, w = 48, 64

    # the graph layout keeps its input buffers (render, which then holds its gradient: 3 HW floats; the index
    # of the step's image in the trainer's stack of them, which it reads in place; the two 8x8 tables) and
    # outputs (the four values, r_b: one float a block; no observation without keep_last): 12 bytes a pixel
    # (15 with a copy of the image, 19 with r(p) too)
    extra = gl["resident_bytes"]["method hook"] - j["resident_bytes"]["method hook"]
    assert extra == 3 * h * w * 4 + 8 + (h // 8) * (w // 8) * 4 + 2 * 64 * 4 + 4 * 4
    assert gl["resident_bytes"]["training images"] == j["resident_bytes"]["training images"] == 3 * h * w * 3
    assert g["resident_bytes"]["method hook"] == 0
    assert gl["pool_peak_bytes"] > 0 and j["pool_peak_bytes"] == g["pool_peak_bytes"] == 0
    assert j["step_peak_bytes"] > g["step_peak_bytes"]
    assert gl["step_peak_bytes"] < j["step_peak_bytes"]  # JO, L_obs and DS live in the pool instead
    assert gl["peaks"]["all"]["bytes"] >= gl["step_peak_bytes"]
    for r in res.values():  # the backward's own peak: a part of the step's, reached in the backward
        assert 0 < r["backward_peak_bytes"] <= r["step_peak_bytes"] == r["peaks"]["outside_pool"]["bytes"]
        assert r["peaks"]["backward"]["bytes"] == r["backward_peak_bytes"]
        assert r["peaks"]["backward"]["reached_by"]["phase"] == "backward"
    for r in res.values():
        assert r["num_gaussians"] > 0 and (r["width"], r["height"]) == (w, h)
        assert r["step_end_bytes"] <= r["made_bytes"] and r["step_peak_bytes"] <= r["made_bytes"]
        pk = r["peaks"]["outside_pool"]
        assert sum(pk["by_part"].values()) == pk["bytes"] == sum(pk["by_scale"].values())
        assert [t["nbytes"] for t in pk["top"]] == sorted((t["nbytes"] for t in pk["top"]), reverse=True)
    parts = {p.removesuffix(" (backward)") for p in j["peaks"]["all"]["by_part"]}
    assert "rasteriser" in parts and parts & {"JO", "DS", "GC probe"}
    made_parts = {p.removesuffix(" (backward)") for p in g["peaks"]["all"]["by_part"]}
    assert not made_parts & {"JO", "DS", "GC probe", "GC", "hook"}
    printed = capsys.readouterr().out
    assert (
        "| method | Gaussians | resident | step peak |" in printed and "jsgs-graph-layout: largest" in printed
    )


def test_bad_settings_are_one_line(tmp_path: Path, capsys: Any) -> None:
    assert sm.main(["--methods", "gsplat,nope"]) == 1
    assert sm.main(["--manifest", str(tmp_path / "missing.json")]) == 1
    assert sm.main(["--size", "big"]) == 1
    assert sm.main(["--preset", "paper", "--cap-max", "5000"]) == 1  # DefaultStrategy has no budget
    assert sm.main(["--cap-max", "many"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 5 and all(line.startswith("error: ") for line in err)
    assert "--cap-max applies to strategy.type mcmc" in err[3] and "--cap-max: expected a number" in err[4]


def test_budget_is_the_published_fixed_one_unless_given(tmp_path: Path) -> None:
    """The mcmc preset's budget here is the fixed 300,000 of the published figures (not the preset's
    scene-sized default), a config file's budget over it and ``--cap-max`` over both."""
    over = tmp_path / "over.json"
    over.write_text(json.dumps({"strategy": {"cap_max": 777}}))
    budget = [
        (c.strategy.cap_max, c.strategy.cap_max_auto)
        for c in (
            sm.start_config("mcmc", None, None),
            sm.start_config("mcmc", over, None),
            sm.start_config("mcmc", over, "300000"),
        )
    ]
    assert budget == [(300_000, False), (777, False), (300_000, False)]
    assert sm.start_config("mcmc", None, "auto").strategy.cap_max_auto
    assert sm.parse_args(["--cap-max", "auto"]).cap_max == "auto"
