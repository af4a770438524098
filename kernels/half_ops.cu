// The 16-bit activation kernels of half_ops.cuh: one thread per output element in grid-stride
// loops (memory bound; the tensor-core convolutions around them dominate).
#include "kernels/half_ops.cuh"

#include <algorithm>

#include "core/bilinear_taps.hpp"
#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kBlock = 256;
constexpr std::int64_t kMaxBlocks = 8192;

dim3 grid_for(std::int64_t n) {
  return dim3(static_cast<unsigned>(std::min(ceil_div(n, kBlock), kMaxBlocks)));
}

__device__ __forceinline__ std::int64_t first_index() {
  return static_cast<std::int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
}
__device__ __forceinline__ std::int64_t stride() {
  return static_cast<std::int64_t>(gridDim.x) * blockDim.x;
}

template <Half16 H>
__global__ void to_half_kernel(const float* __restrict__ x, std::int64_t n,
                               std::uint16_t* __restrict__ y) {
  for (std::int64_t i = first_index(); i < n; i += stride()) y[i] = to_half16<H>(x[i]);
}

// One thread a pixel; its outputs in chunks of kPointwiseOutputs sums held in registers, x read
// once a chunk.
constexpr int kPointwiseOutputs = 16;

template <Half16 H>
__global__ void pointwise_conv_kernel(const std::uint16_t* __restrict__ x, const float* __restrict__ w,
                                      const float* __restrict__ bias, std::int64_t batch,
                                      std::int64_t in_channels, std::int64_t out_channels,
                                      std::int64_t plane, float* __restrict__ y) {
  const std::int64_t n = batch * plane;
  for (std::int64_t i = first_index(); i < n; i += stride()) {
    const std::int64_t b = i / plane, p = i % plane;
    const std::uint16_t* xp = x + b * in_channels * plane + p;
    float* yp = y + b * out_channels * plane + p;
    for (std::int64_t o0 = 0; o0 < out_channels; o0 += kPointwiseOutputs) {
      const std::int64_t m = out_channels - o0 < kPointwiseOutputs ? out_channels - o0 : kPointwiseOutputs;
      float acc[kPointwiseOutputs];
      for (int j = 0; j < kPointwiseOutputs; ++j) acc[j] = 0.0f;
      for (std::int64_t c = 0; c < in_channels; ++c) {
        const float v = from_half16<H>(xp[c * plane]);
        for (int j = 0; j < kPointwiseOutputs; ++j)
          if (j < m) acc[j] += w[(o0 + j) * in_channels + c] * v;
      }
      for (int j = 0; j < kPointwiseOutputs; ++j)
        if (j < m) yp[(o0 + j) * plane] = acc[j] + bias[o0 + j];
    }
  }
}

template <Half16 H>
__global__ void maxpool_kernel(const std::uint16_t* __restrict__ x, std::int64_t planes,
                               std::int64_t height, std::int64_t width,
                               std::uint16_t* __restrict__ y) {
  const std::int64_t oh = height / 2, ow = width / 2, n = planes * oh * ow;
  for (std::int64_t i = first_index(); i < n; i += stride()) {
    const std::int64_t plane = i / (oh * ow), oy = i / ow % oh, ox = i % ow;
    const std::uint16_t* in = x + plane * height * width + 2 * oy * width + 2 * ox;
    const std::uint16_t window[4] = {in[0], in[1], in[width], in[width + 1]};
    std::uint16_t best_bits = window[0];
    float best = from_half16<H>(window[0]);
    for (int k = 1; k < 4; ++k) {
      // The FP32 kernel's rule: a greater value, or NaN, replaces the best so far.
      const float value = from_half16<H>(window[k]);
      if (value > best || value != value) best = value, best_bits = window[k];
    }
    y[i] = best_bits;
  }
}

template <Half16 H>
__global__ void upsample_kernel(const std::uint16_t* __restrict__ x, std::int64_t planes,
                                std::int64_t in_h, std::int64_t in_w,
                                std::uint16_t* __restrict__ y) {
  const std::int64_t out_h = 2 * in_h, out_w = 2 * in_w, n = planes * out_h * out_w;
  for (std::int64_t i = first_index(); i < n; i += stride()) {
    const std::int64_t plane = i / (out_h * out_w), oy = i / out_w % out_h, ox = i % out_w;
    const BilinearTap<float> r = bilinear_tap<float>(oy, in_h, out_h), c = bilinear_tap<float>(ox, in_w, out_w);
    const std::uint16_t* top = x + plane * in_h * in_w + r.i0 * in_w;
    const std::uint16_t* bottom = x + plane * in_h * in_w + r.i1 * in_w;
    const float value =
        r.w0 * (c.w0 * from_half16<H>(top[c.i0]) + c.w1 * from_half16<H>(top[c.i1])) +
        r.w1 * (c.w0 * from_half16<H>(bottom[c.i0]) + c.w1 * from_half16<H>(bottom[c.i1]));
    y[i] = to_half16<H>(value);
  }
}

__global__ void pad_concat_kernel(const std::uint16_t* __restrict__ skip,
                                  const std::uint16_t* __restrict__ up, PadConcatShape s,
                                  std::uint16_t* __restrict__ y) {
  const std::int64_t channels = s.skip_channels + s.up_channels, plane = s.height * s.width;
  const std::int64_t n = s.batch * channels * plane;
  const std::int64_t top = (s.height - s.up_height) / 2, left = (s.width - s.up_width) / 2;
  for (std::int64_t i = first_index(); i < n; i += stride()) {
    const std::int64_t b = i / (channels * plane), c = i / plane % channels, p = i % plane;
    if (c < s.skip_channels) {
      y[i] = skip[(b * s.skip_channels + c) * plane + p];
      continue;
    }
    const std::int64_t uy = p / s.width - top, ux = p % s.width - left;
    const bool inside = uy >= 0 && uy < s.up_height && ux >= 0 && ux < s.up_width;
    y[i] =
        inside
            ? up[((b * s.up_channels + c - s.skip_channels) * s.up_height + uy) * s.up_width + ux]
            : 0;
  }
}

__global__ void copy_channels_kernel(const std::uint16_t* __restrict__ x, ChannelBand band,
                                     std::uint16_t* __restrict__ y) {
  const std::int64_t n = band.batch * band.channels * band.inner;
  for (std::int64_t i = first_index(); i < n; i += stride()) {
    const std::int64_t b = i / (band.channels * band.inner), c = i / band.inner % band.channels,
                       p = i % band.inner;
    y[(b * band.wide_channels + band.channel0 + c) * band.inner + p] = x[i];
  }
}

}  // namespace

void to_half16(const float* x, std::int64_t n, Half16 type, std::uint16_t* y, cudaStream_t stream) {
  if (n == 0) return;
  with_half16(type, [&](auto h) {
    launch_kernel(to_half_kernel<decltype(h)::value>, grid_for(n), dim3(kBlock), 0, stream, x, n, y);
  });
}

void pointwise_conv_half16(const std::uint16_t* x, Half16 type, const float* w, const float* bias,
                           std::int64_t batch, std::int64_t in_channels, std::int64_t out_channels,
                           std::int64_t plane, float* y, cudaStream_t stream) {
  const std::int64_t n = batch * plane;
  if (n == 0 || out_channels == 0) return;
  with_half16(type, [&](auto h) {
    launch_kernel(pointwise_conv_kernel<decltype(h)::value>, grid_for(n), dim3(kBlock), 0, stream, x, w,
                  bias, batch, in_channels, out_channels, plane, y);
  });
}

void maxpool2d_half16(const std::uint16_t* x, std::int64_t planes, std::int64_t height,
                       std::int64_t width, Half16 type, std::uint16_t* y, cudaStream_t stream) {
  const std::int64_t n = planes * (height / 2) * (width / 2);
  if (n == 0) return;
  with_half16(type, [&](auto h) {
    launch_kernel(maxpool_kernel<decltype(h)::value>, grid_for(n), dim3(kBlock), 0, stream, x, planes,
                  height, width, y);
  });
}

void upsample_bilinear_half16(const std::uint16_t* x, std::int64_t planes, std::int64_t height,
                       std::int64_t width, Half16 type, std::uint16_t* y, cudaStream_t stream) {
  const std::int64_t n = planes * 4 * height * width;
  if (n == 0) return;
  PS_CHECK(height >= 1 && width >= 1, "upsample_bilinear_half16: x must have H, W >= 1, got {} x {}",
           height, width);
  with_half16(type, [&](auto h) {
    launch_kernel(upsample_kernel<decltype(h)::value>, grid_for(n), dim3(kBlock), 0, stream, x, planes,
                  height, width, y);
  });
}

void pad_concat_half16(const std::uint16_t* skip, const std::uint16_t* up,
                       const PadConcatShape& shape, std::uint16_t* y, cudaStream_t stream) {
  const std::int64_t n =
      shape.batch * (shape.skip_channels + shape.up_channels) * shape.height * shape.width;
  if (n == 0) return;
  launch_kernel(pad_concat_kernel, grid_for(n), dim3(kBlock), 0, stream, skip, up, shape, y);
}

void copy_channels_half16(const std::uint16_t* x, const ChannelBand& band, std::uint16_t* y,
                          cudaStream_t stream) {
  const std::int64_t n = band.batch * band.channels * band.inner;
  if (n == 0) return;
  launch_kernel(copy_channels_kernel, grid_for(n), dim3(kBlock), 0, stream, x, band, y);
}

}  // namespace pillarseg::cuda
