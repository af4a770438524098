// Conv2d forward and backward kernels (see conv2d.cuh): implicit GEMMs on the tiles of
// kernels/gemm_tile.cuh, with a column p a flattened pixel (b, y, x) of the result and a
// reduction index r = (c, ky, kx) a tap of the kernel:
//   forward: y (O x B Ho Wo) = w (O x I k k) * im2col(x) (I k k x B Ho Wo), plus bias;
//   dx:      dx (I x B H W) = w' (I x O k k) * im2col'(dy) (O k k x B H W), where w' is w with
//            the kernel flipped in y and x and its channel axes swapped, and im2col' pads dy by
//            k - 1 - pad: a stride-1 correlation's input gradient is again a correlation;
//   dw:      dw (O x I k k) = dy (O x B Ho Wo) * im2col(x)^T (B Ho Wo x I k k), the long
//            B Ho Wo axis split into chunks that are summed through the workspace in chunk order;
//   db:      db (O) = dy summed over B Ho Wo in the same chunks.
// Taps are gathered while a slice loads, a tap outside the image loading 0 (a predicated load),
// so no im2col matrix is ever written. GEMMs of M <= 16 rows run on the narrow tile, the others
// on the wide one; the 1x1 convolution without padding reads its input as plain channel rows
// (float4 loads).
#include "kernels/conv2d.cuh"

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

// The implicit im2col matrix of a stride-1 correlation: column p = flattened target pixel
// (b, ty, tx) of the (B, M, Ht, Wt) result; row r = (c, ky, kx), a tap into the source
// (B, C, Hs, Ws); entry source[b, c, ty + ky - pad, tx + kx - pad], 0 outside the source.
struct Im2col {
  PixelAxis target;             // B x Ht Wt; image_stride M Ht Wt, the result's
  FastDivmod target_width;      // Wt
  int source_height = 0;        // Hs
  int source_width = 0;         // Ws
  int source_image_stride = 0;  // C Hs Ws
  FastDivmod taps;              // k k
  FastDivmod kernel;            // k
  int pad = 0;                  // negative for the input gradient of a convolution with pad >= k
  int depth = 0;                // C k k

  __device__ __forceinline__ void tap(int r, int& channel, int& ky, int& kx) const {
    int t;
    taps.divmod(r, channel, t);
    kernel.divmod(t, ky, kx);
  }
};

Im2col make_im2col(std::int64_t batch, std::int64_t target_channels, std::int64_t target_height,
                   std::int64_t target_width, std::int64_t source_channels,
                   std::int64_t source_height, std::int64_t source_width, std::int64_t kernel,
                   std::int64_t pad) {
  Im2col g;
  g.target = gemm::make_pixel_axis(batch, target_channels, target_height * target_width);
  g.target_width = FastDivmod(static_cast<int>(target_width));
  g.source_height = static_cast<int>(source_height);
  g.source_width = static_cast<int>(source_width);
  g.source_image_stride = static_cast<int>(source_channels * source_height * source_width);
  g.taps = FastDivmod(static_cast<int>(kernel * kernel));
  g.kernel = FastDivmod(static_cast<int>(kernel));
  g.pad = static_cast<int>(pad);
  g.depth = static_cast<int>(source_channels * kernel * kernel);
  return g;
}

// ---- operand loaders (see gemm_tile.cuh for the shared ones) ----

// B = im2col(source) (depth x B Ht Wt): each thread gathers the taps of one target pixel.
template <class Tile>
struct Im2colLoaderB {
  using Layout = gemm::ColumnLayoutB<Tile>;
  const float* image;  // this thread's image of the source
  Im2col g;
  bool in_range;  // the pixel exists (the last block's tile reaches past B Ht Wt)
  int y0, x0;     // the source position of tap (0, 0): ty - pad, tx - pad
  float values[Layout::kPerThread];

  __device__ Im2colLoaderB(const float* source, const Im2col& g_, int n0) : g(g_) {
    const int p = n0 + Layout::column(static_cast<int>(threadIdx.x));
    in_range = p < g.target.total;
    int b, pixel, ty, tx;
    g.target.pixels.divmod(in_range ? p : 0, b, pixel);
    g.target_width.divmod(pixel, ty, tx);
    image = source + b * g.source_image_stride;
    y0 = ty - g.pad;
    x0 = tx - g.pad;
  }
  __device__ __forceinline__ void fetch(int k0) {
    const int first_row = Layout::first_row(static_cast<int>(threadIdx.x));
#pragma unroll
    for (int j = 0; j < Layout::kPerThread; ++j) {
      const int r = k0 + first_row + Layout::kRowStep * j;
      float value = 0.0f;
      if (in_range && r < g.depth) {
        int channel, ky, kx;
        g.tap(r, channel, ky, kx);
        const int sy = y0 + ky;
        const int sx = x0 + kx;
        // One unsigned comparison per axis tests 0 <= s < size.
        if (static_cast<unsigned>(sy) < static_cast<unsigned>(g.source_height) &&
            static_cast<unsigned>(sx) < static_cast<unsigned>(g.source_width)) {
          value = image[(channel * g.source_height + sy) * g.source_width + sx];
        }
      }
      values[j] = value;
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

// A = w' (I x O k k): w'[i][(o, t)] = w[o, i, k k - 1 - t], the kernel of w flipped in y and x
// (tap t = ky k + kx becomes (k - 1 - ky) k + (k - 1 - kx) = k k - 1 - t) with its channel axes
// swapped. Each thread reads a run of consecutive r for one input channel i.
template <class Tile>
struct FlippedWeightsLoaderA {
  using Layout = gemm::RunLayout<Tile::kBlockM, Tile::kBlockK, Tile::kThreads>;
  const float* w;
  int in_channels;
  int depth;  // O k k
  FastDivmod taps;
  int line, channel;  // this thread's row in the tile and input channel
  float values[Layout::kPerThread];

  __device__ FlippedWeightsLoaderA(const float* w_, int in_channels_, int depth_,
                                   const FastDivmod& taps_, int m0)
      : w(w_),
        in_channels(in_channels_),
        depth(depth_),
        taps(taps_),
        line(Layout::line(static_cast<int>(threadIdx.x))),
        channel(m0 + line) {}
  __device__ __forceinline__ void fetch(int k0) {
    const int r = k0 + Layout::offset(static_cast<int>(threadIdx.x));
    int o, t;
    taps.divmod(r, o, t);
#pragma unroll
    for (int j = 0; j < Layout::kPerThread; ++j) {
      values[j] = channel < in_channels && r + j < depth
                      ? w[(o * in_channels + channel) * taps.divisor + taps.divisor - 1 - t]
                      : 0.0f;
      if (++t == taps.divisor) {
        t = 0;
        ++o;
      }
    }
  }
  __device__ __forceinline__ void store(gemm::SliceA<Tile>& slice) const {
    const int offset = Layout::offset(static_cast<int>(threadIdx.x));
#pragma unroll
    for (int j = 0; j < Layout::kPerThread; ++j) slice[offset + j][line] = values[j];
  }
};

// A tap of the weight gradient's block, decoded once per block into shared memory: the source
// offset of its channel (c Hs Ws), its displacement (ky - pad, kx - pad), and whether it exists
// (the last block's tile reaches past I k k).
struct DecodedTap {
  int channel_offset;
  int dy;
  int dx;
  int exists;
};

// B = im2col(x)^T (B Ho Wo x I k k) for the weight gradient: each thread takes one pixel of the
// slice and gathers the block's taps at it (tap columns fixed per block, decoded in `taps`).
template <class Tile>
struct Im2colTransposedLoaderB {
  using Layout = gemm::RowLayoutB<Tile>;
  const float* source;
  Im2col g;
  const DecodedTap* taps;  // kBlockN, in shared memory
  float values[Layout::kPerThread];

  __device__ Im2colTransposedLoaderB(const float* source_, const Im2col& g_,
                                     const DecodedTap* taps_)
      : source(source_), g(g_), taps(taps_) {}
  __device__ __forceinline__ void fetch(int k0) {
    const int thread = static_cast<int>(threadIdx.x);
    const int p = k0 + Layout::row(thread);
    const bool in_range = p < g.target.total;
    int b, pixel, ty, tx;
    g.target.pixels.divmod(in_range ? p : 0, b, pixel);
    g.target_width.divmod(pixel, ty, tx);
    const float* image = source + b * g.source_image_stride;
#pragma unroll
    for (int j = 0; j < Layout::kPerThread; ++j) {
      const DecodedTap tap = taps[Layout::first_column(thread) + Layout::kColumnStep * j];
      const int sy = ty + tap.dy;
      const int sx = tx + tap.dx;
      values[j] = in_range && tap.exists != 0 &&
                          static_cast<unsigned>(sy) < static_cast<unsigned>(g.source_height) &&
                          static_cast<unsigned>(sx) < static_cast<unsigned>(g.source_width)
                      ? image[tap.channel_offset + sy * g.source_width + sx]
                      : 0.0f;
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

}  // namespace

// ---- kernels ----

// x (B, I, H, W), w (O, I, k, k), bias (O) or nullptr -> y (B, O, Ho, Wo); g: im2col of x onto
// y. Pointwise (k = 1, pad = 0): the im2col matrix is x itself, read through x_pixels.
template <class Tile, bool kPointwise>
static __global__ void __launch_bounds__(Tile::kThreads)
    conv2d_forward_kernel(const float* __restrict__ x, const float* __restrict__ w,
                          const float* __restrict__ bias, float* __restrict__ y, Im2col g,
                          PixelAxis x_pixels, int out_channels) {
  const int m0 = static_cast<int>(blockIdx.y) * Tile::kBlockM;
  const int n0 = static_cast<int>(blockIdx.x) * Tile::kBlockN;
  gemm::RowMajorLoaderA<Tile> loader_w(w, out_channels, g.depth, g.depth, m0);
  gemm::Accumulators<Tile> acc = {};
  if constexpr (kPointwise) {
    gemm::PixelColumnsLoaderB<Tile> loader_x(x, x_pixels, g.depth, n0);
    gemm::accumulate_products<Tile>(loader_w, loader_x, 0, g.depth, acc);
  } else {
    Im2colLoaderB<Tile> loader_x(x, g, n0);
    gemm::accumulate_products<Tile>(loader_w, loader_x, 0, g.depth, acc);
  }
  gemm::store_to_images<Tile>(acc, m0, n0, out_channels, g.target, bias, y);
}

// dy (B, O, Ho, Wo), w (O, I, k, k) -> dx (B, I, H, W); g: im2col of dy onto dx with pad
// k - 1 - pad.
template <class Tile>
static __global__ void __launch_bounds__(Tile::kThreads)
    conv2d_backward_data_kernel(const float* __restrict__ dy, const float* __restrict__ w,
                                float* __restrict__ dx, Im2col g, int in_channels) {
  const int m0 = static_cast<int>(blockIdx.y) * Tile::kBlockM;
  const int n0 = static_cast<int>(blockIdx.x) * Tile::kBlockN;
  FlippedWeightsLoaderA<Tile> loader_w(w, in_channels, g.depth, g.taps, m0);
  Im2colLoaderB<Tile> loader_dy(dy, g, n0);
  gemm::Accumulators<Tile> acc = {};
  gemm::accumulate_products<Tile>(loader_w, loader_dy, 0, g.depth, acc);
  gemm::store_to_images<Tile>(acc, m0, n0, in_channels, g.target, nullptr, dx);
}

// x (B, I, H, W), dy (B, O, Ho, Wo) -> partials (splits, O, I k k): slice z (blockIdx.z) holds
// the weight gradient summed over the flattened pixels [z chunk, (z + 1) chunk) of dy; g: im2col
// of x onto dy.
template <class Tile>
static __global__ void __launch_bounds__(Tile::kThreads)
    conv2d_weight_gradient_kernel(const float* __restrict__ x, const float* __restrict__ dy,
                                  float* __restrict__ partials, Im2col g, int out_channels,
                                  int chunk) {
  __shared__ DecodedTap taps[Tile::kBlockN];
  const int m0 = static_cast<int>(blockIdx.y) * Tile::kBlockM;
  const int n0 = static_cast<int>(blockIdx.x) * Tile::kBlockN;
  const int z = static_cast<int>(blockIdx.z);
  for (int n = static_cast<int>(threadIdx.x); n < Tile::kBlockN; n += Tile::kThreads) {
    const int r = n0 + n;
    int channel, ky, kx;
    g.tap(r, channel, ky, kx);
    taps[n] = DecodedTap{channel * g.source_height * g.source_width, ky - g.pad, kx - g.pad,
                         r < g.depth ? 1 : 0};
  }
  __syncthreads();
  gemm::PixelRowsLoaderA<Tile> loader_dy(dy, g.target, out_channels, m0);
  Im2colTransposedLoaderB<Tile> loader_x(x, g, taps);
  gemm::Accumulators<Tile> acc = {};
  const int k_begin = z * chunk;
  gemm::accumulate_products<Tile>(loader_dy, loader_x, k_begin,
                                  min(k_begin + chunk, g.target.total), acc);
  gemm::store_row_major<Tile>(acc, m0, n0, out_channels, g.depth, g.depth,
                              partials + static_cast<std::int64_t>(z) * out_channels * g.depth);
}

// dy (B, O, plane) -> partials (splits, O): the bias gradient's share of each split.
static __global__ void __launch_bounds__(gemm::kReduceThreads)
    conv2d_bias_gradient_kernel(const float* __restrict__ dy, int out_channels, FastDivmod plane,
                                int total, int chunk, float* __restrict__ partials) {
  gemm::channel_sum_chunk(dy, out_channels, plane, total, chunk, partials);
}

// partials (splits, count) -> out (count), summed in split order.
static __global__ void __launch_bounds__(gemm::kReduceThreads)
    conv2d_sum_splits_kernel(const float* __restrict__ partials, int splits, int count,
                             float* __restrict__ out) {
  gemm::sum_splits(partials, splits, count, out);
}

// ---- launchers ----
namespace {

// Checks the sizes (and that every tensor fits int indices); `op` names the caller.
void check_shape(const char* op, const Conv2dShape& s) {
  PS_CHECK(s.batch >= 0 && s.in_channels >= 0 && s.out_channels >= 0,
           "{}: batch B = {}, in_channels I = {} and out_channels O = {} must be >= 0", op, s.batch,
           s.in_channels, s.out_channels);
  PS_CHECK(s.kernel >= 1 && s.pad >= 0,
           "{}: expected a kernel k >= 1 and pad >= 0, got k = {}, pad = {}", op, s.kernel, s.pad);
  PS_CHECK(s.height >= 1 && s.width >= 1 && s.out_height() >= 1 && s.out_width() >= 1,
           "{}: a {}x{} kernel with pad {} needs an image of at least {}x{} (H x W), got {}x{}", op,
           s.kernel, s.kernel, s.pad, std::max<std::int64_t>(1, s.kernel - 2 * s.pad),
           std::max<std::int64_t>(1, s.kernel - 2 * s.pad), s.height, s.width);
  // Channels count at least 1 so that the flattened pixel axes fit int as well.
  const std::int64_t in_channels = std::max<std::int64_t>(s.in_channels, 1);
  const std::int64_t out_channels = std::max<std::int64_t>(s.out_channels, 1);
  gemm::check_elements(op, "x (B, I, H, W)", s.batch * in_channels * s.height * s.width);
  gemm::check_elements(op, "y (B, O, Ho, Wo)",
                       s.batch * out_channels * s.out_height() * s.out_width());
  gemm::check_elements(op, "w (O, I, k, k)", out_channels * in_channels * s.kernel * s.kernel);
}

gemm::OperandCounts element_counts(const Conv2dShape& s) {
  return gemm::OperandCounts{s.batch * s.in_channels * s.height * s.width,
                             s.out_channels * s.in_channels * s.kernel * s.kernel,
                             s.batch * s.out_channels * s.out_height() * s.out_width()};
}

template <class Tile>
void launch_forward(const float* x, const float* w, const float* bias, float* y,
                    const Conv2dShape& s, cudaStream_t stream) {
  const Im2col g = make_im2col(s.batch, s.out_channels, s.out_height(), s.out_width(),
                               s.in_channels, s.height, s.width, s.kernel, s.pad);
  const PixelAxis x_pixels = gemm::make_pixel_axis(s.batch, s.in_channels, s.height * s.width);
  const dim3 grid = gemm::tile_grid<Tile>("conv2d_forward", s.out_channels, g.target.total);
  const int out_channels = static_cast<int>(s.out_channels);
  if (s.kernel == 1 && s.pad == 0) {
    launch_kernel(conv2d_forward_kernel<Tile, true>, grid, dim3(Tile::kThreads), 0, stream, x, w,
                  bias, y, g, x_pixels, out_channels);
  } else {
    launch_kernel(conv2d_forward_kernel<Tile, false>, grid, dim3(Tile::kThreads), 0, stream, x, w,
                  bias, y, g, x_pixels, out_channels);
  }
}

template <class Tile>
void launch_backward_data(const float* dy, const float* w, float* dx, const Conv2dShape& s,
                          cudaStream_t stream) {
  const Im2col g = make_im2col(s.batch, s.in_channels, s.height, s.width, s.out_channels,
                               s.out_height(), s.out_width(), s.kernel, s.kernel - 1 - s.pad);
  launch_kernel(conv2d_backward_data_kernel<Tile>,
                gemm::tile_grid<Tile>("conv2d_backward_data", s.in_channels, g.target.total),
                dim3(Tile::kThreads), 0, stream, dy, w, dx, g, static_cast<int>(s.in_channels));
}

// The weight-gradient GEMM: M = O, N = I k k, K = B Ho Wo.
template <class Tile>
gemm::SplitPlan plan_weight_gradient(const Conv2dShape& s) {
  const std::int64_t tiles =
      ceil_div(s.out_channels, std::int64_t{Tile::kBlockM}) *
      ceil_div(s.in_channels * s.kernel * s.kernel, std::int64_t{Tile::kBlockN});
  return gemm::plan_splits(s.batch * s.out_height() * s.out_width(), tiles, Tile::kBlockK);
}
gemm::SplitPlan plan_weight_gradient(const Conv2dShape& s) {
  return s.out_channels <= gemm::kNarrowTileMaxRows ? plan_weight_gradient<NarrowTile>(s)
                                                    : plan_weight_gradient<WideTile>(s);
}

template <class Tile>
void launch_weight_gradient(const float* x, const float* dy, float* partials, const Conv2dShape& s,
                            const gemm::SplitPlan& plan, cudaStream_t stream) {
  const Im2col g = make_im2col(s.batch, s.out_channels, s.out_height(), s.out_width(),
                               s.in_channels, s.height, s.width, s.kernel, s.pad);
  launch_kernel(
      conv2d_weight_gradient_kernel<Tile>,
      gemm::tile_grid<Tile>("conv2d_backward_weights", s.out_channels, g.depth, plan.splits),
      dim3(Tile::kThreads), 0, stream, x, dy, partials, g, static_cast<int>(s.out_channels),
      plan.chunk);
}

}  // namespace

void conv2d_forward(const float* x, const float* w, const float* bias, float* y,
                    const Conv2dShape& shape, cudaStream_t stream) {
  constexpr const char* kOp = "conv2d_forward";
  check_shape(kOp, shape);
  const gemm::OperandCounts n = element_counts(shape);
  gemm::check_forward_operands(kOp, n, x, w, bias, shape.out_channels, y);
  if (n.y == 0) return;
  if (shape.out_channels <= gemm::kNarrowTileMaxRows) {
    launch_forward<NarrowTile>(x, w, bias, y, shape, stream);
  } else {
    launch_forward<WideTile>(x, w, bias, y, shape, stream);
  }
}

void conv2d_backward_data(const float* dy, const float* w, float* dx, const Conv2dShape& shape,
                          cudaStream_t stream) {
  constexpr const char* kOp = "conv2d_backward_data";
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

std::size_t conv2d_backward_weights_workspace(const Conv2dShape& shape) {
  check_shape("conv2d_backward_weights_workspace", shape);
  const gemm::SplitPlan plan = plan_weight_gradient(shape);
  if (plan.chunk == 0) return 0;  // no pixels: the gradients are zero, nothing is summed
  const std::int64_t per_split =
      shape.out_channels * shape.in_channels * shape.kernel * shape.kernel + shape.out_channels;
  return static_cast<std::size_t>(plan.splits * per_split);
}

void conv2d_backward_weights(const float* x, const float* dy, float* dw, float* db,
                             const Conv2dShape& shape, float* workspace,
                             std::size_t workspace_floats, cudaStream_t stream) {
  constexpr const char* kOp = "conv2d_backward_weights";
  check_shape(kOp, shape);
  const gemm::OperandCounts n = element_counts(shape);
  const std::size_t needed = conv2d_backward_weights_workspace(shape);
  const std::int64_t nb = db != nullptr ? shape.out_channels : 0;
  gemm::check_backward_weights_operands(kOp, "conv2d_backward_weights_workspace", n, x, dy, dw, db,
                                        nb, workspace, workspace_floats, needed);
  if (shape.out_channels == 0) return;

  const gemm::SplitPlan plan = plan_weight_gradient(shape);
  if (plan.chunk == 0) {  // an empty batch: sums over no pixels
    if (n.w > 0)
      PS_CUDA_CHECK(cudaMemsetAsync(dw, 0, static_cast<std::size_t>(n.w) * sizeof(float), stream));
    if (nb > 0)
      PS_CUDA_CHECK(cudaMemsetAsync(db, 0, static_cast<std::size_t>(nb) * sizeof(float), stream));
    return;
  }
  float* dw_partials = workspace;
  float* db_partials = workspace + plan.splits * n.w;
  if (n.w > 0) {
    if (shape.out_channels <= gemm::kNarrowTileMaxRows) {
      launch_weight_gradient<NarrowTile>(x, dy, dw_partials, shape, plan, stream);
    } else {
      launch_weight_gradient<WideTile>(x, dy, dw_partials, shape, plan, stream);
    }
    launch_kernel(conv2d_sum_splits_kernel, gemm::reduce_grid(n.w), dim3(gemm::kReduceThreads), 0,
                  stream, dw_partials, plan.splits, static_cast<int>(n.w), dw);
  }
  if (db != nullptr) {
    const std::int64_t plane = shape.out_height() * shape.out_width();
    launch_kernel(
        conv2d_bias_gradient_kernel,
        dim3(static_cast<unsigned>(shape.out_channels), static_cast<unsigned>(plan.splits)),
        dim3(gemm::kReduceThreads), 0, stream, dy, static_cast<int>(shape.out_channels),
        FastDivmod(static_cast<int>(plane)), static_cast<int>(shape.batch * plane), plan.chunk,
        db_partials);
    launch_kernel(conv2d_sum_splits_kernel, gemm::reduce_grid(nb), dim3(gemm::kReduceThreads), 0,
                  stream, db_partials, plan.splits, static_cast<int>(nb), db);
  }
}

}  // namespace pillarseg::cuda
