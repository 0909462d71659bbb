// The Python module of jsgs's CUDA kernels (built on first use by jsgs.cuda_ext): the fused SSIM
// (ssim.cu) and the fused Gaussian Controller (controller.cu). Each has a torch twin that is its reference.
#include <torch/extension.h>

#include <vector>

std::vector<at::Tensor> ssim_forward(at::Tensor x, at::Tensor y, at::Tensor window, double c1, double c2,
                                     bool same);
at::Tensor ssim_backward(at::Tensor grad, at::Tensor x, at::Tensor y, at::Tensor window, at::Tensor d_mu,
                         at::Tensor d_xx, at::Tensor d_xy, bool same);
std::vector<at::Tensor> controller_forward(at::Tensor probe_grad, at::Tensor logits, at::Tensor log_scales,
                                           at::Tensor means, at::Tensor quats, at::Tensor viewmat,
                                           at::Tensor K, int64_t width, int64_t height, double weight,
                                           double near_plane, double eps_proj, double tau_s);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("ssim_forward", &ssim_forward, "SSIM map and its partial derivatives (jsgs/csrc/ssim.cu)");
  m.def("ssim_backward", &ssim_backward, "gradient of a weighted SSIM map sum w.r.t. x (jsgs/csrc/ssim.cu)");
  m.def("controller_forward", &controller_forward,
        "deferred Gaussian Controller of one view: weighted L_fro gradients and stats (controller.cu)");
}
