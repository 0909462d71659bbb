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

namespace {

// Argument checks live here, in the g++-compiled translation unit, where a failed TORCH_CHECK becomes a
// Python RuntimeError; thrown from the nvcc-compiled kernels' unit it crashed the process instead.
void check_like(const at::Tensor& t, const at::Tensor& like, std::vector<int64_t> shape, const char* name) {
  TORCH_CHECK(t.is_cuda() && t.device() == like.device() && t.scalar_type() == like.scalar_type(),
              "fused controller: ", name, " is ", t.scalar_type(), " on ", t.device(), "; every tensor must be ",
              like.scalar_type(), " on one CUDA device");
  TORCH_CHECK(t.sizes() == at::IntArrayRef(shape), "fused controller: ", name, " has shape ", t.sizes(),
              ", expected ", at::IntArrayRef(shape));
  TORCH_CHECK(t.is_contiguous(), "fused controller: ", name, " must be contiguous");
}

std::vector<at::Tensor> controller_forward_checked(at::Tensor probe_grad, at::Tensor logits,
                                                   at::Tensor log_scales, at::Tensor means, at::Tensor quats,
                                                   at::Tensor viewmat, at::Tensor K, int64_t width,
                                                   int64_t height, double weight, double near_plane,
                                                   double eps_proj, double tau_s) {
  TORCH_CHECK(logits.dim() == 1, "fused controller: opacity_logits must be [N], got ", logits.sizes());
  TORCH_CHECK(logits.scalar_type() == at::kFloat || logits.scalar_type() == at::kDouble,
              "fused controller: needs float32 or float64, got ", logits.scalar_type());
  TORCH_CHECK(weight > 0, "fused controller: weight must be > 0, got ", weight);
  const int64_t n = logits.size(0);
  check_like(logits, logits, {n}, "opacity_logits");
  check_like(probe_grad, logits, {1, n, 2}, "probe_grad");
  check_like(log_scales, logits, {n, 3}, "log_scales");
  check_like(means, logits, {n, 3}, "means");
  check_like(quats, logits, {n, 4}, "quats");
  check_like(viewmat, logits, {4, 4}, "viewmat");
  check_like(K, logits, {3, 3}, "K");
  return controller_forward(probe_grad, logits, log_scales, means, quats, viewmat, K, width, height, weight,
                            near_plane, eps_proj, tau_s);
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("ssim_forward", &ssim_forward, "SSIM map and its partial derivatives (jsgs/csrc/ssim.cu)");
  m.def("ssim_backward", &ssim_backward, "gradient of a weighted SSIM map sum w.r.t. x (jsgs/csrc/ssim.cu)");
  m.def("controller_forward", &controller_forward_checked,
        "deferred Gaussian Controller of one view: weighted L_fro gradients and stats (controller.cu)");
}
