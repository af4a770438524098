// The INT8 convolution's products on AMX-INT8 tiles, written once over a tile interface `Tiles`
// and compiled twice: on the AMX instructions (AmxInt8Tiles in int8_conv_avx512.cpp, built with
// -mamx-tile -mamx-int8, called only where amx_int8_available) and on EmulatedAmxInt8Tiles
// (int8_isa_emulated.hpp), which the tests run on every CPU. The quantization and the epilogue
// are the VNNI micro-kernel's (int8_microkernel.hpp), the same quads xq[b][row][cq][col][4].
//
// Why TDPBSUD (signed A x unsigned B) and not TDPBUSD: the unsigned operand is the quantized
// input, and as the B tile its rows are channel quads and its 16 dwords 16 pixels, which is the
// quads' layout as it lies in memory (row k of B = quad cq0 + k at stride quad_stride), and C's
// rows are output channels over 16 pixels, NCHW's order; TDPBUSD would need the input as A,
// pixels by rows with 64 channels contiguous, and C transposed before the store. Both are
// AMX-INT8 (CPUID leaf 7 EDX bit 25) with the same arithmetic.
//
// One step of the products, for 32 columns x 32 pixels and 16 channel quads of one tap, palette
// 1, every tile 16 rows of 64 bytes:
//   A (tmm4, tmm5)  row m = column n0 + m (n0 + 16 + m): the 64 weight bytes of quads cq0..cq0 +
//                   15 of tap t, from the Amx packing w[n][tap][cq][4] (the columns padded to a
//                   multiple of 32 and the quads to 16 with zeros), row stride taps quads 4;
//   B (tmm6, tmm7)  row k = quad cq0 + k of pixels x0.. (x0 + 16..) of the tap's input row;
//   C (tmm0..tmm3)  (A4, B6), (A4, B7), (A5, B6), (A5, B7): int32 column x pixel, stored to a
//                   32 x 32 block that the epilogue reads.
// A band (batch, rows [row_begin, row_end)) as int8_microkernel.hpp's, by groups of 32 columns:
// each group over the band's rows, each row's pixels 32 at a time (16 at its end, and where one
// of the two vectors' windows is idle).
// Like the micro-kernel's, this code is in an unnamed namespace and calls no library function.
#pragma once

#include <cstdint>

#include "engine/cpu/int8_microkernel.hpp"

namespace pillarseg::cpu {

inline constexpr std::int64_t kInt8AmxColumns = 32;  // columns of a group (two A tiles)
inline constexpr std::int64_t kInt8AmxQuads = 16;    // channel quads of one TDPBSUD

// The band (b, rows [row_begin, row_end)) on the tiles (int8_conv_avx512.cpp, where the build has
// AMX).
void int8_gemm_band_amx(const Int8Gemm& g, std::int64_t b, std::int64_t row_begin,
                        std::int64_t row_end);

namespace {

// The LDTILECFG memory layout: palette, start row, 14 reserved bytes, 16 colsb words, 16 rows.
struct alignas(64) AmxInt8TileConfig {
  std::uint8_t palette = 1;
  std::uint8_t start_row = 0;
  std::uint8_t reserved[14] = {};
  std::uint16_t colsb[16] = {};
  std::uint8_t rows[16] = {};
};
static_assert(sizeof(AmxInt8TileConfig) == 64);

inline AmxInt8TileConfig amx_int8_config() {
  AmxInt8TileConfig c;
  for (int t = 0; t < 8; ++t) c.colsb[t] = 64, c.rows[t] = 16;
  return c;
}

// C[m][16 j + lane] for the columns n0 + m (m < 32) and the pixels x0 + 16 j + lane (j < NPX)
// into c (32 x 32 int32), then the epilogue; over the channel quads from cq_begin on (0, or for
// windows idle in the leading idle_quads, a multiple of 16 here, the quads after them on top of
// the idle accumulators).
template <class Isa, class Tiles, int NPX>
void amx_tile(const Int8Gemm& g, std::int64_t b, std::int64_t row, std::int64_t n0, std::int64_t x0,
              std::int64_t cq_begin) {
  using Acc = typename Isa::Acc;
  const std::int64_t k_bytes = g.taps * g.quads * 4;  // A's row stride
  const std::uint8_t* x_row = g.xq + (b * g.batch_stride + row * g.row_stride - g.origin) + 4 * x0;
  const std::int64_t columns = g.columns - n0 < 32 ? g.columns - n0 : 32;
  alignas(64) std::int32_t c[32][32];
  if (cq_begin > 0) {
    for (std::int64_t m = 0; m < 32; ++m) {
      const std::int32_t idle = m < columns ? g.idle[b * g.columns + n0 + m] : 0;
      for (int j = 0; j < 32; ++j) c[m][j] = idle;
    }
    Tiles::template load<0>(&c[0][0], 128);
    Tiles::template load<2>(&c[16][0], 128);
    if constexpr (NPX > 1) {
      Tiles::template load<1>(&c[0][16], 128);
      Tiles::template load<3>(&c[16][16], 128);
    }
  } else {
    Tiles::template zero<0>();
    Tiles::template zero<2>();
    if constexpr (NPX > 1) {
      Tiles::template zero<1>();
      Tiles::template zero<3>();
    }
  }
  for (std::int64_t m = 0; m < columns; m += g.transposed ? 2 : 1)
    prefetch_column<Isa, NPX>(g, b, row, n0 + m, x0);
  for (int t = 0; t < g.taps; ++t) {
    const std::int8_t* w = g.w + n0 * k_bytes + t * g.quads * 4;
    const std::uint8_t* x = x_row + g.tap_offsets[t];
    for (std::int64_t cq = cq_begin; cq < g.quads; cq += kInt8AmxQuads) {
      Tiles::template load<4>(w + 4 * cq, k_bytes);
      Tiles::template load<5>(w + 16 * k_bytes + 4 * cq, k_bytes);
      Tiles::template load<6>(x + cq * g.quad_stride, g.quad_stride);
      Tiles::template dot<0, 4, 6>();
      Tiles::template dot<2, 5, 6>();
      if constexpr (NPX > 1) {
        Tiles::template load<7>(x + cq * g.quad_stride + 64, g.quad_stride);
        Tiles::template dot<1, 4, 7>();
        Tiles::template dot<3, 5, 7>();
      }
    }
  }
  Tiles::template store<0>(&c[0][0], 128);
  Tiles::template store<2>(&c[16][0], 128);
  if constexpr (NPX > 1) {
    Tiles::template store<1>(&c[0][16], 128);
    Tiles::template store<3>(&c[16][16], 128);
  }
  for (std::int64_t m = 0; m < columns; ++m) {
    Acc acc[NPX];
#pragma GCC unroll 2
    for (int p = 0; p < NPX; ++p) acc[p] = Isa::load_acc(&c[m][16 * p]);
    if (!g.transposed) {
      store_column<Isa, NPX>(g, b, row, n0 + m, x0, acc);
    } else if (m % 2 == 0) {
      Acc odd[NPX];
#pragma GCC unroll 2
      for (int p = 0; p < NPX; ++p) odd[p] = Isa::load_acc(&c[m + 1][16 * p]);
      store_column_pair<Isa, NPX>(g, b, row, n0 + m, x0, acc, odd);
    }
  }
}

// The band, the tiles configured for the calling thread around it (LDTILECFG, TILERELEASE).
template <class Isa, class Tiles>
void amx_band(const Int8Gemm& g, std::int64_t b, std::int64_t row_begin, std::int64_t row_end) {
  Tiles::configure(amx_int8_config());
  for (std::int64_t n0 = 0; n0 < g.columns; n0 += kInt8AmxColumns) {
    for (std::int64_t row = row_begin; row < row_end; ++row) {
      for (std::int64_t x0 = 0; x0 < g.row_pixels; x0 += 32) {
        const int vectors = g.row_pixels - x0 > 16 ? 2 : 1;
        // The vectors whose windows hold a busy pixel (int8_microkernel.hpp) over every quad, the
        // idle ones over the quads after idle_quads.
        const std::uint32_t busy = int8_busy_vectors(g, b, row, x0, vectors);
        if (vectors == 2 && (busy == 3 || busy == 0)) {
          amx_tile<Isa, Tiles, 2>(g, b, row, n0, x0, busy == 0 ? g.idle_quads : 0);
          continue;
        }
        for (int p = 0; p < vectors; ++p) {
          amx_tile<Isa, Tiles, 1>(g, b, row, n0, x0 + 16 * p,
                                  (busy >> p & 1u) != 0 ? 0 : g.idle_quads);
        }
      }
    }
  }
  Tiles::release();
}

}  // namespace
}  // namespace pillarseg::cpu
