// The tensor-core convolutions of conv2d_mma.cuh. One kernel, conv_gemm_kernel, serves the
// forward of both kinds and the input gradients: each is an implicit GEMM D (pixels x columns) =
// A (pixels x K) B (K x columns) whose A gathers, for output pixel (oy, ox) and K element
// k = t Ip + c (tap-major, op::half16_weight_k), the value of channel c of the gathered tensor at
// (oy S + t / KS - pad, ox S + t % KS - pad), zero outside it:
//   - convolution forward: x (B, I, H, W), KS = k, S = 1; y (B, O, Ho, Wo);
//   - convolution input gradient: dy (B, O, Ho, Wo) with the flipped weights, KS = k, S = 1,
//     pad k - 1 - pad; dx (B, I, H, W);
//   - transposed forward: x (B, I, H, W), KS = 1, S = 1, pad 0; column (o, dy, dx) of D goes to
//     y's sub-pixel (2 h + dy, 2 w + dx);
//   - transposed input gradient: dy (B, O, 2H, 2W) as O channels of 4 taps, KS = 2, S = 2, pad 0.
// A block of 128 threads (4 warps, 2 x 2) computes a 128 x BN tile of D (BN = 128, or 64 for at
// most 64 columns; a warp 64 x BN / 2) in steps of 32 along K, through a pipeline of 3 stages in
// dynamic shared memory:
//   - A: each thread owns one pixel of the tile; a K step lies within one tap (Ip is a multiple
//     of 32), so the thread checks the tap's position once and reads its 32 channels plane after
//     plane (a warp reads 32 neighbouring pixels of each plane), rounds them to the 16-bit type
//     and stores them as its pixel's row As[m][0..32) in four 16-byte stores. The loads for step
//     s + 2 are issued before step s is computed and stored after it, so their latency hides
//     behind the tensor cores;
//   - B: the weights' BN x 32 block, rows (N, Kp) contiguous along K, by cp.async in 16-byte
//     pieces (zero-filled past the last column), committed per step and waited for two steps
//     later;
//   - compute: per 16 of K, each warp loads its four 16 x 16 A fragments (ldmatrix.x4 of As, rows
//     = pixels) and its BN / 16 B fragment pairs (ldmatrix.x4 of Bs, rows = columns), and issues
//     4 x BN / 16 mma.sync m16n8k16. Rows of 32 elements are padded to 40 (80 bytes) so that
//     stores and ldmatrix rows fall in distinct banks;
//   - epilogue: bias, ReLU, and the store of each accumulator (FP32 or rounded once to 16 bits)
//     to its pixel and column, for the transposed forward at its sub-pixel;
//   - split K (gemm_splits, where the tiles are few and K long): block z runs its range of K
//     steps and stores its FP32 sums, and split_reduce_kernel adds the splits in order and does
//     the epilogue's work.
// The weight gradients have their own kernel (mma_weight_grad_kernel, 64 x 64 tiles, one stage):
// D (weights x columns) over the pixels, split over blocks, the parts summed in order.
#include "kernels/conv2d_mma.cuh"

#include <array>
#include <atomic>
#include <cstring>
#include <string>
#include <type_traits>

#include "core/ops.hpp"
#include "kernels/block_reduce.cuh"
#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kTileM = 64, kTileN = 64, kTileK = 32, kThreads = 128;  // the weight gradients' tile
constexpr int kPadA = kTileM + 8, kPadB = kTileK + 8;  // shared row lengths, in 16-bit elements

// The implicit GEMM of conv_gemm_kernel (see the top of the file).
struct ConvGemm {
  std::int64_t batch;
  std::int64_t channels;               // C of the gathered tensor (I, or O for the gradients)
  std::int64_t channels_padded;        // Ip: C rounded up to 32, the K step
  std::int64_t in_height, in_width;    // the gathered tensor's planes
  std::int64_t out_height, out_width;  // the pixels D's rows are
  std::int64_t columns;                // N: O, I, or 4 O for the transposed forward
  std::int64_t k_padded;               // taps x Ip
  int kernel, stride, pad;             // KS, S, pad of the gather
  bool sub_pixels;                     // D's column (o, dy, dx) goes to y's sub-pixel
  bool relu;
  // Split K: block z runs steps [z split_steps, (z + 1) split_steps) and writes its FP32 sums to
  // partial[z] (columns x rows, the pixel fastest) for split_reduce_kernel; unsplit: split_steps
  // = k_padded / 32, partial = nullptr.
  std::int64_t split_steps;
  float* partial;
};

// The block tile: 128 pixels x BN columns, 4 warps of 64 x BN / 2, 3 stages of 32 along K.
template <int BN>
struct ConvTile {
  static constexpr int kM = 128, kN = BN, kK = 32, kThreads = 128, kStages = 3;
  // A warp's kWarpM x kWarpN: kFragsM m16 by kFragsN n8 fragments.
  static constexpr int kWarpM = 64, kWarpN = BN / 2;
  static constexpr int kFragsM = kWarpM / 16, kFragsN = kWarpN / 8;
  static constexpr int kPitch = kK + 8;  // 80-byte rows
  static constexpr int kStageElements = (kM + kN) * kPitch;
  static constexpr std::size_t kSharedBytes = std::size_t{kStages} * kStageElements * 2;
  static_assert(kM == kThreads, "a thread stages one pixel's row of A");
  static_assert(2 * kWarpM == kM && kThreads == 4 * 32, "four warps, 2 x 2 over the tile");
  static_assert(kFragsM * 16 == kWarpM && kFragsN * 8 == kWarpN, "whole m16 by n8 fragments");
};

// The 16-bit bits of an activation: rounded from FP32, or as stored.
template <Half16 H, class T>
__device__ __forceinline__ std::uint16_t half_bits_of(T value) {
  if constexpr (std::is_same_v<T, float>)
    return to_half16<H>(value);
  else
    return value;
}

// One thread's pixel of A and the K step it stages next: steps are staged in order, so the tap
// (ky, kx) and the first channel c0 of the step advance by 32 channels at a time, without a
// division.
template <class TIn>
struct PixelGather {
  const TIn* image = nullptr;  // the pixel's image of the gathered tensor
  std::int64_t oy = 0, ox = 0;
  bool valid = false;
  std::int64_t c0 = 0;
  int ky = 0, kx = 0;

  // Starts at K step `step` (a split's first): its tap and first channel.
  __device__ __forceinline__ void start_at(const ConvGemm& g, std::int64_t step) {
    const std::int64_t k = step * 32, tap = k / g.channels_padded;
    c0 = k % g.channels_padded;
    ky = static_cast<int>(tap / g.kernel), kx = static_cast<int>(tap % g.kernel);
  }

  // The next step's 32 values, channels c0 .. c0 + 31 at tap (ky, kx), as 16 words of two 16-bit
  // values each (the lower channel in the low half), zero outside the tensor and past C.
  template <Half16 H>
  __device__ __forceinline__ void load_next(const ConvGemm& g, std::uint32_t (&words)[16]) {
    const std::int64_t iy = oy * g.stride + ky - g.pad, ix = ox * g.stride + kx - g.pad;
    const bool inside = valid && iy >= 0 && iy < g.in_height && ix >= 0 && ix < g.in_width;
    const std::int64_t plane = g.in_height * g.in_width;
    const TIn* p = image + c0 * plane + iy * g.in_width + ix;
    const std::int64_t channels_here = g.channels - c0;  // > 0; < 32 only in a tap's last step
    if (!inside) {
#pragma unroll
      for (int j = 0; j < 16; ++j) words[j] = 0;  // +0 in both types
    } else if (channels_here >= 32) {
#pragma unroll
      for (int j = 0; j < 16; ++j)
        words[j] = half_bits_of<H>(p[(2 * j) * plane]) |
                   std::uint32_t{half_bits_of<H>(p[(2 * j + 1) * plane])} << 16;
    } else {
#pragma unroll
      for (int j = 0; j < 16; ++j) {
        const std::uint32_t lo = 2 * j < channels_here ? half_bits_of<H>(p[(2 * j) * plane]) : 0u;
        const std::uint32_t hi =
            2 * j + 1 < channels_here ? half_bits_of<H>(p[(2 * j + 1) * plane]) : 0u;
        words[j] = lo | hi << 16;
      }
    }
    c0 += 32;
    if (c0 == g.channels_padded) {
      c0 = 0;
      if (++kx == g.kernel) kx = 0, ++ky;
    }
  }
};

template <class Tile>
struct ConvStage {
  std::uint16_t* a;  // [kM][kPitch]: a pixel's 32 K values per row
  std::uint16_t* b;  // [kN][kPitch]: a column's 32 K values per row
  __device__ ConvStage(std::uint16_t* shared, int stage)
      : a(shared + stage * Tile::kStageElements), b(a + Tile::kM * Tile::kPitch) {}
};

// The weights' kN x 32 block of step k0 into the stage by cp.async, zero past the last column.
template <class Tile>
__device__ __forceinline__ void issue_weights(const ConvStage<Tile>& s, const std::uint16_t* w16,
                                              const ConvGemm& g, std::int64_t n0, std::int64_t k0,
                                              int tid) {
#pragma unroll
  for (int v = tid; v < Tile::kN * 4; v += Tile::kThreads) {
    const int row = v / 4, part = v % 4;
    const bool fill = n0 + row < g.columns;
    const std::uint16_t* source = fill ? w16 + (n0 + row) * g.k_padded + k0 + part * 8 : w16;
    cp_async_16(s.b + row * Tile::kPitch + part * 8, source, fill);
  }
}

// One stage's 32 of K for a warp: per 16 of K, its 4 A fragments (rows = pixels) and its
// kFragsN B fragments (ldmatrix.x4 of two n8 tiles: (n 0-7, k 0-7), (n 0-7, k 8-15), (n 8-15,
// k 0-7), (n 8-15, k 8-15)), and 4 kFragsN mma.sync.
template <Half16 H, class Tile>
__device__ __forceinline__ void compute_stage(const ConvStage<Tile>& s,
                                              float (&acc)[Tile::kFragsM][Tile::kFragsN][4],
                                              int warp_m, int warp_n, int lane) {
  const int j = lane / 8, r = lane % 8;
#pragma unroll
  for (int kk = 0; kk < Tile::kK; kk += 16) {
    std::uint32_t a[Tile::kFragsM][4], b[Tile::kFragsN][2];
#pragma unroll
    for (int mt = 0; mt < Tile::kFragsM; ++mt) {
      // Matrices (pixels 0-7, k 0-7), (8-15, 0-7), (0-7, 8-15), (8-15, 8-15): a0..a3.
      const int row = warp_m * Tile::kWarpM + mt * 16 + lane % 16;
      ldmatrix_x4<false>(a[mt], s.a + row * Tile::kPitch + kk + (lane / 16) * 8);
    }
#pragma unroll
    for (int np = 0; np < Tile::kFragsN / 2; ++np) {
      const int row = warp_n * Tile::kWarpN + np * 16 + (j / 2) * 8 + r;
      std::uint32_t regs[4];
      ldmatrix_x4<false>(regs, s.b + row * Tile::kPitch + kk + (j % 2) * 8);
      b[2 * np][0] = regs[0], b[2 * np][1] = regs[1], b[2 * np + 1][0] = regs[2],
            b[2 * np + 1][1] = regs[3];
    }
#pragma unroll
    for (int mt = 0; mt < Tile::kFragsM; ++mt)
#pragma unroll
      for (int nt = 0; nt < Tile::kFragsN; ++nt)
        mma_m16n8k16<H>(acc[mt][nt], a[mt], b[nt], acc[mt][nt]);
  }
}

// Where D's row (pixel p of `image`) and column n go in y: y[pixel_offset + column_offset].
// Planar: y[image][n][p]; sub-pixels: y[image][o][2 oy + dy][2 ox + dx], n = 4 o + 2 dy + dx.
__device__ __forceinline__ std::int64_t pixel_offset(const ConvGemm& g, std::int64_t image,
                                                     std::int64_t p) {
  const std::int64_t pixels_per_image = g.out_height * g.out_width;
  const std::int64_t start = image * g.columns * pixels_per_image;
  return g.sub_pixels ? start + 2 * (p / g.out_width) * 2 * g.out_width + 2 * (p % g.out_width)
                      : start + p;
}
__device__ __forceinline__ std::int64_t column_offset(const ConvGemm& g, std::int64_t n) {
  const std::int64_t pixels_per_image = g.out_height * g.out_width;
  return g.sub_pixels ? (n / 4) * 4 * pixels_per_image + (n % 4) / 2 * 2 * g.out_width + n % 2
                      : n * pixels_per_image;
}

// TIn, TOut: float (FP32 activations) or std::uint16_t (16-bit activations of type H).
template <Half16 H, class TIn, class TOut, class Tile>
__global__ void __launch_bounds__(Tile::kThreads, 2)
    conv_gemm_kernel(const TIn* __restrict__ x, const std::uint16_t* __restrict__ w16,
                     const float* __restrict__ bias, ConvGemm g, TOut* __restrict__ y) {
#if !PILLARSEG_MMA_ARCH
  __trap();  // before sm_80 (see PILLARSEG_MMA_ARCH)
#else
  std::uint16_t* shared = dynamic_shared<std::uint16_t>();
  const int tid = static_cast<int>(threadIdx.x), lane = tid % 32, warp = tid / 32;
  const int warp_m = warp % 2, warp_n = warp / 2;
  const std::int64_t pixels_per_image = g.out_height * g.out_width;
  const std::int64_t rows = g.batch * pixels_per_image;
  const std::int64_t m0 = static_cast<std::int64_t>(blockIdx.x) * Tile::kM;
  const std::int64_t n0 = static_cast<std::int64_t>(blockIdx.y) * Tile::kN;

  // Where each pixel of the tile goes in y, but for its column's offset (column_offset below),
  // -1 past the last pixel: worked out once, by the thread that stages the pixel, for the
  // epilogue's threads.
  __shared__ std::int64_t row_offset[Tile::kM];
  PixelGather<TIn> pixel;
  {
    const std::int64_t m = m0 + tid;
    pixel.valid = m < rows;
    const std::int64_t image = pixel.valid ? m / pixels_per_image : 0;
    const std::int64_t p = pixel.valid ? m % pixels_per_image : 0;
    pixel.oy = p / g.out_width, pixel.ox = p % g.out_width;
    pixel.image = x + image * g.channels * g.in_height * g.in_width;
    row_offset[tid] = pixel.valid ? pixel_offset(g, image, p) : -1;
  }
  const auto store_pixel = [&](const ConvStage<Tile>& s, const std::uint32_t(&words)[16]) {
    auto* row = reinterpret_cast<uint4*>(s.a + tid * Tile::kPitch);  // 80-byte rows: aligned
#pragma unroll
    for (int q = 0; q < 4; ++q)
      row[q] = make_uint4(words[4 * q], words[4 * q + 1], words[4 * q + 2], words[4 * q + 3]);
  };

  float acc[Tile::kFragsM][Tile::kFragsN][4];
#pragma unroll
  for (int mt = 0; mt < Tile::kFragsM; ++mt)
#pragma unroll
    for (int nt = 0; nt < Tile::kFragsN; ++nt)
#pragma unroll
      for (int e = 0; e < 4; ++e) acc[mt][nt][e] = 0.0f;

  // This block's K steps: [first, first + steps) of the whole (all of them unless split).
  const std::int64_t first = static_cast<std::int64_t>(blockIdx.z) * g.split_steps;
  const std::int64_t all_steps = g.k_padded / Tile::kK;
  const std::int64_t steps = all_steps - first < g.split_steps ? all_steps - first : g.split_steps;
  pixel.start_at(g, first);
  // Prologue: steps 0 .. kStages - 2 staged (an empty group where there are fewer steps).
#pragma unroll
  for (int s = 0; s < Tile::kStages - 1; ++s) {
    if (s < steps) {
      const ConvStage<Tile> stage(shared, s);
      std::uint32_t words[16];
      pixel.template load_next<H>(g, words);
      store_pixel(stage, words);
      issue_weights(stage, w16, g, n0, (first + s) * Tile::kK, tid);
    }
    cp_async_commit();
  }
  for (std::int64_t step = 0; step < steps; ++step) {
    cp_async_wait<Tile::kStages - 2>();  // this step's weights have landed
    __syncthreads();  // ... and every thread's, and its pixels; the oldest stage is free
    const std::int64_t next = step + Tile::kStages - 1;
    const ConvStage<Tile> next_stage(shared, static_cast<int>(next % Tile::kStages));
    std::uint32_t words[16] = {};  // loaded and stored under the same condition
    if (next < steps) {
      pixel.template load_next<H>(g, words);
      issue_weights(next_stage, w16, g, n0, (first + next) * Tile::kK, tid);
    }
    cp_async_commit();
    compute_stage<H, Tile>(ConvStage<Tile>(shared, static_cast<int>(step % Tile::kStages)), acc,
                           warp_m, warp_n, lane);
    if (next < steps) store_pixel(next_stage, words);
  }

  // Epilogue: accumulator i of (mt, nt) is D[row group + 8 (i >= 2)][column 2 t + (i & 1)], at
  // row_offset[row] + column_offsets[column] of y (pixel_offset, column_offset).
  const int group = lane / 4, t = lane % 4;
  if (g.partial != nullptr) {  // split: this block's sums, for split_reduce_kernel
    float* part = g.partial + static_cast<std::int64_t>(blockIdx.z) * g.columns * rows;
#pragma unroll
    for (int mt = 0; mt < Tile::kFragsM; ++mt)
#pragma unroll
      for (int half = 0; half < 2; ++half) {
        const std::int64_t m = m0 + warp_m * Tile::kWarpM + mt * 16 + group + 8 * half;
        if (m >= rows) continue;
#pragma unroll
        for (int nt = 0; nt < Tile::kFragsN; ++nt)
#pragma unroll
          for (int e = 0; e < 2; ++e) {
            const std::int64_t n = n0 + warp_n * Tile::kWarpN + nt * 8 + 2 * t + e;
            if (n < g.columns) part[n * rows + m] = acc[mt][nt][2 * half + e];
          }
      }
    return;
  }
  // This thread's columns: their offsets in y (-1 past the last) and biases.
  std::int64_t column_offsets[Tile::kFragsN][2];
  float column_bias[Tile::kFragsN][2];
#pragma unroll
  for (int nt = 0; nt < Tile::kFragsN; ++nt) {
#pragma unroll
    for (int e = 0; e < 2; ++e) {
      const std::int64_t n = n0 + warp_n * Tile::kWarpN + nt * 8 + 2 * t + e;  // >= 0
      const bool valid = n < g.columns;
      column_offsets[nt][e] = valid ? column_offset(g, n) : -1;
      column_bias[nt][e] = valid && bias != nullptr ? bias[n] : 0.0f;
    }
  }
  __syncthreads();  // row_offset
#pragma unroll
  for (int mt = 0; mt < Tile::kFragsM; ++mt) {
#pragma unroll
    for (int half = 0; half < 2; ++half) {
      const std::int64_t row = row_offset[warp_m * Tile::kWarpM + mt * 16 + group + 8 * half];
      if (row < 0) continue;
#pragma unroll
      for (int nt = 0; nt < Tile::kFragsN; ++nt) {
#pragma unroll
        for (int e = 0; e < 2; ++e) {
          if (column_offsets[nt][e] < 0) continue;
          float value = acc[mt][nt][2 * half + e] + column_bias[nt][e];
          if (g.relu) value = value > 0.0f ? value : 0.0f;
          const std::int64_t index = row + column_offsets[nt][e];
          if constexpr (std::is_same_v<TOut, float>)
            y[index] = value;
          else
            y[index] = to_half16<H>(value);
        }
      }
    }
  }
#endif
}

// Split K: y at pixel m (blockIdx.x, threadIdx.x) and column n (blockIdx.y) = act(the splits'
// sums in split order + bias), stored as conv_gemm_kernel's epilogue stores it.
template <Half16 H, class TOut>
__global__ void __launch_bounds__(256)
    split_reduce_kernel(const float* __restrict__ partial, std::int64_t splits,
                        const float* __restrict__ bias, ConvGemm g, TOut* __restrict__ y) {
  const std::int64_t pixels_per_image = g.out_height * g.out_width;
  const std::int64_t rows = g.batch * pixels_per_image;
  const std::int64_t m = static_cast<std::int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const std::int64_t n = blockIdx.y;
  if (m >= rows) return;
  float value = 0.0f;
  for (std::int64_t z = 0; z < splits; ++z) value += partial[(z * g.columns + n) * rows + m];
  value += bias != nullptr ? bias[n] : 0.0f;
  if (g.relu) value = value > 0.0f ? value : 0.0f;
  const std::int64_t index =
      pixel_offset(g, m / pixels_per_image, m % pixels_per_image) + column_offset(g, n);
  if constexpr (std::is_same_v<TOut, float>)
    y[index] = value;
  else
    y[index] = to_half16<H>(value);
}

// A warp's 2 x 4 accumulator fragments of mma_tile_step = 0.
__device__ __forceinline__ void zero_accumulators(float (&acc)[2][4][4]) {
#pragma unroll
  for (int a = 0; a < 2; ++a)
#pragma unroll
    for (int b = 0; b < 4; ++b)
#pragma unroll
      for (int c = 0; c < 4; ++c) acc[a][b][c] = 0.0f;
}

// One step of 32 along K of the weight gradients' 64 x 64 tile for a warp of the 2 x 2
// arrangement: per 16 of K, its two 16 x 16 A fragments with ldmatrix.x4.trans (as holds A
// transposed: as[k][m]) and its four 16 x 8 B fragments with two ldmatrix.x4 (bs[n][k]), and 8
// mma.sync m16n8k16 into acc.
template <Half16 H>
__device__ __forceinline__ void mma_tile_step(const std::uint16_t (&as)[kTileK][kPadA],
                                              const std::uint16_t (&bs)[kTileN][kPadB],
                                              float (&acc)[2][4][4], int warp_m, int warp_n,
                                              int lane) {
#pragma unroll
  for (int kk = 0; kk < kTileK; kk += 16) {
    std::uint32_t a[2][4], b[4][2];
    const int j = lane / 8, r = lane % 8;
#pragma unroll
    for (int mt = 0; mt < 2; ++mt) {
      // Matrix j of the fragment: k rows kk + (j / 2) 8 .. + 8, pixels + (j % 2) 8.
      const int pm = warp_m * 32 + mt * 16 + (j % 2) * 8;
      ldmatrix_x4<true>(a[mt], &as[kk + (j / 2) * 8 + r][pm]);
    }
#pragma unroll
    for (int np = 0; np < 2; ++np) {
      // Matrices: (n 0-7, k 0-7), (n 0-7, k 8-15), (n 8-15, k 0-7), (n 8-15, k 8-15).
      const int pn = warp_n * 32 + np * 16 + (j / 2) * 8 + r;
      std::uint32_t regs[4];
      ldmatrix_x4<false>(regs, &bs[pn][kk + (j % 2) * 8]);
      b[2 * np][0] = regs[0], b[2 * np][1] = regs[1], b[2 * np + 1][0] = regs[2],
            b[2 * np + 1][1] = regs[3];
    }
#pragma unroll
    for (int mt = 0; mt < 2; ++mt)
#pragma unroll
      for (int nt = 0; nt < 4; ++nt) mma_m16n8k16<H>(acc[mt][nt], a[mt], b[nt], acc[mt][nt]);
  }
}

// The training weight gradient as D (M x N) = A (M x Q) B (Q x N) over the Q = B x pixels of its
// pixel grid, each block (blockIdx.z) summing `chunk` of them into partial[z] (M x N):
//   convolution, w (O, I, k, k): m = (i, tap), n = o, q a pixel of dy (B, O, Ho, Wo); A[m][q] = x
//     at q + tap - pad (zero outside), B[q][n] = dy[o] at q; dw[o][m] = D[m][o];
//   transposed, w (I, O, 2, 2): m = i, n = (o, dy, dx), q a pixel of x (B, I, H, W); A[m][q] = x[i]
//     at q, B[q][n] = dy[o] at (2 h + dy, 2 w + dx); dw[m][n] = D[m][n].
// The staging rounds x and dy to the 16-bit type; the compute is mma_tile_step's.
struct MmaWeightGrad {
  std::int64_t batch, in_channels, height, width;  // x
  std::int64_t out_channels;                       // O
  std::int64_t rows, columns;                      // M, N
  std::int64_t out_height, out_width;              // the pixel grid of q (conv: dy's; transposed: x's)
  std::int64_t chunk;                              // pixels per split, a multiple of kTileK
  int kernel, pad;
  bool transposed;
};

template <Half16 H>
__global__ void __launch_bounds__(kThreads)
    mma_weight_grad_kernel(const float* __restrict__ x, const float* __restrict__ dy, MmaWeightGrad g,
                           float* __restrict__ partial) {
  __shared__ __align__(16) std::uint16_t as[kTileK][kPadA];
  __shared__ __align__(16) std::uint16_t bs[kTileN][kPadB];
  const int tid = static_cast<int>(threadIdx.x), lane = tid % 32, warp = tid / 32;
  const int warp_m = warp % 2, warp_n = warp / 2;
  const std::int64_t m0 = static_cast<std::int64_t>(blockIdx.x) * kTileM;
  const std::int64_t n0 = static_cast<std::int64_t>(blockIdx.y) * kTileN;
  const std::int64_t pixels = g.out_height * g.out_width, total = g.batch * pixels;
  const std::int64_t q_begin = static_cast<std::int64_t>(blockIdx.z) * g.chunk;
  const std::int64_t q_end = q_begin + g.chunk < total ? q_begin + g.chunk : total;
  const std::int64_t plane = g.height * g.width;
  const int taps = g.kernel * g.kernel;

  float acc[2][4][4];
  zero_accumulators(acc);

  // A thread stages one pixel column q0 + sk of every step (a warp: 32 consecutive pixels) for
  // the A rows sm = tid / 32 + 4 j and the B rows sn = tid / 32 + 4 j, j < 16. The A rows' input
  // channel planes and tap offsets do not change from step to step: worked out once, into shared
  // memory (a warp's lanes then read one row's entry at a time).
  constexpr int kRowsPerThread = kTileK * kTileM / kThreads;
  const int sk = tid % kTileK, row0 = tid / kTileK;
  __shared__ std::int64_t row_plane[kTileM];  // channel plane offset in x's image; -1: past M
  __shared__ int row_dy[kTileM], row_dx[kTileM];
  if (tid < kTileM) {
    const std::int64_t m = m0 + tid;
    const std::int64_t channel = g.transposed ? m : m / taps;
    const int tap = g.transposed ? 0 : static_cast<int>(m % taps);
    row_plane[tid] = m < g.rows ? channel * plane : -1;
    row_dy[tid] = tap / g.kernel - g.pad, row_dx[tid] = tap % g.kernel - g.pad;
  }
  __syncthreads();

  for (std::int64_t q0 = q_begin; q0 < q_end; q0 += kTileK) {
    // This thread's pixel q of the step: its image and position, once per step.
    const std::int64_t q = q0 + sk;
    const bool q_valid = q < q_end;
    const std::int64_t image = q_valid ? q / pixels : 0, p = q_valid ? q % pixels : 0;
    const std::int64_t py = p / g.out_width, px = p % g.out_width;
    const float* x_image = x + image * g.in_channels * plane;
    // A: as[sk][sm] = A[m0 + sm][q]: x at the pixel + the row's tap (transposed: the pixel).
#pragma unroll 4
    for (int j = 0; j < kRowsPerThread; ++j) {
      const int sm = row0 + (kThreads / kTileK) * j;
      const std::int64_t channel_plane = row_plane[sm];
      std::uint16_t bits = 0;
      if (q_valid && channel_plane >= 0) {
        const std::int64_t iy = py + row_dy[sm], ix = px + row_dx[sm];
        if (g.transposed)
          bits = to_half16<H>(x_image[channel_plane + p]);
        else if (iy >= 0 && iy < g.height && ix >= 0 && ix < g.width)
          bits = to_half16<H>(x_image[channel_plane + iy * g.width + ix]);
      }
      as[sk][sm] = bits;
    }
    // B: bs[sn][sk] = B[q][n0 + sn]: dy[n] at the pixel (transposed: dy[o] at its sub-pixel
    // (2 py + sy, 2 px + sx) for n = 4 o + 2 sy + sx).
    const float* dy_image = dy + image * g.out_channels * (g.transposed ? 4 * pixels : pixels);
#pragma unroll 4
    for (int j = 0; j < kTileN * kTileK / kThreads; ++j) {
      const int sn = row0 + (kThreads / kTileK) * j;
      const std::int64_t n = n0 + sn;
      std::uint16_t bits = 0;
      if (q_valid && n < g.columns) {
        const std::int64_t index =
            g.transposed ? ((n / 4) * 2 * g.out_height + 2 * py + (n % 4) / 2) * 2 * g.out_width +
                               2 * px + n % 2
                         : n * pixels + p;
        bits = to_half16<H>(dy_image[index]);
      }
      bs[sn][sk] = bits;
    }
    __syncthreads();
    mma_tile_step<H>(as, bs, acc, warp_m, warp_n, lane);
    __syncthreads();
  }

  const int group = lane / 4, t = lane % 4;
  float* out = partial + static_cast<std::int64_t>(blockIdx.z) * g.rows * g.columns;
#pragma unroll
  for (int mt = 0; mt < 2; ++mt) {
#pragma unroll
    for (int half = 0; half < 2; ++half) {
      const std::int64_t row = m0 + warp_m * 32 + mt * 16 + group + 8 * half;
      if (row >= g.rows) continue;
#pragma unroll
      for (int nt = 0; nt < 4; ++nt) {
#pragma unroll
        for (int e = 0; e < 2; ++e) {
          const std::int64_t n = n0 + warp_n * 32 + nt * 8 + 2 * t + e;
          if (n < g.columns) out[row * g.columns + n] = acc[mt][nt][2 * half + e];
        }
      }
    }
  }
}

// dw = the sum of the splits' partials in split order (the same bits on every run), laid out as
// w: convolution dw[n][m], transposed dw[m][n].
__global__ void weight_grad_reduce_kernel(const float* __restrict__ partial, std::int64_t splits,
                                          std::int64_t rows, std::int64_t columns, bool transposed,
                                          float* __restrict__ dw) {
  const std::int64_t n_total = rows * columns;
  for (std::int64_t i = static_cast<std::int64_t>(blockIdx.x) * blockDim.x + threadIdx.x; i < n_total;
       i += static_cast<std::int64_t>(gridDim.x) * blockDim.x) {
    float sum = 0.0f;
    for (std::int64_t z = 0; z < splits; ++z) sum += partial[z * n_total + i];
    const std::int64_t m = i / columns, n = i % columns;
    dw[transposed ? i : n * rows + m] = sum;
  }
}

// dbias[o] = the sum of dy[b, o] over its planes (B, O, plane), one block a channel, in double.
constexpr int kBiasThreads = 256;
__global__ void __launch_bounds__(kBiasThreads)
    bias_grad_kernel(const float* __restrict__ dy, std::int64_t batch, std::int64_t channels,
                     std::int64_t plane, float* __restrict__ dbias) {
  const std::int64_t o = blockIdx.x;
  double sum = 0.0;
  for (std::int64_t i = threadIdx.x; i < batch * plane; i += kBiasThreads)
    sum += dy[((i / plane) * channels + o) * plane + i % plane];
  sum = block_sum<kBiasThreads>(sum);
  if (threadIdx.x == 0) dbias[o] = static_cast<float>(sum);
}

// The weights of the input gradients, w16t (I, Kp) rounded: convolution w (O, I, k, k) flipped,
// row i column (o, tap) = w[o][i][taps - 1 - tap]; transposed w (I, O, 2, 2): row i = its 4 O
// values.
template <Half16 H>
__global__ void prepare_data_weights_kernel(const float* __restrict__ w, std::int64_t rows,
                                            std::int64_t channels, std::int64_t channels_padded,
                                            int taps, bool transposed,
                                            std::uint16_t* __restrict__ w16t) {
  const std::int64_t k_padded = taps * channels_padded;
  const std::int64_t i = static_cast<std::int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= rows * k_padded) return;
  const std::int64_t r = i / k_padded, kk = i % k_padded;
  const std::int64_t tap = kk / channels_padded, o = kk % channels_padded;
  float value = 0.0f;
  if (o < channels) {
    // Convolution w (O, I, k, k): the flipped tap; transposed w (I, O, 2, 2): sub-pixel `tap`.
    value =
        transposed ? w[(r * channels + o) * 4 + tap] : w[(o * rows + r) * taps + (taps - 1 - tap)];
  }
  w16t[i] = to_half16<H>(value);
}

// w16 row n, column t Ip + c = w[n][c][t] (transposed: w[c][n / 4][n % 4]), the BatchNorm scale
// multiplied in; bias_out[n] with its shift.
template <Half16 H>
__global__ void prepare_weights_kernel(const float* __restrict__ w, const float* __restrict__ bias,
                                       FoldedBatchNorm bn, std::int64_t rows, std::int64_t channels,
                                       std::int64_t channels_padded, int taps, bool transposed,
                                       std::int64_t out_channels, std::uint16_t* __restrict__ w16,
                                       float* __restrict__ bias_out) {
  const std::int64_t k_padded = taps * channels_padded;
  const std::int64_t i = static_cast<std::int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= rows * k_padded) return;
  const std::int64_t n = i / k_padded, kk = i % k_padded;
  const std::int64_t tap = kk / channels_padded, c = kk % channels_padded;
  float scale = 1.0f, shift = 0.0f;
  const std::int64_t o = transposed ? n / 4 : n;
  if (!transposed && bn.gamma != nullptr) {
    scale = bn.gamma[o] / sqrtf(bn.running_var[o] + bn.eps);
    shift = bn.beta[o] - scale * bn.running_mean[o];
  }
  float value = 0.0f;
  if (c < channels)
    value = transposed ? w[(c * out_channels + o) * 4 + n % 4]
                       : w[(n * channels + c) * taps + tap] * scale;
  w16[i] = to_half16<H>(value);
  if (kk == 0) bias_out[n] = scale * (bias != nullptr ? bias[o] : 0.0f) + shift;
}

// One warp: each lane builds its A and B registers from row-major A (16 x 16) and B (16 x 8) by
// the ISA's formulas, runs the mma, and writes its four results to D (16 x 8) by the formula.
template <Half16 H>
__global__ void mma_probe_kernel(const float* a, const float* b, const float* c, float* d) {
  const int lane = static_cast<int>(threadIdx.x), g = lane / 4, t = lane % 4;
  std::uint32_t ra[4], rb[2];
  for (int r = 0; r < 4; ++r) {
    std::uint32_t reg = 0;
    for (int half = 0; half < 2; ++half) {
      const int i = 2 * r + half;
      const int row = g + ((i == 2 || i == 3 || i == 6 || i == 7) ? 8 : 0);
      const int col = 2 * t + (i & 1) + (i >= 4 ? 8 : 0);
      reg |= std::uint32_t{to_half16<H>(a[row * 16 + col])} << (16 * half);
    }
    ra[r] = reg;
  }
  for (int r = 0; r < 2; ++r) {
    std::uint32_t reg = 0;
    for (int half = 0; half < 2; ++half) {
      const int i = 2 * r + half;
      const int row = 2 * t + (i & 1) + (i >= 2 ? 8 : 0);
      reg |= std::uint32_t{to_half16<H>(b[row * 8 + g])} << (16 * half);
    }
    rb[r] = reg;
  }
  float rc[4], rd[4];
  for (int i = 0; i < 4; ++i) rc[i] = c[(g + (i >= 2 ? 8 : 0)) * 8 + 2 * t + (i & 1)];
  mma_m16n8k16<H>(rd, ra, rb, rc);
  for (int i = 0; i < 4; ++i) d[(g + (i >= 2 ? 8 : 0)) * 8 + 2 * t + (i & 1)] = rd[i];
}

// One warp loads a 16 x 16 matrix of 16-bit values v[r][c] = 256 r + c (as bits) into shared
// memory and reads it with ldmatrix.x4 (matrices: rows 0-7 / 8-15 by columns 0-7 / 8-15, in the
// order (0, 0), (8, 0), (0, 8), (8, 8)) and x2 (the first two), plain and transposed.
__global__ void ldmatrix_probe_kernel(std::uint32_t* out) {
  __shared__ __align__(16) std::uint16_t m[16][16];
  const int lane = static_cast<int>(threadIdx.x);
  for (int i = lane; i < 256; i += 32)
    m[i / 16][i % 16] = static_cast<std::uint16_t>(256 * (i / 16) + i % 16);
  __syncwarp();
  const int j = lane / 8, r = lane % 8;
  const int row = (j % 2) * 8 + r, col = (j / 2) * 8;
  std::uint32_t x4[4], x4t[4], x2[2], x2t[2];
  ldmatrix_x4<false>(x4, &m[row][col]);
  ldmatrix_x4<true>(x4t, &m[row][col]);
  ldmatrix_x2<false>(x2, &m[row][col]);
  ldmatrix_x2<true>(x2t, &m[row][col]);
  for (int q = 0; q < 4; ++q) {
    out[lane * 12 + q] = x4[q];
    out[lane * 12 + 4 + q] = x4t[q];
  }
  for (int q = 0; q < 2; ++q) {
    out[lane * 12 + 8 + q] = x2[q];
    out[lane * 12 + 10 + q] = x2t[q];
  }
}

__global__ void cp_async_probe_kernel(const std::uint32_t* source, std::uint32_t* out,
                                      bool misalign) {
  __shared__ __align__(16)
      std::uint32_t stages[3][32 * 4 + 4];  // rows of 16-byte multiples, room to misalign
  const int lane = static_cast<int>(threadIdx.x);
  for (int s = 0; s < 3; ++s)
    for (int w = 0; w < 4; ++w) stages[s][lane * 4 + w] = 0xDEADBEEFu;
  __syncwarp();
  for (int s = 0; s < 3; ++s) {
    cp_async_16(&stages[s][lane * 4 + (misalign ? 1 : 0)], source + (s * 32 + lane) * 4, s != 1);
    cp_async_commit();
  }
  cp_async_wait<2>();
  for (int s = 0; s < 3; ++s)
    for (int w = 0; w < 4; ++w) out[lane * 24 + s * 4 + w] = stages[s][lane * 4 + w];
  cp_async_wait<0>();
  for (int s = 0; s < 3; ++s)
    for (int w = 0; w < 4; ++w) out[lane * 24 + 12 + s * 4 + w] = stages[s][lane * 4 + w];
}

// Raises the kernel's dynamic shared memory limit to `bytes` on the current device, once per
// device (the default limit is 48 KiB).
template <auto Kernel>
void allow_dynamic_shared(std::size_t bytes) {
  static std::array<std::atomic<bool>, 64> allowed{};
  int device = 0;
  PS_CUDA_CHECK(cudaGetDevice(&device));
  const bool cached = device >= 0 && device < 64;
  if (cached && allowed[static_cast<std::size_t>(device)].load()) return;
  PS_CUDA_CHECK(cudaFuncSetAttribute(Kernel, cudaFuncAttributeMaxDynamicSharedMemorySize,
                                     static_cast<int>(bytes)));
  if (cached) allowed[static_cast<std::size_t>(device)].store(true);
}

template <Half16 H, class Tile, class TIn, class TOut>
void launch_conv_gemm(const void* x, const std::uint16_t* w16, const float* bias, const ConvGemm& g,
                      void* y, cudaStream_t stream) {
  constexpr auto kernel = conv_gemm_kernel<H, TIn, TOut, Tile>;
  allow_dynamic_shared<kernel>(Tile::kSharedBytes);
  const std::int64_t rows = g.batch * g.out_height * g.out_width;
  const std::int64_t splits = ceil_div(g.k_padded / Tile::kK, g.split_steps);
  const dim3 grid(static_cast<unsigned>(ceil_div(rows, std::int64_t{Tile::kM})),
                  static_cast<unsigned>(ceil_div(g.columns, std::int64_t{Tile::kN})),
                  static_cast<unsigned>(splits));
  launch_kernel(kernel, grid, dim3(Tile::kThreads), Tile::kSharedBytes, stream,
                static_cast<const TIn*>(x), w16, bias, g, static_cast<TOut*>(y));
  if (g.partial != nullptr) {
    launch_kernel(split_reduce_kernel<H, TOut>,
                  dim3(static_cast<unsigned>(ceil_div(rows, std::int64_t{256})),
                       static_cast<unsigned>(g.columns)),
                  dim3(256), 0, stream, g.partial, splits, bias, g, static_cast<TOut*>(y));
  }
}

template <Half16 H, class Tile>
void launch_conv_gemm(const void* x, bool x_half, const std::uint16_t* w16, const float* bias,
                      const ConvGemm& g, void* y, bool y_half, cudaStream_t stream) {
  using U = std::uint16_t;
  if (x_half && y_half)
    launch_conv_gemm<H, Tile, U, U>(x, w16, bias, g, y, stream);
  else if (x_half)
    launch_conv_gemm<H, Tile, U, float>(x, w16, bias, g, y, stream);
  else if (y_half)
    launch_conv_gemm<H, Tile, float, U>(x, w16, bias, g, y, stream);
  else
    launch_conv_gemm<H, Tile, float, float>(x, w16, bias, g, y, stream);
}

// Where a GEMM's tiles are few (the U-Net's deepest layers: 31 x 62 pixels are 16 tiles of 128)
// and K is long, K is split over blockIdx.z so that about kSplitTargetBlocks blocks run (a fixed
// count, as the weight gradients' split, so that the bits do not depend on the GPU), each split
// at least kMinSplitSteps steps of 32; the splits' FP32 sums are added in split order by
// split_reduce_kernel. 1: unsplit.
constexpr std::int64_t kSplitTargetBlocks = 256, kMinSplitSteps = 8;

std::int64_t gemm_splits(const ConvGemm& g) {
  const std::int64_t rows = g.batch * g.out_height * g.out_width;
  const std::int64_t tile_n = g.columns <= 64 ? ConvTile<64>::kN : ConvTile<128>::kN;
  const std::int64_t blocks =
      ceil_div(rows, std::int64_t{ConvTile<64>::kM}) * ceil_div(g.columns, tile_n);
  if (blocks == 0) return 1;
  const std::int64_t splits =
      std::min(kSplitTargetBlocks / blocks, g.k_padded / ConvTile<64>::kK / kMinSplitSteps);
  return splits < 2 ? 1 : splits;
}

// The floats of run_gemm's workspace for g: the splits' sums, 0 unsplit.
std::int64_t gemm_workspace(const ConvGemm& g) {
  const std::int64_t splits = gemm_splits(g);
  return splits > 1 ? splits * g.batch * g.out_height * g.out_width * g.columns : 0;
}

// workspace: nullptr (unsplit), or gemm_workspace(g) floats.
void run_gemm(const void* x, bool x_half, const std::uint16_t* w16, const float* bias, ConvGemm g,
              Half16 type, void* y, bool y_half, cudaStream_t stream, float* workspace) {
  const std::int64_t rows = g.batch * g.out_height * g.out_width;
  if (rows == 0 || g.columns == 0) return;
  const std::int64_t steps = g.k_padded / ConvTile<64>::kK;
  const std::int64_t splits = workspace != nullptr ? gemm_splits(g) : 1;
  g.split_steps = ceil_div(steps, splits);
  g.partial = splits > 1 ? workspace : nullptr;
  std::string why;
  PS_CHECK(mma_supported(&why), "conv2d_mma: {}", why);
  PS_CHECK(
      g.channels_padded % 32 == 0 && g.k_padded % g.channels_padded == 0,
      "conv2d_mma: the prepared weights' K ({}) must be whole taps of {} channels padded to 32",
      g.k_padded, g.channels);
  with_half16(type, [&](auto h) {
    // Layers of at most 64 columns (the U-Net's widest-resolution ones) in 128 x 64 tiles.
    if (g.columns <= 64)
      launch_conv_gemm<decltype(h)::value, ConvTile<64>>(x, x_half, w16, bias, g, y, y_half,
                                                         stream);
    else
      launch_conv_gemm<decltype(h)::value, ConvTile<128>>(x, x_half, w16, bias, g, y, y_half,
                                                          stream);
  });
}

void run_prepare(const float* w, const float* bias, const FoldedBatchNorm& bn, std::int64_t rows,
                 std::int64_t channels, int taps, bool transposed, std::int64_t out_channels,
                 Half16 type, std::uint16_t* w16, float* bias_out, cudaStream_t stream) {
  const std::int64_t total = rows * op::half16_weight_k(channels, taps);
  if (total == 0) return;
  const dim3 grid(static_cast<unsigned>(ceil_div(total, 256)));
  with_half16(type, [&](auto h) {
    launch_kernel(prepare_weights_kernel<decltype(h)::value>, grid, dim3(256), 0, stream, w, bias,
                  bn, rows, channels, op::half16_padded_channels(channels), taps, transposed,
                  out_channels, w16, bias_out);
  });
}

}  // namespace

static_assert(ConvTile<64>::kK == op::kHalf16WeightK && ConvTile<128>::kK == op::kHalf16WeightK,
              "the prepared weights' channel padding is the kernel's K step");

bool mma_supported(std::string* why_not) {
#if defined(PILLARSEG_CUDA_EMULATION)
  static_cast<void>(why_not);
  return true;
#else
  int device = 0;
  PS_CUDA_CHECK(cudaGetDevice(&device));
  // Asked once per device: every launch checks it.
  static std::array<std::atomic<int>, 64> cached{};  // 10 major + minor, 0: not asked yet
  int capability = device >= 0 && device < 64 ? cached[static_cast<size_t>(device)].load() : 0;
  if (capability == 0) {
    int major = 0, minor = 0;
    PS_CUDA_CHECK(cudaDeviceGetAttribute(&major, cudaDevAttrComputeCapabilityMajor, device));
    PS_CUDA_CHECK(cudaDeviceGetAttribute(&minor, cudaDevAttrComputeCapabilityMinor, device));
    capability = 10 * major + minor;
    if (device >= 0 && device < 64) cached[static_cast<size_t>(device)].store(capability);
  }
  const int major = capability / 10, minor = capability % 10;
  if (major >= 8) return true;
  if (why_not != nullptr) {
    *why_not = fmt::format(
        "BF16 and FP16 tensor-core convolutions (mma.sync m16n8k16) need compute capability 8.0 or "
        "later; device {} "
        "has {}.{}",
        device, major, minor);
  }
  return false;
#endif
}

void prepare_conv_weights(const float* w, const float* bias, const FoldedBatchNorm& bn,
                          const Conv2dShape& shape, Half16 type, std::uint16_t* w16,
                          float* bias_out, cudaStream_t stream) {
  run_prepare(w, bias, bn, shape.out_channels, shape.in_channels,
              static_cast<int>(shape.kernel * shape.kernel), false, shape.out_channels, type, w16,
              bias_out, stream);
}

namespace {

// folded[i] = w[i] scale[o] for i in row o (O rows of k_row values); bias_out[o] = scale bias[o] +
// shift, the scale and shift as prepare_weights_kernel computes them.
__global__ void fold_weights_kernel(const float* __restrict__ w, const float* __restrict__ bias,
                                    FoldedBatchNorm bn, std::int64_t rows, std::int64_t k_row,
                                    float* __restrict__ folded, float* __restrict__ bias_out) {
  const std::int64_t i = static_cast<std::int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= rows * k_row) return;
  const std::int64_t o = i / k_row;
  float scale = 1.0f, shift = 0.0f;
  if (bn.gamma != nullptr) {
    scale = bn.gamma[o] / sqrtf(bn.running_var[o] + bn.eps);
    shift = bn.beta[o] - scale * bn.running_mean[o];
  }
  folded[i] = w[i] * scale;
  if (i % k_row == 0) bias_out[o] = scale * (bias != nullptr ? bias[o] : 0.0f) + shift;
}

}  // namespace

void fold_conv_weights(const float* w, const float* bias, const FoldedBatchNorm& bn,
                       const Conv2dShape& shape, float* folded, float* bias_out,
                       cudaStream_t stream) {
  const std::int64_t k_row = shape.in_channels * shape.kernel * shape.kernel;
  const std::int64_t total = shape.out_channels * k_row;
  if (total == 0) return;
  launch_kernel(fold_weights_kernel, dim3(static_cast<unsigned>(ceil_div(total, 256))), dim3(256),
                0, stream, w, bias, bn, shape.out_channels, k_row, folded, bias_out);
}

void prepare_conv_transpose_weights(const float* w, const float* bias, std::int64_t in_channels,
                                    std::int64_t out_channels, Half16 type, std::uint16_t* w16,
                                    float* bias_out, cudaStream_t stream) {
  run_prepare(w, bias, FoldedBatchNorm{}, 4 * out_channels, in_channels, 1, true, out_channels,
              type, w16, bias_out, stream);
}

namespace {

// The gather of a stride-1 convolution of x (B, C, H, W) with a k x k kernel: D's rows are the
// output pixels, its columns the weights' rows.
ConvGemm conv_gather(std::int64_t batch, std::int64_t channels, std::int64_t height,
                     std::int64_t width, std::int64_t kernel, std::int64_t pad,
                     std::int64_t columns) {
  ConvGemm g{};
  g.batch = batch, g.channels = channels, g.channels_padded = op::half16_padded_channels(channels);
  g.in_height = height, g.in_width = width;
  g.out_height = height + 2 * pad - kernel + 1, g.out_width = width + 2 * pad - kernel + 1;
  g.columns = columns, g.k_padded = op::half16_weight_k(channels, kernel * kernel);
  g.kernel = static_cast<int>(kernel), g.stride = 1, g.pad = static_cast<int>(pad);
  return g;
}

}  // namespace

namespace {

ConvGemm conv_forward_gemm(const Conv2dShape& shape, bool relu) {
  ConvGemm g = conv_gather(shape.batch, shape.in_channels, shape.height, shape.width, shape.kernel,
                           shape.pad, shape.out_channels);
  g.relu = relu;
  return g;
}

// The pixels are x's (a 1 x 1 gather); each of the 4 O columns writes its sub-pixel of y.
ConvGemm conv_transpose_forward_gemm(std::int64_t batch, std::int64_t in_channels,
                                     std::int64_t height, std::int64_t width,
                                     std::int64_t out_channels) {
  ConvGemm g = conv_gather(batch, in_channels, height, width, 1, 0, 4 * out_channels);
  g.sub_pixels = true;
  return g;
}

}  // namespace

std::int64_t conv2d_mma_forward_workspace(const Conv2dShape& shape) {
  return gemm_workspace(conv_forward_gemm(shape, false));
}

void conv2d_mma_forward(const void* x, bool x_half, const std::uint16_t* w16, const float* bias,
                        const Conv2dShape& shape, Half16 type, bool relu, void* y, bool y_half,
                        cudaStream_t stream, float* workspace) {
  run_gemm(x, x_half, w16, bias, conv_forward_gemm(shape, relu), type, y, y_half, stream,
           workspace);
}

std::int64_t conv_transpose2d_mma_forward_workspace(std::int64_t batch, std::int64_t in_channels,
                                                     std::int64_t height, std::int64_t width,
                                                     std::int64_t out_channels) {
  return gemm_workspace(
      conv_transpose_forward_gemm(batch, in_channels, height, width, out_channels));
}

void conv_transpose2d_mma_forward(const void* x, bool x_half, const std::uint16_t* w16,
                                   const float* bias, std::int64_t batch, std::int64_t in_channels,
                                   std::int64_t height, std::int64_t width,
                                   std::int64_t out_channels, Half16 type, void* y, bool y_half,
                                   cudaStream_t stream, float* workspace) {
  run_gemm(x, x_half, w16, bias,
           conv_transpose_forward_gemm(batch, in_channels, height, width, out_channels), type, y,
           y_half, stream, workspace);
}

// ---- training gradients ----

namespace {

// The split of the weight gradient's Q pixels: about 256 blocks in all (a fixed count, so that
// the sums, and their bits, do not depend on the GPU), chunks of whole K steps.
MmaWeightGrad weight_grad_split(MmaWeightGrad g) {
  const std::int64_t total = g.batch * g.out_height * g.out_width;
  const std::int64_t tiles = ceil_div(g.rows, kTileM) * ceil_div(g.columns, kTileN);
  const std::int64_t steps = ceil_div(total, kTileK);
  std::int64_t splits = ceil_div(std::int64_t{256}, tiles);
  if (splits > steps) splits = steps;
  if (splits < 1) splits = 1;
  g.chunk = ceil_div(steps, splits) * kTileK;
  return g;
}

std::int64_t split_count(const MmaWeightGrad& g) {
  return g.chunk == 0 ? 0 : ceil_div(g.batch * g.out_height * g.out_width, g.chunk);
}

MmaWeightGrad conv_weight_grad(const Conv2dShape& shape) {
  MmaWeightGrad g{};
  g.batch = shape.batch, g.in_channels = shape.in_channels, g.height = shape.height, g.width = shape.width;
  g.out_channels = shape.out_channels;
  g.rows = shape.in_channels * shape.kernel * shape.kernel, g.columns = shape.out_channels;
  g.out_height = shape.out_height(), g.out_width = shape.out_width();
  g.kernel = static_cast<int>(shape.kernel), g.pad = static_cast<int>(shape.pad), g.transposed = false;
  return weight_grad_split(g);
}

MmaWeightGrad conv_transpose_weight_grad(const ConvTranspose2dShape& shape) {
  MmaWeightGrad g{};
  g.batch = shape.batch, g.in_channels = shape.in_channels, g.height = shape.height, g.width = shape.width;
  g.out_channels = shape.out_channels;
  g.rows = shape.in_channels, g.columns = 4 * shape.out_channels;
  g.out_height = shape.height, g.out_width = shape.width;
  g.kernel = 1, g.pad = 0, g.transposed = true;
  return weight_grad_split(g);
}

void run_weight_grad(const float* x, const float* dy, const MmaWeightGrad& g, Half16 type, float* dw,
                     float* workspace, cudaStream_t stream) {
  const std::int64_t splits = split_count(g);
  if (g.rows == 0 || g.columns == 0) return;
  if (splits == 0) {  // no pixels: the gradient is zero
    PS_CUDA_CHECK(cudaMemsetAsync(dw, 0, static_cast<size_t>(g.rows * g.columns) * sizeof(float), stream));
    return;
  }
  std::string why;
  PS_CHECK(mma_supported(&why), "conv2d_mma backward: {}", why);
  const dim3 grid(static_cast<unsigned>(ceil_div(g.rows, kTileM)), static_cast<unsigned>(ceil_div(g.columns, kTileN)),
                  static_cast<unsigned>(splits));
  with_half16(type, [&](auto h) {
    launch_kernel(mma_weight_grad_kernel<decltype(h)::value>, grid, dim3(kThreads), 0, stream, x, dy, g, workspace);
  });
  const std::int64_t n = g.rows * g.columns;
  launch_kernel(weight_grad_reduce_kernel, dim3(static_cast<unsigned>(ceil_div(n, 256) < 4096 ? ceil_div(n, 256) : 4096)),
                dim3(256), 0, stream, workspace, splits, g.rows, g.columns, g.transposed, dw);
}

void run_bias_grad(const float* dy, std::int64_t batch, std::int64_t channels, std::int64_t plane, float* dbias,
                   cudaStream_t stream) {
  if (dbias == nullptr || channels == 0) return;
  launch_kernel(bias_grad_kernel, dim3(static_cast<unsigned>(channels)), dim3(kBiasThreads), 0, stream, dy, batch,
                channels, plane, dbias);
}

void run_prepare_data(const float* w, std::int64_t rows, std::int64_t channels, int taps,
                      bool transposed, Half16 type, std::uint16_t* w16t, cudaStream_t stream) {
  const std::int64_t total = rows * op::half16_weight_k(channels, taps);
  if (total == 0) return;
  with_half16(type, [&](auto h) {
    launch_kernel(prepare_data_weights_kernel<decltype(h)::value>,
                  dim3(static_cast<unsigned>(ceil_div(total, 256))), dim3(256), 0, stream, w, rows,
                  channels, op::half16_padded_channels(channels), taps, transposed, w16t);
  });
}

}  // namespace

void prepare_conv_data_weights(const float* w, const Conv2dShape& shape, Half16 type, std::uint16_t* w16t,
                               cudaStream_t stream) {
  const int taps = static_cast<int>(shape.kernel * shape.kernel);
  run_prepare_data(w, shape.in_channels, shape.out_channels, taps, false, type, w16t, stream);
}

namespace {

// dx = the convolution of dy (B, O, Ho, Wo) with the flipped weights, padding k - 1 - pad.
ConvGemm conv_data_gemm(const Conv2dShape& shape) {
  return conv_gather(shape.batch, shape.out_channels, shape.out_height(), shape.out_width(),
                     shape.kernel, shape.kernel - 1 - shape.pad, shape.in_channels);
}

// dx (B, I, H, W): pixels of x, K = the O channels of dy (B, O, 2H, 2W) at the 4 sub-pixels
// above each, a 2 x 2 gather of stride 2.
ConvGemm conv_transpose_data_gemm(const ConvTranspose2dShape& shape) {
  ConvGemm g{};
  g.batch = shape.batch, g.channels = shape.out_channels;
  g.channels_padded = op::half16_padded_channels(shape.out_channels);
  g.in_height = 2 * shape.height, g.in_width = 2 * shape.width;
  g.out_height = shape.height, g.out_width = shape.width;
  g.columns = shape.in_channels, g.k_padded = op::half16_weight_k(shape.out_channels, 4);
  g.kernel = 2, g.stride = 2, g.pad = 0;
  return g;
}

}  // namespace

std::int64_t conv2d_mma_backward_data_workspace(const Conv2dShape& shape) {
  return gemm_workspace(conv_data_gemm(shape));
}

void conv2d_mma_backward_data(const float* dy, const std::uint16_t* w16t, const Conv2dShape& shape,
                              Half16 type, float* dx, cudaStream_t stream, float* workspace) {
  run_gemm(dy, false, w16t, nullptr, conv_data_gemm(shape), type, dx, false, stream, workspace);
}

std::int64_t conv2d_mma_backward_weights_workspace(const Conv2dShape& shape) {
  const MmaWeightGrad g = conv_weight_grad(shape);
  return split_count(g) * g.rows * g.columns;
}

void conv2d_mma_backward_weights(const float* x, const float* dy, const Conv2dShape& shape, Half16 type, float* dw,
                                 float* dbias, float* workspace, cudaStream_t stream) {
  run_weight_grad(x, dy, conv_weight_grad(shape), type, dw, workspace, stream);
  run_bias_grad(dy, shape.batch, shape.out_channels, shape.out_height() * shape.out_width(), dbias, stream);
}

void prepare_conv_transpose_data_weights(const float* w, const ConvTranspose2dShape& shape, Half16 type,
                                         std::uint16_t* w16t, cudaStream_t stream) {
  run_prepare_data(w, shape.in_channels, shape.out_channels, 4, true, type, w16t, stream);
}

std::int64_t conv_transpose2d_mma_backward_data_workspace(const ConvTranspose2dShape& shape) {
  return gemm_workspace(conv_transpose_data_gemm(shape));
}

void conv_transpose2d_mma_backward_data(const float* dy, const std::uint16_t* w16t,
                                         const ConvTranspose2dShape& shape, Half16 type, float* dx,
                                         cudaStream_t stream, float* workspace) {
  run_gemm(dy, false, w16t, nullptr, conv_transpose_data_gemm(shape), type, dx, false, stream,
           workspace);
}

std::int64_t conv_transpose2d_mma_backward_weights_workspace(const ConvTranspose2dShape& shape) {
  const MmaWeightGrad g = conv_transpose_weight_grad(shape);
  return split_count(g) * g.rows * g.columns;
}

void conv_transpose2d_mma_backward_weights(const float* x, const float* dy, const ConvTranspose2dShape& shape,
                                            Half16 type, float* dw, float* dbias, float* workspace,
                                            cudaStream_t stream) {
  run_weight_grad(x, dy, conv_transpose_weight_grad(shape), type, dw, workspace, stream);
  run_bias_grad(dy, shape.batch, shape.out_channels, 4 * shape.height * shape.width, dbias, stream);
}

void mma_fragment_probe(const float* a, const float* b, const float* c, Half16 type, float* d,
                        cudaStream_t stream) {
  std::string why;
  PS_CHECK(mma_supported(&why), "mma_fragment_probe: {}", why);
  with_half16(type, [&](auto h) {
    launch_kernel(mma_probe_kernel<decltype(h)::value>, dim3(1), dim3(32), 0, stream, a, b, c, d);
  });
}

void ldmatrix_probe(std::uint32_t* out, cudaStream_t stream) {
  launch_kernel(ldmatrix_probe_kernel, dim3(1), dim3(32), 0, stream, out);
}

void cp_async_probe(const std::uint32_t* source, std::uint32_t* out, bool misalign,
                    cudaStream_t stream) {
  std::string why;
  PS_CHECK(mma_supported(&why), "cp_async_probe: {}", why);
  launch_kernel(cp_async_probe_kernel, dim3(1), dim3(32), 0, stream, source, out, misalign);
}

}  // namespace pillarseg::cuda
