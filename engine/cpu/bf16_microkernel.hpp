// The CPU's BF16 convolution micro-kernel, written once over an instruction set `Isa` and
// compiled twice: on the AVX512_BF16 instructions (bf16_conv_avx512.cpp, built with the AVX-512
// flags and only ever called where the CPU has them) and on an exact scalar model of the same
// instructions (bf16_isa_emulated.hpp, in bf16_conv.cpp), which the tests run on every CPU so
// that an indexing, masking or rounding mistake fails on machines without AVX-512 too.
//
// The GEMM: y[n, pixel] = act(sum_k w16[n, k] a[k, pixel] + bias[n]) over the K values of each
// output pixel, taken two at a time (k, k + 1) as VDPBF16PS does: a register holds 16 pixels of
// one output column, each lane the two BF16 inputs (a[k], a[k + 1]) of its pixel; the weight
// pair (w16[n, j], w16[n, j + 1]) of the weights' column j = k_taps[k].column is broadcast to
// every lane. Element k of the pixel (row, col) is the input x[k_taps[k].offset + row W + col] of
// its batch, where offset = c H W + dy W + dx for the channel c and the spatial tap (dy, dx) =
// offsets[k_taps[k].tap], and zero where (row + dy, col + dx) is outside the image (masked loads:
// nothing outside x is read; each tile works out the masks of every spatial tap once). The
// weights are tap-major (op::half16_weight_k): the elements of tap t are the channels c, in
// column t Ip + c, and an odd channel count's last pair has a zero partner. A register tile is NCO
// <= 8 columns x NPX <= 3 vectors of 16 pixels (24 accumulators, 3 operands and a broadcast in the
// 32 registers).
//   - Convolution (stride 1): rows are output rows; k = (ky, kx, c), tap ky kw + kx with offset
//     (ky - pad, kx - pad); y (B, N, Ho, Wo).
//   - Transposed 2x2 stride 2: rows are input rows, k = c, one tap (0, 0); column n = o 4 + 2 dy
//     + dx goes to y[b, o, 2 row + dy, 2 col + dx]; columns n (dx = 0) and n + 1 (dx = 1) are
//     stored interleaved.
//
// Everything here is in an unnamed namespace and calls no library function: the AVX-512 copy's
// code must not be merged by the linker with a copy that other CPUs run (an inline function
// compiled with AVX-512 flags and picked for the whole program would fault on them).
#pragma once

#include <cstdint>

namespace pillarseg::cpu {

// Element k of the GEMM's K: see above. tap == the number of spatial taps marks the partner of a
// tap's last channel when the channel count is odd (always zero).
struct KTap {
  std::int64_t offset = 0;
  std::int64_t column = 0;  // in the weights' rows; even for the first of a pair
  std::int32_t tap = 0;
};
// A spatial tap (dy, dx): the input pixel (row + dy, col + dx) of the output pixel (row, col).
struct TapOffset {
  std::int32_t dy = 0;
  std::int32_t dx = 0;
};
inline constexpr int kMaxTaps = 49;  // kernels up to 7 x 7

// One convolution for the micro-kernel: plain data, so that the AVX-512 translation unit needs
// no library types.
struct Bf16Gemm {
  const std::uint16_t* x = nullptr;  // BF16 input (B, C, H, W)
  std::int64_t batch = 0, x_batch_stride = 0, height = 0, width = 0;
  const KTap* k_taps = nullptr;  // k entries, an even count
  std::int64_t k = 0;
  const TapOffset* offsets = nullptr;  // taps <= kMaxTaps entries
  int taps = 0;
  const std::uint16_t* w = nullptr;  // (columns, kp) BF16, tap-major
  std::int64_t kp = 0, columns = 0;
  const float* bias = nullptr;  // (columns)
  bool relu = false;
  bool transposed = false;
  void* y = nullptr;  // FP32 or (y_bf16) BF16
  bool y_bf16 = false;
  std::int64_t rows = 0, row_pixels = 0;                       // the GEMM's pixel grid of a batch
  std::int64_t out_height = 0, out_width = 0, out_planes = 0;  // y (B, out_planes, ...)
};

// Work items: (batch, row, block of kColumnBlock columns), in that order.
inline constexpr std::int64_t kColumnBlock = 64;

// Items [begin, end) on the AVX-512 instructions (bf16_conv_avx512.cpp).
void bf16_gemm_rows_avx512(const Bf16Gemm& g, std::int64_t begin, std::int64_t end);

namespace {

inline std::int64_t gemm_items(const Bf16Gemm& g) {
  return g.batch * g.rows * ((g.columns + kColumnBlock - 1) / kColumnBlock);
}

// Bits of the lanes i < count with 0 <= start + i < width (count <= 16).
inline std::uint32_t lane_mask(std::int64_t start, std::int64_t width, std::int64_t count) {
  const std::int64_t lo = start < 0 ? -start : 0;
  std::int64_t hi = width - start;
  if (hi > count) hi = count;
  if (hi <= lo) return 0;
  return ((std::uint32_t{1} << hi) - 1) & ~((std::uint32_t{1} << lo) - 1);
}

inline std::uint32_t first_lanes(std::int64_t count) {
  return count >= 32 ? ~std::uint32_t{0} : (std::uint32_t{1} << count) - 1;
}

// One register tile: columns [n0, n0 + NCO), pixels [x0, x0 + 16 NPX) of `row` (those before
// row_pixels) of batch b.
template <class Isa, int NCO, int NPX>
void gemm_tile(const Bf16Gemm& g, std::int64_t b, std::int64_t row, std::int64_t n0,
               std::int64_t x0) {
  using Acc = typename Isa::Acc;
  using Pair = typename Isa::Pair;
  std::int64_t count[NPX];
#pragma GCC unroll 4
  for (int p = 0; p < NPX; ++p) {
    const std::int64_t left = g.row_pixels - (x0 + 16 * p);
    count[p] = left < 16 ? left : 16;
  }
  Acc acc[NCO][NPX];
#pragma GCC unroll 8
  for (int c = 0; c < NCO; ++c)
#pragma GCC unroll 4
    for (int p = 0; p < NPX; ++p) acc[c][p] = Isa::zero();
  // The masks of every spatial tap (and the all-zero one of the padding element).
  std::uint32_t masks[kMaxTaps + 1][NPX];
  for (int t = 0; t < g.taps; ++t) {
    const std::int64_t r = row + g.offsets[t].dy;
    const bool inside = r >= 0 && r < g.height;
#pragma GCC unroll 4
    for (int p = 0; p < NPX; ++p) {
      masks[t][p] = inside ? lane_mask(x0 + 16 * p + g.offsets[t].dx, g.width, count[p]) : 0;
    }
  }
#pragma GCC unroll 4
  for (int p = 0; p < NPX; ++p) masks[g.taps][p] = 0;
  const std::uint16_t* x = g.x + b * g.x_batch_stride;
  const std::uint16_t* w = g.w + n0 * g.kp;
  const KTap* k_taps = g.k_taps;
  const std::int64_t k_end = g.k, kp = g.kp, pixel0 = row * g.width + x0;
  for (std::int64_t k = 0; k < k_end; k += 2) {
    const KTap t0 = k_taps[k], t1 = k_taps[k + 1];
    Pair a[NPX];
#pragma GCC unroll 4
    for (int p = 0; p < NPX; ++p) {
      a[p] = Isa::load_pairs(x, t0.offset + pixel0 + 16 * p, masks[t0.tap][p],
                             t1.offset + pixel0 + 16 * p, masks[t1.tap][p]);
    }
#pragma GCC unroll 8
    for (int c = 0; c < NCO; ++c) {
      const Pair weights = Isa::broadcast_pair(w + c * kp + t0.column);
#pragma GCC unroll 4
      for (int p = 0; p < NPX; ++p) acc[c][p] = Isa::dot(acc[c][p], a[p], weights);
    }
  }
#pragma GCC unroll 8
  for (int c = 0; c < NCO; ++c)
#pragma GCC unroll 4
    for (int p = 0; p < NPX; ++p) acc[c][p] = Isa::bias_act(acc[c][p], g.bias[n0 + c], g.relu);
  if (!g.transposed) {
#pragma GCC unroll 8
    for (int c = 0; c < NCO; ++c) {
      const std::int64_t base =
          ((b * g.out_planes + n0 + c) * g.out_height + row) * g.out_width + x0;
#pragma GCC unroll 4
      for (int p = 0; p < NPX; ++p) {
        if (g.y_bf16) {
          Isa::store_bf16(static_cast<std::uint16_t*>(g.y) + base + 16 * p, acc[c][p],
                          first_lanes(count[p]));
        } else {
          Isa::store_f32(static_cast<float*>(g.y) + base + 16 * p, acc[c][p],
                         first_lanes(count[p]));
        }
      }
    }
    return;
  }
  if constexpr (NCO % 2 == 0) {
#pragma GCC unroll 8
    for (int c = 0; c < NCO; c += 2) {
      const std::int64_t n = n0 + c, o = n / 4, dy = (n % 4) / 2;
      const std::int64_t base =
          ((b * g.out_planes + o) * g.out_height + 2 * row + dy) * g.out_width + 2 * x0;
#pragma GCC unroll 4
      for (int p = 0; p < NPX; ++p) {
        if (g.y_bf16) {
          Isa::store_bf16_interleaved(static_cast<std::uint16_t*>(g.y) + base + 32 * p, acc[c][p],
                                      acc[c + 1][p], first_lanes(2 * count[p]));
        } else {
          Isa::store_f32_interleaved(static_cast<float*>(g.y) + base + 32 * p, acc[c][p],
                                     acc[c + 1][p], first_lanes(2 * count[p]));
        }
      }
    }
  }
}

// fn.template operator()<N>() for N = n, First <= n <= Last (n beyond Last as Last): the switch
// from a run-time count to the register tiles' compile-time sizes.
template <int First, int Last, class Fn>
void with_count(std::int64_t n, Fn&& fn) {
  if constexpr (First < Last) {
    if (n > First) {
      with_count<First + 1, Last>(n, fn);
      return;
    }
  }
  fn.template operator()<First>();
}

template <class Isa>
void gemm_tile_any(const Bf16Gemm& g, std::int64_t b, std::int64_t row, std::int64_t n0,
                   std::int64_t x0, std::int64_t columns, std::int64_t vectors) {
  with_count<1, 8>(columns, [&]<int NCO>() {
    with_count<1, 3>(vectors, [&]<int NPX>() { gemm_tile<Isa, NCO, NPX>(g, b, row, n0, x0); });
  });
}

// Items [begin, end) (bf16_gemm_items): within one, the columns of its block eight at a time,
// and for each the row's pixels 48 at a time, so that the eight columns' weights stay in cache
// while the row streams past them.
template <class Isa>
void gemm_rows(const Bf16Gemm& g, std::int64_t begin, std::int64_t end) {
  const std::int64_t blocks = (g.columns + kColumnBlock - 1) / kColumnBlock;
  for (std::int64_t item = begin; item < end; ++item) {
    const std::int64_t block = item % blocks, row = item / blocks % g.rows,
                       b = item / blocks / g.rows;
    const std::int64_t n_end =
        (block + 1) * kColumnBlock < g.columns ? (block + 1) * kColumnBlock : g.columns;
    for (std::int64_t n0 = block * kColumnBlock; n0 < n_end; n0 += 8) {
      const std::int64_t columns = n_end - n0 < 8 ? n_end - n0 : 8;
      for (std::int64_t x0 = 0; x0 < g.row_pixels; x0 += 48) {
        const std::int64_t left = g.row_pixels - x0;
        const std::int64_t vectors = left > 32 ? 3 : left > 16 ? 2 : 1;
        gemm_tile_any<Isa>(g, b, row, n0, x0, columns, vectors);
      }
    }
  }
}

}  // namespace
}  // namespace pillarseg::cpu
