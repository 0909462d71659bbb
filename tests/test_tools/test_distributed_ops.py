"""tools/diagnostics/distributed_ops.py on the synthetic JPEG scene, JSGS on 2 processes (gloo, the torch
exchange): an ordinary step's collectives are the parameters' all-gather (each process's rows, 59 float32
each at SH degree 3) and the gradients' reduce-scatter (every process's block: its rows' 59 float32 and the
flag column, which also carries both processes' step values: 3 + 64 float32 each, the block padded to hold
them on this small scene), and nothing else; the step makes more aten ops than one process's."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest
from _train_scene import make_scene
from conftest import load_benchmark

ops = load_benchmark("distributed_ops", "tools/diagnostics")


@pytest.mark.slow
def test_an_ordinary_steps_collectives_and_extra_ops(tmp_path: Path) -> None:
    scene = make_scene(tmp_path / "scene", n_views=6, jpeg_train=True)
    args = argparse.Namespace(manifest=str(scene), method="jsgs", processes=2, cap=200, steps=10)
    docs = ops.measure(args)
    two = docs[2]
    rows = max(-(-two["gaussians"] // 2), 1)  # the larger shard (MCMC's shares differ by one at most)
    block = max(rows, 1 + 2 * (3 + 64))  # the count, then each process's step values
    assert two["collectives"] == {
        f"all_gather {rows * 59 * 4}": 1.0,
        f"reduce_scatter {2 * block * (59 + 1) * 4}": 1.0,
    }, two
    assert not docs[1]["collectives"]
    extra = sum(two["ops"].values()) - sum(docs[1]["ops"].values())
    assert extra > 0 and two["ops"]["_reduce_scatter_base_"] == 1.0
    text = ops.report(docs)
    assert "reduce_scatter: 1.0 x" in text and "B per Gaussian" in text
