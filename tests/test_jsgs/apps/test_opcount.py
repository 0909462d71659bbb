"""The kernel counter, and the number of kernels one JSGS step launches (a regression guard: at real scene
sizes these terms are launch-bound on a GPU, so the count is their cost;
tools/diagnostics/bench_kernel_count.py prints it per phase)."""

from __future__ import annotations

import torch

from jsgs.apps.opcount import KernelCounter, count_phases, jsgs_step
from jsgs.render.reference import quat_to_rotmat


def test_the_counter_counts_kernels_not_views() -> None:
    x = torch.rand(4, 6, requires_grad=True)
    with KernelCounter() as k:
        y = x.view(6, 4).t().detach()  # views and detach: nothing launched
    assert k.total == 0
    with KernelCounter() as k:
        z = (x * 2 + 1).sum()
    assert k.total == 3 and k.ops["aten.mul"] == 1 and k.ops["aten.add"] == 1
    with KernelCounter() as k:
        z.backward()  # the backward on CPU runs on this thread and is counted
    assert k.total > 0 and y.shape == (4, 6)


def test_the_counter_adds_up_the_bytes_each_kernel_moves() -> None:
    a, row = torch.rand(100, 50), torch.rand(50)
    with KernelCounter() as k:
        b = a + row  # reads a (20,000 B) and the broadcast row once (200 B), writes b (20,000 B)
        b.view(50, 100).t()  # views move nothing
    assert k.bytes == 20_000 + 200 + 20_000 == k.traffic["aten.add"]
    with KernelCounter() as k:
        a.mul_(2.0)  # in place: read and written
    assert k.bytes == 2 * 20_000


def _jsgs_step_kernels(mode: str) -> tuple[int, int]:
    """(JO + L_obs + DS forward and their backward, deferred GC in the backward) kernels for one view."""
    n = count_phases(jsgs_step(mode, "4:2:0", (96, 64), 500))
    return n["JO"] + n["L_obs"] + n["DS"] + n["backward"], n["GC (in backward)"]


def test_a_jsgs_step_launches_few_kernels() -> None:
    # Measured when written (torch 2.13, CPU; CUDA dispatches the same ops, not counted there yet): 222 and
    # 64, down from 346 and 144 before the JO/DS/GC code was rewritten for launch count (one coding pass for
    # all planes, colour and DCT as single matrix products, R(q) as one quadratic form, shared factors in the
    # closed-form GC). A change that adds kernels to every step must raise these bounds knowingly. The GC
    # counts 71 (r̄ from the probe's gradient counted with it, and Rw R(q) as one plain GEMM, whose operand
    # needs a copy, instead of N batched 3x3 GEMMs); on CUDA it is one graph replay anyway.
    image, gc = _jsgs_step_kernels("paper")
    assert image <= 230, image
    assert gc <= 72, gc


def test_rotation_from_the_quadratic_form_is_the_usual_matrix() -> None:
    q = torch.randn(2000, 4, dtype=torch.float64) * torch.rand(2000, 1, dtype=torch.float64) * 3
    qn = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = qn.unbind(-1)
    ref = torch.stack(
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
         2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
         2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1,
    ).reshape(-1, 3, 3)  # fmt: skip
    R = quat_to_rotmat(q)
    torch.testing.assert_close(R, ref, rtol=0, atol=1e-14)
    torch.testing.assert_close(
        R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand_as(R), atol=1e-14, rtol=0
    )
    # batch shapes other than [N, 4] and float32
    assert quat_to_rotmat(torch.randn(2, 3, 4)).shape == (2, 3, 3, 3)
