"""tools/diagnostics/graph_pool.py: the image terms' graph function counted in the CUDA layout on the CPU
(the fused SSIM stood in by its outputs; the Triton kernels under the interpreter where it runs)."""

from __future__ import annotations

import pytest
import torch
from conftest import load_benchmark

from jsgs.kernels._triton_jo import interpreting, triton_available

cm = load_benchmark("graph_pool", "tools/diagnostics")

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_the_peak_is_the_sum_of_what_is_alive_at_it_and_the_stand_in_is_undone() -> None:
    import jsgs.kernels._wrapper as wrapper

    before = wrapper.extension, wrapper._use_fused
    out = cm.chain_peak(64, 48, "torch")
    assert (wrapper.extension, wrapper._use_fused) == before
    assert out["bytes"] == sum(r[0] for r in out["rows"]) > 0
    assert out["per_pixel"] == out["bytes"] / (64 * 48)
    # the target made from the image, laid out once as the fused SSIM keeps it (12 B a pixel)
    assert any(r[1:5] == ("forward", "clone.default", "[1, 3, 48, 64]", "float32") for r in out["rows"])


def test_a_bad_size_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert cm.main(["--jo", "torch", "--size", "64by48"]) != 0
    assert "--size '64by48': expected WxH" in capsys.readouterr().err


@pytest.mark.skipif(not (triton_available() and interpreting()), reason="needs Triton and TRITON_INTERPRET=1")
def test_with_the_fused_kernels_the_peak_holds_the_ssims_three_saved_maps() -> None:
    out = cm.chain_peak(64, 48, "triton")
    maps = [r for r in out["rows"] if "_wrapper.py" in r[5] and r[1] == "forward"]
    assert [r[0] for r in maps] == [3 * 3 * 38 * 54 * 4]  # three (1, 3, 38, 54) maps, "valid" padding
    assert any(r[1] == "backward" for r in out["rows"])  # the peak is in the backward
    assert torch.get_num_threads() >= 1
