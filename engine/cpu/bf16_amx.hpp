// The Winograd F(2x2, 3x3) products (bf16_winograd.hpp) on AMX-BF16 tiles, written once over a
// tile interface `Tiles` and compiled twice: on the AMX instructions (AmxTiles in
// bf16_conv_avx512.cpp, built with -mamx-tile -mamx-bf16 and called only where the CPU has them
// and Linux has granted this process the tile data state) and on EmulatedAmxTiles
// (bf16_isa_emulated.hpp), an exact scalar model of the instructions after the Intel SDM, which the
// tests run on every CPU so that a layout or indexing mistake fails on machines without AMX too.
//
// The GEMM of one frequency p: M_p (16 output channels x 16 tiles) += U_p (16 channels x 32 input
// channels) . V_p (32 input channels x 16 tiles) is one TDPBF16PS on three tiles of 16 rows of 64
// bytes, palette 1:
//   A (tmm3)        row m = output channel o0 + m: 16 pairs (c, c + 1) of U_p's row, the row
//                   stride that of U (channel_pairs pairs), as U is already laid out;
//   B (tmm4..tmm6)  row k = channel pair k: 16 tiles' pairs (V's VNNI layout, as VDPBF16PS reads
//                   it too), the row stride that of V (block_tiles pairs);
//   C (tmm0..tmm2)  row m = output channel, 16 FP32 for 16 tiles, stored into M (16, 16, 48).
// A group of 16 output channels x 48 tiles keeps three accumulators, one A and three B tiles
// (7 of the 8 registers): for each block of 16 channel pairs, one load of A and three of B feed
// three TDPBF16PS. channel_pairs and the rows of U are multiples of 16 (zero padded:
// conv3x3_winograd_forward), so every tile is full; tiles past the block's count are zero in V.
// Like the micro-kernel's, this code is in an unnamed namespace and calls no library function
// (bf16_microkernel.hpp says why).
//
// Arithmetic: per the SDM's pseudo-code, TDPBF16PS accumulates into each C element the products
// of the pairs in order, the even element's before the odd one's, each an FMA rounded to nearest
// even, BF16 denormals and a denormal accumulator read as zero, denormal results flushed to zero
// (the products of two BF16 values are exact in FP32, so each step is one rounding of a sum).
// VDPBF16PS takes the odd element first, and Intel documents the tile instruction's internal
// order less firmly than the vector one's (later SDM editions sum the even and the odd products
// apart before adding them to C), so the AMX path's bits are not the AVX-512 path's, and the
// tests hold the hardware to the rounding bound of any order rather than to this model's bits.
#pragma once

#include <cstdint>

#include "engine/cpu/bf16_winograd.hpp"

namespace pillarseg::cpu {

inline constexpr std::int64_t kAmxGroupColumns = 16;  // output channels per group
inline constexpr std::int64_t kAmxPairs = 16;         // channel pairs per TDPBF16PS

namespace {

// The palette-1 configuration of every tile the products use: 16 rows of 64 bytes (the LDTILECFG
// memory layout: palette, start row, 14 reserved bytes, 16 colsb words, 16 row bytes).
struct alignas(64) AmxTileConfig {
  std::uint8_t palette = 1;
  std::uint8_t start_row = 0;
  std::uint8_t reserved[14] = {};
  std::uint16_t colsb[16] = {};
  std::uint8_t rows[16] = {};
};

inline AmxTileConfig amx_products_config() {
  AmxTileConfig c;
  for (int t = 0; t < 7; ++t) c.colsb[t] = 64, c.rows[t] = 16;
  return c;
}
static_assert(sizeof(AmxTileConfig) == 64);

// M[p][c][16 j + lane] = U_p[o0 + c] . V_p[tiles tl0 + 16 j + lane] for c < 16, j < NPX.
template <class Tiles, int NPX>
void winograd_amx_gemm(const Bf16Winograd& g, const std::uint16_t* v, std::int64_t o0,
                       std::int64_t tl0, float* m) {
  const std::int64_t pairs = g.channel_pairs;
  const std::int64_t u_stride = pairs * 4, v_stride = g.block_tiles * 4;  // bytes a row
  const std::int64_t m_stride = kWinogradGroupTiles * 4;
  for (int p = 0; p < 16; ++p) {
    const std::uint16_t* vp = v + p * pairs * g.block_tiles * 2 + 2 * tl0;
    const std::uint16_t* up = g.u + (p * g.u_rows + o0) * pairs * 2;
    Tiles::template zero<0>();
    if constexpr (NPX > 1) Tiles::template zero<1>();
    if constexpr (NPX > 2) Tiles::template zero<2>();
    for (std::int64_t k = 0; k < pairs; k += kAmxPairs) {
      const std::uint16_t* vk = vp + k * g.block_tiles * 2;
      Tiles::template load<3>(up + 2 * k, u_stride);
      Tiles::template load<4>(vk, v_stride);
      Tiles::template dot<0, 3, 4>();
      if constexpr (NPX > 1) {
        Tiles::template load<5>(vk + 32, v_stride);
        Tiles::template dot<1, 3, 5>();
      }
      if constexpr (NPX > 2) {
        Tiles::template load<6>(vk + 64, v_stride);
        Tiles::template dot<2, 3, 6>();
      }
    }
    float* mp = m + p * kAmxGroupColumns * kWinogradGroupTiles;
    Tiles::template store<0>(mp, m_stride);
    if constexpr (NPX > 1) Tiles::template store<1>(mp + 16, m_stride);
    if constexpr (NPX > 2) Tiles::template store<2>(mp + 32, m_stride);
  }
}

// The products for winograd_blocks: groups of 16 output channels (all 16 rows computed; rows past
// O are U's zero padding and never read back).
template <class Tiles>
struct WinogradAmxProducts {
  static constexpr int kColumns = kAmxGroupColumns;
  static void run(const Bf16Winograd& g, const std::uint16_t* v, std::int64_t o0, std::int64_t,
                  std::int64_t tl0, std::int64_t vectors, float* m) {
    with_count<1, 3>(vectors, [&]<int NPX>() { winograd_amx_gemm<Tiles, NPX>(g, v, o0, tl0, m); });
  }
};

// winograd_blocks with the products on tiles, the tiles configured for the calling thread around
// it (LDTILECFG, TILERELEASE).
template <class Isa, class Tiles>
void winograd_blocks_amx(const Bf16Winograd& g, std::int64_t begin, std::int64_t end, int thread) {
  Tiles::configure(amx_products_config());
  winograd_blocks<Isa, WinogradAmxProducts<Tiles>>(g, begin, end, thread);
  Tiles::release();
}

}  // namespace
}  // namespace pillarseg::cpu
