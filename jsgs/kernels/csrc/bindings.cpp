// The Python module of jsgs's CUDA kernels (built on first use by jsgs.kernels._backend): the fused SSIM
// (ssim.cu) and the fused Gaussian Controller (controller.cu). Each has a torch twin that is its reference.
#include <torch/extension.h>

#include <initializer_list>
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

// The fused controller's argument checks, as a yes/no: nothing in this extension builds an error message or
// throws. On the GPU machine (torch 2.11, CUDA 13) both a failed TORCH_CHECK and a c10::str message built
// here ends the process (SIGSEGV), so the Python caller words the refusal itself.
bool like(const at::Tensor& t, const at::Tensor& ref, std::initializer_list<int64_t> shape) {
  return t.is_cuda() && t.device() == ref.device() && t.scalar_type() == ref.scalar_type() &&
         t.sizes() == at::IntArrayRef(shape) && t.is_contiguous();
}

bool controller_arguments_ok(const at::Tensor& probe_grad, const at::Tensor& logits,
                             const at::Tensor& log_scales, const at::Tensor& means, const at::Tensor& quats,
                             const at::Tensor& viewmat, const at::Tensor& K, double weight) {
  if (logits.dim() != 1 || !(weight > 0)) return false;
  if (logits.scalar_type() != at::kFloat && logits.scalar_type() != at::kDouble) return false;
  const int64_t n = logits.size(0);
  return like(logits, logits, {n}) && like(probe_grad, logits, {1, n, 2}) && like(log_scales, logits, {n, 3}) &&
         like(means, logits, {n, 3}) && like(quats, logits, {n, 4}) && like(viewmat, logits, {4, 4}) &&
         like(K, logits, {3, 3});
}

// An empty result for arguments the kernels cannot take.
std::vector<at::Tensor> controller_forward_checked(at::Tensor probe_grad, at::Tensor logits,
                                                   at::Tensor log_scales, at::Tensor means, at::Tensor quats,
                                                   at::Tensor viewmat, at::Tensor K, int64_t width,
                                                   int64_t height, double weight, double near_plane,
                                                   double eps_proj, double tau_s) {
  if (!controller_arguments_ok(probe_grad, logits, log_scales, means, quats, viewmat, K, weight)) return {};
  return controller_forward(probe_grad, logits, log_scales, means, quats, viewmat, K, width, height, weight,
                            near_plane, eps_proj, tau_s);
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("ssim_forward", &ssim_forward, "SSIM map and its partial derivatives (ssim.cu)");
  m.def("ssim_backward", &ssim_backward, "gradient of a weighted SSIM map sum w.r.t. x (ssim.cu)");
  m.def("controller_forward", &controller_forward_checked,
        "deferred Gaussian Controller of one view: weighted L_fro gradients and stats (controller.cu); "
        "an empty list for bad arguments");
}
