// Conv2d 3x3 / pad 1 by Winograd F(4x4, 3x3): weight, input and output transforms around 36
// Eigen GEMMs per block of tiles. x (B, I, H, W), w (O, I, 3, 3) -> y (B, O, H, W); and the
// weight gradient, the same transforms transposed: dw = G^T [sum over tiles (A e A^T) . V] G.
//
// Layout. The output is cut into 4x4 tiles, th = ceil(H / 4) rows of tw = ceil(W / 4) tiles; a
// block is a run of whole tile rows of one image, or a run of tiles within one tile row, T
// tiles in all. For a block:
//   V (36, I, T): V[p][i][t] = (B^T d B)[p] of input channel i's 6x6 tile t,
//   M (36, O, T): M[p] = U[p] (O, I) * V[p] (I, T), one GEMM per position p = 6 k + j,
//   y: the 4x4 tile A^T M[., o, t] A, through the epilogue, where it lies inside the image.
// The transforms run over a block's tile row at once so that they vectorise: the input row band
// is split by column phase (x mod 4) first, which makes tile tx's six columns contiguous runs
// over tx.
// Scheduling. Where V and M of a block fit in a core's cache (few channels, large images), the
// threads take whole blocks, each with its own V and M. Otherwise (many channels, small images)
// the blocks are large and run one after the other, each in three parallel phases: input
// transform by channel, the 36 GEMMs, output transform by channel. Either way the arithmetic
// of every block is the same, so the scheduling cannot change the results.
// Activations stored as BF16 bits are widened as the input rows are read and rounded as the
// output rows are written, so that the FP32 arithmetic runs on them without a converted copy.
#include "host/conv2d_winograd.hpp"

#include <algorithm>
#include <array>
#include <cstdint>
#include <type_traits>

#include <omp.h>

#include "core/bf16.hpp"
#include "core/eigen.hpp"
#include "core/error.hpp"
#include "core/parallel.hpp"

namespace pillarseg::host {
namespace {

using RowMajorMatrix = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using MatrixView = Eigen::Map<RowMajorMatrix, Eigen::Unaligned, Eigen::OuterStride<>>;
using ConstMatrixView = Eigen::Map<const RowMajorMatrix, Eigen::Unaligned, Eigen::OuterStride<>>;

constexpr int kTile = 4;        // output tile side
constexpr int kInputTile = 6;   // input tile side: kTile + 3 - 1
constexpr int kPositions = 36;  // kInputTile^2 products per tile and channel pair
// Block sizes. A block whose V and M fit in kCacheBlockBytes (about a core's L2) is a cache
// block, taken whole by one thread; it needs at least kMinCacheBlockTiles tiles so that its
// GEMMs are not too thin. Otherwise a block has up to kMaxTilesPerBlock tiles (enough that
// packing U[p] for a GEMM, O I values for 2 O I T flops, costs little) within kScratchBytes.
constexpr int64_t kCacheBlockBytes = int64_t{2} << 20;
constexpr int64_t kMinCacheBlockTiles = 32;
constexpr int64_t kMaxTilesPerBlock = 512;
constexpr int64_t kScratchBytes = int64_t{32} << 20;
// Below this many multiply-adds in a block, an OpenMP region costs more than it saves.
constexpr int64_t kMinParallelWork = int64_t{1} << 16;

// G (6 x 3) of F(4x4, 3x3): u = G g G^T.
constexpr std::array<std::array<double, 3>, kInputTile> kG = {{{1.0 / 4, 0, 0},
                                                               {-1.0 / 6, -1.0 / 6, -1.0 / 6},
                                                               {-1.0 / 6, 1.0 / 6, -1.0 / 6},
                                                               {1.0 / 24, 1.0 / 12, 1.0 / 6},
                                                               {1.0 / 24, -1.0 / 12, 1.0 / 6},
                                                               {0, 0, 1}}};

// out[k][n] = (B^T d)[k] for the six rows d[0..5] of length n, B^T =
//   [4  0 -5  0 1 0; 0 -4 -4  1 1 0; 0 4 -4 -1 1 0; 0 -2 -1 2 1 0; 0 2 -1 -2 1 0; 0 4 0 -5 0 1].
// The output rows may be offset views of one array, so they are written through distinct
// restrict pointers, never read.
inline void input_transform_rows(const float* __restrict d0, const float* __restrict d1,
                                 const float* __restrict d2, const float* __restrict d3,
                                 const float* __restrict d4, const float* __restrict d5,
                                 float* __restrict o0, float* __restrict o1, float* __restrict o2,
                                 float* __restrict o3, float* __restrict o4, float* __restrict o5,
                                 int64_t n) {
  for (int64_t m = 0; m < n; ++m) {
    const float a = d4[m] - 4.0f * d2[m];
    const float b = d3[m] - 4.0f * d1[m];
    const float c = d4[m] - d2[m];
    const float e = 2.0f * (d3[m] - d1[m]);
    o0[m] = 4.0f * d0[m] - 5.0f * d2[m] + d4[m];
    o1[m] = a + b;
    o2[m] = a - b;
    o3[m] = c + e;
    o4[m] = c - e;
    o5[m] = 4.0f * d1[m] - 5.0f * d3[m] + d5[m];
  }
}

// out[r][n] = (A^T m)[r] for six rows m[0..5] of length n, A^T =
//   [1 1 1 1 1 0; 0 1 -1 2 -2 0; 0 1 1 4 4 0; 0 1 -1 8 -8 1].
inline void output_transform_rows(const float* __restrict m0, const float* __restrict m1,
                                  const float* __restrict m2, const float* __restrict m3,
                                  const float* __restrict m4, const float* __restrict m5,
                                  float* __restrict o0, float* __restrict o1, float* __restrict o2,
                                  float* __restrict o3, int64_t n) {
  for (int64_t t = 0; t < n; ++t) {
    const float sum12 = m1[t] + m2[t], diff12 = m1[t] - m2[t];
    const float sum34 = m3[t] + m4[t], diff34 = m3[t] - m4[t];
    o0[t] = m0[t] + sum12 + sum34;
    o1[t] = diff12 + 2.0f * diff34;
    o2[t] = sum12 + 4.0f * sum34;
    o3[t] = diff12 + 8.0f * diff34 + m5[t];
  }
}

// out[k][n] = (A d)[k] for the four rows d[0..3] of length n, A = the transpose of A^T above:
//   [1 0 0 0; 1 1 1 1; 1 -1 1 -1; 1 2 4 8; 1 -2 4 -8; 0 0 0 1].
inline void gradient_transform_rows(const float* __restrict d0, const float* __restrict d1,
                                    const float* __restrict d2, const float* __restrict d3,
                                    float* __restrict o0, float* __restrict o1,
                                    float* __restrict o2, float* __restrict o3,
                                    float* __restrict o4, float* __restrict o5, int64_t n) {
  for (int64_t m = 0; m < n; ++m) {
    const float even = d0[m] + d2[m], odd = d1[m] + d3[m];
    const float even4 = d0[m] + 4.0f * d2[m], odd8 = 2.0f * d1[m] + 8.0f * d3[m];
    o0[m] = d0[m];
    o1[m] = even + odd;
    o2[m] = even - odd;
    o3[m] = even4 + odd8;
    o4[m] = even4 - odd8;
    o5[m] = d3[m];
  }
}

struct WinogradShape {
  int64_t batch = 0, in_channels = 0, height = 0, width = 0, out_channels = 0;
  int64_t tile_rows() const { return (height + kTile - 1) / kTile; }
  int64_t tile_cols() const { return (width + kTile - 1) / kTile; }
  int64_t bytes_per_tile() const {
    return kPositions * (in_channels + out_channels) * int64_t{sizeof(float)};
  }
  bool cache_blocks() const { return kCacheBlockBytes / bytes_per_tile() >= kMinCacheBlockTiles; }
  // Tiles per block, from the shapes alone (so the blocking, and every sum, is the same
  // whatever the thread count).
  int64_t target_tiles() const {
    if (cache_blocks()) return std::min(kMaxTilesPerBlock, kCacheBlockBytes / bytes_per_tile());
    return std::max<int64_t>(1, std::min(kMaxTilesPerBlock, kScratchBytes / bytes_per_tile()));
  }
};

// Tile rows [ty0, ty0 + rows) x tile columns [tx0, tx0 + cols) of image b.
struct Block {
  int64_t b = 0, ty0 = 0, rows = 0, tx0 = 0, cols = 0;
  int64_t tiles() const { return rows * cols; }
};

// Whole tile rows per block when a tile row fits in the target, else each tile row split
// into equal runs; either way the blocks of an image are of (nearly) equal size.
std::vector<Block> plan_blocks(const WinogradShape& s) {
  const int64_t th = s.tile_rows(), tw = s.tile_cols(), target = s.target_tiles();
  std::vector<Block> blocks;
  for (int64_t b = 0; b < s.batch; ++b) {
    if (target >= tw) {
      // As many blocks as the target needs, of equal rows (a last block of a few tiles would
      // run thin GEMMs that repack all of U).
      const int64_t blocks_per_image = (th + target / tw - 1) / (target / tw);
      const int64_t rows = (th + blocks_per_image - 1) / blocks_per_image;
      for (int64_t ty0 = 0; ty0 < th; ty0 += rows)
        blocks.push_back({b, ty0, std::min(rows, th - ty0), 0, tw});
    } else {
      const int64_t runs = (tw + target - 1) / target;
      for (int64_t ty = 0; ty < th; ++ty)
        for (int64_t r = 0; r < runs; ++r) {
          const int64_t tx0 = tw * r / runs, tx1 = tw * (r + 1) / runs;
          blocks.push_back({b, ty, 1, tx0, tx1 - tx0});
        }
    }
  }
  return blocks;
}

// Runs body(item) for item in [0, count) inside the enclosing parallel region (or serially
// when there is none), dynamic schedule; items write disjoint outputs.
template <class Body>
void for_each_item(int64_t count, const Body& body) {
#pragma omp for schedule(dynamic, 1)
  for (int64_t item = 0; item < count; ++item) body(item);
}

// Where the 3x3 kernel of the convolution's (o, i) lies in the weight array:
// kernel(o, i)[ky][kx] = w[o * o_stride + i * i_stride + tap], tap = 3 ky + kx, or 8 - tap when
// flipped (the input gradient's kernel is w flipped in y and x, its channel axes swapped).
struct WeightLayout {
  const float* w = nullptr;
  int64_t o_stride = 0, i_stride = 0;
  bool flipped = false;
};

// U (36, O, I): U[p][o][i] = (G g G^T)[p] of the kernel g = kernel(o, i), in double, rounded
// once. Per output channel, vectorised over i: the nine taps of every i, then G g (6 x 3), then
// the 36 rows U[p][o][.], each written as one contiguous run.
void transform_weights(const WinogradShape& s, const WeightLayout& layout, float* u) {
  const int64_t O = s.out_channels, I = s.in_channels;
  parallel_chunks(O, [&](int64_t o_begin, int64_t o_end, int) {
    std::vector<double> taps(static_cast<size_t>(9 * I));
    std::vector<double> gg(static_cast<size_t>(kInputTile * 3 * I));  // (G g)[k][kx][i]
    for (int64_t o = o_begin; o < o_end; ++o) {
      const float* kernels = layout.w + o * layout.o_stride;
      for (int64_t i = 0; i < I; ++i)
        for (int tap = 0; tap < 9; ++tap)
          taps[static_cast<size_t>(tap * I + i)] =
              kernels[i * layout.i_stride + (layout.flipped ? 8 - tap : tap)];
      for (int k = 0; k < kInputTile; ++k)
        for (int kx = 0; kx < 3; ++kx) {
          double* row = gg.data() + (k * 3 + kx) * I;
          const double* t0 = taps.data() + kx * I;
          const double* t1 = taps.data() + (3 + kx) * I;
          const double* t2 = taps.data() + (6 + kx) * I;
          for (int64_t i = 0; i < I; ++i)
            row[i] = kG[k][0] * t0[i] + kG[k][1] * t1[i] + kG[k][2] * t2[i];
        }
      for (int k = 0; k < kInputTile; ++k)
        for (int j = 0; j < kInputTile; ++j) {
          const double* g0 = gg.data() + (k * 3) * I;
          const double* g1 = g0 + I;
          const double* g2 = g1 + I;
          float* row = u + ((k * kInputTile + j) * O + o) * I;
          for (int64_t i = 0; i < I; ++i)
            row[i] = static_cast<float>(g0[i] * kG[j][0] + g1[i] * kG[j][1] + g2[i] * kG[j][2]);
        }
    }
  });
}

// An activation value as FP32: itself, or widened from its BF16 bits.
inline float widen(float v) { return v; }
inline float widen(std::uint16_t bits) { return bf16_bits_to_float(bits); }
// An output value in the activations' storage: itself, or rounded to BF16 (nearest even).
template <class Out>
inline Out narrow(float v) {
  if constexpr (std::is_same_v<Out, float>) {
    return v;
  } else {
    return float_to_bf16_bits(v);
  }
}

// dst[ph * entries + m] = plane(iy, x0 + 4 m + ph) for m < entries, ph < 4: row iy of the (H, W)
// plane from column x0 on, split by column phase, zero outside the image. padded_row (4 entries
// values, zero on first use) keeps zeros outside the image's columns from call to call.
template <class In>
void split_row_by_phase(const In* plane, int64_t H, int64_t W, int64_t iy, int64_t x0,
                        int64_t entries, std::vector<float>& padded_row, float* dst) {
  const int64_t row_len = kTile * entries;
  if (iy < 0 || iy >= H) {
    std::fill(dst, dst + row_len, 0.0f);
    return;
  }
  // padded_row[q] = plane(iy, x0 + q) for q in [q0, q1); the rest stays zero.
  const int64_t q0 = std::max<int64_t>(0, -x0), q1 = std::min(row_len, W - x0);
  std::transform(plane + iy * W + x0 + q0, plane + iy * W + x0 + q1, padded_row.begin() + q0,
                 [](In v) { return widen(v); });
  for (int64_t m = 0; m < entries; ++m)
    for (int ph = 0; ph < kTile; ++ph)
      dst[ph * entries + m] = padded_row[static_cast<size_t>(kTile * m + ph)];
}

// V[p][i][t] for input channel i of one image plane (H, W) over the block's tiles, t = tile
// row in the block * cols + tile column in the block. Scratch: band and vert (6 rows of
// 4 (cols + 1) values), padded_row (4 (cols + 1)).
template <class In>
void transform_input_channel(const In* plane, const WinogradShape& s, const Block& blk,
                             int64_t i, float* v, std::vector<float>& band,
                             std::vector<float>& vert, std::vector<float>& padded_row) {
  const int64_t H = s.height, W = s.width, I = s.in_channels, cols = blk.cols;
  const int64_t phase_len = cols + 1;  // tile tx reads phase entries tx and tx + 1
  const int64_t row_len = kTile * phase_len;
  const int64_t tiles = blk.tiles();
  const int64_t x0 = kTile * blk.tx0 - 1;  // the band's first column (pad 1)
  band.resize(static_cast<size_t>(kInputTile * row_len));
  vert.resize(static_cast<size_t>(kInputTile * row_len));
  padded_row.assign(static_cast<size_t>(row_len), 0.0f);
  for (int64_t r_t = 0; r_t < blk.rows; ++r_t) {
    const int64_t ty = blk.ty0 + r_t;
    // band[r][ph * phase_len + m] = x(4 ty - 1 + r, x0 + 4 m + ph), zero outside the image.
    for (int r = 0; r < kInputTile; ++r)
      split_row_by_phase(plane, H, W, kTile * ty - 1 + r, x0, phase_len, padded_row,
                         band.data() + r * row_len);
    const float* b = band.data();
    float* t = vert.data();
    input_transform_rows(b, b + row_len, b + 2 * row_len, b + 3 * row_len, b + 4 * row_len,
                         b + 5 * row_len, t, t + row_len, t + 2 * row_len, t + 3 * row_len,
                         t + 4 * row_len, t + 5 * row_len, row_len);
    // Columns: tile tx's column c is phase c mod 4, entry tx + c / 4.
    for (int k = 0; k < kInputTile; ++k) {
      const float* z = vert.data() + k * row_len;
      float* out[kInputTile];
      for (int j = 0; j < kInputTile; ++j)
        out[j] = v + ((k * kInputTile + j) * I + i) * tiles + r_t * cols;
      input_transform_rows(z, z + phase_len, z + 2 * phase_len, z + 3 * phase_len, z + 1,
                           z + phase_len + 1, out[0], out[1], out[2], out[3], out[4], out[5], cols);
    }
  }
}

// Output channel o of one image plane (H, W) from M[.][o][.] over the block's tiles, through
// the epilogue. Scratch: cols (6 x 4 rows of tw), tile_out (4 rows of tw), out_rows (4 rows of
// 4 tw), tw the block's tile columns.
template <class Out>
void transform_output_channel(const float* m, const WinogradShape& s, const Block& blk, int64_t o,
                              const ConvEpilogue& e, Out* plane, std::vector<float>& cols,
                              std::vector<float>& tile_out, std::vector<float>& out_rows) {
  const int64_t H = s.height, W = s.width, tw = blk.cols, O = s.out_channels;
  const int64_t block_tiles = blk.tiles();
  const int64_t row_len = kTile * tw;
  const int64_t x0 = kTile * blk.tx0, out_cols = std::min(row_len, W - x0);
  const float scale = e.scale != nullptr ? e.scale[o] : 1.0f;
  const float shift = e.shift != nullptr ? e.shift[o] : 0.0f;
  cols.resize(static_cast<size_t>(kInputTile * kTile * tw));
  tile_out.resize(static_cast<size_t>(kTile * tw));
  out_rows.resize(static_cast<size_t>(kTile * row_len));
  for (int64_t r_t = 0; r_t < blk.rows; ++r_t) {
    const int64_t ty = blk.ty0 + r_t;
    // cols[k][cx][tx] = (M_k A)[cx] of tile tx, M_k the k-th row of its 6x6 products.
    for (int k = 0; k < kInputTile; ++k) {
      const float* mk[kInputTile];
      for (int j = 0; j < kInputTile; ++j)
        mk[j] = m + ((k * kInputTile + j) * O + o) * block_tiles + r_t * tw;
      float* c = cols.data() + k * kTile * tw;
      output_transform_rows(mk[0], mk[1], mk[2], mk[3], mk[4], mk[5], c, c + tw, c + 2 * tw,
                            c + 3 * tw, tw);
    }
    // tile_out[ry][tx] = (A^T cols[.][cx])[ry]: output (4 ty + ry, 4 tx + cx).
    const int64_t k_stride = kTile * tw;
    for (int cx = 0; cx < kTile; ++cx) {
      const float* c = cols.data() + cx * tw;
      float* t = tile_out.data();
      output_transform_rows(c, c + k_stride, c + 2 * k_stride, c + 3 * k_stride, c + 4 * k_stride,
                            c + 5 * k_stride, t, t + tw, t + 2 * tw, t + 3 * tw, tw);
      for (int ry = 0; ry < kTile; ++ry) {
        float* dst = out_rows.data() + ry * row_len + cx;
        const float* src = tile_out.data() + ry * tw;
        for (int64_t tx = 0; tx < tw; ++tx) dst[kTile * tx] = src[tx];
      }
    }
    for (int ry = 0; ry < kTile; ++ry) {
      const int64_t oy = kTile * ty + ry;
      if (oy >= H) break;
      const float* src = out_rows.data() + ry * row_len;
      Out* dst = plane + oy * W + x0;
      if (e.relu) {
        for (int64_t ox = 0; ox < out_cols; ++ox) dst[ox] = narrow<Out>(std::max(src[ox] * scale + shift, 0.0f));
      } else {
        for (int64_t ox = 0; ox < out_cols; ++ox) dst[ox] = narrow<Out>(src[ox] * scale + shift);
      }
    }
  }
}

// G[p][o][t] = (A e A^T)[p] for the 4x4 tile e of output-gradient channel o of one image plane
// (H, W) over the block's tiles (zero beyond the image), t as in V: the transform that the
// weight gradient pairs with V (the transpose of the output transform). Scratch: band (4 rows)
// and vert (6 rows) of 4 cols values, padded_row (4 cols).
void transform_gradient_channel(const float* plane, const WinogradShape& s, const Block& blk,
                                int64_t o, float* g, std::vector<float>& band,
                                std::vector<float>& vert, std::vector<float>& padded_row) {
  const int64_t H = s.height, W = s.width, O = s.out_channels, cols = blk.cols;
  const int64_t row_len = kTile * cols, tiles = blk.tiles();
  const int64_t x0 = kTile * blk.tx0;  // the band's first column
  band.resize(static_cast<size_t>(kTile * row_len));
  vert.resize(static_cast<size_t>(kInputTile * row_len));
  padded_row.assign(static_cast<size_t>(row_len), 0.0f);
  for (int64_t r_t = 0; r_t < blk.rows; ++r_t) {
    const int64_t ty = blk.ty0 + r_t;
    // band[r][ph * cols + m] = e(4 ty + r, x0 + 4 m + ph), zero outside the image.
    for (int r = 0; r < kTile; ++r)
      split_row_by_phase(plane, H, W, kTile * ty + r, x0, cols, padded_row,
                         band.data() + r * row_len);
    const float* b = band.data();
    float* z = vert.data();
    gradient_transform_rows(b, b + row_len, b + 2 * row_len, b + 3 * row_len, z, z + row_len,
                            z + 2 * row_len, z + 3 * row_len, z + 4 * row_len, z + 5 * row_len,
                            row_len);
    // Columns: tile tx's column c is phase c, entry tx.
    for (int k = 0; k < kInputTile; ++k) {
      const float* zk = vert.data() + k * row_len;
      float* out[kInputTile];
      for (int j = 0; j < kInputTile; ++j)
        out[j] = g + ((k * kInputTile + j) * O + o) * tiles + r_t * cols;
      gradient_transform_rows(zk, zk + cols, zk + 2 * cols, zk + 3 * cols, out[0], out[1], out[2],
                              out[3], out[4], out[5], cols);
    }
  }
}

// Scratch of one thread for one block: the transforms' rows.
struct TransformScratch {
  std::vector<float> a, b, c;
};

// The transforms and GEMMs of one block on the calling thread: V and M hold its tiles.
template <class In, class Out>
void run_block(const In* x, const WinogradShape& s, const Block& blk, const float* u, float* v,
               float* m, const ConvEpilogue& e, Out* y, TransformScratch& scratch) {
  const int64_t I = s.in_channels, O = s.out_channels, plane = s.height * s.width;
  const int64_t tiles = blk.tiles();
  for (int64_t i = 0; i < I; ++i)
    transform_input_channel(x + (blk.b * I + i) * plane, s, blk, i, v, scratch.a, scratch.b,
                            scratch.c);
  for (int p = 0; p < kPositions; ++p) {
    const ConstMatrixView u_p(u + p * O * I, O, I, Eigen::OuterStride<>(I));
    const ConstMatrixView v_p(v + p * I * tiles, I, tiles, Eigen::OuterStride<>(tiles));
    MatrixView m_p(m + p * O * tiles, O, tiles, Eigen::OuterStride<>(tiles));
    m_p.noalias() = u_p * v_p;
  }
  for (int64_t o = 0; o < O; ++o)
    transform_output_channel(m, s, blk, o, e, y + (blk.b * O + o) * plane, scratch.a, scratch.b,
                             scratch.c);
}

// The convolution of x (B, I, H, W) with the kernels kernel(o, i) of the layout (O, I, 3, 3), pad
// 1, through the epilogue, into y (B, O, H, W).
template <class In, class Out>
void winograd_convolution(const In* x, const WinogradShape& s, const WeightLayout& layout,
                          const ConvEpilogue& e, Out* y, WinogradWorkspace& ws) {
  const int64_t I = s.in_channels, O = s.out_channels, plane = s.height * s.width;
  const std::vector<Block> blocks = plan_blocks(s);
  int64_t max_tiles = 0;
  for (const Block& blk : blocks) max_tiles = std::max(max_tiles, blk.tiles());
  const int threads = num_threads();
  // Cache blocks: one V and M per thread; large blocks: one V and M shared by the threads.
  const int64_t copies = s.cache_blocks() ? threads : 1;
  const auto grow = [](std::vector<float>& buffer, int64_t n) {
    buffer.resize(std::max(buffer.size(), static_cast<size_t>(n)));
  };
  grow(ws.weights, kPositions * O * I);
  grow(ws.inputs, copies * kPositions * I * max_tiles);
  grow(ws.products, copies * kPositions * O * max_tiles);
  transform_weights(s, layout, ws.weights.data());
  const float* u = ws.weights.data();
  const int64_t count = static_cast<int64_t>(blocks.size());
  const bool parallel =
      threads > 1 &&
      kPositions * O * I * s.batch * s.tile_rows() * s.tile_cols() >= kMinParallelWork;

  if (s.cache_blocks()) {
#pragma omp parallel num_threads(threads) if (parallel)
    {
      TransformScratch scratch;
      const int64_t thread = parallel ? omp_get_thread_num() : 0;
      float* v = ws.inputs.data() + thread * kPositions * I * max_tiles;
      float* m = ws.products.data() + thread * kPositions * O * max_tiles;
      for_each_item(count, [&](int64_t k) {
        run_block(x, s, blocks[static_cast<size_t>(k)], u, v, m, e, y, scratch);
      });
    }
    return;
  }
  float* v = ws.inputs.data();
  float* m = ws.products.data();
  for (const Block& blk : blocks) {
    const int64_t tiles = blk.tiles();
#pragma omp parallel num_threads(threads) if (parallel)
    {
      TransformScratch scratch;
      for_each_item(I, [&](int64_t i) {
        transform_input_channel(x + (blk.b * I + i) * plane, s, blk, i, v, scratch.a, scratch.b,
                                scratch.c);
      });
      for_each_item(kPositions, [&](int64_t p) {
        const ConstMatrixView u_p(u + p * O * I, O, I, Eigen::OuterStride<>(I));
        const ConstMatrixView v_p(v + p * I * tiles, I, tiles, Eigen::OuterStride<>(tiles));
        MatrixView m_p(m + p * O * tiles, O, tiles, Eigen::OuterStride<>(tiles));
        m_p.noalias() = u_p * v_p;
      });
      for_each_item(O, [&](int64_t o) {
        transform_output_channel(m, s, blk, o, e, y + (blk.b * O + o) * plane, scratch.a, scratch.b,
                                 scratch.c);
      });
    }
  }
}

// Checks a 4D float tensor and returns its sizes with `out_channels` outputs.
template <class T>
WinogradShape shape_of(const char* op, const Tensor<T>& x, const Tensor<float>& w,
                       int64_t weight_in_axis, int64_t weight_out_axis) {
  PS_CHECK(x.rank() == 4, "{}: input must be (B, C, H, W), got shape {}", op, shape_str(x.shape()));
  PS_CHECK(w.rank() == 4 && w.dim(2) == 3 && w.dim(3) == 3,
           "{}: w must be (O, I, 3, 3), got shape {}", op, shape_str(w.shape()));
  PS_CHECK(w.dim(weight_in_axis) == x.dim(1),
           "{}: w {} expects {} channels in its input, but it has shape {}", op,
           shape_str(w.shape()), w.dim(weight_in_axis), shape_str(x.shape()));
  WinogradShape s;
  s.batch = x.dim(0);
  s.in_channels = x.dim(1);
  s.height = x.dim(2);
  s.width = x.dim(3);
  s.out_channels = w.dim(weight_out_axis);
  PS_CHECK(s.height >= 1 && s.width >= 1, "{}: the image must be at least 1x1, got {}x{}", op,
           s.height, s.width);
  return s;
}

template <class In, class Out>
void forward(const Tensor<In>& x, const Tensor<float>& w, const ConvEpilogue& epilogue, Tensor<Out>& y,
             WinogradWorkspace& workspace) {
  const WinogradShape s = shape_of("conv3x3_winograd_forward", x, w, 1, 0);
  y.resize_for_overwrite({s.batch, s.out_channels, s.height, s.width});  // every element written
  if (y.numel() == 0) return;
  const WeightLayout layout{w.data(), s.in_channels * 9, 9, false};
  winograd_convolution(x.data(), s, layout, epilogue, y.data(), workspace);
}

}  // namespace

void conv3x3_winograd_forward(const Tensor<float>& x, const Tensor<float>& w,
                              const ConvEpilogue& epilogue, Tensor<float>& y,
                              WinogradWorkspace& workspace) {
  PS_CHECK(&y != &x && &y != &w,
           "conv3x3_winograd_forward: the output y must be a different tensor from x and w");
  forward(x, w, epilogue, y, workspace);
}
void conv3x3_winograd_forward(const Tensor<std::uint16_t>& x, const Tensor<float>& w,
                              const ConvEpilogue& epilogue, Tensor<std::uint16_t>& y,
                              WinogradWorkspace& workspace) {
  PS_CHECK(&y != &x, "conv3x3_winograd_forward: the output y must be a different tensor from x");
  forward(x, w, epilogue, y, workspace);
}

void conv3x3_winograd_input_gradient(const Tensor<float>& dy, const Tensor<float>& w,
                                     Tensor<float>& dx, WinogradWorkspace& workspace) {
  // The correlation's "input" is dy (O channels), its "output" dx (I channels).
  const WinogradShape s = shape_of("conv3x3_winograd_input_gradient", dy, w, 0, 1);
  PS_CHECK(&dx != &dy && &dx != &w,
           "conv3x3_winograd_input_gradient: dx must be a different tensor from dy and w");
  dx.resize_for_overwrite({s.batch, s.out_channels, s.height, s.width});  // every element written
  if (dx.numel() == 0) return;
  // The correlation's kernel(c, o) = w[o][c] flipped: c indexes dx's channels (w's I), o dy's.
  const WeightLayout layout{w.data(), 9, w.dim(1) * 9, true};
  winograd_convolution(dy.data(), s, layout, ConvEpilogue{}, dx.data(), workspace);
}

void conv3x3_winograd_weight_gradient(const Tensor<float>& x, const Tensor<float>& dy,
                                      Tensor<float>& dw, WinogradWorkspace& workspace) {
  constexpr const char* kOp = "conv3x3_winograd_weight_gradient";
  PS_CHECK(x.rank() == 4, "{}: x must be (B, I, H, W), got shape {}", kOp, shape_str(x.shape()));
  PS_CHECK(
      dy.rank() == 4 && dy.dim(0) == x.dim(0) && dy.dim(2) == x.dim(2) && dy.dim(3) == x.dim(3),
      "{}: dy must be (B, O, H, W) with x's B, H, W {}, got shape {}", kOp, shape_str(x.shape()),
      shape_str(dy.shape()));
  PS_CHECK(&dw != &x && &dw != &dy, "{}: dw must be a different tensor from x and dy", kOp);
  WinogradShape s;
  s.batch = x.dim(0);
  s.in_channels = x.dim(1);
  s.height = x.dim(2);
  s.width = x.dim(3);
  s.out_channels = dy.dim(1);
  PS_CHECK(s.height >= 1 && s.width >= 1, "{}: the image must be at least 1x1, got {}x{}", kOp,
           s.height, s.width);
  const int64_t I = s.in_channels, O = s.out_channels, plane = s.height * s.width;
  dw.resize_for_overwrite({O, I, 3, 3});  // every element written
  if (dw.numel() == 0) return;
  // dU (36, O, I) = sum over blocks of G[p] (O, T) V[p]^T (T, I), each position's sum in block
  // order: the blocks run one after the other, each in three parallel phases (input transform
  // by channel, gradient transform by channel, the 36 GEMMs), so every sum is the same for any
  // thread count.
  const std::vector<Block> blocks = plan_blocks(s);
  int64_t max_tiles = 0;
  for (const Block& blk : blocks) max_tiles = std::max(max_tiles, blk.tiles());
  const auto grow = [](std::vector<float>& buffer, int64_t n) {
    buffer.resize(std::max(buffer.size(), static_cast<size_t>(n)));
  };
  grow(workspace.weights, kPositions * O * I);
  grow(workspace.inputs, kPositions * I * max_tiles);
  grow(workspace.products, kPositions * O * max_tiles);
  float* du = workspace.weights.data();
  float* v = workspace.inputs.data();
  float* g = workspace.products.data();
  if (blocks.empty()) std::fill(du, du + kPositions * O * I, 0.0f);  // no image: dw = 0
  const int threads = num_threads();
  const bool parallel =
      threads > 1 &&
      kPositions * O * I * s.batch * s.tile_rows() * s.tile_cols() >= kMinParallelWork;
  for (const Block& blk : blocks) {
    const int64_t tiles = blk.tiles();
#pragma omp parallel num_threads(threads) if (parallel)
    {
      TransformScratch scratch;
      for_each_item(I, [&](int64_t i) {
        transform_input_channel(x.data() + (blk.b * I + i) * plane, s, blk, i, v, scratch.a,
                                scratch.b, scratch.c);
      });
      for_each_item(O, [&](int64_t o) {
        transform_gradient_channel(dy.data() + (blk.b * O + o) * plane, s, blk, o, g, scratch.a,
                                   scratch.b, scratch.c);
      });
      for_each_item(kPositions, [&](int64_t p) {
        const ConstMatrixView g_p(g + p * O * tiles, O, tiles, Eigen::OuterStride<>(tiles));
        const ConstMatrixView v_p(v + p * I * tiles, I, tiles, Eigen::OuterStride<>(tiles));
        MatrixView du_p(du + p * O * I, O, I, Eigen::OuterStride<>(I));
        if (&blk == blocks.data()) du_p.setZero();  // zeroed by the thread that sums it first
        du_p.noalias() += g_p * v_p.transpose();
      });
    }
  }
  // dw[o][i] = G^T dU[.][o][i] G (3 x 3 from 6 x 6), in double, vectorised over i.
  float* out = dw.data();
  parallel_chunks(O, [&](int64_t o_begin, int64_t o_end, int) {
    std::vector<double> gt_du(static_cast<size_t>(3 * kInputTile * I));  // (G^T dU)[ky][j][i]
    std::vector<double> taps(static_cast<size_t>(9 * I));
    for (int64_t o = o_begin; o < o_end; ++o) {
      for (int ky = 0; ky < 3; ++ky)
        for (int j = 0; j < kInputTile; ++j) {
          double* row = gt_du.data() + (ky * kInputTile + j) * I;
          std::fill(row, row + I, 0.0);
          for (int k = 0; k < kInputTile; ++k) {
            const float* du_row = du + ((k * kInputTile + j) * O + o) * I;
            for (int64_t i = 0; i < I; ++i) row[i] += kG[k][ky] * du_row[i];
          }
        }
      for (int ky = 0; ky < 3; ++ky)
        for (int kx = 0; kx < 3; ++kx) {
          double* tap = taps.data() + (ky * 3 + kx) * I;
          std::fill(tap, tap + I, 0.0);
          for (int j = 0; j < kInputTile; ++j) {
            const double* row = gt_du.data() + (ky * kInputTile + j) * I;
            for (int64_t i = 0; i < I; ++i) tap[i] += row[i] * kG[j][kx];
          }
        }
      for (int64_t i = 0; i < I; ++i)
        for (int tap = 0; tap < 9; ++tap)
          out[(o * I + i) * 9 + tap] = static_cast<float>(taps[static_cast<size_t>(tap * I + i)]);
    }
  });
}

}  // namespace pillarseg::host
