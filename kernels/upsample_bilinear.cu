// Bilinear x2 upsampling, align_corners = true (see upsample_bilinear.cuh). Blocks of 32 x 8
// threads cover 32 x 8 pixels of a plane (outputs forward, inputs backward), so warps run along
// rows; each thread works out its row and column taps once (exact integer arithmetic: the source
// coordinate d (in - 1) / (out - 1) is a quotient and remainder) and then walks up to
// kPlanesPerThread planes along the grid's z axis with them.
#include "kernels/upsample_bilinear.cuh"

#include <algorithm>
#include <cstdint>
#include <limits>

#include "core/bilinear_taps.hpp"
#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kTileX = 32;
constexpr int kTileY = 8;
constexpr int kBlockSize = kTileX * kTileY;
constexpr std::int64_t kPlanesPerThread = 8;
// Outputs of an axis that read one input: at most 7 (in = 2, out = 4), about 5 for larger axes.
constexpr int kMaxTapsPerInput = 8;

dim3 tile_grid(std::int64_t planes, std::int64_t rows, std::int64_t columns) {
  return dim3(
      static_cast<unsigned>(ceil_div(columns, kTileX)),
      static_cast<unsigned>(ceil_div(rows, kTileY)),
      static_cast<unsigned>(std::min<std::int64_t>(ceil_div(planes, kPlanesPerThread), 65535)));
}

void check_sizes(const char* op, std::int64_t planes, std::int64_t height, std::int64_t width) {
  PS_CHECK(planes >= 0 && height >= 1 && width >= 1,
           "{}: expected x (B * C, H, W) with B * C >= 0 and H, W >= 1, given ({}, {}, {})", op,
           planes, height, width);
  PS_CHECK(ceil_div(2 * width, kTileX) <= std::numeric_limits<int>::max() &&
               ceil_div(2 * height, kTileY) <= 65535,
           "{}: an output plane of {} x {} exceeds the grid", op, 2 * height, 2 * width);
}

}  // namespace

// The outputs of an axis that read input i, with the weight each gives it: those d whose i0 is
// i - 1 or i.
struct InputTaps {
  std::int64_t first;  // output index of weight[0]
  int count;
  float weight[kMaxTapsPerInput];
};

static __device__ __forceinline__ InputTaps input_taps(std::int64_t i, std::int64_t in,
                                                       std::int64_t out) {
  InputTaps taps{};
  std::int64_t last = out - 1;
  if (in > 1) {
    // i0(d) = floor(d (in - 1) / (out - 1)) >= i - 1 and <= i.
    taps.first = i == 0 ? 0 : ceil_div((i - 1) * (out - 1), in - 1);
    const std::int64_t below_next = ((i + 1) * (out - 1) - 1) / (in - 1);
    last = below_next < last ? below_next : last;
  }
  taps.count = static_cast<int>(last - taps.first + 1);
#pragma unroll
  for (int k = 0; k < kMaxTapsPerInput; ++k) {
    if (k < taps.count) {
      const BilinearTap<float> tap = bilinear_tap<float>(taps.first + k, in, out);
      taps.weight[k] = (tap.i0 == i ? tap.w0 : 0.0f) + (tap.i1 == i ? tap.w1 : 0.0f);
    }
  }
  return taps;
}

// x (planes, in_h, in_w) -> y (planes, 2 in_h, 2 in_w), one output pixel per thread and plane.
static __global__ void __launch_bounds__(kBlockSize)
    upsample_forward_kernel(const float* x, std::int64_t planes, std::int64_t in_h,
                            std::int64_t in_w, float* y) {
  const std::int64_t out_h = 2 * in_h;
  const std::int64_t out_w = 2 * in_w;
  const std::int64_t ox = std::int64_t{blockIdx.x} * kTileX + threadIdx.x;
  const std::int64_t oy = std::int64_t{blockIdx.y} * kTileY + threadIdx.y;
  if (ox >= out_w || oy >= out_h) return;
  const BilinearTap<float> r = bilinear_tap<float>(oy, in_h, out_h);
  const BilinearTap<float> c = bilinear_tap<float>(ox, in_w, out_w);
  for (std::int64_t plane = blockIdx.z; plane < planes; plane += gridDim.z) {
    const float* top = x + plane * in_h * in_w + r.i0 * in_w;
    const float* bottom = x + plane * in_h * in_w + r.i1 * in_w;
    y[plane * out_h * out_w + oy * out_w + ox] = r.w0 * (c.w0 * top[c.i0] + c.w1 * top[c.i1]) +
                                                 r.w1 * (c.w0 * bottom[c.i0] + c.w1 * bottom[c.i1]);
  }
}

// dy (planes, 2 in_h, 2 in_w) -> dx (planes, in_h, in_w), one input pixel per thread and plane:
// dx = sum over the outputs (oy, ox) that read it of w_row(oy) w_column(ox) dy(oy, ox).
static __global__ void __launch_bounds__(kBlockSize)
    upsample_backward_kernel(const float* dy, std::int64_t planes, std::int64_t in_h,
                             std::int64_t in_w, float* dx) {
  const std::int64_t out_h = 2 * in_h;
  const std::int64_t out_w = 2 * in_w;
  const std::int64_t ix = std::int64_t{blockIdx.x} * kTileX + threadIdx.x;
  const std::int64_t iy = std::int64_t{blockIdx.y} * kTileY + threadIdx.y;
  if (ix >= in_w || iy >= in_h) return;
  const InputTaps rows = input_taps(iy, in_h, out_h);
  const InputTaps columns = input_taps(ix, in_w, out_w);
  for (std::int64_t plane = blockIdx.z; plane < planes; plane += gridDim.z) {
    const float* grad_out = dy + plane * out_h * out_w;
    float total = 0.0f;
#pragma unroll
    for (int a = 0; a < kMaxTapsPerInput; ++a) {
      if (a >= rows.count) break;
      const float* row = grad_out + (rows.first + a) * out_w + columns.first;
      float row_total = 0.0f;
#pragma unroll
      for (int b = 0; b < kMaxTapsPerInput; ++b) {
        if (b < columns.count) row_total += columns.weight[b] * row[b];
      }
      total += rows.weight[a] * row_total;
    }
    dx[plane * in_h * in_w + iy * in_w + ix] = total;
  }
}

void upsample_bilinear_forward(const float* x, std::int64_t planes, std::int64_t height,
                               std::int64_t width, float* y, cudaStream_t stream) {
  const char* op = "upsample_bilinear_forward";
  check_sizes(op, planes, height, width);
  if (planes == 0) return;
  PS_CHECK(x != nullptr && y != nullptr,
           "{}: x ({} floats) and y ({} floats) must be device memory", op, planes * height * width,
           4 * planes * height * width);
  launch_kernel(upsample_forward_kernel, tile_grid(planes, 2 * height, 2 * width),
                dim3(kTileX, kTileY), 0, stream, x, planes, height, width, y);
}

void upsample_bilinear_backward(const float* dy, std::int64_t planes, std::int64_t height,
                                std::int64_t width, float* dx, cudaStream_t stream) {
  const char* op = "upsample_bilinear_backward";
  check_sizes(op, planes, height, width);
  if (planes == 0) return;
  PS_CHECK(dy != nullptr && dx != nullptr,
           "{}: dy ({} floats) and dx ({} floats) must be device memory", op,
           4 * planes * height * width, planes * height * width);
  launch_kernel(upsample_backward_kernel, tile_grid(planes, height, width), dim3(kTileX, kTileY), 0,
                stream, dy, planes, height, width, dx);
}

}  // namespace pillarseg::cuda
