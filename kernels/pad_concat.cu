// Pad + concat along channels (see pad_concat.cuh). The skip channels are contiguous runs of
// Cs * H * W floats per batch item: kernels/elementwise.cu's band copies move them (float4 when
// aligned). The up channels go through a tiled kernel: blocks of 32 x 8 threads cover 32 x 8
// pixels of one plane (grid z walks the B * Cu planes), so warps read and write along rows; the
// forward writes every pixel of the padded plane (the value or 0), the backward reads the window.
#include "kernels/pad_concat.cuh"

#include <algorithm>
#include <cstdint>
#include <limits>

#include "kernels/common.cuh"
#include "kernels/elementwise.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kTileX = 32;
constexpr int kTileY = 8;
constexpr int kBlockSize = kTileX * kTileY;
constexpr std::int64_t kMaxGridZ = 65535;

dim3 tile_grid(std::int64_t planes, std::int64_t rows, std::int64_t columns) {
  return dim3(static_cast<unsigned>(ceil_div(columns, kTileX)),
              static_cast<unsigned>(ceil_div(rows, kTileY)),
              static_cast<unsigned>(std::min(planes, kMaxGridZ)));
}

void check_shape(const PadConcatShape& s, const char* op) {
  PS_CHECK(s.batch >= 0 && s.skip_channels >= 0 && s.up_channels >= 0 && s.up_height >= 0 &&
               s.up_width >= 0 && s.up_height <= s.height && s.up_width <= s.width,
           "{}: expected skip (B, Cs, H, W) = ({}, {}, {}, {}) and up (B, Cu, h, w) = ({}, {}, {}, "
           "{}) with sizes >= 0, h <= H and w <= W",
           op, s.batch, s.skip_channels, s.height, s.width, s.batch, s.up_channels, s.up_height,
           s.up_width);
  PS_CHECK(ceil_div(s.width, kTileX) <= std::numeric_limits<int>::max() &&
               ceil_div(s.height, kTileY) <= 65535,
           "{}: a plane of {} x {} exceeds the grid", op, s.height, s.width);
}

ChannelBand skip_band(const PadConcatShape& s) {
  return ChannelBand{s.batch, s.skip_channels, s.height * s.width, s.skip_channels + s.up_channels,
                     0};
}

}  // namespace

// up (B * Cu planes, h, w) -> the up channels of y (B, Cs + Cu, H, W), zero-padded.
static __global__ void __launch_bounds__(kBlockSize)
    pad_up_kernel(const float* up, PadConcatShape shape, float* y) {
  const std::int64_t column = std::int64_t{blockIdx.x} * kTileX + threadIdx.x;
  const std::int64_t row = std::int64_t{blockIdx.y} * kTileY + threadIdx.y;
  if (column >= shape.width || row >= shape.height) return;
  const std::int64_t top = (shape.height - shape.up_height) / 2;
  const std::int64_t left = (shape.width - shape.up_width) / 2;
  const std::int64_t up_row = row - top;
  const std::int64_t up_column = column - left;
  const bool inside =
      up_row >= 0 && up_row < shape.up_height && up_column >= 0 && up_column < shape.up_width;
  const std::int64_t planes = shape.batch * shape.up_channels;
  const std::int64_t channels = shape.skip_channels + shape.up_channels;
  for (std::int64_t plane = blockIdx.z; plane < planes; plane += gridDim.z) {
    const std::int64_t b = plane / shape.up_channels;
    const std::int64_t c = plane - b * shape.up_channels;
    const float value =
        inside ? up[(plane * shape.up_height + up_row) * shape.up_width + up_column] : 0.0f;
    y[((b * channels + shape.skip_channels + c) * shape.height + row) * shape.width + column] =
        value;
  }
}

// The up channels of dy (B, Cs + Cu, H, W) -> d_up (B * Cu planes, h, w), the placed window.
static __global__ void __launch_bounds__(kBlockSize)
    crop_up_kernel(const float* dy, PadConcatShape shape, float* d_up) {
  const std::int64_t up_column = std::int64_t{blockIdx.x} * kTileX + threadIdx.x;
  const std::int64_t up_row = std::int64_t{blockIdx.y} * kTileY + threadIdx.y;
  if (up_column >= shape.up_width || up_row >= shape.up_height) return;
  const std::int64_t row = up_row + (shape.height - shape.up_height) / 2;
  const std::int64_t column = up_column + (shape.width - shape.up_width) / 2;
  const std::int64_t planes = shape.batch * shape.up_channels;
  const std::int64_t channels = shape.skip_channels + shape.up_channels;
  for (std::int64_t plane = blockIdx.z; plane < planes; plane += gridDim.z) {
    const std::int64_t b = plane / shape.up_channels;
    const std::int64_t c = plane - b * shape.up_channels;
    d_up[(plane * shape.up_height + up_row) * shape.up_width + up_column] =
        dy[((b * channels + shape.skip_channels + c) * shape.height + row) * shape.width + column];
  }
}

void pad_concat_forward(const float* skip, const float* up, const PadConcatShape& shape, float* y,
                        cudaStream_t stream) {
  const char* op = "pad_concat_forward";
  check_shape(shape, op);
  const std::int64_t plane_size = shape.height * shape.width;
  if (shape.batch * plane_size == 0) return;
  PS_CHECK(y != nullptr && (shape.skip_channels == 0 || skip != nullptr) &&
               (shape.up_channels * shape.up_height * shape.up_width == 0 || up != nullptr),
           "{}: skip ({} floats), up ({} floats) and y ({} floats) must be device memory", op,
           shape.batch * shape.skip_channels * plane_size,
           shape.batch * shape.up_channels * shape.up_height * shape.up_width,
           shape.batch * (shape.skip_channels + shape.up_channels) * plane_size);
  copy_channels(skip, skip_band(shape), y, stream);
  const std::int64_t planes = shape.batch * shape.up_channels;
  if (planes == 0) return;
  launch_kernel(pad_up_kernel, tile_grid(planes, shape.height, shape.width), dim3(kTileX, kTileY),
                0, stream, up, shape, y);
}

void pad_concat_backward(const float* dy, const PadConcatShape& shape, float* d_skip, float* d_up,
                         cudaStream_t stream) {
  const char* op = "pad_concat_backward";
  check_shape(shape, op);
  const std::int64_t plane_size = shape.height * shape.width;
  if (shape.batch * plane_size == 0) return;
  PS_CHECK(dy != nullptr, "{}: dy must point to {} floats of device memory", op,
           shape.batch * (shape.skip_channels + shape.up_channels) * plane_size);
  if (d_skip != nullptr) extract_channels(dy, skip_band(shape), d_skip, stream);
  const std::int64_t planes = shape.batch * shape.up_channels;
  if (d_up == nullptr || planes * shape.up_height * shape.up_width == 0) return;
  launch_kernel(crop_up_kernel, tile_grid(planes, shape.up_height, shape.up_width),
                dim3(kTileX, kTileY), 0, stream, dy, shape, d_up);
}

}  // namespace pillarseg::cuda
