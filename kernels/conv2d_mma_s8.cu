// The INT8 tensor-core convolutions of conv2d_mma_s8.cuh. One kernel, conv_gemm_s8_kernel, runs
// the forward of both kinds as an implicit GEMM D (pixels x columns) = A (pixels x K) B (K x
// columns), as conv_gemm_kernel of conv2d_mma.cu does in 16 bits: A gathers, for output pixel
// (oy, ox) and K element k = t Ip + c (tap-major), channel c of x at (oy + t / KS - pad,
// ox + t % KS - pad), zero outside it and past I (KS = k for a convolution; a 1 x 1 gather for the
// transposed kind, whose column (o, dy, dx) goes to y's sub-pixel (2 h + dy, 2 w + dx)).
// A block of 128 threads (4 warps, 2 x 2) computes a 128 x BN tile of D (BN = 128, or 64 for at
// most 64 columns; a warp 64 x BN / 2) in steps of 32 along K (one mma.sync m16n8k32 deep),
// through a pipeline of 3 stages in dynamic shared memory:
//   - A: each thread owns one pixel of the tile; a K step lies within one tap (Ip is a multiple
//     of 32), so the thread checks the tap's position once and stages its pixel's 32-byte row:
//       FP32 or BF16 x: reads its 32 channels plane after plane (a warp reads 32 neighbouring
//       pixels of each plane), quantizes them (quantize_i8: to s8, or to u8 for non_negative x)
//       and stores them in two 16-byte stores; the loads for step s + 2 are issued before step s
//       is computed and stored after;
//       S8x32 x: the 32 channels are the pixel's 32 contiguous bytes of its channel block, copied
//       by two cp.async (zero-filled outside x) with the weights of the step;
//   - B: the weights' BN x 32 bytes, rows (N, Kp) contiguous along K, by cp.async in 16-byte
//     pieces (zero-filled past the last column), committed per step and waited for two steps
//     later;
//   - compute: each warp loads its four 16 x 32 A fragments (ldmatrix.x4 of As, rows = pixels,
//     each 16-bit element two int8 along K: the m16n8k32 layout) and its BN / 16 B fragment pairs
//     (ldmatrix.x4 of Bs, rows = columns), and issues 4 x BN / 16 mma.sync m16n8k32 (.s8.s8, or
//     .u8.s8 with u8 activations: the same fragments, A's bytes read unsigned). Rows of 32
//     bytes are padded to 48 so that stores and ldmatrix rows of 8 neighbouring rows fall in
//     distinct banks;
//   - epilogue: acc to float, times sx sw[n], plus the bias (one FMA), ReLU, stored FP32, BF16 or
//     quantized with y's scale, at its pixel and column of y (the transposed kind's at its
//     sub-pixel);
//   - split K (gemm_splits_s8, where the tiles are few and K long): block z runs its range of K
//     steps and stores its 32-bit sums; split_reduce_s8_kernel adds them (exactly, modulo 2^32 as
//     the tensor cores do) and does the epilogue's work.
#include "kernels/conv2d_mma_s8.cuh"

#include <algorithm>
#include <cmath>
#include <string>
#include <type_traits>

#include "core/ops.hpp"
#include "kernels/common.cuh"
#include "kernels/mma.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

// The implicit GEMM of conv_gemm_s8_kernel (see the top of the file).
struct GemmS8 {
  std::int64_t batch;
  std::int64_t channels;               // I
  std::int64_t channels_padded;        // Ip: I rounded up to 32, the K step
  std::int64_t in_height, in_width;    // x's planes
  std::int64_t out_height, out_width;  // the pixels D's rows are
  std::int64_t columns;                // N: O, or 4 O for the transposed kind
  std::int64_t k_padded;               // taps x Ip
  int kernel, pad;                     // KS and pad of the gather (stride 1)
  bool sub_pixels;                     // D's column (o, dy, dx) goes to y's sub-pixel
  bool relu;
  bool y_blocked;         // y is S8x32 ...
  std::int64_t y_blocks;  // ... of Op / 32 channel blocks
  float x_scale;          // sx
  float x_inv_scale;      // r = 1 / sx, rounded to FP32
  float y_inv_scale;      // 1 / y's scale (S8x32 y)
  // Split K: block z runs steps [z split_steps, (z + 1) split_steps) and writes its sums to
  // partial[z] (columns x rows, the pixel fastest); unsplit: split_steps = k_padded / 32,
  // partial = nullptr.
  std::int64_t split_steps;
  std::int32_t* partial;
};

// The block tile: 128 pixels x BN columns, 4 warps of 64 x BN / 2, 3 stages of 32 bytes of K.
template <int BN>
struct TileS8 {
  static constexpr int kM = 128, kN = BN, kK = 32, kThreads = 128, kStages = 3;
  static constexpr int kWarpM = 64, kWarpN = BN / 2;
  static constexpr int kFragsM = kWarpM / 16, kFragsN = kWarpN / 8;
  static constexpr int kPitch = kK + 16;  // bytes: 8 rows of 48 bytes cover the 32 banks once
  static constexpr int kStageBytes = (kM + kN) * kPitch;
  static constexpr std::size_t kSharedBytes = std::size_t{kStages} * kStageBytes;
  static_assert(kM == kThreads, "a thread stages one pixel's row of A");
  static_assert(2 * kWarpM == kM && kThreads == 4 * 32, "four warps, 2 x 2 over the tile");
  static_assert(kFragsN % 2 == 0, "B fragments are loaded in pairs");
  static_assert(kFragsM * 16 == kWarpM && kFragsN * 8 == kWarpN, "whole m16 by n8 fragments");
  static_assert(kSharedBytes <= 48 * 1024, "within the default dynamic shared memory limit");
};

// q = clamp(rint(x r), -127, 127) (s8: as the low byte of its two's complement) or clamp(rint(x
// r), 0, 255) (u8), x r rounded to FP32 first (never fused into the addition), NaN -> 0. Adding
// 1.5 2^23 rounds x r to an integer (ties to even: 1.5 2^23 is even) where the sum lies in [2^23,
// 2^24), whose ulp is 1, and leaves that integer in the sum's low bits; the clamp keeps the sum
// there (infinities clamp too).
template <Int8A Q>
__device__ __forceinline__ std::uint32_t quantize_i8(float x, float r) {
  constexpr float kMagic = 12582912.0f;  // 1.5 x 2^23
  constexpr float kLow = Q == Int8A::U8 ? kMagic : kMagic - 127.0f;
  constexpr float kHigh = Q == Int8A::U8 ? kMagic + 255.0f : kMagic + 127.0f;
  float t = __fmul_rn(x, r);
  t = t == t ? t : 0.0f;
  t = fminf(fmaxf(__fadd_rn(t, kMagic), kLow), kHigh);
  return __float_as_uint(t) & 0xFFu;
}
__device__ __forceinline__ std::uint32_t quantize_s8(float x, float r) {
  return quantize_i8<Int8A::S8>(x, r);
}

template <class T>
constexpr bool kQuantizedInput = std::is_same_v<T, std::int8_t>;  // S8x32 x

template <class T>
__device__ __forceinline__ float activation_value(T value) {
  if constexpr (std::is_same_v<T, float>)
    return value;
  else
    return bf16_bits_to_float(value);
}

// One thread's pixel of A and the K step it stages next: steps are staged in order, so the tap
// (ky, kx) and the first channel c0 of the step advance by 32 channels at a time.
template <class TIn>
struct PixelGatherS8 {
  const TIn* image = nullptr;  // the pixel's image of x (S8x32: its first channel block)
  std::int64_t oy = 0, ox = 0;
  bool valid = false;
  std::int64_t c0 = 0;
  int ky = 0, kx = 0;

  __device__ __forceinline__ void start_at(const GemmS8& g, std::int64_t step) {
    const std::int64_t k = step * 32, tap = k / g.channels_padded;
    c0 = k % g.channels_padded;
    ky = static_cast<int>(tap / g.kernel), kx = static_cast<int>(tap % g.kernel);
  }

  // The next step's 32 quantized values (s8 or u8: XA), channels c0 .. c0 + 31 at tap (ky, kx),
  // as 8 words of four bytes (the lowest channel in the lowest byte), zero outside x and past I.
  template <Int8A XA>
  __device__ __forceinline__ void load_next(const GemmS8& g, std::uint32_t (&words)[8]) {
    const std::int64_t iy = oy + ky - g.pad, ix = ox + kx - g.pad;
    const bool inside = valid && iy >= 0 && iy < g.in_height && ix >= 0 && ix < g.in_width;
    const std::int64_t plane = g.in_height * g.in_width;
    const TIn* p = image + c0 * plane + iy * g.in_width + ix;
    const std::int64_t channels_here = g.channels - c0;  // > 0; < 32 only in a tap's last step
    const float r = g.x_inv_scale;
    if (!inside) {
#pragma unroll
      for (int j = 0; j < 8; ++j) words[j] = 0;
    } else if (channels_here >= 32) {
#pragma unroll
      for (int j = 0; j < 8; ++j) {
        std::uint32_t word = 0;
#pragma unroll
        for (int e = 0; e < 4; ++e)
          word |= quantize_i8<XA>(activation_value(p[(4 * j + e) * plane]), r) << (8 * e);
        words[j] = word;
      }
    } else {
#pragma unroll
      for (int j = 0; j < 8; ++j) {
        std::uint32_t word = 0;
#pragma unroll
        for (int e = 0; e < 4; ++e) {
          if (4 * j + e < channels_here)
            word |= quantize_i8<XA>(activation_value(p[(4 * j + e) * plane]), r) << (8 * e);
        }
        words[j] = word;
      }
    }
    advance(g);
  }

  // S8x32 x: the next step's 32 bytes, channels c0 .. c0 + 31 at tap (ky, kx), by two cp.async
  // into `row` (zeros outside x; past I the tensor holds zeros).
  __device__ __forceinline__ void issue_next(const GemmS8& g, std::uint8_t* row) {
    const std::int64_t iy = oy + ky - g.pad, ix = ox + kx - g.pad;
    const bool inside = valid && iy >= 0 && iy < g.in_height && ix >= 0 && ix < g.in_width;
    const TIn* source =
        inside ? image + ((c0 / 32) * g.in_height * g.in_width + iy * g.in_width + ix) * 32 : image;
    cp_async_16(row, source, inside);
    cp_async_16(row + 16, inside ? source + 16 : image, inside);
    advance(g);
  }

  __device__ __forceinline__ void advance(const GemmS8& g) {
    c0 += 32;
    if (c0 == g.channels_padded) {
      c0 = 0;
      if (++kx == g.kernel) kx = 0, ++ky;
    }
  }
};

template <class Tile>
struct StageS8 {
  std::uint8_t* a;  // [kM][kPitch]: a pixel's 32 K bytes per row
  std::uint8_t* b;  // [kN][kPitch]: a column's 32 K bytes per row
  __device__ StageS8(std::uint8_t* shared, int stage)
      : a(shared + stage * Tile::kStageBytes), b(a + Tile::kM * Tile::kPitch) {}
};

// The weights' kN x 32 bytes of step k0 into the stage by cp.async, zero past the last column.
template <class Tile>
__device__ __forceinline__ void issue_weights_s8(const StageS8<Tile>& s, const std::int8_t* w8,
                                                 const GemmS8& g, std::int64_t n0, std::int64_t k0,
                                                 int tid) {
#pragma unroll
  for (int v = tid; v < Tile::kN * 2; v += Tile::kThreads) {
    const int row = v / 2, part = v % 2;
    const bool fill = n0 + row < g.columns;
    const std::int8_t* source = fill ? w8 + (n0 + row) * g.k_padded + k0 + part * 16 : w8;
    cp_async_16(s.b + row * Tile::kPitch + part * 16, source, fill);
  }
}

// One stage's 32 of K for a warp: its kFragsM A fragments (ldmatrix.x4: (pixels 0-7, k 0-15),
// (8-15, 0-15), (0-7, 16-31), (8-15, 16-31) are a0..a3) and kFragsN B fragments (ldmatrix.x4 of
// two n8 tiles: (n 0-7, k 0-15), (n 0-7, k 16-31), (n 8-15, k 0-15), (n 8-15, k 16-31)), and
// kFragsM kFragsN mma.sync (A's bytes s8 or u8: XA).
template <class Tile, Int8A XA>
__device__ __forceinline__ void compute_stage_s8(
    const StageS8<Tile>& s, std::int32_t (&acc)[Tile::kFragsM][Tile::kFragsN][4], int warp_m,
    int warp_n, int lane) {
  const int j = lane / 8, r = lane % 8;
  std::uint32_t a[Tile::kFragsM][4], b[Tile::kFragsN][2];
#pragma unroll
  for (int mt = 0; mt < Tile::kFragsM; ++mt) {
    const int row = warp_m * Tile::kWarpM + mt * 16 + lane % 16;
    ldmatrix_x4<false>(a[mt], s.a + row * Tile::kPitch + (lane / 16) * 16);
  }
#pragma unroll
  for (int np = 0; np < Tile::kFragsN / 2; ++np) {
    const int row = warp_n * Tile::kWarpN + np * 16 + (j / 2) * 8 + r;
    std::uint32_t regs[4];
    ldmatrix_x4<false>(regs, s.b + row * Tile::kPitch + (j % 2) * 16);
    b[2 * np][0] = regs[0], b[2 * np][1] = regs[1], b[2 * np + 1][0] = regs[2],
          b[2 * np + 1][1] = regs[3];
  }
#pragma unroll
  for (int mt = 0; mt < Tile::kFragsM; ++mt)
#pragma unroll
    for (int nt = 0; nt < Tile::kFragsN; ++nt)
      mma_m16n8k32_i8<XA>(acc[mt][nt], a[mt], b[nt], acc[mt][nt]);
}

// Where D's row (pixel p of `image`) and column n go in y: y[pixel_offset + column_offset], in
// elements of y. y's pixel of row p is p, or for sub-pixels (2 oy, 2 ox) of its 2 Ho x 2 Wo, and
// column n is channel n, or channel n / 4 at the sub-pixel offset (n % 4 / 2, n % 2). Planar:
// y[image][channel][pixel]; S8x32: byte ((image Op / 32 + channel / 32) plane + pixel) 32 +
// channel % 32.
__device__ __forceinline__ std::int64_t y_plane_s8(const GemmS8& g) {
  return g.out_height * g.out_width * (g.sub_pixels ? 4 : 1);
}
__device__ __forceinline__ std::int64_t pixel_offset_s8(const GemmS8& g, std::int64_t image,
                                                        std::int64_t p) {
  const std::int64_t plane = y_plane_s8(g);
  const std::int64_t pixel =
      g.sub_pixels ? 2 * (p / g.out_width) * 2 * g.out_width + 2 * (p % g.out_width) : p;
  return g.y_blocked ? (image * g.y_blocks * plane + pixel) * 32
                     : image * (g.sub_pixels ? g.columns / 4 : g.columns) * plane + pixel;
}
__device__ __forceinline__ std::int64_t column_offset_s8(const GemmS8& g, std::int64_t n) {
  const std::int64_t plane = y_plane_s8(g);
  const std::int64_t channel = g.sub_pixels ? n / 4 : n;
  const std::int64_t sub_pixel = g.sub_pixels ? (n % 4) / 2 * 2 * g.out_width + n % 2 : 0;
  return g.y_blocked ? ((channel / 32) * plane + sub_pixel) * 32 + channel % 32
                     : channel * plane + sub_pixel;
}

// act(float(acc) s + bias) stored as TOut: FP32, BF16 bits, or quantized (S8x32).
template <class TOut>
__device__ __forceinline__ void store_output(TOut* y, std::int64_t index, std::int32_t acc,
                                             float scale, float bias, const GemmS8& g) {
  float value = fmaf(static_cast<float>(acc), scale, bias);
  if (g.relu) value = value > 0.0f ? value : 0.0f;
  if constexpr (std::is_same_v<TOut, float>)
    y[index] = value;
  else if constexpr (std::is_same_v<TOut, std::int8_t>)
    y[index] =
        static_cast<std::int8_t>(static_cast<std::uint8_t>(quantize_s8(value, g.y_inv_scale)));
  else
    y[index] = float_to_bf16_bits(value);
}

// TIn, TOut: float (FP32), std::uint16_t (BF16 bits) or std::int8_t (S8x32). XA: x quantized to
// s8, or to u8 (non-negative x, FP32 or BF16 only), and the matching mma.sync.
template <class TIn, class TOut, class Tile, Int8A XA>
__global__ void __launch_bounds__(Tile::kThreads, 2)
    conv_gemm_s8_kernel(const TIn* __restrict__ x, const std::int8_t* __restrict__ w8,
                        const float* __restrict__ w_scale, const float* __restrict__ bias, GemmS8 g,
                        TOut* __restrict__ y) {
#if !PILLARSEG_MMA_ARCH
  __trap();  // before sm_80 (see PILLARSEG_MMA_ARCH)
#else
  std::uint8_t* shared = dynamic_shared<std::uint8_t>();
  const int tid = static_cast<int>(threadIdx.x), lane = tid % 32, warp = tid / 32;
  const int warp_m = warp % 2, warp_n = warp / 2;
  const std::int64_t pixels_per_image = g.out_height * g.out_width;
  const std::int64_t rows = g.batch * pixels_per_image;
  const std::int64_t m0 = static_cast<std::int64_t>(blockIdx.x) * Tile::kM;
  const std::int64_t n0 = static_cast<std::int64_t>(blockIdx.y) * Tile::kN;

  // Where each pixel of the tile goes in y but for its column's offset, -1 past the last pixel:
  // worked out once, by the thread that stages the pixel, for the epilogue's threads.
  __shared__ std::int64_t row_offset[Tile::kM];
  PixelGatherS8<TIn> pixel;
  {
    const std::int64_t m = m0 + tid;
    pixel.valid = m < rows;
    const std::int64_t image = pixel.valid ? m / pixels_per_image : 0;
    const std::int64_t p = pixel.valid ? m % pixels_per_image : 0;
    pixel.oy = p / g.out_width, pixel.ox = p % g.out_width;
    const std::int64_t planes = kQuantizedInput<TIn> ? g.channels_padded : g.channels;
    pixel.image = x + image * planes * g.in_height * g.in_width;
    row_offset[tid] = pixel.valid ? pixel_offset_s8(g, image, p) : -1;
  }
  const auto store_pixel = [&](const StageS8<Tile>& s, const std::uint32_t(&words)[8]) {
    auto* row = reinterpret_cast<uint4*>(s.a + tid * Tile::kPitch);  // 48-byte rows: aligned
    row[0] = make_uint4(words[0], words[1], words[2], words[3]);
    row[1] = make_uint4(words[4], words[5], words[6], words[7]);
  };

  std::int32_t acc[Tile::kFragsM][Tile::kFragsN][4];
#pragma unroll
  for (int mt = 0; mt < Tile::kFragsM; ++mt)
#pragma unroll
    for (int nt = 0; nt < Tile::kFragsN; ++nt)
#pragma unroll
      for (int e = 0; e < 4; ++e) acc[mt][nt][e] = 0;

  // This block's K steps: [first, first + steps) of the whole (all of them unless split).
  const std::int64_t first = static_cast<std::int64_t>(blockIdx.z) * g.split_steps;
  const std::int64_t all_steps = g.k_padded / Tile::kK;
  const std::int64_t steps = all_steps - first < g.split_steps ? all_steps - first : g.split_steps;
  pixel.start_at(g, first);
  // Prologue: steps 0 .. kStages - 2 staged (an empty group where there are fewer steps).
#pragma unroll
  for (int s = 0; s < Tile::kStages - 1; ++s) {
    if (s < steps) {
      const StageS8<Tile> stage(shared, s);
      if constexpr (kQuantizedInput<TIn>) {
        pixel.issue_next(g, stage.a + tid * Tile::kPitch);
      } else {
        std::uint32_t words[8];
        pixel.template load_next<XA>(g, words);
        store_pixel(stage, words);
      }
      issue_weights_s8(stage, w8, g, n0, (first + s) * Tile::kK, tid);
    }
    cp_async_commit();
  }
  for (std::int64_t step = 0; step < steps; ++step) {
    cp_async_wait<Tile::kStages - 2>();  // this step's copies have landed
    __syncthreads();  // ... and every thread's, and its pixels; the oldest stage is free
    const std::int64_t next = step + Tile::kStages - 1;
    const StageS8<Tile> next_stage(shared, static_cast<int>(next % Tile::kStages));
    const StageS8<Tile> stage(shared, static_cast<int>(step % Tile::kStages));
    if constexpr (kQuantizedInput<TIn>) {
      if (next < steps) {
        pixel.issue_next(g, next_stage.a + tid * Tile::kPitch);
        issue_weights_s8(next_stage, w8, g, n0, (first + next) * Tile::kK, tid);
      }
      cp_async_commit();
      compute_stage_s8<Tile, XA>(stage, acc, warp_m, warp_n, lane);
    } else {
      std::uint32_t words[8] = {};  // loaded and stored under the same condition
      if (next < steps) {
        pixel.template load_next<XA>(g, words);
        issue_weights_s8(next_stage, w8, g, n0, (first + next) * Tile::kK, tid);
      }
      cp_async_commit();
      compute_stage_s8<Tile, XA>(stage, acc, warp_m, warp_n, lane);
      if (next < steps) store_pixel(next_stage, words);
    }
  }

  // Epilogue: accumulator i of (mt, nt) is D[row group + 8 (i >= 2)][column 2 t + (i & 1)].
  const int group = lane / 4, t = lane % 4;
  if (g.partial != nullptr) {  // split: this block's sums, for split_reduce_s8_kernel
    std::int32_t* part = g.partial + static_cast<std::int64_t>(blockIdx.z) * g.columns * rows;
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
  // This thread's columns: their offsets in y (-1 past the last), scales and biases.
  std::int64_t column_offsets[Tile::kFragsN][2];
  float column_scale[Tile::kFragsN][2], column_bias[Tile::kFragsN][2];
#pragma unroll
  for (int nt = 0; nt < Tile::kFragsN; ++nt) {
#pragma unroll
    for (int e = 0; e < 2; ++e) {
      const std::int64_t n = n0 + warp_n * Tile::kWarpN + nt * 8 + 2 * t + e;
      const bool valid = n < g.columns;
      column_offsets[nt][e] = valid ? column_offset_s8(g, n) : -1;
      column_scale[nt][e] = valid ? g.x_scale * w_scale[n] : 0.0f;
      column_bias[nt][e] = valid ? bias[n] : 0.0f;
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
          store_output(y, row + column_offsets[nt][e], acc[mt][nt][2 * half + e],
                       column_scale[nt][e], column_bias[nt][e], g);
        }
      }
    }
  }
#endif
}

// Split K: y at pixel m (blockIdx.x, threadIdx.x) and column n (blockIdx.y) from the splits'
// sums, added modulo 2^32 (unsigned: the same bits as one accumulator), stored as
// conv_gemm_s8_kernel's epilogue stores it.
template <class TOut>
__global__ void __launch_bounds__(256)
    split_reduce_s8_kernel(const std::int32_t* __restrict__ partial, std::int64_t splits,
                           const float* __restrict__ w_scale, const float* __restrict__ bias,
                           GemmS8 g, TOut* __restrict__ y) {
  const std::int64_t pixels_per_image = g.out_height * g.out_width;
  const std::int64_t rows = g.batch * pixels_per_image;
  const std::int64_t m = static_cast<std::int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const std::int64_t n = blockIdx.y;
  if (m >= rows) return;
  std::uint32_t sum = 0;
  for (std::int64_t z = 0; z < splits; ++z)
    sum += static_cast<std::uint32_t>(partial[(z * g.columns + n) * rows + m]);
  const std::int64_t index =
      pixel_offset_s8(g, m / pixels_per_image, m % pixels_per_image) + column_offset_s8(g, n);
  store_output(y, index, static_cast<std::int32_t>(sum), g.x_scale * w_scale[n], bias[n], g);
}

// The preparation's view of one weight: w (O, I, k, k), or w (I, O, 2, 2) for the transposed
// kind; column n of the GEMM is output channel n (transposed: n / 4, sub-pixel n % 4).
struct WeightsS8 {
  const float* w;
  const float* bias;
  FoldedBatchNorm bn;
  std::int64_t columns, channels, channels_padded, out_channels;
  int taps;
  bool transposed;

  // The BatchNorm's scale of column n (1 without one).
  __device__ float bn_scale(std::int64_t n) const {
    if (transposed || bn.gamma == nullptr) return 1.0f;
    return bn.gamma[n] / sqrtf(bn.running_var[n] + bn.eps);
  }
  // w' at column n, input channel c < I and tap `tap` (transposed: w of column n's sub-pixel).
  __device__ float value(std::int64_t n, std::int64_t c, int tap, float scale) const {
    return transposed ? w[(c * out_channels + n / 4) * 4 + n % 4]
                      : w[(n * channels + c) * taps + tap] * scale;
  }
};

// One thread a column n: w_scale[n] = max |w'| over the output channel's weights / 127, and
// bias_out[n] = scale bias + shift.
__global__ void prepare_scales_s8_kernel(WeightsS8 p, float* __restrict__ w_scale,
                                         float* __restrict__ bias_out) {
  const std::int64_t n = static_cast<std::int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (n >= p.columns) return;
  const float scale = p.bn_scale(n);
  float largest = 0.0f;
  if (p.transposed) {
    const std::int64_t first = n - n % 4;  // the output channel's four sub-pixel columns
    for (std::int64_t c = 0; c < p.channels; ++c)
      for (std::int64_t s = first; s < first + 4; ++s)
        largest = fmaxf(largest, fabsf(p.value(s, c, 0, scale)));
  } else {
    for (std::int64_t c = 0; c < p.channels; ++c)
      for (int tap = 0; tap < p.taps; ++tap)
        largest = fmaxf(largest, fabsf(p.value(n, c, tap, scale)));
  }
  w_scale[n] = largest / 127.0f;
  const std::int64_t o = p.transposed ? n / 4 : n;
  const float shift =
      p.transposed || p.bn.gamma == nullptr ? 0.0f : p.bn.beta[o] - scale * p.bn.running_mean[o];
  bias_out[n] = scale * (p.bias != nullptr ? p.bias[o] : 0.0f) + shift;
}

// w8 row n, column t Ip + c = clamp(rint(w' / w_scale[n]), -127, 127), 0 past I or where the
// channel's scale is 0.
__global__ void quantize_weights_s8_kernel(WeightsS8 p, const float* __restrict__ w_scale,
                                           std::int8_t* __restrict__ w8) {
  const std::int64_t k_padded = p.taps * p.channels_padded;
  const std::int64_t i = static_cast<std::int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= p.columns * k_padded) return;
  const std::int64_t n = i / k_padded, kk = i % k_padded;
  const int tap = static_cast<int>(kk / p.channels_padded);
  const std::int64_t c = kk % p.channels_padded;
  const float sw = w_scale[n];
  float q = 0.0f;
  if (c < p.channels && sw > 0.0f)
    q = rintf(fminf(fmaxf(p.value(n, c, tap, p.bn_scale(n)) / sw, -127.0f), 127.0f));
  w8[i] = static_cast<std::int8_t>(q);
}

// One thread per (image, channel block, pixel): the pixel's 32 channels of the block, quantized,
// as its 32 bytes of q (S8x32), zeros past C.
template <class T>
__global__ void __launch_bounds__(256)
    quantize_activations_s8_kernel(const T* __restrict__ x, std::int64_t channels,
                                   std::int64_t blocks, std::int64_t plane, std::int64_t total,
                                   float r, std::int8_t* __restrict__ q) {
  const std::int64_t i = static_cast<std::int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= total) return;
  const std::int64_t p = i % plane, block = (i / plane) % blocks, image = i / (plane * blocks);
  const std::int64_t first = block * 32, here = channels - first;  // > 0
  const T* source = x + (image * channels + first) * plane + p;
  std::uint32_t words[8];
#pragma unroll
  for (int j = 0; j < 8; ++j) {
    std::uint32_t word = 0;
#pragma unroll
    for (int e = 0; e < 4; ++e) {
      if (4 * j + e < here)
        word |= quantize_s8(activation_value(source[(4 * j + e) * plane]), r) << (8 * e);
    }
    words[j] = word;
  }
  auto* out = reinterpret_cast<uint4*>(q + i * 32);
  out[0] = make_uint4(words[0], words[1], words[2], words[3]);
  out[1] = make_uint4(words[4], words[5], words[6], words[7]);
}

// One warp: each lane builds its A and B registers from row-major A (16 x 32 bytes, s8 or u8: XA)
// and B (32 x 8) by the ISA's formulas, runs the mma, and writes its four results to D (16 x 8) by
// the formula.
template <Int8A XA>
__global__ void mma_i8_probe_kernel(const std::uint8_t* a, const std::int8_t* b,
                                    const std::int32_t* c, std::int32_t* d) {
  const int lane = static_cast<int>(threadIdx.x), g = lane / 4, t = lane % 4;
  std::uint32_t ra[4], rb[2];
  for (int r = 0; r < 4; ++r) {
    std::uint32_t reg = 0;
    for (int byte = 0; byte < 4; ++byte) {
      const int i = 4 * r + byte;  // element a_i
      const int row = (i < 4 || (i >= 8 && i < 12)) ? g : g + 8;
      const int col = 4 * t + (i & 3) + (i >= 8 ? 16 : 0);
      reg |= std::uint32_t{a[row * 32 + col]} << (8 * byte);
    }
    ra[r] = reg;
  }
  for (int r = 0; r < 2; ++r) {
    std::uint32_t reg = 0;
    for (int byte = 0; byte < 4; ++byte) {
      const int i = 4 * r + byte;  // element b_i
      const int row = 4 * t + (i & 3) + (i >= 4 ? 16 : 0);
      reg |= std::uint32_t{static_cast<std::uint8_t>(b[row * 8 + g])} << (8 * byte);
    }
    rb[r] = reg;
  }
  std::int32_t rc[4], rd[4];
  for (int i = 0; i < 4; ++i) rc[i] = c[(g + (i >= 2 ? 8 : 0)) * 8 + 2 * t + (i & 1)];
  mma_m16n8k32_i8<XA>(rd, ra, rb, rc);
  for (int i = 0; i < 4; ++i) d[(g + (i >= 2 ? 8 : 0)) * 8 + 2 * t + (i & 1)] = rd[i];
}

template <class Tile, class TIn, Int8A XA, class TOut>
void launch_gemm_s8(const void* x, const std::int8_t* w8, const float* w_scale, const float* bias,
                    const GemmS8& g, void* y, cudaStream_t stream) {
  const std::int64_t rows = g.batch * g.out_height * g.out_width;
  const std::int64_t splits = ceil_div(g.k_padded / Tile::kK, g.split_steps);
  const dim3 grid(static_cast<unsigned>(ceil_div(rows, std::int64_t{Tile::kM})),
                  static_cast<unsigned>(ceil_div(g.columns, std::int64_t{Tile::kN})),
                  static_cast<unsigned>(splits));
  launch_kernel(conv_gemm_s8_kernel<TIn, TOut, Tile, XA>, grid, dim3(Tile::kThreads),
                Tile::kSharedBytes, stream, static_cast<const TIn*>(x), w8, w_scale, bias, g,
                static_cast<TOut*>(y));
  if (g.partial != nullptr) {
    launch_kernel(split_reduce_s8_kernel<TOut>,
                  dim3(static_cast<unsigned>(ceil_div(rows, std::int64_t{256})),
                       static_cast<unsigned>(g.columns)),
                  dim3(256), 0, stream, g.partial, splits, w_scale, bias, g, static_cast<TOut*>(y));
  }
}

template <class Tile, class TIn, Int8A XA>
void launch_gemm_s8(const void* x, const std::int8_t* w8, const float* w_scale, const float* bias,
                    const GemmS8& g, const OutputS8& y, cudaStream_t stream) {
  switch (y.layout) {
    case ActivationLayout::F32:
      launch_gemm_s8<Tile, TIn, XA, float>(x, w8, w_scale, bias, g, y.data, stream);
      break;
    case ActivationLayout::BF16:
      launch_gemm_s8<Tile, TIn, XA, std::uint16_t>(x, w8, w_scale, bias, g, y.data, stream);
      break;
    case ActivationLayout::S8x32:
      launch_gemm_s8<Tile, TIn, XA, std::int8_t>(x, w8, w_scale, bias, g, y.data, stream);
      break;
  }
}

// FP32 or BF16 x quantized to s8, or to u8 where x is non-negative.
template <class Tile, class TIn>
void launch_gemm_s8(const ActivationsS8& x, const std::int8_t* w8, const float* w_scale,
                    const float* bias, const GemmS8& g, const OutputS8& y, cudaStream_t stream) {
  if (x.non_negative)
    launch_gemm_s8<Tile, TIn, Int8A::U8>(x.data, w8, w_scale, bias, g, y, stream);
  else
    launch_gemm_s8<Tile, TIn, Int8A::S8>(x.data, w8, w_scale, bias, g, y, stream);
}

template <class Tile>
void launch_gemm_s8(const ActivationsS8& x, const std::int8_t* w8, const float* w_scale,
                    const float* bias, const GemmS8& g, const OutputS8& y, cudaStream_t stream) {
  switch (x.layout) {
    case ActivationLayout::F32:
      launch_gemm_s8<Tile, float>(x, w8, w_scale, bias, g, y, stream);
      break;
    case ActivationLayout::BF16:
      launch_gemm_s8<Tile, std::uint16_t>(x, w8, w_scale, bias, g, y, stream);
      break;
    case ActivationLayout::S8x32:  // signed bytes as they are (run_gemm_s8 refuses non_negative)
      launch_gemm_s8<Tile, std::int8_t, Int8A::S8>(x.data, w8, w_scale, bias, g, y, stream);
      break;
  }
}

// As conv2d_mma.cu's gemm_splits: where the tiles are few and K long, K splits over blockIdx.z
// so that about 256 blocks run (a fixed count: the same on every GPU), each split at least 8
// steps of 32. 1: unsplit.
constexpr std::int64_t kSplitTargetBlocks = 256, kMinSplitSteps = 8;

std::int64_t gemm_splits_s8(const GemmS8& g) {
  const std::int64_t rows = g.batch * g.out_height * g.out_width;
  const std::int64_t tile_n = g.columns <= 64 ? TileS8<64>::kN : TileS8<128>::kN;
  const std::int64_t blocks =
      ceil_div(rows, std::int64_t{TileS8<64>::kM}) * ceil_div(g.columns, tile_n);
  if (blocks == 0) return 1;
  const std::int64_t splits =
      std::min(kSplitTargetBlocks / blocks, g.k_padded / TileS8<64>::kK / kMinSplitSteps);
  return splits < 2 ? 1 : splits;
}

std::int64_t gemm_workspace_s8(const GemmS8& g) {
  const std::int64_t splits = gemm_splits_s8(g);
  return splits > 1 ? splits * g.batch * g.out_height * g.out_width * g.columns : 0;
}

bool is_16_byte_aligned(const void* p) {
  return reinterpret_cast<std::uintptr_t>(p) % 16 == 0;
}

void check_scale(float scale, const char* what) {
  PS_CHECK(std::isfinite(scale) && scale > 0.0f,
           "conv2d_mma_s8: the {} scale must be positive and finite, not {}", what, scale);
}

// y_channels, y_height, y_width: y's shape (for clearing an S8x32 y's padding channels).
void run_gemm_s8(const ActivationsS8& x, const std::int8_t* w8, const float* w_scale,
                 const float* bias, GemmS8 g, const OutputS8& y, std::int64_t y_channels,
                 std::int64_t y_height, std::int64_t y_width, cudaStream_t stream,
                 std::int32_t* workspace) {
  const std::int64_t rows = g.batch * g.out_height * g.out_width;
  if (rows == 0 || g.columns == 0) return;
  std::string why;
  PS_CHECK(mma_supported(&why), "conv2d_mma_s8: {}", why);
  check_scale(x.scale, "activation");
  PS_CHECK(is_16_byte_aligned(w8),
           "conv2d_mma_s8: the prepared weights must be 16-byte aligned (device allocations are); "
           "{} is not",
           static_cast<const void*>(w8));
  PS_CHECK(x.layout != ActivationLayout::S8x32 || is_16_byte_aligned(x.data),
           "conv2d_mma_s8: an S8x32 input must be 16-byte aligned; {} is not", x.data);
  PS_CHECK(!(x.non_negative && x.layout == ActivationLayout::S8x32),
           "conv2d_mma_s8: non_negative needs an FP32 or BF16 input, which the kernel quantizes to "
           "u8; an S8x32 input holds signed bytes (there is no unsigned int8 layout): give x as "
           "FP32 or BF16, or clear non_negative");
  PS_CHECK(w_scale != nullptr && bias != nullptr,
           "conv2d_mma_s8: the prepared weight scales and bias are required");
  g.x_scale = x.scale;
  g.x_inv_scale = 1.0f / x.scale;
  g.y_blocked = y.layout == ActivationLayout::S8x32;
  if (g.y_blocked) {
    check_scale(y.scale, "output");
    g.y_blocks = op::half16_padded_channels(y_channels) / 32;
    g.y_inv_scale = 1.0f / y.scale;
    if (y_channels % 32 != 0) {  // the padding channels hold zeros; the kernels write the others
      PS_CUDA_CHECK(cudaMemsetAsync(
          y.data, 0,
          static_cast<std::size_t>(activations_s8_bytes(g.batch, y_channels, y_height, y_width)),
          stream));
    }
  }
  const std::int64_t steps = g.k_padded / TileS8<64>::kK;
  const std::int64_t splits = workspace != nullptr ? gemm_splits_s8(g) : 1;
  g.split_steps = ceil_div(steps, splits);
  g.partial = splits > 1 ? workspace : nullptr;
  // Layers of at most 64 columns (the U-Net's widest-resolution ones) in 128 x 64 tiles.
  if (g.columns <= 64)
    launch_gemm_s8<TileS8<64>>(x, w8, w_scale, bias, g, y, stream);
  else
    launch_gemm_s8<TileS8<128>>(x, w8, w_scale, bias, g, y, stream);
}

// The gather of a stride-1 convolution of x (B, I, H, W) with a k x k kernel: D's rows are the
// output pixels, its columns the weights' rows.
GemmS8 conv_forward_gemm_s8(const Conv2dShape& s, bool relu) {
  GemmS8 g{};
  g.batch = s.batch, g.channels = s.in_channels;
  g.channels_padded = op::half16_padded_channels(s.in_channels);
  g.in_height = s.height, g.in_width = s.width;
  g.out_height = s.out_height(), g.out_width = s.out_width();
  g.columns = s.out_channels, g.k_padded = op::half16_weight_k(s.in_channels, s.kernel * s.kernel);
  g.kernel = static_cast<int>(s.kernel), g.pad = static_cast<int>(s.pad);
  g.relu = relu;
  return g;
}

// The pixels are x's (a 1 x 1 gather); each of the 4 O columns writes its sub-pixel of y.
GemmS8 conv_transpose_forward_gemm_s8(std::int64_t batch, std::int64_t in_channels,
                                      std::int64_t height, std::int64_t width,
                                      std::int64_t out_channels, bool relu) {
  const Conv2dShape one_by_one{batch, in_channels, height, width, 4 * out_channels, 1, 0};
  GemmS8 g = conv_forward_gemm_s8(one_by_one, relu);
  g.sub_pixels = true;
  return g;
}

void run_prepare_s8(const WeightsS8& p, std::int8_t* w8, float* w_scale, float* bias_out,
                    cudaStream_t stream) {
  if (p.columns == 0) return;
  launch_kernel(prepare_scales_s8_kernel, dim3(static_cast<unsigned>(ceil_div(p.columns, 128))),
                dim3(128), 0, stream, p, w_scale, bias_out);
  const std::int64_t total = p.columns * p.taps * p.channels_padded;
  if (total == 0) return;
  launch_kernel(quantize_weights_s8_kernel, dim3(static_cast<unsigned>(ceil_div(total, 256))),
                dim3(256), 0, stream, p, w_scale, w8);
}

}  // namespace

static_assert(TileS8<64>::kK == op::kHalf16WeightK && TileS8<128>::kK == op::kHalf16WeightK,
              "the prepared weights' channel padding is the kernel's K step");

void prepare_conv_weights_s8(const float* w, const float* bias, const FoldedBatchNorm& bn,
                             const Conv2dShape& shape, std::int8_t* w8, float* w_scale,
                             float* bias_out, cudaStream_t stream) {
  const WeightsS8 p{w,
                    bias,
                    bn,
                    shape.out_channels,
                    shape.in_channels,
                    op::half16_padded_channels(shape.in_channels),
                    shape.out_channels,
                    static_cast<int>(shape.kernel * shape.kernel),
                    false};
  run_prepare_s8(p, w8, w_scale, bias_out, stream);
}

void prepare_conv_transpose_weights_s8(const float* w, const float* bias, std::int64_t in_channels,
                                       std::int64_t out_channels, std::int8_t* w8, float* w_scale,
                                       float* bias_out, cudaStream_t stream) {
  const WeightsS8 p{w,
                    bias,
                    FoldedBatchNorm{},
                    4 * out_channels,
                    in_channels,
                    op::half16_padded_channels(in_channels),
                    out_channels,
                    1,
                    true};
  run_prepare_s8(p, w8, w_scale, bias_out, stream);
}

std::int64_t conv2d_mma_s8_forward_workspace(const Conv2dShape& shape) {
  return gemm_workspace_s8(conv_forward_gemm_s8(shape, false));
}

void conv2d_mma_s8_forward(const ActivationsS8& x, const std::int8_t* w8, const float* w_scale,
                           const float* bias_out, const Conv2dShape& shape, bool relu,
                           const OutputS8& y, cudaStream_t stream, std::int32_t* workspace) {
  run_gemm_s8(x, w8, w_scale, bias_out, conv_forward_gemm_s8(shape, relu), y, shape.out_channels,
              shape.out_height(), shape.out_width(), stream, workspace);
}

std::int64_t conv_transpose2d_mma_s8_forward_workspace(std::int64_t batch,
                                                        std::int64_t in_channels,
                                                        std::int64_t height, std::int64_t width,
                                                        std::int64_t out_channels) {
  return gemm_workspace_s8(
      conv_transpose_forward_gemm_s8(batch, in_channels, height, width, out_channels, false));
}

void conv_transpose2d_mma_s8_forward(const ActivationsS8& x, const std::int8_t* w8,
                                      const float* w_scale, const float* bias_out,
                                      std::int64_t batch, std::int64_t in_channels,
                                      std::int64_t height, std::int64_t width,
                                      std::int64_t out_channels, bool relu, const OutputS8& y,
                                      cudaStream_t stream, std::int32_t* workspace) {
  run_gemm_s8(x, w8, w_scale, bias_out,
              conv_transpose_forward_gemm_s8(batch, in_channels, height, width, out_channels, relu),
              y, out_channels, 2 * height, 2 * width, stream, workspace);
}

std::int64_t activations_s8_bytes(std::int64_t batch, std::int64_t channels, std::int64_t height,
                                  std::int64_t width) {
  return batch * op::half16_padded_channels(channels) * height * width;
}

void quantize_activations_s8(const void* x, ActivationLayout x_layout, float scale,
                             std::int64_t batch, std::int64_t channels, std::int64_t height,
                             std::int64_t width, std::int8_t* q, cudaStream_t stream) {
  PS_CHECK(x_layout != ActivationLayout::S8x32,
           "quantize_activations_s8: the input must be FP32 or BF16, not already S8x32");
  check_scale(scale, "activation");
  PS_CHECK(is_16_byte_aligned(q), "quantize_activations_s8: q must be 16-byte aligned; {} is not",
           static_cast<const void*>(q));
  const std::int64_t blocks = op::half16_padded_channels(channels) / 32, plane = height * width;
  const std::int64_t total = batch * blocks * plane;
  if (total == 0) return;
  const dim3 grid(static_cast<unsigned>(ceil_div(total, 256)));
  if (x_layout == ActivationLayout::F32)
    launch_kernel(quantize_activations_s8_kernel<float>, grid, dim3(256), 0, stream,
                  static_cast<const float*>(x), channels, blocks, plane, total, 1.0f / scale, q);
  else
    launch_kernel(quantize_activations_s8_kernel<std::uint16_t>, grid, dim3(256), 0, stream,
                  static_cast<const std::uint16_t*>(x), channels, blocks, plane, total,
                  1.0f / scale, q);
}

void mma_s8_fragment_probe(const std::int8_t* a, const std::int8_t* b, const std::int32_t* c,
                           std::int32_t* d, cudaStream_t stream) {
  std::string why;
  PS_CHECK(mma_supported(&why), "mma_s8_fragment_probe: {}", why);
  launch_kernel(mma_i8_probe_kernel<Int8A::S8>, dim3(1), dim3(32), 0, stream,
                reinterpret_cast<const std::uint8_t*>(a), b, c, d);
}

void mma_u8s8_fragment_probe(const std::uint8_t* a, const std::int8_t* b, const std::int32_t* c,
                             std::int32_t* d, cudaStream_t stream) {
  std::string why;
  PS_CHECK(mma_supported(&why), "mma_u8s8_fragment_probe: {}", why);
  launch_kernel(mma_i8_probe_kernel<Int8A::U8>, dim3(1), dim3(32), 0, stream, a, b, c, d);
}

}  // namespace pillarseg::cuda
