// The CPU's Winograd-domain INT8 3x3 convolution (stride 1, pad 1), F(2x2, 3x3), written once over
// the instruction set `Isa` of the direct micro-kernel (int8_microkernel.hpp) and compiled twice:
// on AVX512-VNNI (int8_conv_avx512.cpp) and on the scalar model EmulatedVnniIsa.
//
// Each 2x2 output tile (ty, tx) comes from the 4x4 input tile d at rows 2 ty - 1.., columns
// 2 tx - 1.. (zero outside the image): Y = A^T [sum_c U_oc . V_c] A with V_c = B^T d_c B and
// U_oc = G g_oc G^T (bf16_winograd.hpp has the matrices). Quantized in the Winograd domain as in
// LoWino (Li et al., 2021): V_p of each of the 16 positions p with its own per-tensor scale, U_p
// per position and output channel (su[p][o] = max over the input channels / 127). The input
// transform runs in 16-bit integers (int8_winograd_input_scales in int8_conv.hpp derives the
// constants from the calibrated scales): each input element to x16 = clamp(round_half_even(x
// r16), -8191, 8191) (NaN -> 0; r16 = 1 / s16 rounded to FP32, s16 = max_p sv / 64, so that the
// x16 grid is 64 times finer than the coarsest V's; min_p sv where the positions' scales differ
// 64-fold), V16 = B^T x16 B exactly (|V16| <= 4 8191 fits int16), then V_p = clamp((V16 m[p] +
// 2^14) >> 15, -127, 127) (VPMULHRSW: nearest, ties up) with the 15-bit multiplier m[p] =
// round(2^15 s16 / sv[p]), whose scale s16 2^15 / m[p] is the one the products are dequantized
// with (sv_eff). The FP32 transform spent 7 of its about 10 operations a V value on quantizing it;
// here that is one VPMULHRSW, the adds run on 32 tiles a vector, and each element is converted
// once a tile row (the two tiles of the row that read it share it). The products M_p = sum_c qU qV
// in INT32, M_p = float(acc) * (sv_eff[p] su[p][o]) (one rounding each); the output transform adds
// M in FP32 in a fixed order, then the bias and the ReLU, and rounds once for a BF16 output. Every
// step is exact integer arithmetic or one FP32 rounding, so the two compilations give the same
// bits, and the tests compare them bit for bit.
//
// Layout and blocking. A block is a run of `block_tiles` (a multiple of 16) tiles of one tile row
// of one image, taken by one thread from its input transform to its output: per quad of input
// channels, its 4 x 4 input rows' x16 in even and odd columns (x16_tiles int16 each, in L1), then
// V (16, quads, block_tiles, 4) in bytes, u = q + 128 of four channels a dword as the direct
// kernel's quads, 32 tiles a step (the tiles past the row's end are transformed from the zero
// padding and never stored); then for
// each group of 8 output channels and 32 tiles, the 16 products in a register tile of 8 channels
// x 2 vectors of 16 tiles into M (16, 8, 32) FP32, and that group's output transform, whose 16
// tiles a vector are 32 consecutive output columns of two rows. U (16, O / 8, quads, 8, 4) is
// read from every block (the Vnni packing's order, per position).
#pragma once

#include <cstdint>

#include "engine/cpu/int8_microkernel.hpp"

namespace pillarseg::cpu {

struct Int8Winograd {
  const void* x = nullptr;  // (B, C, H, W) FP32 or (x_bf16) BF16
  bool x_bf16 = false;
  std::int64_t batch = 0, channels = 0, height = 0, width = 0;
  float r16 = 0.0f;                          // 1 / s16: x16 = clamp(round(x r16), +-8191)
  const std::int16_t* multiplier = nullptr;  // (16): V_p = (V16 multiplier[p] + 2^14) >> 15
  const float* sv = nullptr;                 // (16): V_p's scale, s16 2^15 / multiplier[p]
  std::int64_t quads = 0;
  const std::int8_t* u = nullptr;                    // packed qU
  const float* su = nullptr;                         // (16, O)
  const std::int32_t* compensation = nullptr;        // (16, O)
  const float* bias = nullptr;                       // (O)
  std::int64_t out_channels = 0, column_groups = 0;  // O, ceil(O / 8)
  bool relu = false;
  void* y = nullptr;  // (B, O, H, W) FP32 or (y_bf16) BF16
  bool y_bf16 = false;
  std::int64_t tiles_h = 0, tiles_w = 0, block_tiles = 0, blocks_per_row = 0;
  // Per thread t: v + t v_stride bytes, m + t m_stride floats, x16 + t x16_stride int16 (64-byte
  // aligned); x16_tiles = block_tiles rounded up to 32, plus 32.
  std::uint8_t* v = nullptr;
  float* m = nullptr;
  std::int16_t* x16 = nullptr;
  std::int64_t v_stride = 0, m_stride = 0, x16_stride = 0, x16_tiles = 0;
};

// Tiles of a group: 2 vectors of 16 (16 accumulators; a 3-vector tile of 24, which the nested
// quad loop also keeps in registers, measured no faster: docs/benchmarks.md#int8).
inline constexpr std::int64_t kInt8WinogradGroupTiles = 32;
// How many quads ahead the input transform asks for its rows: the 16-bit transform waits on the
// rows' loads (perf: most of its samples after them), and 2 ahead ran 4-8% faster than 1 on the
// full-size Winograd layers (docs/benchmarks.md, 2026-12-06).
inline constexpr std::int64_t kInt8WinogradPrefetchQuads = 2;
// Quads of a run of the products' loop (int8_winograd_position).
inline constexpr std::int64_t kInt8WinogradQuadRun = 64;

// Blocks [begin, end) (block j of tile row r of image b is item (b tiles_h + r) blocks_per_row
// + j) on the AVX-512 instructions with the scratch of thread `thread` (int8_conv_avx512.cpp).
void int8_winograd_blocks_vnni(const Int8Winograd& g, std::int64_t begin, std::int64_t end,
                               int thread);

namespace {

// Row 0..3 of B^T d: the input rows (first, second) combined as first - second or first + second.
struct Int8WinogradPick {
  int first, second;
  bool sum;
};
inline constexpr Int8WinogradPick kInt8WinogradPick[4] = {
    {0, 2, false}, {1, 2, true}, {2, 1, false}, {1, 3, false}};

// The 64-lane mask of the columns x0.. inside the image.
inline std::uint64_t int8_winograd_column_mask(std::int64_t x0, std::int64_t width) {
  const std::int64_t lo = x0 < 0 ? -x0 : 0, hi = width - x0 < 64 ? width - x0 : 64;
  if (hi <= lo) return 0;
  const std::uint64_t below_hi = hi == 64 ? ~std::uint64_t{0} : (std::uint64_t{1} << hi) - 1;
  return below_hi & ~((std::uint64_t{1} << lo) - 1);
}

// x16 of the quad cq's input rows for the block (tile row ty of image b, tiles tx0..): for channel
// i < 4 and row r < 4 (input row 2 ty - 1 + r), the even and odd columns of the tiles' inputs,
// E[t] = x16(column 2 (tx0 + t) - 1), O[t] = x16(column 2 (tx0 + t)) for t <= block_tiles
// rounded up to 32 (32 a step, the one after them as scalars), at
// x16 + ((i 4 + r) 2 + {0: E, 1: O}) g.x16_tiles. Rows and channels outside the image are marked
// in `inside` and not converted.
template <class Isa>
void int8_winograd_quad_x16(const Int8Winograd& g, std::int64_t b, std::int64_t ty,
                            std::int64_t tx0, std::int64_t cq, std::int16_t* x16,
                            bool (&inside)[4][4]) {
  using I16 = typename Isa::I16;
  const std::int64_t plane_size = g.height * g.width;
  for (int i = 0; i < 4; ++i) {
    const std::int64_t c = 4 * cq + i;
    for (int r = 0; r < 4; ++r) {
      const std::int64_t iy = 2 * ty - 1 + r;
      inside[i][r] = c < g.channels && iy >= 0 && iy < g.height;
      if (!inside[i][r]) continue;
      const std::int64_t row = (b * g.channels + c) * plane_size + iy * g.width;
      std::int16_t* even = x16 + (i * 4 + r) * 2 * g.x16_tiles;
      std::int16_t* odd = even + g.x16_tiles;
      const std::int64_t steps = int8_round_up(g.block_tiles, 32);
      for (std::int64_t t = 0; t < steps; t += 32) {
        const std::int64_t x0 = 2 * (tx0 + t) - 1;
        const std::uint64_t mask = int8_winograd_column_mask(x0, g.width);
        I16 e, o;
        if (g.x_bf16) {
          Isa::quantize_x16_pairs_bf16(static_cast<const std::uint16_t*>(g.x), row + x0, mask,
                                       g.r16, e, o);
        } else {
          Isa::quantize_x16_pairs_f32(static_cast<const float*>(g.x), row + x0, mask, g.r16, e, o);
        }
        Isa::store_i16(even + t, e);
        Isa::store_i16(odd + t, o);
      }
      // The last step's tiles also read E and O of the tile after them: two columns, one at a time.
      const std::int64_t x0 = 2 * (tx0 + steps) - 1;
      for (int k = 0; k < 2; ++k) {
        const std::int64_t column = x0 + k;
        std::int16_t q = 0;
        if (column >= 0 && column < g.width) {
          q = g.x_bf16 ? Isa::quantize_x16_bf16(
                             static_cast<const std::uint16_t*>(g.x)[row + column], g.r16)
                       : Isa::quantize_x16_f32(static_cast<const float*>(g.x)[row + column], g.r16);
        }
        (k == 0 ? even : odd)[steps] = q;
      }
    }
  }
}

// Asks for the input rows quad cq of the block (tile row ty, tiles from tx0) reads, so that the
// conversion does not wait for them: each channel's four rows are a short run of cache lines in a
// plane far from the last one, which the hardware prefetchers do not foresee.
template <class Isa>
void int8_winograd_prefetch_quad(const Int8Winograd& g, std::int64_t b, std::int64_t ty,
                                 std::int64_t tx0, std::int64_t cq) {
  const std::int64_t element = g.x_bf16 ? 2 : 4;
  const std::int64_t first = 2 * tx0 - 1 < 0 ? 0 : 2 * tx0 - 1;
  const std::int64_t end_column = 2 * (tx0 + g.block_tiles) + 1;
  const std::int64_t last = (end_column < g.width ? end_column : g.width) - 1;
  for (std::int64_t c = 4 * cq; c < 4 * cq + 4 && c < g.channels; ++c) {
    for (std::int64_t iy = 2 * ty - 1; iy <= 2 * ty + 2; ++iy) {
      if (iy < 0 || iy >= g.height) continue;
      const char* row = static_cast<const char*>(g.x) +
                        ((b * g.channels + c) * g.height + iy) * g.width * element;
      for (std::int64_t at = first * element; at <= last * element; at += 64)
        Isa::prefetch_for_read(row + at);
      Isa::prefetch_for_read(row + last * element);
    }
  }
}

// V[p][cq][tl][i] for the block's tiles tl (32 at a time) of tile row ty from tile tx0 on: each
// quad's rows converted to x16 once (int8_winograd_quad_x16), then V = B^T d B in int16 from
// them (E[t], O[t], E[t + 1], O[t + 1] are a tile's four columns), each position requantized by
// its multiplier[p] and four channels' bytes interleaved into dwords.
template <class Isa>
void int8_winograd_input(const Int8Winograd& g, std::int64_t b, std::int64_t ty, std::int64_t tx0,
                         std::int16_t* x16, std::uint8_t* v) {
  using I16 = typename Isa::I16;
  for (std::int64_t cq = 0; cq < g.quads; ++cq) {
    if (cq == 0) {
      for (std::int64_t k = 1; k < kInt8WinogradPrefetchQuads && k < g.quads; ++k)
        int8_winograd_prefetch_quad<Isa>(g, b, ty, tx0, k);
    }
    if (cq + kInt8WinogradPrefetchQuads < g.quads)
      int8_winograd_prefetch_quad<Isa>(g, b, ty, tx0, cq + kInt8WinogradPrefetchQuads);
    bool inside[4][4];
    int8_winograd_quad_x16<Isa>(g, b, ty, tx0, cq, x16, inside);
    for (std::int64_t tl = 0; tl < g.block_tiles; tl += 32) {
      I16 u[4][16];
      for (int i = 0; i < 4; ++i) {
        I16 h[4][4];
#pragma GCC unroll 4
        for (int r = 0; r < 4; ++r) {
          if (!inside[i][r]) {
            for (int j = 0; j < 4; ++j) h[r][j] = Isa::zero_i16();
            continue;
          }
          const std::int16_t* even = x16 + (i * 4 + r) * 2 * g.x16_tiles + tl;
          const std::int16_t* odd = even + g.x16_tiles;
          const I16 d0 = Isa::load_i16(even), d1 = Isa::load_i16(odd);
          const I16 d2 = Isa::load_i16(even + 1), d3 = Isa::load_i16(odd + 1);
          h[r][0] = Isa::sub_i16(d0, d2);
          h[r][1] = Isa::add_i16(d1, d2);
          h[r][2] = Isa::sub_i16(d2, d1);
          h[r][3] = Isa::sub_i16(d1, d3);
        }
        for (int row = 0; row < 4; ++row) {
          const Int8WinogradPick pick = kInt8WinogradPick[row];
          for (int j = 0; j < 4; ++j) {
            const I16 vij = pick.sum ? Isa::add_i16(h[pick.first][j], h[pick.second][j])
                                     : Isa::sub_i16(h[pick.first][j], h[pick.second][j]);
            u[i][4 * row + j] = Isa::requantize(vij, g.multiplier[4 * row + j]);
          }
        }
      }
      const int tiles = g.block_tiles - tl < 32 ? 16 : 32;
      for (int p = 0; p < 16; ++p) {
        Isa::store_quads_i16(v + ((p * g.quads + cq) * g.block_tiles + tl) * 4, u[0][p], u[1][p],
                             u[2][p], u[3][p], tiles);
      }
    }
  }
}

// M[p][c][16 px + lane] for the output channels o0 + c (c < 8) and the tiles tl0 + 16 px + lane
// of the block: the products over the quads, dequantized, M = float(acc - comp[c]) scale[c] (the
// epilogue without bias or ReLU), inline (handing the accumulators to a function by reference
// sends them through memory). Not inlined: in the caller the output transform's constants would
// take registers from the accumulators.
template <class Isa, int NPX>
[[gnu::noinline]] void int8_winograd_position(const Int8Winograd& g, const std::uint8_t* v, int p,
                                              std::int64_t o0, std::int64_t tl0, float* m) {
  using Acc = typename Isa::Acc;
  using Bytes = typename Isa::Bytes;
  constexpr int kCols = static_cast<int>(kInt8GroupColumns);
  const std::int64_t quads = g.quads, v_step = g.block_tiles * 4;
  Acc acc[kCols][NPX];
#pragma GCC unroll 8
  for (int c = 0; c < kCols; ++c)
#pragma GCC unroll 4
    for (int px = 0; px < NPX; ++px) acc[c][px] = Isa::zero();
  const std::uint8_t* vp = v + (p * quads * g.block_tiles + tl0) * 4;
  const std::int8_t* w = g.u + ((p * g.column_groups + o0 / kCols) * quads) * 4 * kCols;
  // The quads in runs, a loop in a loop as in vnni_tile (taps, quads): over one flat loop GCC kept
  // each accumulator in two registers and copied it back on every step (32 moves and a spill a
  // step); nested, it allocates them in place.
  for (std::int64_t run = 0; run < quads; run += kInt8WinogradQuadRun) {
    const std::int64_t run_end =
        run + kInt8WinogradQuadRun < quads ? run + kInt8WinogradQuadRun : quads;
    for (std::int64_t cq = run; cq < run_end; ++cq, vp += v_step, w += 4 * kCols) {
      Bytes a[NPX];
#pragma GCC unroll 4
      for (int px = 0; px < NPX; ++px) a[px] = Isa::load(vp + 64 * px);
#pragma GCC unroll 8
      for (int c = 0; c < kCols; ++c) {
        const Bytes weights = Isa::broadcast4(w + 4 * c);
#pragma GCC unroll 4
        for (int px = 0; px < NPX; ++px) acc[c][px] = Isa::dot(acc[c][px], a[px], weights);
      }
    }
  }
  float* mp = m + p * kCols * kInt8WinogradGroupTiles;
#pragma GCC unroll 8
  for (int c = 0; c < kCols; ++c) {
    const std::int64_t o = o0 + c < g.out_channels ? o0 + c : g.out_channels - 1;
    const float scale = g.sv[p] * g.su[p * g.out_channels + o];  // g.sv: the effective scales
    const std::int32_t comp = g.compensation[p * g.column_groups * kCols + o0 + c];
#pragma GCC unroll 4
    for (int px = 0; px < NPX; ++px)
      Isa::store_f(mp + c * kInt8WinogradGroupTiles + 16 * px,
                   Isa::epilogue(acc[c][px], comp, scale, 0.0f, false));
  }
}

// The products of output channels [o0, o0 + 8) and tiles [tl0, tl0 + 16 NPX) of the block into M
// (16, 8, 32), then their output transform into y.
template <class Isa, int NPX>
void int8_winograd_group(const Int8Winograd& g, const std::uint8_t* v, std::int64_t b,
                         std::int64_t ty, std::int64_t tx0, std::int64_t o0, std::int64_t tl0,
                         float* m) {
  using F = typename Isa::F;
  constexpr int kCols = static_cast<int>(kInt8GroupColumns);
  for (int p = 0; p < 16; ++p) int8_winograd_position<Isa, NPX>(g, v, p, o0, tl0, m);
  // Y = A^T M A, A^T = [1 1 1 0; 0 1 -1 -1]: row 0 of A^T M is M0 + M1 + M2, row 1 M1 - M2 - M3
  // (rows of 4 positions), then the same along the columns.
  const std::int64_t oy = 2 * ty;
  for (int c = 0; c < kCols && o0 + c < g.out_channels; ++c) {
    const std::int64_t o = o0 + c;
    for (int px = 0; px < NPX; ++px) {
      const std::int64_t tx = tx0 + tl0 + 16 * px, ox = 2 * tx;
      if (ox >= g.width) break;
      F mm[16];
      for (int p = 0; p < 16; ++p)
        mm[p] = Isa::load_f(m + (p * kCols + c) * kInt8WinogradGroupTiles + 16 * px);
      F rows[2][4];
      for (int j = 0; j < 4; ++j) {
        rows[0][j] = Isa::add(Isa::add(mm[j], mm[4 + j]), mm[8 + j]);
        rows[1][j] = Isa::sub(Isa::sub(mm[4 + j], mm[8 + j]), mm[12 + j]);
      }
      const std::int64_t left = g.width - ox;
      const std::uint32_t mask = int8_first_lanes(left < 32 ? left : 32);
      for (int dy = 0; dy < 2 && oy + dy < g.height; ++dy) {
        const F y0 = Isa::bias_act(Isa::add(Isa::add(rows[dy][0], rows[dy][1]), rows[dy][2]),
                                   g.bias[o], g.relu);
        const F y1 = Isa::bias_act(Isa::sub(Isa::sub(rows[dy][1], rows[dy][2]), rows[dy][3]),
                                   g.bias[o], g.relu);
        const std::int64_t base = ((b * g.out_channels + o) * g.height + oy + dy) * g.width + ox;
        if (g.y_bf16) {
          Isa::store_bf16_interleaved(static_cast<std::uint16_t*>(g.y) + base, y0, y1, mask);
        } else {
          Isa::store_f32_interleaved(static_cast<float*>(g.y) + base, y0, y1, mask);
        }
      }
    }
  }
}

template <class Isa>
void int8_winograd_blocks(const Int8Winograd& g, std::int64_t begin, std::int64_t end, int thread) {
  std::uint8_t* v = g.v + thread * g.v_stride;
  float* m = g.m + thread * g.m_stride;
  std::int16_t* x16 = g.x16 + thread * g.x16_stride;
  for (std::int64_t item = begin; item < end; ++item) {
    const std::int64_t block = item % g.blocks_per_row, ty = item / g.blocks_per_row % g.tiles_h,
                       b = item / g.blocks_per_row / g.tiles_h;
    const std::int64_t tx0 = block * g.block_tiles;
    int8_winograd_input<Isa>(g, b, ty, tx0, x16, v);
    const std::int64_t tiles = g.tiles_w - tx0 < g.block_tiles ? g.tiles_w - tx0 : g.block_tiles;
    for (std::int64_t o0 = 0; o0 < g.out_channels; o0 += kInt8GroupColumns) {
      for (std::int64_t tl0 = 0; tl0 < tiles; tl0 += kInt8WinogradGroupTiles) {
        if (tiles - tl0 > 16) {
          int8_winograd_group<Isa, 2>(g, v, b, ty, tx0, o0, tl0, m);
        } else {
          int8_winograd_group<Isa, 1>(g, v, b, ty, tx0, o0, tl0, m);
        }
      }
    }
  }
}

}  // namespace
}  // namespace pillarseg::cpu
