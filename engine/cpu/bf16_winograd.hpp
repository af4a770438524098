// The CPU's BF16 3x3 convolutions (stride 1, pad 1) by Winograd's minimal filtering F(2x2, 3x3)
// (Lavin & Gray, 2016), written once over an instruction set `Isa` like the direct micro-kernel
// (bf16_microkernel.hpp) and compiled twice: on AVX512_BF16 (bf16_conv_avx512.cpp) and on the
// exact scalar model of the instructions (bf16_isa_emulated.hpp, in bf16_conv.cpp).
//
// Each 2x2 output tile (ty, tx) comes from the 4x4 input tile d at rows 2 ty - 1.., columns
// 2 tx - 1.. (zero outside the image):
//   Y = A^T [sum_c U_oc . V_c] A,  U_oc = G g_oc G^T,  V_c = B^T d_c B,
//   B^T = [1 0 -1 0; 0 1 1 0; 0 -1 1 0; 0 1 0 -1],  G = [1 0 0; 1/2 1/2 1/2; 1/2 -1/2 1/2; 0 0 1],
//   A^T = [1 1 1 0; 0 1 -1 -1],
// 16 multiplies per tile and channel pair instead of 36. Why F(2x2) and not the FP32 path's
// F(4x4): V and U are rounded to BF16 (8 significant bits); F(2x2)'s transforms only add and
// halve, so the rounding of V and U adds about half again to the direct BF16 convolution's error
// (relative RMS 0.38% against 0.24% on a 128-channel layer), where F(4x4)'s coefficients (up to
// 5 in B, 8 in A) make it about nine times larger (2.2%).
//
// Arithmetic. The input transform adds BF16 values in FP32 (exact unless their exponents differ
// by more than 14) and rounds V once to BF16 (round to nearest even, denormals to zero, as
// VCVTNEPS2BF16); U comes from the prepared BF16 weights (BatchNorm folded in) in double,
// rounded once (bf16_conv.cpp); the 16 products M_p = sum_c U_p V_p are VDPBF16PS in FP32 over
// the channel pairs in order; the output transform adds M in FP32 in a fixed order, then the bias
// and the ReLU, and rounds once for a BF16 output. The transforms are the instruction
// interface's adds and subtractions only (16 tiles a vector: two loads of 16 BF16 word pairs
// give the four columns of a tile row, as shifted and masked words), with no multiply that a
// compiler could contract into an FMA, so the two compilations give the same bits, and the tests
// compare them bit for bit.
//
// Layout and blocking. The tiles of an image are taken in row-major order (ty, tx) in blocks of
// `block_tiles` (a multiple of 48; the last block of an image may be shorter), each block by one
// thread from its input transform to its output: V (16, channel pairs, block_tiles, 2) in BF16,
// pairs (c, c + 1) interleaved as VDPBF16PS reads them, sized to stay in a core's L2; then for
// each group of 8 output channels and 48 tiles, the 16 products in a register tile of 8 channels
// x 3 vectors of 16 tiles (24 accumulators) into M (16, 8, 48) FP32 (in L1), and that group's
// output transform. U (16, O, channel pairs, 2) is read from every block. On AMX-BF16 the
// products of a group of 16 output channels run on the tiles instead (bf16_amx.hpp), the
// transforms as here; U's rows and the channel pairs are then zero padded to multiples of 16.
#pragma once

#include <cstdint>

#include "engine/cpu/bf16_microkernel.hpp"

namespace pillarseg::cpu {

struct Bf16Winograd {
  const std::uint16_t* x = nullptr;  // BF16 input (B, C, H, W)
  std::int64_t batch = 0, channels = 0, height = 0, width = 0;
  std::int64_t channel_pairs = 0;    // ceil(C / 2) (AMX: rounded up to 16)
  const std::uint16_t* u = nullptr;  // (16, u_rows, channel_pairs, 2) BF16, zero for c >= C
  std::int64_t out_channels = 0;
  std::int64_t u_rows = 0;      // O (AMX: rounded up to 16, the rows beyond O zero)
  const float* bias = nullptr;  // (O)
  bool relu = false;
  void* y = nullptr;  // (B, O, H, W), FP32 or (y_bf16) BF16
  bool y_bf16 = false;
  std::int64_t tiles_h = 0, tiles_w = 0;  // ceil(H / 2), ceil(W / 2)
  std::int64_t block_tiles = 0;           // a multiple of 48
  // Per thread t: v + t v_stride words, m + t m_stride floats.
  std::uint16_t* v = nullptr;
  float* m = nullptr;
  std::int64_t v_stride = 0, m_stride = 0;
};

inline constexpr std::int64_t kWinogradGroupTiles = 48;  // 3 vectors of 16 tiles
inline constexpr std::int64_t kWinogradGroupColumns = 8;

// Scratch sizes per thread.
inline std::int64_t winograd_v_words(std::int64_t channel_pairs, std::int64_t block_tiles) {
  return 16 * channel_pairs * block_tiles * 2;
}
inline std::int64_t winograd_m_floats(std::int64_t group_columns) {  // with one vector of slack
  return 16 * group_columns * kWinogradGroupTiles + 16;
}

// Blocks [begin, end) of the batch's images (block j of image b is item b blocks + j) on the
// AVX-512 instructions, with the scratch of thread `thread` (bf16_conv_avx512.cpp).
void bf16_winograd_blocks_avx512(const Bf16Winograd& g, std::int64_t begin, std::int64_t end,
                                 int thread);
// The same with the products on AMX-BF16 tiles (bf16_amx.hpp; channel_pairs and u_rows multiples
// of 16, M groups of kAmxGroupColumns), in bf16_conv_avx512.cpp where the build has AMX.
void bf16_winograd_blocks_amx(const Bf16Winograd& g, std::int64_t begin, std::int64_t end,
                              int thread);

namespace {

inline std::int64_t winograd_blocks_per_image(const Bf16Winograd& g) {
  const std::int64_t tiles = g.tiles_h * g.tiles_w;
  return (tiles + g.block_tiles - 1) / g.block_tiles;
}

// Bits i < count (<= 32) of the words with 0 <= start + i < width.
inline std::uint32_t winograd_word_mask(std::int64_t start, std::int64_t width,
                                        std::int64_t count) {
  const std::int64_t lo = start < 0 ? -start : 0;
  std::int64_t hi = width - start;
  if (hi > count) hi = count;
  if (hi <= lo) return 0;
  return static_cast<std::uint32_t>(((std::uint64_t{1} << hi) - 1) &
                                    ~((std::uint64_t{1} << lo) - 1));
}

inline std::uint32_t winograd_first_words(std::int64_t count) {
  return static_cast<std::uint32_t>((std::uint64_t{1} << count) - 1);
}

// Row i of B^T combines rows (first, second) of d as first + second (sum) or first - second:
// i = 0: d0 - d2, 1: d1 + d2, 2: d2 - d1, 3: d1 - d3.
struct WinogradPick {
  int first, second;
  bool sum;
};
inline constexpr WinogradPick kWinogradPick[4] = {
    {0, 2, false}, {1, 2, true}, {2, 1, false}, {1, 3, false}};

template <class Isa>
typename Isa::Acc winograd_combine(const typename Isa::Acc& a, const typename Isa::Acc& b,
                                   bool sum) {
  return sum ? Isa::add(a, b) : Isa::sub(a, b);
}

// h[j] = (d_r B)[j] for row r = iy of the plane (null, or iy outside the image: zeros) over 16
// tiles whose inputs start at column x0 (d_r[j] of lane i = x(iy, x0 + 2 i + j)): two loads of
// 16 word pairs, x0 and x0 + 2, zero outside the row.
template <class Isa>
void winograd_input_row(const Bf16Winograd& g, const std::uint16_t* plane, std::int64_t iy,
                        std::int64_t x0, std::int64_t lanes, typename Isa::Acc* h) {
  using Acc = typename Isa::Acc;
  if (plane == nullptr || iy < 0 || iy >= g.height) {
    for (int j = 0; j < 4; ++j) h[j] = Isa::zero();
    return;
  }
  const std::uint16_t* row = plane + iy * g.width;
  const auto a = Isa::load_words_masked(row, x0, winograd_word_mask(x0, g.width, 2 * lanes));
  const auto b =
      Isa::load_words_masked(row, x0 + 2, winograd_word_mask(x0 + 2, g.width, 2 * lanes));
  const Acc d0 = Isa::even_words(a), d1 = Isa::odd_words(a);
  const Acc d2 = Isa::even_words(b), d3 = Isa::odd_words(b);
  h[0] = Isa::sub(d0, d2);
  h[1] = Isa::add(d1, d2);
  h[2] = Isa::sub(d2, d1);
  h[3] = Isa::sub(d1, d3);
}

// V[p][cp][tl] (pairs of channels 2 cp, 2 cp + 1) of image b over the block's tiles [t0, t0 +
// count) (tl = t - t0), and zero pairs for tl in [count, count rounded up to 16). For each run of
// tiles in one tile row, 16 tiles at a time: the rows (first, second) of B^T's row i for both
// channels, then V_ij = B^T's row i of (d B)[j], rounded to BF16 and stored as pairs.
template <class Isa>
void winograd_input_pair(const Bf16Winograd& g, std::int64_t b, std::int64_t cp, std::int64_t t0,
                         std::int64_t count, std::uint16_t* v) {
  using Acc = typename Isa::Acc;
  const std::int64_t p_stride = g.channel_pairs * g.block_tiles * 2;  // in words
  std::uint16_t* vc = v + cp * g.block_tiles * 2;
  const std::int64_t padded = (count + 15) / 16 * 16;
  if (padded > count) {
    for (int p = 0; p < 16; ++p) {
      for (std::int64_t w = 2 * count; w < 2 * padded; ++w) vc[p * p_stride + w] = 0;
    }
  }
  const std::int64_t plane_size = g.height * g.width, c0 = 2 * cp;
  // Pairs past the channels (AMX's padding to 16 pairs) are zero, as is an odd count's partner.
  const std::uint16_t* planes[2] = {nullptr, nullptr};
  if (c0 < g.channels) planes[0] = g.x + (b * g.channels + c0) * plane_size;
  if (c0 + 1 < g.channels) planes[1] = planes[0] + plane_size;
  for (std::int64_t tl = 0; tl < count;) {
    // A run of tiles in one tile row: tiles tx0 .. tx0 + n - 1 of row ty.
    const std::int64_t t = t0 + tl, ty = t / g.tiles_w, tx0 = t % g.tiles_w;
    const std::int64_t n = (g.tiles_w - tx0) < (count - tl) ? (g.tiles_w - tx0) : (count - tl);
    for (std::int64_t k = 0; k < n; k += 16) {
      const std::int64_t lanes = (n - k) < 16 ? (n - k) : 16;
      const std::int64_t x0 = 2 * (tx0 + k) - 1;
      const std::uint32_t mask = winograd_first_words(2 * lanes);
      std::uint16_t* out = vc + 2 * (tl + k);
#pragma GCC unroll 4
      for (int i = 0; i < 4; ++i) {
        const WinogradPick pick = kWinogradPick[i];
        Acc first[2][4], second[2][4];
        for (int ch = 0; ch < 2; ++ch) {
          winograd_input_row<Isa>(g, planes[ch], 2 * ty - 1 + pick.first, x0, lanes, first[ch]);
          winograd_input_row<Isa>(g, planes[ch], 2 * ty - 1 + pick.second, x0, lanes, second[ch]);
        }
#pragma GCC unroll 4
        for (int j = 0; j < 4; ++j) {
          Isa::store_bf16_interleaved(out + (4 * i + j) * p_stride,
                                      winograd_combine<Isa>(first[0][j], second[0][j], pick.sum),
                                      winograd_combine<Isa>(first[1][j], second[1][j], pick.sum),
                                      mask);
        }
      }
    }
    tl += n;
  }
}

// M[p][c][16 px + lane] = sum over the channel pairs of U_p[o0 + c] . V_p[tiles tl0 + 16 px +
// lane] for c < NCO, px < NPX.
template <class Isa, int NCO, int NPX>
void winograd_gemm_tile(const Bf16Winograd& g, const std::uint16_t* v, std::int64_t o0,
                        std::int64_t tl0, float* m) {
  using Acc = typename Isa::Acc;
  using Pair = typename Isa::Pair;
  const std::int64_t pairs = g.channel_pairs, pair_stride = g.block_tiles * 2;
  for (int p = 0; p < 16; ++p) {
    Acc acc[NCO][NPX];
#pragma GCC unroll 8
    for (int c = 0; c < NCO; ++c)
#pragma GCC unroll 4
      for (int px = 0; px < NPX; ++px) acc[c][px] = Isa::zero();
    const std::uint16_t* vp = v + p * pairs * pair_stride + 2 * tl0;
    const std::uint16_t* up = g.u + (p * g.u_rows + o0) * pairs * 2;
    for (std::int64_t cp = 0; cp < pairs; ++cp) {
      Pair a[NPX];
#pragma GCC unroll 4
      for (int px = 0; px < NPX; ++px) a[px] = Isa::load_words(vp + cp * pair_stride + 32 * px);
#pragma GCC unroll 8
      for (int c = 0; c < NCO; ++c) {
        const Pair weights = Isa::broadcast_pair(up + (c * pairs + cp) * 2);
#pragma GCC unroll 4
        for (int px = 0; px < NPX; ++px) acc[c][px] = Isa::dot(acc[c][px], a[px], weights);
      }
    }
#pragma GCC unroll 8
    for (int c = 0; c < NCO; ++c)
#pragma GCC unroll 4
      for (int px = 0; px < NPX; ++px)
        Isa::store_f32(m + (p * kWinogradGroupColumns + c) * kWinogradGroupTiles + 16 * px,
                       acc[c][px], 0xFFFFu);
  }
}

template <class Isa>
void winograd_gemm_tile_any(const Bf16Winograd& g, const std::uint16_t* v, std::int64_t o0,
                            std::int64_t columns, std::int64_t tl0, std::int64_t vectors,
                            float* m) {
  with_count<1, 8>(columns, [&]<int NCO>() {
    with_count<1, 3>(vectors,
                     [&]<int NPX>() { winograd_gemm_tile<Isa, NCO, NPX>(g, v, o0, tl0, m); });
  });
}

// y of the output channels o0 .. o0 + columns - 1 over the block's tiles t0 + tl0 .. + count - 1
// from M (winograd_gemm_tile), 16 tiles of a tile row at a time: Y = A^T M A, plus the bias,
// then the ReLU; output rows 2 ty and 2 ty + 1 as the interleaved Y[i][0], Y[i][1].
template <class Isa, int GroupColumns>
void winograd_output_group(const Bf16Winograd& g, std::int64_t b, std::int64_t o0,
                           std::int64_t columns, std::int64_t t0, std::int64_t tl0,
                           std::int64_t count, const float* m) {
  using Acc = typename Isa::Acc;
  const std::int64_t group = GroupColumns * kWinogradGroupTiles;  // floats per p
  for (std::int64_t k = 0; k < count;) {
    const std::int64_t t = t0 + tl0 + k, ty = t / g.tiles_w, tx0 = t % g.tiles_w;
    const std::int64_t n = (g.tiles_w - tx0) < (count - k) ? (g.tiles_w - tx0) : (count - k);
    for (std::int64_t kk = 0; kk < n; kk += 16) {
      const std::int64_t lanes = (n - kk) < 16 ? (n - kk) : 16, ox = 2 * (tx0 + kk);
      const std::int64_t pixels = (g.width - ox) < 2 * lanes ? (g.width - ox) : 2 * lanes;
      const std::uint32_t mask = winograd_first_words(pixels);
      for (std::int64_t c = 0; c < columns; ++c) {
        const std::int64_t o = o0 + c;
        const float* mc = m + c * kWinogradGroupTiles + k + kk;
        Acc s[2][4];  // A^T M
#pragma GCC unroll 4
        for (int j = 0; j < 4; ++j) {
          const Acc m0 = Isa::load_f32(mc + (0 * 4 + j) * group);
          const Acc m1 = Isa::load_f32(mc + (1 * 4 + j) * group);
          const Acc m2 = Isa::load_f32(mc + (2 * 4 + j) * group);
          const Acc m3 = Isa::load_f32(mc + (3 * 4 + j) * group);
          s[0][j] = Isa::add(Isa::add(m0, m1), m2);
          s[1][j] = Isa::sub(Isa::sub(m1, m2), m3);
        }
        for (int i = 0; i < 2; ++i) {
          const std::int64_t oy = 2 * ty + i;
          if (oy >= g.height) break;
          const Acc y0 =
              Isa::bias_act(Isa::add(Isa::add(s[i][0], s[i][1]), s[i][2]), g.bias[o], g.relu);
          const Acc y1 =
              Isa::bias_act(Isa::sub(Isa::sub(s[i][1], s[i][2]), s[i][3]), g.bias[o], g.relu);
          const std::int64_t at = ((b * g.out_channels + o) * g.height + oy) * g.width + ox;
          if (g.y_bf16) {
            Isa::store_bf16_interleaved(static_cast<std::uint16_t*>(g.y) + at, y0, y1, mask);
          } else {
            Isa::store_f32_interleaved(static_cast<float*>(g.y) + at, y0, y1, mask);
          }
        }
      }
    }
    k += n;
  }
}

// The products of the VDPBF16PS register tiles: groups of 8 output channels.
template <class Isa>
struct WinogradVectorProducts {
  static constexpr int kColumns = kWinogradGroupColumns;
  static void run(const Bf16Winograd& g, const std::uint16_t* v, std::int64_t o0,
                  std::int64_t columns, std::int64_t tl0, std::int64_t vectors, float* m) {
    winograd_gemm_tile_any<Isa>(g, v, o0, columns, tl0, vectors, m);
  }
};

// Items [begin, end) (winograd_blocks_per_image per image) with thread `thread`'s scratch: each
// block's input transform, then for each group of Products::kColumns output channels and 48
// tiles the products into M and the group's output transform.
template <class Isa, class Products = WinogradVectorProducts<Isa>>
void winograd_blocks(const Bf16Winograd& g, std::int64_t begin, std::int64_t end, int thread) {
  constexpr std::int64_t kColumns = Products::kColumns;
  const std::int64_t blocks = winograd_blocks_per_image(g), tiles = g.tiles_h * g.tiles_w;
  std::uint16_t* v = g.v + thread * g.v_stride;
  float* m = g.m + thread * g.m_stride;
  for (std::int64_t item = begin; item < end; ++item) {
    const std::int64_t b = item / blocks, t0 = item % blocks * g.block_tiles;
    const std::int64_t count = (tiles - t0) < g.block_tiles ? (tiles - t0) : g.block_tiles;
    for (std::int64_t cp = 0; cp < g.channel_pairs; ++cp)
      winograd_input_pair<Isa>(g, b, cp, t0, count, v);
    for (std::int64_t o0 = 0; o0 < g.out_channels; o0 += kColumns) {
      const std::int64_t columns =
          (g.out_channels - o0) < kColumns ? (g.out_channels - o0) : kColumns;
      for (std::int64_t tl0 = 0; tl0 < count; tl0 += kWinogradGroupTiles) {
        const std::int64_t n =
            (count - tl0) < kWinogradGroupTiles ? (count - tl0) : kWinogradGroupTiles;
        Products::run(g, v, o0, columns, tl0, (n + 15) / 16, m);
        winograd_output_group<Isa, kColumns>(g, b, o0, columns, t0, tl0, n, m);
      }
    }
  }
}

}  // namespace
}  // namespace pillarseg::cpu
