"""jsgs's kernels, each CUDA op beside its torch twin (gsplat's ``gsplat/cuda`` layout):

- ``csrc/``: the CUDA sources, one Python extension built on first use by :mod:`jsgs.kernels._backend`
  (which also decides, for a setting "auto" / "torch" / "cuda", whether the kernels run: :func:`use_kernels`);
- :mod:`jsgs.kernels._wrapper`: what callers call; it runs the CUDA op or falls back to the twin;
- :mod:`jsgs.kernels._torch_impl`: the twins, which run anywhere and are the CUDA ops' references in the
  tests (against each other on a GPU, against float64 and independent formulas on the CPU).

====================  ===================================  ===========================================
op                    CUDA                                 torch twin (``_torch_impl``)
====================  ===================================  ===========================================
SSIM                  ``csrc/ssim.cu`` (:func:`ssim`)      ``ssim_map_torch``
Gaussian Controller   ``csrc/controller.cu``               :func:`fro_from_probe_grad`
                      (:func:`fro_from_probe_grad_fused`)
MCMC relocation       gsplat's ``relocation`` and          :func:`compute_relocation`,
                      ``quat_scale_to_covar_preci``        :func:`quat_scale_to_covar` (:func:`cpu_twins`)
JO's coding pass      Triton: ``_triton_jo.py``            ``jsgs.jpeg.observe._code_blocks`` (modes
(modes "paper" and    (``paper_code``, ``float_code``,     "paper" and "float")
"float")              optional)
DS's Delta            Triton: ``_triton_jo.py``            ``jsgs.jpeg.supervision._delta``
                      (``ds_delta``, optional)             (kernel "torch")
====================  ===================================  ===========================================

The Triton kernels are imported only where used (:mod:`jsgs.kernels._triton_jo`, by ``jsgs.jpeg.observe``
with ``kernel="triton"``); without Triton that module still imports and says so (``triton_available``).
"""

from jsgs.kernels._backend import KERNEL_CHOICES, build_error, extension, use_kernels
from jsgs.kernels._torch_impl import (
    C1,
    C2,
    EPS_PROJ,
    FOV_MARGIN,
    TAU_S,
    ControllerStats,
    DeferredFro,
    FroTerms,
    PooledSums,
    compute_relocation,
    controller_matrix,
    fro_from_probe_grad,
    fro_loss,
    fro_loss_and_grads,
    gaussian_window,
    packed_fro_stats,
    projected_rms_scale_sq,
    quat_scale_to_covar,
    sums_from_probe_grad,
)
from jsgs.kernels._wrapper import (
    SSIM_KERNELS,
    cpu_twins,
    fro_from_probe_grad_fused,
    ssim,
    ssim_is_fused,
    ssim_map,
)

__all__ = [
    "C1",
    "C2",
    "EPS_PROJ",
    "FOV_MARGIN",
    "KERNEL_CHOICES",
    "SSIM_KERNELS",
    "TAU_S",
    "ControllerStats",
    "DeferredFro",
    "FroTerms",
    "PooledSums",
    "build_error",
    "compute_relocation",
    "controller_matrix",
    "cpu_twins",
    "extension",
    "fro_from_probe_grad",
    "fro_from_probe_grad_fused",
    "fro_loss",
    "fro_loss_and_grads",
    "gaussian_window",
    "packed_fro_stats",
    "projected_rms_scale_sq",
    "quat_scale_to_covar",
    "ssim",
    "ssim_is_fused",
    "ssim_map",
    "sums_from_probe_grad",
    "use_kernels",
]
