// ConvTranspose2d (2x2 kernel, stride 2) forward and backward kernels (see conv_transpose2d.cuh).
// With stride equal to the kernel size the output windows do not overlap: output pixel
// (2h + sy, 2w + sx) depends on input pixel (h, w) only. The op is a 1x1 convolution from I to
// 4 O "sub-pixel" channels q = 4 o + 2 sy + sx, whose weight is w seen as an I x 4 O matrix
// (w (I, O, 2, 2) is row-major in exactly that order), followed by a pixel shuffle that puts
// channel q at (2h + sy, 2w + sx) of channel o. Each pass is one GEMM on the tiles of
// kernels/gemm_tile.cuh with the shuffle folded into its loads or stores, with a column p a
// flattened input pixel (b, h, w):
//   forward: y~ (4 O x B H W) = w^T (4 O x I) * x (I x B H W), stored shuffled, plus bias;
//   dx:      dx (I x B H W) = w (I x 4 O) * dy~ (4 O x B H W), dy~ = dy unshuffled on load;
//   dw:      dw (I x 4 O) = x (I x B H W) * dy~^T (B H W x 4 O), the B H W axis split into
//            chunks summed through the workspace in chunk order;
//   db:      db (O) = dy summed over B 2H 2W in the same chunks.
#include "kernels/conv_transpose2d.cuh"

#include <algorithm>
#include <cstddef>
#include <cstdint>

#include "core/error.hpp"
#include "kernels/common.cuh"
#include "kernels/gemm_tile.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

using gemm::FastDivmod;
using gemm::NarrowTile;
using gemm::PixelAxis;
using gemm::WideTile;

constexpr int kSubPixels = 4;  // (sy, sx) in {0, 1}^2, index s = 2 sy + sx

// Where the sub-pixel channels of an input pixel live in the (B, O, 2H, 2W) output.
struct Shuffle {
  PixelAxis input;           // B x H W; image_stride I H W (x, dx)
  FastDivmod width;          // W
  int out_channels = 0;      // O
  int out_width = 0;         // 2W
  int out_plane = 0;         // 2H 2W
  int out_image_stride = 0;  // O 2H 2W

  // The offset of output (b, 0, 2h, 2w) for flattened input pixel p = (b, h, w).
  __device__ __forceinline__ int corner(int p) const {
    int b, pixel, h, w;
    input.pixels.divmod(p, b, pixel);
    width.divmod(pixel, h, w);
    return b * out_image_stride + 2 * h * out_width + 2 * w;
  }
  // The offset of sub-pixel channel q = 4 o + 2 sy + sx from its pixel's corner.
  __device__ __forceinline__ int sub_pixel(int q) const {
    const int s = q % kSubPixels;
    return q / kSubPixels * out_plane + s / 2 * out_width + s % 2;
  }
};

Shuffle make_shuffle(const ConvTranspose2dShape& s) {
  Shuffle g;
  g.input = gemm::make_pixel_axis(s.batch, s.in_channels, s.height * s.width);
  g.width = FastDivmod(static_cast<int>(s.width));
  g.out_channels = static_cast<int>(s.out_channels);
  g.out_width = static_cast<int>(s.out_width());
  g.out_plane = static_cast<int>(s.out_height() * s.out_width());
  g.out_image_stride = static_cast<int>(s.out_channels * s.out_height() * s.out_width());
  return g;
}

// B = dy~ (4 O x B H W), the unshuffled output gradient: dy~[q][p] = dy at sub-pixel q of pixel
// p. Each thread gathers the sub-pixel channels of one pixel, rows q = k0 + first_row + kRowStep j
// of the slice at k0. sub_pixel(q) reads q's bits (sx, sy, then o), so it splits into a sum over
// parts of q that share no bits: first_row (< kRowStep, a power of 2) and kRowStep j (< kBlockK)
// are two such parts, and k0, a multiple of 4, adds k0 / 4 planes. first_row's share is folded into
// the pointer once, k0's once per slice, and j's is a constant per value.
template <class Tile>
struct UnshuffleLoaderB {
  using Layout = gemm::ColumnLayoutB<Tile>;
  static_assert(Tile::kBlockK % kSubPixels == 0, "a slice must start at sub-pixel 0 of a channel");
  static_assert((Layout::kRowStep & (Layout::kRowStep - 1)) == 0, "kRowStep must be a power of 2");
  const float* rows;  // dy at this thread's pixel, at sub-pixel row first_row
  int out_plane;      // 2H 2W
  int out_width;      // 2W
  int rows_end;       // 4 O - first_row, or 0 when the pixel is past the end
  float values[Layout::kPerThread];

  __device__ UnshuffleLoaderB(const float* dy, const Shuffle& g, int n0)
      : out_plane(g.out_plane), out_width(g.out_width) {
    const int thread = static_cast<int>(threadIdx.x);
    const int p = n0 + Layout::column(thread);
    const int first_row = Layout::first_row(thread);
    const bool in_range = p < g.input.total;
    rows = dy + g.corner(in_range ? p : 0) + g.sub_pixel(first_row);
    rows_end = in_range ? kSubPixels * g.out_channels - first_row : 0;
  }
  __device__ __forceinline__ void fetch(int k0) {
    const float* channels = rows + k0 / kSubPixels * out_plane;
#pragma unroll
    for (int j = 0; j < Layout::kPerThread; ++j) {
      const int r = Layout::kRowStep * j;  // offset = sub_pixel(r), with constant factors
      const int offset = r / kSubPixels * out_plane + r % kSubPixels / 2 * out_width + r % 2;
      values[j] = k0 + r < rows_end ? channels[offset] : 0.0f;
    }
  }
  __device__ __forceinline__ void store(gemm::SliceB<Tile>& slice) const {
    const int thread = static_cast<int>(threadIdx.x);
#pragma unroll
    for (int j = 0; j < Layout::kPerThread; ++j) {
      slice[Layout::first_row(thread) + Layout::kRowStep * j][Layout::column(thread)] = values[j];
    }
  }
};

// B = dy~^T (B H W x 4 O) for the weight gradient: each thread takes one pixel of the slice and
// gathers the block's sub-pixel channels at it.
template <class Tile>
struct UnshuffleTransposedLoaderB {
  using Layout = gemm::RowLayoutB<Tile>;
  const float* dy;
  Shuffle g;
  int n0;
  float values[Layout::kPerThread];

  __device__ UnshuffleTransposedLoaderB(const float* dy_, const Shuffle& g_, int n0_)
      : dy(dy_), g(g_), n0(n0_) {}
  __device__ __forceinline__ void fetch(int k0) {
    const int thread = static_cast<int>(threadIdx.x);
    const int p = k0 + Layout::row(thread);
    const bool in_range = p < g.input.total;
    const float* corner = dy + g.corner(in_range ? p : 0);
#pragma unroll
    for (int j = 0; j < Layout::kPerThread; ++j) {
      const int q = n0 + Layout::first_column(thread) + Layout::kColumnStep * j;
      values[j] = in_range && q < kSubPixels * g.out_channels ? corner[g.sub_pixel(q)] : 0.0f;
    }
  }
  __device__ __forceinline__ void store(gemm::SliceB<Tile>& slice) const {
    const int thread = static_cast<int>(threadIdx.x);
#pragma unroll
    for (int j = 0; j < Layout::kPerThread; ++j) {
      slice[Layout::row(thread)][Layout::first_column(thread) + Layout::kColumnStep * j] =
          values[j];
    }
  }
};

// y~ (4 O x B H W) -> y (B, O, 2H, 2W), shuffled, plus bias (or nullptr). A thread's rows are
// whole groups of 4 sub-pixels (kThreadM is a multiple of 4): for each output channel and sy, its
// 4 pixels (h, w..w+3) fill 8 consecutive outputs (2h + sy, 2w..2w+7), two float4 stores where
// aligned; else (a row ends inside the 4 pixels, or misaligned) pixel by pixel. (When the first
// float4 is aligned so is the second: out + 4 moves 16 bytes.)
template <class Tile>
__device__ __forceinline__ void store_pixel_shuffle(const gemm::Accumulators<Tile>& acc, int m0,
                                                    int n0, const Shuffle& g, const float* bias,
                                                    float* y) {
  const int q0 = gemm::thread_row0<Tile>(m0);
  const int p = gemm::thread_column0<Tile>(n0);
  if (p >= g.input.total) return;
  int b, pixel, h, w;
  g.input.pixels.divmod(p, b, pixel);
  g.width.divmod(pixel, h, w);
  const bool one_row = w + 4 <= g.width.divisor;  // then p + 3 < total as well
  const int corner = g.corner(p);
#pragma unroll
  for (int group = 0; group < Tile::kThreadM / kSubPixels; ++group) {
    const int o = q0 / kSubPixels + group;
    if (o >= g.out_channels) break;
#pragma unroll
    for (int sy = 0; sy < 2; ++sy) {
      float left[Tile::kThreadN];   // sx = 0
      float right[Tile::kThreadN];  // sx = 1
#pragma unroll
      for (int j = 0; j < Tile::kThreadN; ++j) {
        left[j] = acc[kSubPixels * group + 2 * sy][j];
        right[j] = acc[kSubPixels * group + 2 * sy + 1][j];
        if (bias != nullptr) {
          left[j] += bias[o];
          right[j] += bias[o];
        }
      }
      float* out = y + corner + o * g.out_plane + sy * g.out_width;
      if (one_row && gemm::store_float4_if_aligned(out, left[0], right[0], left[1], right[1]) &&
          gemm::store_float4_if_aligned(out + 4, left[2], right[2], left[3], right[3])) {
        continue;
      }
#pragma unroll
      for (int j = 0; j < Tile::kThreadN; ++j) {
        if (p + j >= g.input.total) break;
        float* pixel_out = y + g.corner(p + j) + o * g.out_plane + sy * g.out_width;
        pixel_out[0] = left[j];
        pixel_out[1] = right[j];
      }
    }
  }
}

}  // namespace

// ---- kernels ----

// x (B, I, H, W), w (I, O, 2, 2), bias (O) or nullptr -> y (B, O, 2H, 2W).
template <class Tile>
static __global__ void __launch_bounds__(Tile::kThreads)
    conv_transpose2d_forward_kernel(const float* __restrict__ x, const float* __restrict__ w,
                                    const float* __restrict__ bias, float* __restrict__ y,
                                    Shuffle g, int in_channels) {
  const int m0 = static_cast<int>(blockIdx.y) * Tile::kBlockM;
  const int n0 = static_cast<int>(blockIdx.x) * Tile::kBlockN;
  const int sub_channels = kSubPixels * g.out_channels;
  gemm::ColumnMajorLoaderA<Tile> loader_w(w, sub_channels, in_channels, sub_channels, m0);
  gemm::PixelColumnsLoaderB<Tile> loader_x(x, g.input, in_channels, n0);
  gemm::Accumulators<Tile> acc = {};
  gemm::accumulate_products<Tile>(loader_w, loader_x, 0, in_channels, acc);
  store_pixel_shuffle<Tile>(acc, m0, n0, g, bias, y);
}

// dy (B, O, 2H, 2W), w (I, O, 2, 2) -> dx (B, I, H, W).
template <class Tile>
static __global__ void __launch_bounds__(Tile::kThreads)
    conv_transpose2d_backward_data_kernel(const float* __restrict__ dy, const float* __restrict__ w,
                                          float* __restrict__ dx, Shuffle g, int in_channels) {
  const int m0 = static_cast<int>(blockIdx.y) * Tile::kBlockM;
  const int n0 = static_cast<int>(blockIdx.x) * Tile::kBlockN;
  const int sub_channels = kSubPixels * g.out_channels;
  gemm::RowMajorLoaderA<Tile> loader_w(w, in_channels, sub_channels, sub_channels, m0);
  UnshuffleLoaderB<Tile> loader_dy(dy, g, n0);
  gemm::Accumulators<Tile> acc = {};
  gemm::accumulate_products<Tile>(loader_w, loader_dy, 0, sub_channels, acc);
  gemm::store_to_images<Tile>(acc, m0, n0, in_channels, g.input, nullptr, dx);
}

// x (B, I, H, W), dy (B, O, 2H, 2W) -> partials (splits, I, O, 2, 2): slice z (blockIdx.z)
// holds the weight gradient summed over the flattened input pixels [z chunk, (z + 1) chunk).
template <class Tile>
static __global__ void __launch_bounds__(Tile::kThreads)
    conv_transpose2d_weight_gradient_kernel(const float* __restrict__ x,
                                            const float* __restrict__ dy,
                                            float* __restrict__ partials, Shuffle g,
                                            int in_channels, int chunk) {
  const int m0 = static_cast<int>(blockIdx.y) * Tile::kBlockM;
  const int n0 = static_cast<int>(blockIdx.x) * Tile::kBlockN;
  const int z = static_cast<int>(blockIdx.z);
  const int sub_channels = kSubPixels * g.out_channels;
  gemm::PixelRowsLoaderA<Tile> loader_x(x, g.input, in_channels, m0);
  UnshuffleTransposedLoaderB<Tile> loader_dy(dy, g, n0);
  gemm::Accumulators<Tile> acc = {};
  const int k_begin = z * chunk;
  gemm::accumulate_products<Tile>(loader_x, loader_dy, k_begin, min(k_begin + chunk, g.input.total),
                                  acc);
  gemm::store_row_major<Tile>(acc, m0, n0, in_channels, sub_channels, sub_channels,
                              partials + static_cast<std::int64_t>(z) * in_channels * sub_channels);
}

// dy (B, O, plane) -> partials (splits, O): the bias gradient's share of each split.
static __global__ void __launch_bounds__(gemm::kReduceThreads)
    conv_transpose2d_bias_gradient_kernel(const float* __restrict__ dy, int out_channels,
                                          FastDivmod plane, int total, int chunk,
                                          float* __restrict__ partials) {
  gemm::channel_sum_chunk(dy, out_channels, plane, total, chunk, partials);
}

// partials (splits, count) -> out (count), summed in split order.
static __global__ void __launch_bounds__(gemm::kReduceThreads)
    conv_transpose2d_sum_splits_kernel(const float* __restrict__ partials, int splits, int count,
                                       float* __restrict__ out) {
  gemm::sum_splits(partials, splits, count, out);
}

// ---- launchers ----
namespace {

void check_shape(const char* op, const ConvTranspose2dShape& s) {
  PS_CHECK(s.batch >= 0 && s.in_channels >= 0 && s.out_channels >= 0,
           "{}: batch B = {}, in_channels I = {} and out_channels O = {} must be >= 0", op, s.batch,
           s.in_channels, s.out_channels);
  PS_CHECK(s.height >= 1 && s.width >= 1, "{}: the input must be at least 1x1 (H x W), got {}x{}",
           op, s.height, s.width);
  // Channels count at least 1 so that the flattened pixel axes fit int as well.
  const std::int64_t in_channels = std::max<std::int64_t>(s.in_channels, 1);
  const std::int64_t out_channels = std::max<std::int64_t>(s.out_channels, 1);
  gemm::check_elements(op, "x (B, I, H, W)", s.batch * in_channels * s.height * s.width);
  gemm::check_elements(op, "y (B, O, 2H, 2W)",
                       s.batch * out_channels * s.out_height() * s.out_width());
  gemm::check_elements(op, "w (I, O, 2, 2)", in_channels * out_channels * kSubPixels);
}

gemm::OperandCounts element_counts(const ConvTranspose2dShape& s) {
  return gemm::OperandCounts{s.batch * s.in_channels * s.height * s.width,
                             s.in_channels * s.out_channels * kSubPixels,
                             s.batch * s.out_channels * s.out_height() * s.out_width()};
}

template <class Tile>
void launch_forward(const float* x, const float* w, const float* bias, float* y,
                    const ConvTranspose2dShape& s, cudaStream_t stream) {
  const Shuffle g = make_shuffle(s);
  launch_kernel(
      conv_transpose2d_forward_kernel<Tile>,
      gemm::tile_grid<Tile>("conv_transpose2d_forward", kSubPixels * s.out_channels, g.input.total),
      dim3(Tile::kThreads), 0, stream, x, w, bias, y, g, static_cast<int>(s.in_channels));
}

template <class Tile>
void launch_backward_data(const float* dy, const float* w, float* dx, const ConvTranspose2dShape& s,
                          cudaStream_t stream) {
  const Shuffle g = make_shuffle(s);
  launch_kernel(
      conv_transpose2d_backward_data_kernel<Tile>,
      gemm::tile_grid<Tile>("conv_transpose2d_backward_data", s.in_channels, g.input.total),
      dim3(Tile::kThreads), 0, stream, dy, w, dx, g, static_cast<int>(s.in_channels));
}

// The weight-gradient GEMM: M = I, N = 4 O, K = B H W.
template <class Tile>
gemm::SplitPlan plan_weight_gradient(const ConvTranspose2dShape& s) {
  const std::int64_t tiles = ceil_div(s.in_channels, std::int64_t{Tile::kBlockM}) *
                             ceil_div(kSubPixels * s.out_channels, std::int64_t{Tile::kBlockN});
  return gemm::plan_splits(s.batch * s.height * s.width, tiles, Tile::kBlockK);
}
gemm::SplitPlan plan_weight_gradient(const ConvTranspose2dShape& s) {
  return s.in_channels <= gemm::kNarrowTileMaxRows ? plan_weight_gradient<NarrowTile>(s)
                                                   : plan_weight_gradient<WideTile>(s);
}

template <class Tile>
void launch_weight_gradient(const float* x, const float* dy, float* partials,
                            const ConvTranspose2dShape& s, const gemm::SplitPlan& plan,
                            cudaStream_t stream) {
  launch_kernel(conv_transpose2d_weight_gradient_kernel<Tile>,
                gemm::tile_grid<Tile>("conv_transpose2d_backward_weights", s.in_channels,
                                      kSubPixels * s.out_channels, plan.splits),
                dim3(Tile::kThreads), 0, stream, x, dy, partials, make_shuffle(s),
                static_cast<int>(s.in_channels), plan.chunk);
}

}  // namespace

void conv_transpose2d_forward(const float* x, const float* w, const float* bias, float* y,
                              const ConvTranspose2dShape& shape, cudaStream_t stream) {
  constexpr const char* kOp = "conv_transpose2d_forward";
  check_shape(kOp, shape);
  const gemm::OperandCounts n = element_counts(shape);
  gemm::check_forward_operands(kOp, n, x, w, bias, shape.out_channels, y);
  if (n.y == 0) return;
  if (kSubPixels * shape.out_channels <= gemm::kNarrowTileMaxRows) {
    launch_forward<NarrowTile>(x, w, bias, y, shape, stream);
  } else {
    launch_forward<WideTile>(x, w, bias, y, shape, stream);
  }
}

void conv_transpose2d_backward_data(const float* dy, const float* w, float* dx,
                                    const ConvTranspose2dShape& shape, cudaStream_t stream) {
  constexpr const char* kOp = "conv_transpose2d_backward_data";
  check_shape(kOp, shape);
  const gemm::OperandCounts n = element_counts(shape);
  gemm::check_backward_data_operands(kOp, n, dy, w, dx);
  if (n.x == 0) return;
  if (shape.in_channels <= gemm::kNarrowTileMaxRows) {
    launch_backward_data<NarrowTile>(dy, w, dx, shape, stream);
  } else {
    launch_backward_data<WideTile>(dy, w, dx, shape, stream);
  }
}

std::size_t conv_transpose2d_backward_weights_workspace(const ConvTranspose2dShape& shape) {
  check_shape("conv_transpose2d_backward_weights_workspace", shape);
  const gemm::SplitPlan plan = plan_weight_gradient(shape);
  if (plan.chunk == 0) return 0;  // no pixels: the gradients are zero, nothing is summed
  const std::int64_t per_split =
      shape.in_channels * shape.out_channels * kSubPixels + shape.out_channels;
  return static_cast<std::size_t>(plan.splits * per_split);
}

void conv_transpose2d_backward_weights(const float* x, const float* dy, float* dw, float* db,
                                       const ConvTranspose2dShape& shape, float* workspace,
                                       std::size_t workspace_floats, cudaStream_t stream) {
  constexpr const char* kOp = "conv_transpose2d_backward_weights";
  check_shape(kOp, shape);
  const gemm::OperandCounts n = element_counts(shape);
  const std::size_t needed = conv_transpose2d_backward_weights_workspace(shape);
  const std::int64_t nb = db != nullptr ? shape.out_channels : 0;
  gemm::check_backward_weights_operands(kOp, "conv_transpose2d_backward_weights_workspace", n, x,
                                        dy, dw, db, nb, workspace, workspace_floats, needed);
  if (shape.out_channels == 0) return;

  const gemm::SplitPlan plan = plan_weight_gradient(shape);
  if (plan.chunk == 0) {  // an empty batch: sums over no pixels
    if (n.w > 0) {
      PS_CUDA_CHECK(cudaMemsetAsync(dw, 0, static_cast<std::size_t>(n.w) * sizeof(float), stream));
    }
    if (nb > 0) {
      PS_CUDA_CHECK(cudaMemsetAsync(db, 0, static_cast<std::size_t>(nb) * sizeof(float), stream));
    }
    return;
  }
  float* dw_partials = workspace;
  float* db_partials = workspace + plan.splits * n.w;
  if (n.w > 0) {
    if (shape.in_channels <= gemm::kNarrowTileMaxRows) {
      launch_weight_gradient<NarrowTile>(x, dy, dw_partials, shape, plan, stream);
    } else {
      launch_weight_gradient<WideTile>(x, dy, dw_partials, shape, plan, stream);
    }
    launch_kernel(conv_transpose2d_sum_splits_kernel, gemm::reduce_grid(n.w),
                  dim3(gemm::kReduceThreads), 0, stream, dw_partials, plan.splits,
                  static_cast<int>(n.w), dw);
  }
  if (db != nullptr) {
    // Split z of the input pixels [z chunk, (z + 1) chunk) owns the output pixels
    // [4 z chunk, 4 (z + 1) chunk) of the flattened (b, 2H 2W) axis.
    const std::int64_t plane = shape.out_height() * shape.out_width();
    launch_kernel(
        conv_transpose2d_bias_gradient_kernel,
        dim3(static_cast<unsigned>(shape.out_channels), static_cast<unsigned>(plan.splits)),
        dim3(gemm::kReduceThreads), 0, stream, dy, static_cast<int>(shape.out_channels),
        FastDivmod(static_cast<int>(plane)), static_cast<int>(shape.batch * plane),
        kSubPixels * plan.chunk, db_partials);
    launch_kernel(conv_transpose2d_sum_splits_kernel, gemm::reduce_grid(nb),
                  dim3(gemm::kReduceThreads), 0, stream, db_partials, plan.splits,
                  static_cast<int>(nb), db);
  }
}

}  // namespace pillarseg::cuda
