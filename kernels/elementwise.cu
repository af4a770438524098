// Elementwise ops and channel-band copies (see elementwise.cuh). All are memory bound: the flat
// ops split the array for float4 (kernels/float4_split.cuh) and walk it with a grid-stride loop;
// the band copies move `batch` runs of Cx * S contiguous floats between two strides, one grid row
// per run, with float4 when the runs, strides and pointers allow it.
#include "kernels/elementwise.cuh"

#include <cstdint>

#include "kernels/common.cuh"
#include "kernels/float4_split.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

// `runs` runs of `run_length` floats: run r starts at source + r * source_stride and goes to
// destination + r * destination_stride. Lengths and strides count floats, or float4s when
// `vectorized`.
struct StridedRuns {
  std::int64_t runs = 0;
  std::int64_t run_length = 0;
  std::int64_t source_stride = 0;
  std::int64_t destination_stride = 0;
  bool vectorized = false;
};

StridedRuns band_runs(const ChannelBand& band, const float* source, const float* destination,
                      bool into_wide) {
  const std::int64_t narrow = band.channels * band.inner;
  const std::int64_t wide = band.wide_channels * band.inner;
  StridedRuns runs{band.batch, narrow, into_wide ? narrow : wide, into_wide ? wide : narrow, false};
  const bool aligned = reinterpret_cast<std::uintptr_t>(source) % 16 == 0 &&
                       reinterpret_cast<std::uintptr_t>(destination) % 16 == 0;
  if (aligned && narrow % 4 == 0 && wide % 4 == 0) {
    runs.run_length /= 4;
    runs.source_stride /= 4;
    runs.destination_stride /= 4;
    runs.vectorized = true;
  }
  return runs;
}

void check_band(const ChannelBand& band, const char* op) {
  PS_CHECK(band.batch >= 0 && band.channels >= 0 && band.inner >= 0 && band.channel0 >= 0 &&
               band.channel0 + band.channels <= band.wide_channels,
           "{}: expected channels [channel0, channel0 + Cx) = [{}, {}) inside the {} channels of "
           "(B, Cy, S) = ({}, {}, {})",
           op, band.channel0, band.channel0 + band.channels, band.wide_channels, band.batch,
           band.wide_channels, band.inner);
  PS_CHECK(band.batch <= 65535, "{}: expected a batch of at most 65535 items, given {}", op,
           band.batch);
}

}  // namespace

static __global__ void __launch_bounds__(kElementwiseBlock)
    add_inplace_kernel(float* a, const float* b, Float4Split split) {
  const std::int64_t items = split.items();
  const std::int64_t stride = std::int64_t{gridDim.x} * blockDim.x;
  for (std::int64_t item = std::int64_t{blockIdx.x} * blockDim.x + threadIdx.x; item < items;
       item += stride) {
    if (item < split.vectors) {
      const std::int64_t i = split.head + 4 * item;
      float4 sum = *reinterpret_cast<const float4*>(a + i);
      const float4 addend = *reinterpret_cast<const float4*>(b + i);
      sum.x += addend.x;
      sum.y += addend.y;
      sum.z += addend.z;
      sum.w += addend.w;
      *reinterpret_cast<float4*>(a + i) = sum;
    } else {
      const std::int64_t i = scalar_element(split, item - split.vectors);
      a[i] += b[i];
    }
  }
}

static __global__ void __launch_bounds__(kElementwiseBlock)
    scale_kernel(float* x, float factor, Float4Split split) {
  const std::int64_t items = split.items();
  const std::int64_t stride = std::int64_t{gridDim.x} * blockDim.x;
  for (std::int64_t item = std::int64_t{blockIdx.x} * blockDim.x + threadIdx.x; item < items;
       item += stride) {
    if (item < split.vectors) {
      const std::int64_t i = split.head + 4 * item;
      float4 v = *reinterpret_cast<const float4*>(x + i);
      v.x *= factor;
      v.y *= factor;
      v.z *= factor;
      v.w *= factor;
      *reinterpret_cast<float4*>(x + i) = v;
    } else {
      x[scalar_element(split, item - split.vectors)] *= factor;
    }
  }
}

// Run blockIdx.y of `runs`, walked by the blocks along x.
static __global__ void __launch_bounds__(kElementwiseBlock)
    copy_runs_kernel(const float* source, float* destination, StridedRuns runs) {
  const std::int64_t run = blockIdx.y;
  const std::int64_t stride = std::int64_t{gridDim.x} * blockDim.x;
  const std::int64_t first = std::int64_t{blockIdx.x} * blockDim.x + threadIdx.x;
  if (runs.vectorized) {
    const auto* from = reinterpret_cast<const float4*>(source) + run * runs.source_stride;
    auto* to = reinterpret_cast<float4*>(destination) + run * runs.destination_stride;
    for (std::int64_t i = first; i < runs.run_length; i += stride) to[i] = from[i];
  } else {
    const float* from = source + run * runs.source_stride;
    float* to = destination + run * runs.destination_stride;
    for (std::int64_t i = first; i < runs.run_length; i += stride) to[i] = from[i];
  }
}

namespace {

void copy_runs(const float* source, float* destination, const StridedRuns& runs,
               cudaStream_t stream) {
  if (runs.runs == 0 || runs.run_length == 0) return;
  const dim3 grid(elementwise_grid(runs.run_length).x,
                  static_cast<unsigned>(runs.runs));
  launch_kernel(copy_runs_kernel, grid, dim3(kElementwiseBlock), 0, stream, source, destination, runs);
}

}  // namespace

void add_inplace(float* a, const float* b, std::int64_t n, cudaStream_t stream) {
  PS_CHECK(n >= 0, "add_inplace: n = {}; expected a number of elements >= 0", n);
  if (n == 0) return;
  PS_CHECK(a != nullptr && b != nullptr,
           "add_inplace: a and b must point to {} floats of device memory, got a = {}, b = {}", n,
           static_cast<const void*>(a), static_cast<const void*>(b));
  const Float4Split split = split_for_float4(n, {a, b});
  launch_kernel(add_inplace_kernel, elementwise_grid(split.items()),
                dim3(kElementwiseBlock), 0, stream, a, b, split);
}

void scale(float* x, float factor, std::int64_t n, cudaStream_t stream) {
  PS_CHECK(n >= 0, "scale: n = {}; expected a number of elements >= 0", n);
  if (n == 0) return;
  PS_CHECK(x != nullptr, "scale: x must point to {} floats of device memory, got null", n);
  const Float4Split split = split_for_float4(n, {x});
  launch_kernel(scale_kernel, elementwise_grid(split.items()),
                dim3(kElementwiseBlock), 0, stream, x, factor, split);
}

void copy_channels(const float* x, const ChannelBand& band, float* y, cudaStream_t stream) {
  check_band(band, "copy_channels");
  if (band.batch * band.channels * band.inner == 0) return;
  PS_CHECK(x != nullptr && y != nullptr, "copy_channels: x and y must be device memory");
  float* band_start = y + band.channel0 * band.inner;
  copy_runs(x, band_start, band_runs(band, x, band_start, true), stream);
}

void extract_channels(const float* y, const ChannelBand& band, float* x, cudaStream_t stream) {
  check_band(band, "extract_channels");
  if (band.batch * band.channels * band.inner == 0) return;
  PS_CHECK(x != nullptr && y != nullptr, "extract_channels: x and y must be device memory");
  const float* band_start = y + band.channel0 * band.inner;
  copy_runs(band_start, x, band_runs(band, band_start, x, false), stream);
}

}  // namespace pillarseg::cuda
