// The deferred Gaussian Controller of one view (jsgs.kernels._torch_impl.fro_from_probe_grad, its torch twin
// and reference) as three kernels instead of about seventy: from the probe's gradient and the parameters to
// the weighted gradients of L_fro and the view's statistics. Per Gaussian j (paper eqs. gaussian_risk,
// controller_scale, fro; the twin's docstrings give the derivation):
//
//   (o S_r, nu) = probe_grad / weight,  alpha = sigmoid(logit),  V = {nu > 0},
//   rbar = (o S_r / alpha) / (nu / alpha + eps_proj)          (alpha replaced by 1 outside V),
//   A = J W R(q) (2 x 3),  c_k s_k^2 = |A[:, k]|^2 exp(2 log s_k),  sbar = sqrt(1/2 sum_k c_k s_k^2),
//   per = [j in V] rbar alpha^2 exp(-sbar / tau_s),
//   L_fro = sum_j per / max(|V|, 1),
//   dL/dlogit = 2 per (1 - alpha) / n,  dL/dlog s_k = -per c_k s_k^2 / (2 tau_s sbar) / n,  n = max(|V|, 1).
//
// 1. per_gaussian: everything above but the division by n, and block partial sums of (per, |V|, sum of
//    rbar over V, #damped) in a fixed order (no atomics: the statistics are reproducible run to run);
// 2. finish: one block sums the partials in a fixed order: stats = (L_fro, |V|, mean rbar over V, #damped)
//    and the factor weight / n;
// 3. scale: the gradients times that factor (read on the device: no host synchronisation anywhere).
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

namespace {

constexpr int kThreads = 256;
constexpr int kMaxBlocks = 1024;  // partial sums per statistic; the grid strides beyond
constexpr double kFovMargin = 0.3;

template <typename T>
struct Camera {
  T R[9];  // world-to-camera rotation, row-major
  T t[3];
  T fx, fy, cx, cy, width, height;
};

template <typename T>
__device__ __forceinline__ T block_sum(T v, T* shared) {
  // fixed-order tree over the block (deterministic)
  shared[threadIdx.x] = v;
  __syncthreads();
  for (int s = blockDim.x / 2; s > 0; s >>= 1) {
    if (threadIdx.x < s) shared[threadIdx.x] += shared[threadIdx.x + s];
    __syncthreads();
  }
  const T out = shared[0];
  __syncthreads();
  return out;
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    per_gaussian_kernel(int64_t n, const T* __restrict__ probe_grad, const T* __restrict__ logits,
                        const T* __restrict__ log_scales, const T* __restrict__ means,
                        const T* __restrict__ quats, const T* __restrict__ viewmat, const T* __restrict__ K,
                        T width, T height, T inv_weight, T near_plane, T eps_proj, T tau_s,
                        T* __restrict__ grad_logit, T* __restrict__ grad_log_scale, T* __restrict__ partials) {
  __shared__ T red[kThreads];
  __shared__ Camera<T> cam;
  if (threadIdx.x == 0) {
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) cam.R[r * 3 + c] = viewmat[r * 4 + c];
      cam.t[r] = viewmat[r * 4 + 3];
    }
    cam.fx = K[0];
    cam.fy = K[4];
    cam.cx = K[2];
    cam.cy = K[5];
    cam.width = width;
    cam.height = height;
  }
  __syncthreads();
  T acc_per = 0, acc_vis = 0, acc_rbar = 0, acc_damped = 0;
  for (int64_t j = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; j < n;
       j += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const T g0 = probe_grad[2 * j] * inv_weight, nu = probe_grad[2 * j + 1] * inv_weight;
    const T alpha = T(1) / (T(1) + exp(-logits[j]));
    const bool vis = nu > T(0);
    T gl = 0, gs[3] = {0, 0, 0};
    if (vis) {
      const T rbar = (g0 / alpha) / (nu / alpha + eps_proj);
      // camera-space mean and the perspective Jacobian (gsplat's FOV clamp of x/z, y/z)
      const T mx = means[3 * j], my = means[3 * j + 1], mz = means[3 * j + 2];
      const T x = cam.R[0] * mx + cam.R[1] * my + cam.R[2] * mz + cam.t[0];
      const T y = cam.R[3] * mx + cam.R[4] * my + cam.R[5] * mz + cam.t[1];
      T z = cam.R[6] * mx + cam.R[7] * my + cam.R[8] * mz + cam.t[2];
      z = z >= near_plane ? z : T(1);
      const T mgx = T(kFovMargin) * T(0.5) * cam.width / cam.fx;
      const T mgy = T(kFovMargin) * T(0.5) * cam.height / cam.fy;
      const T u = fmin(fmax(x / z, -(cam.cx / cam.fx) - mgx), (cam.width - cam.cx) / cam.fx + mgx);
      const T v = fmin(fmax(y / z, -(cam.cy / cam.fy) - mgy), (cam.height - cam.cy) / cam.fy + mgy);
      // R(q) of the normalised quaternion (w, x, y, z), each entry a quadratic form (1 = |q|^2)
      T qw = quats[4 * j], qx = quats[4 * j + 1], qy = quats[4 * j + 2], qz = quats[4 * j + 3];
      const T inv = T(1) / sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
      qw *= inv;
      qx *= inv;
      qy *= inv;
      qz *= inv;
      const T Rq[9] = {qw * qw + qx * qx - qy * qy - qz * qz, 2 * (qx * qy - qw * qz),
                       2 * (qx * qz + qw * qy),                 2 * (qx * qy + qw * qz),
                       qw * qw - qx * qx + qy * qy - qz * qz, 2 * (qy * qz - qw * qx),
                       2 * (qx * qz - qw * qy),                 2 * (qy * qz + qw * qx),
                       qw * qw - qx * qx - qy * qy + qz * qz};
      T cs2[3];
      T s2 = 0;
#pragma unroll
      for (int k = 0; k < 3; ++k) {
        // column k of M = W R(q), then of A = J M: row r of A is (f_r / z) (M[r] - uv_r M[2])
        const T m0 = cam.R[0] * Rq[k] + cam.R[1] * Rq[3 + k] + cam.R[2] * Rq[6 + k];
        const T m1 = cam.R[3] * Rq[k] + cam.R[4] * Rq[3 + k] + cam.R[5] * Rq[6 + k];
        const T m2 = cam.R[6] * Rq[k] + cam.R[7] * Rq[3 + k] + cam.R[8] * Rq[6 + k];
        const T a0 = cam.fx / z * (m0 - u * m2), a1 = cam.fy / z * (m1 - v * m2);
        const T s = exp(log_scales[3 * j + k]);
        cs2[k] = (a0 * a0 + a1 * a1) * (s * s);
        s2 += cs2[k];
      }
      s2 *= T(0.5);
      const T sbar = sqrt(s2);
      const T per = rbar * alpha * alpha * exp(-sbar / tau_s);
      gl = 2 * per * (T(1) - alpha);
      const T f = per / (T(-2) * tau_s * sbar);
#pragma unroll
      for (int k = 0; k < 3; ++k) gs[k] = f * cs2[k];
      acc_per += per;
      acc_vis += T(1);
      acc_rbar += rbar;
      acc_damped += (rbar > T(0) && sbar <= tau_s) ? T(1) : T(0);
    }
    grad_logit[j] = gl;
    grad_log_scale[3 * j] = gs[0];
    grad_log_scale[3 * j + 1] = gs[1];
    grad_log_scale[3 * j + 2] = gs[2];
  }
  const T sums[4] = {acc_per, acc_vis, acc_rbar, acc_damped};
#pragma unroll
  for (int s = 0; s < 4; ++s) {
    const T b = block_sum(sums[s], red);
    if (threadIdx.x == 0) partials[s * gridDim.x + blockIdx.x] = b;
  }
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    finish_kernel(int blocks, const T* __restrict__ partials, T weight, T* __restrict__ stats,
                  T* __restrict__ factor) {
  __shared__ T red[kThreads];
  T total[4];
#pragma unroll
  for (int s = 0; s < 4; ++s) {
    T v = 0;
    for (int b = threadIdx.x; b < blocks; b += blockDim.x) v += partials[s * blocks + b];
    total[s] = block_sum(v, red);
  }
  if (threadIdx.x == 0) {
    const T count = fmax(total[1], T(1));
    stats[0] = total[0] / count;  // L_fro (unweighted)
    stats[1] = total[1];          // |V|
    stats[2] = total[2] / count;  // mean rbar over V
    stats[3] = total[3];          // #damped
    factor[0] = weight / count;
  }
}

template <typename T>
__global__ void scale_kernel(int64_t n, const T* __restrict__ factor, T* __restrict__ grad_logit,
                             T* __restrict__ grad_log_scale) {
  const T f = factor[0];
  for (int64_t j = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; j < n;
       j += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    grad_logit[j] *= f;
    grad_log_scale[3 * j] *= f;
    grad_log_scale[3 * j + 1] *= f;
    grad_log_scale[3 * j + 2] *= f;
  }
}

}  // namespace

// Returns (grad_logit [N], grad_log_scale [N, 3], stats [4]) as fro_from_probe_grad + packed_fro_stats.
std::vector<at::Tensor> controller_forward(at::Tensor probe_grad, at::Tensor logits, at::Tensor log_scales,
                                           at::Tensor means, at::Tensor quats, at::Tensor viewmat,
                                           at::Tensor K, int64_t width, int64_t height, double weight,
                                           double near_plane, double eps_proj, double tau_s) {
  // the arguments are checked by the caller in bindings.cpp: an exception thrown from this nvcc-compiled
  // translation unit does not reach Python cleanly (it ends the process)
  const int64_t n = logits.size(0);
  const c10::cuda::CUDAGuard guard(logits.device());
  auto grad_logit = at::empty({n}, logits.options());
  auto grad_log_scale = at::empty({n, 3}, logits.options());
  auto stats = at::empty({4}, logits.options());
  auto factor = at::empty({1}, logits.options());
  const int64_t wanted = (n + kThreads - 1) / kThreads;
  const int blocks = static_cast<int>(wanted < 1 ? 1 : (wanted > kMaxBlocks ? kMaxBlocks : wanted));
  auto partials = at::empty({4 * blocks}, logits.options());
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(logits.scalar_type(), "jsgs_controller", [&] {
    using T = scalar_t;
    per_gaussian_kernel<T><<<blocks, kThreads, 0, stream>>>(
        n, probe_grad.data_ptr<T>(), logits.data_ptr<T>(), log_scales.data_ptr<T>(), means.data_ptr<T>(),
        quats.data_ptr<T>(), viewmat.data_ptr<T>(), K.data_ptr<T>(), static_cast<T>(width),
        static_cast<T>(height), static_cast<T>(1.0 / weight), static_cast<T>(near_plane),
        static_cast<T>(eps_proj), static_cast<T>(tau_s), grad_logit.data_ptr<T>(),
        grad_log_scale.data_ptr<T>(), partials.data_ptr<T>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    finish_kernel<T><<<1, kThreads, 0, stream>>>(blocks, partials.data_ptr<T>(), static_cast<T>(weight),
                                                  stats.data_ptr<T>(), factor.data_ptr<T>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    scale_kernel<T><<<blocks, kThreads, 0, stream>>>(n, factor.data_ptr<T>(), grad_logit.data_ptr<T>(),
                                                      grad_log_scale.data_ptr<T>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {grad_logit, grad_log_scale, stats};
}
