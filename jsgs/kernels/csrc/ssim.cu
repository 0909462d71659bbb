// Fused SSIM (11x11 Gaussian window) for jsgs.kernels.ssim: one kernel for the forward, one for the
// backward, instead of the separable-convolution twin's cuDNN depthwise convolutions, layout transposes and
// about twenty elementwise kernels each way. The twin (jsgs/kernels/_torch_impl.py) is the reference these
// are tested against (tests/test_jsgs/kernels/test_ssim_cuda.py).
//
// Forward, per output pixel p of one plane (image x channel): the five windowed moments
//   mu_x, mu_y, E[x^2], E[y^2], E[xy]  (window w(a) w(b), zero outside the image),
// S(p) = (2 mu_x mu_y + C1)(2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(s_xx + s_yy + C2)), and the partial
// derivatives of S(p) with respect to mu_x, E[x^2] and E[xy] (y is a constant target):
//   dS/dmu_x = (2 mu_y (B - A) - 2 mu_x S (D - C)) / (C D),  dS/dE[x^2] = -S / D,  dS/dE[xy] = 2 A / (C D)
// (A..D the four factors above; written without dividing by A or B, which can be 0).
// Backward, per input pixel q: dL/dx(q) = sum over the outputs p whose window covers q of
//   g(p) w(p, q) (dS/dmu_x(p) + 2 x(q) dS/dE[x^2](p) + y(q) dS/dE[xy](p)).
//
// Both kernels work on 32 x 8 tiles of one plane: the tile and its 10-pixel halo are read once into shared
// memory, then the separable window is applied along rows and then along columns. The backward is the same
// correlation (the window is symmetric) applied to the three weighted derivative maps, with the tile shifted
// by the halo. Only the 11-tap window exists here (what SSIM uses); jsgs.kernels.ssim sends other sizes to
// the twin.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

namespace {

constexpr int kWindow = 11;
constexpr int kHalo = kWindow - 1;
constexpr int kTileW = 32;
constexpr int kTileH = 8;
constexpr int kRows = kTileH + kHalo;  // rows read per tile
constexpr int kCols = kTileW + kHalo;  // columns read per tile

// out[m][r][c] = sum_b w[b] in[m][r][c + b] for the kRows x kTileW row-filtered values of M maps
template <typename T, int M>
__device__ __forceinline__ void filter_rows(const T (&in)[M][kRows][kCols], T (&out)[M][kRows][kTileW],
                                            const T (&w)[kWindow]) {
  for (int e = threadIdx.y * kTileW + threadIdx.x; e < kRows * kTileW; e += kTileW * kTileH) {
    const int r = e / kTileW, c = e % kTileW;
#pragma unroll
    for (int m = 0; m < M; ++m) {
      T acc = 0;
#pragma unroll
      for (int b = 0; b < kWindow; ++b) acc += w[b] * in[m][r][c + b];
      out[m][r][c] = acc;
    }
  }
}

// sum_a w[a] rows[m][threadIdx.y + a][threadIdx.x]
template <typename T, int M>
__device__ __forceinline__ void filter_cols(const T (&rows)[M][kRows][kTileW], const T (&w)[kWindow],
                                            T (&out)[M]) {
#pragma unroll
  for (int m = 0; m < M; ++m) {
    T acc = 0;
#pragma unroll
    for (int a = 0; a < kWindow; ++a) acc += w[a] * rows[m][threadIdx.y + a][threadIdx.x];
    out[m] = acc;
  }
}

template <typename T>
__global__ void __launch_bounds__(kTileW* kTileH)
    ssim_forward_kernel(const T* __restrict__ x, const T* __restrict__ y, const T* __restrict__ window,
                        int off, int H, int W, int Ho, int Wo, T c1, T c2, T* __restrict__ smap,
                        T* __restrict__ d_mu, T* __restrict__ d_xx, T* __restrict__ d_xy) {
  __shared__ T w[kWindow];
  __shared__ T img[2][kRows][kCols];  // x, y around the tile
  __shared__ T rows[5][kRows][kTileW];
  const int tid = threadIdx.y * kTileW + threadIdx.x;
  if (tid < kWindow) w[tid] = window[tid];
  const int64_t plane = blockIdx.z;
  const T* xp = x + plane * H * W;
  const T* yp = y + plane * H * W;
  const int i0 = blockIdx.y * kTileH, j0 = blockIdx.x * kTileW;  // output tile origin
  for (int e = tid; e < kRows * kCols; e += kTileW * kTileH) {
    const int r = e / kCols, c = e % kCols;
    const int gr = i0 + r - off, gc = j0 + c - off;  // output (i, j) reads input (i + a - off, j + b - off)
    T xv = 0, yv = 0;
    if (gr >= 0 && gr < H && gc >= 0 && gc < W) {
      xv = xp[gr * W + gc];
      yv = yp[gr * W + gc];
    }
    img[0][r][c] = xv;
    img[1][r][c] = yv;
  }
  __syncthreads();
  // along rows: the five moments x, y, x^2, y^2, xy from the two images
  for (int e = tid; e < kRows * kTileW; e += kTileW * kTileH) {
    const int r = e / kTileW, c = e % kTileW;
    T sx = 0, sy = 0, sxx = 0, syy = 0, sxy = 0;
#pragma unroll
    for (int b = 0; b < kWindow; ++b) {
      const T xv = img[0][r][c + b], yv = img[1][r][c + b], wb = w[b];
      sx += wb * xv;
      sy += wb * yv;
      sxx += wb * xv * xv;
      syy += wb * yv * yv;
      sxy += wb * xv * yv;
    }
    rows[0][r][c] = sx;
    rows[1][r][c] = sy;
    rows[2][r][c] = sxx;
    rows[3][r][c] = syy;
    rows[4][r][c] = sxy;
  }
  __syncthreads();
  const int i = i0 + threadIdx.y, j = j0 + threadIdx.x;
  if (i >= Ho || j >= Wo) return;
  T mom[5];
  filter_cols<T, 5>(rows, w, mom);
  const T mx = mom[0], my = mom[1], exx = mom[2], eyy = mom[3], exy = mom[4];
  const T A = 2 * mx * my + c1;
  const T B = 2 * (exy - mx * my) + c2;
  const T C = mx * mx + my * my + c1;
  const T D = (exx - mx * mx) + (eyy - my * my) + c2;
  const T CD = C * D;
  const T s = (A * B) / CD;
  const int64_t o = plane * Ho * Wo + i * Wo + j;
  smap[o] = s;
  d_mu[o] = (2 * my * (B - A) - 2 * mx * s * (D - C)) / CD;
  d_xx[o] = -s / D;
  d_xy[o] = 2 * A / CD;
}

template <typename T>
__global__ void __launch_bounds__(kTileW* kTileH)
    ssim_backward_kernel(const T* __restrict__ grad, bool uniform, const T* __restrict__ x, const T* __restrict__ y,
                         const T* __restrict__ d_mu, const T* __restrict__ d_xx, const T* __restrict__ d_xy,
                         const T* __restrict__ window, int off, int H, int W, int Ho, int Wo,
                         T* __restrict__ grad_x) {
  __shared__ T w[kWindow];
  __shared__ T maps[3][kRows][kCols];  // g dS/dmu_x, g dS/dE[x^2], g dS/dE[xy] around the tile
  __shared__ T rows[3][kRows][kTileW];
  const int tid = threadIdx.y * kTileW + threadIdx.x;
  if (tid < kWindow) w[tid] = window[tid];
  const int64_t base = blockIdx.z * static_cast<int64_t>(Ho) * Wo;
  const int u0 = blockIdx.y * kTileH, v0 = blockIdx.x * kTileW;  // input tile origin
  // input u is read by outputs i = u + off - a, a in [0, 11): rows u0 + off - 10 ... u0 + off + 7
  for (int e = tid; e < kRows * kCols; e += kTileW * kTileH) {
    const int r = e / kCols, c = e % kCols;
    const int i = u0 + off - kHalo + r, j = v0 + off - kHalo + c;
    T m0 = 0, m1 = 0, m2 = 0;
    if (i >= 0 && i < Ho && j >= 0 && j < Wo) {
      const int64_t o = base + i * Wo + j;
      const T g = grad[uniform ? 0 : o];
      m0 = g * d_mu[o];
      m1 = g * d_xx[o];
      m2 = g * d_xy[o];
    }
    maps[0][r][c] = m0;
    maps[1][r][c] = m1;
    maps[2][r][c] = m2;
  }
  __syncthreads();
  // sum over a of w[a] map[u + off - a] = sum over a' of w[a'] map[(u + off - 10) + a'] (w is symmetric)
  filter_rows<T, 3>(maps, rows, w);
  __syncthreads();
  const int u = u0 + threadIdx.y, v = v0 + threadIdx.x;
  if (u >= H || v >= W) return;
  T acc[3];
  filter_cols<T, 3>(rows, w, acc);
  const int64_t q = blockIdx.z * static_cast<int64_t>(H) * W + u * W + v;
  grad_x[q] = acc[0] + 2 * x[q] * acc[1] + y[q] * acc[2];
}

void check_inputs(const at::Tensor& x, const at::Tensor& y, const at::Tensor& window) {
  TORCH_CHECK(x.is_cuda() && y.is_cuda() && window.is_cuda(), "fused SSIM: tensors must be on CUDA");
  TORCH_CHECK(x.dim() == 4 && x.sizes() == y.sizes(), "fused SSIM: x, y must be (B, C, H, W) of one shape");
  TORCH_CHECK(x.scalar_type() == y.scalar_type() && x.scalar_type() == window.scalar_type(),
              "fused SSIM: x, y and the window must share a dtype");
  TORCH_CHECK(window.dim() == 1 && window.size(0) == kWindow, "fused SSIM: the window must have ", kWindow,
              " taps");
  TORCH_CHECK(x.is_contiguous() && y.is_contiguous() && window.is_contiguous(),
              "fused SSIM: tensors must be contiguous");
}

struct Geometry {
  int64_t planes;
  int H, W, Ho, Wo, off;
};

Geometry geometry(const at::Tensor& x, const at::Tensor& window, bool same) {
  Geometry g;
  g.planes = x.size(0) * x.size(1);
  g.H = static_cast<int>(x.size(2));
  g.W = static_cast<int>(x.size(3));
  g.off = same ? kWindow / 2 : 0;
  g.Ho = same ? g.H : g.H - kHalo;
  g.Wo = same ? g.W : g.W - kHalo;
  TORCH_CHECK(g.Ho > 0 && g.Wo > 0, "fused SSIM: valid padding needs H, W >= the window size");
  return g;
}

dim3 tiles(int64_t planes, int rows, int cols) {
  TORCH_CHECK(planes <= 65535, "fused SSIM: at most 65535 images x channels per call");
  return dim3((cols + kTileW - 1) / kTileW, (rows + kTileH - 1) / kTileH, static_cast<unsigned int>(planes));
}

}  // namespace

std::vector<at::Tensor> ssim_forward(at::Tensor x, at::Tensor y, at::Tensor window, double c1,
                                        double c2, bool same) {
  check_inputs(x, y, window);
  const c10::cuda::CUDAGuard guard(x.device());
  const Geometry g = geometry(x, window, same);
  auto smap = at::empty({x.size(0), x.size(1), g.Ho, g.Wo}, x.options());
  auto d_mu = at::empty_like(smap);
  auto d_xx = at::empty_like(smap);
  auto d_xy = at::empty_like(smap);
  if (smap.numel() == 0) return {smap, d_mu, d_xx, d_xy};
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "jsgs_ssim_forward", [&] {
    ssim_forward_kernel<scalar_t><<<tiles(g.planes, g.Ho, g.Wo), dim3(kTileW, kTileH), 0, stream>>>(
        x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), window.data_ptr<scalar_t>(), g.off, g.H, g.W, g.Ho, g.Wo, static_cast<scalar_t>(c1), static_cast<scalar_t>(c2), smap.data_ptr<scalar_t>(),
        d_mu.data_ptr<scalar_t>(), d_xx.data_ptr<scalar_t>(), d_xy.data_ptr<scalar_t>());
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {smap, d_mu, d_xx, d_xy};
}

at::Tensor ssim_backward(at::Tensor grad, at::Tensor x, at::Tensor y, at::Tensor window,
                            at::Tensor d_mu, at::Tensor d_xx, at::Tensor d_xy, bool same) {
  check_inputs(x, y, window);
  const c10::cuda::CUDAGuard guard(x.device());
  const Geometry g = geometry(x, window, same);
  TORCH_CHECK(grad.sizes() == d_mu.sizes() && d_mu.is_contiguous() && d_xx.is_contiguous() &&
                  d_xy.is_contiguous(),
              "fused SSIM: the gradient and saved maps must match the SSIM map");
  // the gradient of a mean is one value broadcast (all strides 0): read it in place, no full map
  bool uniform = true;
  for (const auto st : grad.strides()) uniform = uniform && st == 0;
  if (!uniform) grad = grad.contiguous();
  auto grad_x = at::empty_like(x);
  if (grad_x.numel() == 0) return grad_x;
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "jsgs_ssim_backward", [&] {
    ssim_backward_kernel<scalar_t><<<tiles(g.planes, g.H, g.W), dim3(kTileW, kTileH), 0, stream>>>(
        grad.data_ptr<scalar_t>(), uniform, x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(),
        d_mu.data_ptr<scalar_t>(), d_xx.data_ptr<scalar_t>(), d_xy.data_ptr<scalar_t>(),
        window.data_ptr<scalar_t>(), g.off, g.H, g.W, g.Ho, g.Wo, grad_x.data_ptr<scalar_t>());
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return grad_x;
}
