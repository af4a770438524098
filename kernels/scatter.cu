// Pillar scatter features (P, C) -> canvas band (B, C of Cc, H, W) and its gather backward (see
// scatter.cuh). The forward clears the band (one cudaMemsetAsync per batch item, or one for a
// canvas that is all band), then moves 32 x 32 tiles of (pillar, channel) through shared memory:
// features are read with the channel fastest (coalesced rows of (P, C)), the canvas is written
// with the pillar fastest (consecutive pillars lie in nearby cells, in scan order). The backward
// runs the same tiles the other way.
#include "kernels/scatter.cuh"

#include <cstdint>
#include <limits>
#include <type_traits>

#include "kernels/common.cuh"
#include "kernels/mma.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kTile = 32;     // pillars and channels per tile
constexpr int kTileRows = 8;  // threadIdx.y; each thread moves kTile / kTileRows values
constexpr int kBlockSize = kTile * kTileRows;

void check_arguments(const char* op, std::int64_t pillars, std::int64_t channels,
                     const ScatterCanvas& canvas) {
  PS_CHECK(
      canvas.batch >= 0 && canvas.height >= 0 && canvas.width >= 0 && pillars >= 0 && channels >= 0,
      "{}: expected sizes >= 0, given P = {}, C = {}, canvas (B, Cc, H, W) = ({}, {}, {}, {})", op,
      pillars, channels, canvas.batch, canvas.channels, canvas.height, canvas.width);
  PS_CHECK(canvas.channel0 >= 0 && canvas.channel0 + channels <= canvas.channels,
           "{}: the pillar channels [{}, {}) lie outside the canvas's {} channels", op,
           canvas.channel0, canvas.channel0 + channels, canvas.channels);
  PS_CHECK(ceil_div(pillars, kTile) <= std::numeric_limits<int>::max() &&
               ceil_div(channels, kTile) <= 65535,
           "{}: P = {} pillars and C = {} channels exceed the grid", op, pillars, channels);
}

}  // namespace

// The canvas offset of pillar p's cell (b, iy, ix) in plane (b, channel0), the band's first
// channel; -1 when the cell lies outside the canvas.
static __device__ __forceinline__ std::int64_t cell_offset(const std::int32_t* cells,
                                                           std::int64_t p,
                                                           const ScatterCanvas& canvas) {
  const std::int64_t b = cells[3 * p];
  const std::int64_t iy = cells[3 * p + 1];
  const std::int64_t ix = cells[3 * p + 2];
  if (b < 0 || b >= canvas.batch || iy < 0 || iy >= canvas.height || ix < 0 || ix >= canvas.width) {
    return -1;
  }
  return (b * canvas.channels + canvas.channel0) * canvas.height * canvas.width +
         iy * canvas.width + ix;
}

// features (P, C) -> canvas: the tile of pillars [32 blockIdx.x, +32) and channels
// [32 blockIdx.y, +32). T: float, or std::uint16_t for a 16-bit canvas of type H (each value
// rounded to nearest even as it is stored).
template <class T, Half16 H>
static __global__ void __launch_bounds__(kBlockSize)
    scatter_kernel(const float* features, const std::int32_t* cells, std::int64_t pillars,
                   std::int64_t channels, ScatterCanvas canvas, T* out) {
  __shared__ float tile[kTile][kTile + 1];  // +1: the transposed reads hit distinct banks
  const std::int64_t p0 = std::int64_t{blockIdx.x} * kTile;
  const std::int64_t c0 = std::int64_t{blockIdx.y} * kTile;
  for (int i = static_cast<int>(threadIdx.y); i < kTile; i += kTileRows) {
    const std::int64_t p = p0 + i;
    const std::int64_t c = c0 + threadIdx.x;
    if (p < pillars && c < channels) tile[i][threadIdx.x] = features[p * channels + c];
  }
  __syncthreads();
  const std::int64_t p = p0 + threadIdx.x;
  if (p >= pillars) return;
  const std::int64_t offset = cell_offset(cells, p, canvas);
  if (offset < 0) return;
  const std::int64_t plane_size = canvas.height * canvas.width;
  for (int i = static_cast<int>(threadIdx.y); i < kTile && c0 + i < channels; i += kTileRows) {
    if constexpr (std::is_same_v<T, float>)
      out[offset + (c0 + i) * plane_size] = tile[threadIdx.x][i];
    else
      out[offset + (c0 + i) * plane_size] = to_half16<H>(tile[threadIdx.x][i]);
  }
}

// canvas -> d_features (P, C): the same tiles, read with the pillar fastest.
static __global__ void __launch_bounds__(kBlockSize)
    gather_kernel(const float* d_canvas, ScatterCanvas canvas, const std::int32_t* cells,
                  std::int64_t pillars, std::int64_t channels, float* d_features) {
  __shared__ float tile[kTile][kTile + 1];
  const std::int64_t p0 = std::int64_t{blockIdx.x} * kTile;
  const std::int64_t c0 = std::int64_t{blockIdx.y} * kTile;
  const std::int64_t p_read = p0 + threadIdx.x;
  if (p_read < pillars) {
    const std::int64_t offset = cell_offset(cells, p_read, canvas);
    const std::int64_t plane_size = canvas.height * canvas.width;
    for (int i = static_cast<int>(threadIdx.y); i < kTile; i += kTileRows) {
      if (c0 + i < channels) {
        tile[threadIdx.x][i] = offset < 0 ? 0.0f : d_canvas[offset + (c0 + i) * plane_size];
      }
    }
  }
  __syncthreads();
  for (int i = static_cast<int>(threadIdx.y); i < kTile; i += kTileRows) {
    const std::int64_t p = p0 + i;
    const std::int64_t c = c0 + threadIdx.x;
    if (p < pillars && c < channels) d_features[p * channels + c] = tile[i][threadIdx.x];
  }
}

namespace {

// scatter_forward into a canvas of T (see scatter_kernel), `what` naming the element for messages.
template <class T, Half16 H>
void scatter_into(const char* op, const char* what, const float* features,
                  const std::int32_t* cells, std::int64_t pillars, std::int64_t channels,
                  const ScatterCanvas& canvas_shape, T* canvas, cudaStream_t stream) {
  check_arguments(op, pillars, channels, canvas_shape);
  const std::int64_t plane_size = canvas_shape.height * canvas_shape.width;
  const std::int64_t band = channels * plane_size;
  if (band == 0 || canvas_shape.batch == 0) return;
  PS_CHECK(canvas != nullptr, "{}: canvas must point to {} {} of device memory", op,
           canvas_shape.batch * canvas_shape.channels * plane_size, what);
  if (channels == canvas_shape.channels) {
    PS_CUDA_CHECK(cudaMemsetAsync(
        canvas, 0, static_cast<std::size_t>(canvas_shape.batch * band) * sizeof(T), stream));
  } else {
    for (std::int64_t b = 0; b < canvas_shape.batch; ++b) {
      T* band_start = canvas + (b * canvas_shape.channels + canvas_shape.channel0) * plane_size;
      PS_CUDA_CHECK(
          cudaMemsetAsync(band_start, 0, static_cast<std::size_t>(band) * sizeof(T), stream));
    }
  }
  if (pillars == 0) return;
  PS_CHECK(features != nullptr && cells != nullptr,
           "{}: features ({} floats) and cells ({} int32) must be device memory", op,
           pillars * channels, 3 * pillars);
  launch_kernel(scatter_kernel<T, H>,
                dim3(static_cast<unsigned>(ceil_div(pillars, kTile)),
                     static_cast<unsigned>(ceil_div(channels, kTile))),
                dim3(kTile, kTileRows), 0, stream, features, cells, pillars, channels, canvas_shape,
                canvas);
}

}  // namespace

void scatter_forward(const float* features, const std::int32_t* cells, std::int64_t pillars,
                     std::int64_t channels, const ScatterCanvas& canvas_shape, float* canvas,
                     cudaStream_t stream) {
  scatter_into<float, Half16::BF16>("scatter_forward", "floats", features, cells, pillars, channels,
                                    canvas_shape, canvas, stream);
}

void scatter_forward_half(const float* features, const std::int32_t* cells, std::int64_t pillars,
                          std::int64_t channels, const ScatterCanvas& canvas_shape, Half16 type,
                          std::uint16_t* canvas, cudaStream_t stream) {
  with_half16(type, [&](auto h) {
    scatter_into<std::uint16_t, decltype(h)::value>("scatter_forward_half", "16-bit values",
                                                    features, cells, pillars, channels,
                                                    canvas_shape, canvas, stream);
  });
}

void scatter_backward(const float* d_canvas, const ScatterCanvas& canvas_shape,
                      const std::int32_t* cells, std::int64_t pillars, std::int64_t channels,
                      float* d_features, cudaStream_t stream) {
  const char* op = "scatter_backward";
  check_arguments(op, pillars, channels, canvas_shape);
  if (pillars == 0 || channels == 0) return;
  PS_CHECK(d_canvas != nullptr && cells != nullptr && d_features != nullptr,
           "{}: d_canvas ({} floats), cells ({} int32) and d_features ({} floats) must be device "
           "memory",
           op,
           canvas_shape.batch * canvas_shape.channels * canvas_shape.height * canvas_shape.width,
           3 * pillars, pillars * channels);
  launch_kernel(gather_kernel,
                dim3(static_cast<unsigned>(ceil_div(pillars, kTile)),
                     static_cast<unsigned>(ceil_div(channels, kTile))),
                dim3(kTile, kTileRows), 0, stream, d_canvas, canvas_shape, cells, pillars, channels,
                d_features);
}

static __global__ void __launch_bounds__(kBlockSize)
    batch_cells_kernel(const std::int32_t* __restrict__ cell, std::int64_t rows, int sample,
                       std::int32_t* __restrict__ cells) {
  const std::int64_t r = std::int64_t{blockIdx.x} * kBlockSize + threadIdx.x;
  if (r >= rows) return;
  const bool used = cell[2 * r] >= 0;
  cells[3 * r] = used ? sample : -1;
  cells[3 * r + 1] = used ? cell[2 * r] : -1;
  cells[3 * r + 2] = used ? cell[2 * r + 1] : -1;
}

void batch_cells(const std::int32_t* cell, std::int64_t rows, int sample, std::int32_t* cells,
                 cudaStream_t stream) {
  PS_CHECK(rows >= 0 && sample >= 0,
           "batch_cells: expected R >= 0 rows and a sample index >= 0, given R = {}, sample = {}",
           rows, sample);
  PS_CHECK(rows == 0 || (cell != nullptr && cells != nullptr),
           "batch_cells: cell ({} int32) and cells ({} int32) must be device memory", 2 * rows,
           3 * rows);
  PS_CHECK(ceil_div(rows, std::int64_t{kBlockSize}) <= std::numeric_limits<int>::max(),
           "batch_cells: R = {} rows exceed the grid", rows);
  if (rows == 0) return;
  launch_kernel(batch_cells_kernel, dim3(static_cast<unsigned>(ceil_div(rows, std::int64_t{kBlockSize}))),
                dim3(kBlockSize), 0, stream, cell, rows, sample, cells);
}

}  // namespace pillarseg::cuda
