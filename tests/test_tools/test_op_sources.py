"""tools/diagnostics/op_sources.py on a tiny synthetic scene on the CPU: JSGS's JO and DS parts exist and
the baseline has none, JSGS counts more ops, and the tables print (with ``--products``, JO's colour maps as
matrix products over all 48 x 32 pixels)."""

from __future__ import annotations

from typing import Any

import pytest
from conftest import load_benchmark

ops = load_benchmark("op_sources", "tools/diagnostics")

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_parts_of_a_tiny_window(capsys: Any) -> None:
    counts = {}
    for method in ("gsplat", "jsgs"):
        by_op, reads = ops.run(method, (48, 32), 6, 3, 2)
        parts = {p.removesuffix(" (backward)") for p, _ in by_op}
        counts[method] = sum(by_op.values())
        assert reads >= 0 and counts[method] > 0
        assert ("JO" in parts and "DS" in parts) == (method == "jsgs")
        assert "rasteriser" in parts and "trainer" in parts
    assert counts["jsgs"] > counts["gsplat"]
    assert ops.main(["--size", "48x32", "--views", "6", "--warmup", "3", "--steps", "1", "--detail",
                     "--products"]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "| part (forward and backward) | aten ops per step |" in printed and "| JO |" in printed
    # rgb -> YCbCr and YCbCr -> RGB, [H W, 3] x [3, 3] with the offset; DS's Y8 of observation and target
    assert "| JO | aten::addmm | [[3], [1536, 3], [3, 3]] | 2.0 |" in printed
    assert "| DS | aten::mm | [[1536, 3], [3, 1]] | 2.0 |" in printed


def test_cap_max_is_refused_in_one_line_where_it_means_nothing(capsys: Any) -> None:
    """``--cap-max`` with the default paper preset (DefaultStrategy, no budget) or an unreadable value: one
    line, exit status 1, before anything trains."""
    assert ops.main(["--cap-max", "300000"]) == 1
    assert ops.main(["--preset", "mcmc", "--cap-max", "lots"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "error: --cap-max applies to strategy.type mcmc (--preset mcmc); it is 'default'",
        "error: --cap-max: expected a number of Gaussians or auto (got 'lots')",
    ]
