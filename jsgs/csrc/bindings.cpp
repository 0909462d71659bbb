// The Python module of jsgs's CUDA kernels (built on first use by jsgs.cuda_ext): the fused SSIM
// (ssim.cu) and the fused Gaussian Controller (controller.cu). Each has a torch twin that is its reference.
#include <torch/extension.h>

#include <string>
#include <utility>
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

// The argument checks of the fused controller, as a message rather than an exception: a TORCH_CHECK that
// failed inside this extension crashed the process on the GPU machine (SIGSEGV, session 6 from the .cu
// unit and session 8 from this one), so no exception is thrown across this module's boundary at all.
std::string like_error(const at::Tensor& t, const at::Tensor& like, std::vector<int64_t> shape,
                       const char* name) {
  if (!(t.is_cuda() && t.device() == like.device() && t.scalar_type() == like.scalar_type()))
    return c10::str("fused controller: ", name, " is ", t.scalar_type(), " on ", t.device(),
                    "; every tensor must be ", like.scalar_type(), " on one CUDA device");
  if (t.sizes() != at::IntArrayRef(shape))
    return c10::str("fused controller: ", name, " has shape ", t.sizes(), ", expected ", at::IntArrayRef(shape));
  if (!t.is_contiguous()) return c10::str("fused controller: ", name, " must be contiguous");
  return "";
}

std::string controller_arguments_error(const at::Tensor& probe_grad, const at::Tensor& logits,
                                       const at::Tensor& log_scales, const at::Tensor& means,
                                       const at::Tensor& quats, const at::Tensor& viewmat, const at::Tensor& K,
                                       int64_t, int64_t, double weight, double, double, double) {
  if (logits.dim() != 1) return c10::str("fused controller: opacity_logits must be [N], got ", logits.sizes());
  if (logits.scalar_type() != at::kFloat && logits.scalar_type() != at::kDouble)
    return c10::str("fused controller: needs float32 or float64, got ", logits.scalar_type());
  if (!(weight > 0)) return c10::str("fused controller: weight must be > 0, got ", weight);
  const int64_t n = logits.size(0);
  const std::pair<const at::Tensor*, std::vector<int64_t>> args[] = {
      {&logits, {n}},       {&probe_grad, {1, n, 2}}, {&log_scales, {n, 3}}, {&means, {n, 3}},
      {&quats, {n, 4}},     {&viewmat, {4, 4}},       {&K, {3, 3}}};
  const char* names[] = {"opacity_logits", "probe_grad", "log_scales", "means", "quats", "viewmat", "K"};
  for (int i = 0; i < 7; ++i) {
    std::string e = like_error(*args[i].first, logits, args[i].second, names[i]);
    if (!e.empty()) return e;
  }
  return "";
}

// An empty result for bad arguments; the caller then asks controller_arguments_error why.
std::vector<at::Tensor> controller_forward_checked(at::Tensor probe_grad, at::Tensor logits,
                                                   at::Tensor log_scales, at::Tensor means, at::Tensor quats,
                                                   at::Tensor viewmat, at::Tensor K, int64_t width,
                                                   int64_t height, double weight, double near_plane,
                                                   double eps_proj, double tau_s) {
  if (!controller_arguments_error(probe_grad, logits, log_scales, means, quats, viewmat, K, width, height,
                                  weight, near_plane, eps_proj, tau_s)
           .empty())
    return {};
  return controller_forward(probe_grad, logits, log_scales, means, quats, viewmat, K, width, height, weight,
                            near_plane, eps_proj, tau_s);
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("ssim_forward", &ssim_forward, "SSIM map and its partial derivatives (jsgs/csrc/ssim.cu)");
  m.def("ssim_backward", &ssim_backward, "gradient of a weighted SSIM map sum w.r.t. x (jsgs/csrc/ssim.cu)");
  m.def("controller_forward", &controller_forward_checked,
        "deferred Gaussian Controller of one view: weighted L_fro gradients and stats (controller.cu); "
        "an empty list for bad arguments");
  m.def("controller_arguments_error", &controller_arguments_error,
        "why controller_forward refused its arguments (empty when it would not)");
}
