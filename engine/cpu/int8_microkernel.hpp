// The CPU's INT8 convolution micro-kernel and the input quantization, written once over an
// instruction set `Isa` and compiled twice: on AVX512-VNNI (int8_conv_avx512.cpp, built with the
// AVX-512 flags and only ever called where the CPU has them) and on the exact scalar model
// EmulatedVnniIsa (int8_isa_emulated.hpp, in int8_conv.cpp), which the tests run on every CPU.
//
// The quantized input (the workspace): u = q + 128 (signed rule) or u = q (non-negative rule) in
// bytes, four channels c = 4 cq + i side by side in one dword ("quads"), laid out
// xq[b][row][cq][col][i] over the padded image (Hp = H + 2 pad rows, Wp = W + 2 pad columns
// rounded up to 16, whole cache lines; the padding u = 128, or 0) and `quads` channel quads (the
// channels past I, up to the quads' end, are padding too, with zero weights). A convolution's
// output pixel (row, col) reads, for the tap (ky, kx), the padded input pixel (row + ky, col +
// kx): one plain 64-byte load gives 16 pixels' quads of one channel quad, with no masks and no
// borders.
//
// The GEMM: y[n, pixel] = epilogue(sum over k = (tap, cq, i) of u[k, pixel] w[n, k] - comp[n])
// (comp 0 for the non-negative rule), one VPDPBUSD a channel quad: a register holds 16 pixels'
// dwords (u8 x 4) of one quad, the column's four s8 weights broadcast to every lane. A register
// tile is 8 columns x NPX <= 3 vectors of 16 pixels (24 accumulators, 3 operands, the broadcasts
// from memory). The weights (Vnni packing) are w[n / 8][tap][cq][n % 8][i], the columns padded to
// a multiple of 8 with zeros, so that the 8 broadcasts of one step read 32 consecutive bytes.
//   - Convolution (stride 1): rows are output rows; tap t = ky k + kx at byte offset ky row_stride
//     + 4 kx; y (B, N, Ho, Wo).
//   - Transposed 2x2 stride 2: rows are input rows, pad 0, one tap; column n = 4 o + 2 dy + dx goes
//     to y[b, o, 2 row + dy, 2 col + dx]; columns n (dx = 0) and n + 1 (dx = 1) are stored
//     interleaved.
// A band (batch, rows [row_begin, row_end)), in blocks of 64 columns: each block over the band's
// rows, each row by groups of 8 columns over its pixels 48 at a time, so that the block's weights
// stay in cache while the rows stream by. The caller quantizes a band's input just before (into a
// buffer that holds the quads from byte `origin` of the layout on), so that it is still in cache.
//
// Idle windows. Most of a scan's BEV grid is empty: the U-Net's input canvas is 0 there, and the
// first layers' outputs there are one constant vector (the bias through the layer, then that
// through the next) away from the points and the image's border. The quantization takes the
// quads of one reference pixel of each image (int8_conv.cpp picks it and the leading channel
// quads [0, idle_quads) that are worth it: all of them, or a concatenation's first part, such
// as the canvas beside the decoder's output) and marks every pixel whose quads there differ from
// the reference's busy, a bit per padded pixel, and the padding pixels too where the padding
// differs from the reference. Sixteen output pixels whose input windows hold no busy pixel share
// the leading quads' part of their accumulators, idle[b][n] = sum over (tap, channel < 4
// idle_quads) of u_ref qw (for a reference equal to the padding: comp[n], or 0 for the
// non-negative input), so those products are not run: the tile starts from idle[b][n] and runs the
// quads after idle_quads, none where they are all. The results are the same bits as with every
// product run (the tests hold it).

// Everything here is in an unnamed namespace and calls no library function: the AVX-512 copy's
// code must not be merged by the linker with a copy that other CPUs run (bf16_microkernel.hpp).
#pragma once

#include <cstdint>

namespace pillarseg::cpu {

inline constexpr int kInt8MaxTaps = 49;               // kernels up to 7 x 7
inline constexpr std::int64_t kInt8GroupColumns = 8;  // the Vnni register tile's columns
inline constexpr std::int64_t kInt8ColumnBlock = 64;  // columns of a block (vnni_band)
inline constexpr std::int64_t kInt8Slack = 256;       // bytes after the quads a tile may read

// The quantization of one (batch, padded row): plain data for both compilations.
struct Int8Quantize {
  const void* x = nullptr;  // (B, C, H, W) FP32 or (x_bf16) BF16
  bool x_bf16 = false;
  std::int64_t channels = 0, height = 0, width = 0;
  float reciprocal = 0.0f;    // 1 / sx
  bool non_negative = false;  // u = q by the non-negative rule, padding 0; else q + 128, 128
  int pad = 0;
  std::uint8_t* xq = nullptr;  // (B, Hp, quads, Wp, 4), from byte `origin` on
  std::int64_t origin = 0;
  std::int64_t quads = 0, padded_height = 0, padded_width = 0;
  // The busy bits of padded row r (r = b Hp + padded row, from row busy_origin on): bit col % 64
  // of word col / 64 of the row's busy_words, set where pixel col's quads differ from reference[b
  // quads + cq] (the reference pixel's quad cq of image b, its four u bytes), and for the padding
  // pixels where padding_busy[b] (the padding differs from image b's reference).
  std::uint64_t* busy = nullptr;
  std::int64_t busy_origin = 0, busy_words = 0, idle_quads = 0;  // the bits: quads [0, idle_quads)
  const std::uint32_t* reference = nullptr;
  const std::uint8_t* padding_busy = nullptr;
};

// 64-bit words a padded row's busy bits take: the Wp columns and one word to spare, so that a
// window's test reads the word after its last column without a bound.
inline std::int64_t int8_busy_words(std::int64_t padded_width) {
  return padded_width / 64 + 2;
}

// One convolution for the micro-kernel.
struct Int8Gemm {
  const std::uint8_t* xq = nullptr;                                // the quads above
  std::int64_t origin = 0;                                         // bytes: where xq starts
  std::int64_t batch_stride = 0, row_stride = 0, quad_stride = 0;  // bytes
  std::int64_t quads = 0;
  std::int64_t tap_offsets[kInt8MaxTaps] = {};  // bytes
  int taps = 0;
  const std::int8_t* w = nullptr;              // packed (Vnni or Amx layout)
  std::int64_t columns = 0;                    // real columns (stored); the packing pads them
  const float* sw = nullptr;                   // (O): per output channel o = n (transposed: n / 4)
  const float* bias = nullptr;                 // (columns)
  const std::int32_t* compensation = nullptr;  // (columns), null for the non-negative input
  float sx = 0.0f;
  bool relu = false;
  bool transposed = false;
  void* y = nullptr;  // FP32 or (y_bf16) BF16
  bool y_bf16 = false;
  std::int64_t batch = 0, rows = 0, row_pixels = 0;            // the GEMM's pixel grid
  std::int64_t out_height = 0, out_width = 0, out_planes = 0;  // y (B, out_planes, ...)
  // The quantization's busy bits (Int8Quantize), null to run every window; an output pixel's
  // window is window_rows x window_cols input pixels from (row, col) on (kh x kw; 1 x 1 for the
  // transposed convolution); idle (B, columns): the accumulators of a window of image b's
  // reference pixels.
  const std::uint64_t* busy = nullptr;
  const std::int32_t* idle = nullptr;
  std::int64_t idle_quads = 0;  // the leading quads the busy bits describe
  std::int64_t busy_origin = 0, busy_words = 0, padded_height = 0;
  std::int64_t window_rows = 1, window_cols = 1;
};

// Rows [begin, end) of the quantization, row r = b Hp + padded row (int8_conv_avx512.cpp).
void int8_quantize_rows_avx512(const Int8Quantize& q, std::int64_t begin, std::int64_t end);
// The band (b, rows [row_begin, row_end)) on VPDPBUSD (int8_conv_avx512.cpp).
void int8_gemm_band_vnni(const Int8Gemm& g, std::int64_t b, std::int64_t row_begin,
                         std::int64_t row_end);

namespace {

inline std::uint32_t int8_first_lanes(std::int64_t count) {
  return count >= 32 ? ~std::uint32_t{0} : (std::uint32_t{1} << count) - 1;
}

inline std::int64_t int8_round_up(std::int64_t n, std::int64_t to) {
  return (n + to - 1) / to * to;
}

template <class Isa>
void quantize_rows(const Int8Quantize& q, std::int64_t begin, std::int64_t end) {
  using Acc = typename Isa::Acc;
  using F = typename Isa::F;
  const std::int64_t plane = q.height * q.width, wp = q.padded_width;
  const Acc zero = Isa::set1(0), shifted_zero = Isa::set1(128);
  const Acc padding = q.non_negative ? zero : shifted_zero;
  const auto padding_quads =
      q.non_negative ? Isa::pack_quads(zero, zero, zero, zero)
                     : Isa::pack_quads(shifted_zero, shifted_zero, shifted_zero, shifted_zero);
  if (q.busy != nullptr) {
    // Clear the rows' bits, and mark the padding busy where it differs from the reference.
    for (std::int64_t r = begin; r < end; ++r) {
      const std::int64_t row = r % q.padded_height - q.pad;
      std::uint64_t* words = q.busy + (r - q.busy_origin) * q.busy_words;
      const bool padding_busy = q.padding_busy[r / q.padded_height] != 0;
      const bool padding_row = row < 0 || row >= q.height;
      for (std::int64_t i = 0; i < q.busy_words; ++i)
        words[i] = padding_busy && padding_row ? ~std::uint64_t{0} : 0;
      if (!padding_busy || padding_row) continue;
      for (std::int64_t col = 0; col < q.pad; ++col)
        words[col / 64] |= std::uint64_t{1} << (col % 64);
      for (std::int64_t col = q.pad + q.width; col < 2 * q.pad + q.width; ++col)
        words[col / 64] |= std::uint64_t{1} << (col % 64);
    }
  }
  // Quad by quad, each over the rows: the input's channel planes are read along their rows, a
  // long run each, which the hardware prefetchers follow.
  for (std::int64_t cq = 0; cq < q.quads; ++cq) {
    for (std::int64_t r = begin; r < end; ++r) {
      const std::int64_t b = r / q.padded_height, row = r % q.padded_height - q.pad;
      std::uint8_t* out = q.xq + (r * q.quads * wp * 4 - q.origin) + cq * wp * 4;
      if (row < 0 || row >= q.height) {
        for (std::int64_t col = 0; col < wp; col += 16)
          Isa::store_quads(out + 4 * col, padding_quads,
                           int8_first_lanes(wp - col < 16 ? wp - col : 16));
        continue;
      }
      for (std::int64_t col = 0; col < q.pad; col += 16) {
        Isa::store_quads(out + 4 * col, padding_quads,
                         int8_first_lanes(q.pad - col < 16 ? q.pad - col : 16));
      }
      for (std::int64_t col = q.pad + q.width; col < wp; col += 16)
        Isa::store_quads(out + 4 * col, padding_quads,
                         int8_first_lanes(wp - col < 16 ? wp - col : 16));
      const std::int64_t offset = (b * q.channels + 4 * cq) * plane + row * q.width;
      for (std::int64_t x0 = 0; x0 < q.width; x0 += 16) {
        const std::uint32_t mask = int8_first_lanes(q.width - x0 < 16 ? q.width - x0 : 16);
        Acc u[4];
#pragma GCC unroll 4
        for (int i = 0; i < 4; ++i) {
          if (4 * cq + i >= q.channels) {
            u[i] = padding;
            continue;
          }
          const std::int64_t at = offset + i * plane + x0;
          const F v = q.x_bf16 ? Isa::load_bf16(static_cast<const std::uint16_t*>(q.x) + at, mask)
                               : Isa::load_f32(static_cast<const float*>(q.x) + at, mask);
          u[i] = q.non_negative ? Isa::quantize_unsigned(v, q.reciprocal)
                                : Isa::quantize_u8(v, q.reciprocal);
        }
        const auto quads = Isa::pack_quads(u[0], u[1], u[2], u[3]);
        Isa::store_quads(out + 4 * (q.pad + x0), quads, mask);
        if (q.busy != nullptr && cq < q.idle_quads) {
          const auto* reference =
              reinterpret_cast<const std::int8_t*>(q.reference + b * q.quads + cq);
          const std::uint64_t differ =
              Isa::differing_dwords(quads, Isa::broadcast4(reference)) & mask;
          const std::int64_t col = q.pad + x0, shift = col % 64;
          std::uint64_t* words = q.busy + (r - q.busy_origin) * q.busy_words + col / 64;
          words[0] |= differ << shift;
          if (shift > 48) words[1] |= differ >> (64 - shift);
        }
      }
    }
  }
}

// Column n's output channel, where its scale is.
inline std::int64_t int8_channel(const Int8Gemm& g, std::int64_t n) {
  return g.transposed ? n / 4 : n;
}

// The epilogue of column n.
template <class Isa>
[[gnu::always_inline]] inline typename Isa::F column_result(const Int8Gemm& g, std::int64_t n,
                                                            const typename Isa::Acc& acc) {
  return Isa::epilogue(acc, g.compensation != nullptr ? g.compensation[n] : 0,
                       g.sx * g.sw[int8_channel(g, n)], g.bias[n], g.relu);
}

// Asks for the cache lines that column n's outputs over the pixels [x0, x0 + 16 NPX) of `row`
// will be stored to (transposed: its two output rows' run for dx = 0 and 1), with the intent to
// write, so that the epilogue's stores do not wait for them.
template <class Isa, int NPX>
void prefetch_column(const Int8Gemm& g, std::int64_t b, std::int64_t row, std::int64_t n,
                     std::int64_t x0) {
  const std::int64_t pixels = g.row_pixels - x0 < 16 * NPX ? g.row_pixels - x0 : 16 * NPX;
  const std::int64_t bytes = g.y_bf16 ? 2 : 4;
  std::int64_t first = 0, count = pixels;
  if (!g.transposed) {
    first = ((b * g.out_planes + n) * g.out_height + row) * g.out_width + x0;
  } else {
    const std::int64_t o = n / 4, dy = (n % 4) / 2;
    first = ((b * g.out_planes + o) * g.out_height + 2 * row + dy) * g.out_width + 2 * x0;
    count = 2 * pixels;
  }
  const auto* y = static_cast<const char*>(g.y);
  for (std::int64_t at = first * bytes; at < (first + count) * bytes; at += 64)
    Isa::prefetch_for_write(y + at);
  Isa::prefetch_for_write(y + (first + count) * bytes - 1);
}

// The epilogue and store of column n's accumulators over the pixels [x0, x0 + 16 NPX) of `row`
// (those before row_pixels). Always inlined, like column_result: GCC made it a call per column
// in the AMX tile, whose cost showed on the layers with few channels.
template <class Isa, int NPX>
[[gnu::always_inline]] inline void store_column(const Int8Gemm& g, std::int64_t b, std::int64_t row,
                                                std::int64_t n, std::int64_t x0,
                                                const typename Isa::Acc (&acc)[NPX]) {
  const std::int64_t base = ((b * g.out_planes + n) * g.out_height + row) * g.out_width + x0;
#pragma GCC unroll 4
  for (int p = 0; p < NPX; ++p) {
    const std::int64_t left = g.row_pixels - (x0 + 16 * p);
    if (left <= 0) break;
    const std::uint32_t mask = int8_first_lanes(left < 16 ? left : 16);
    const typename Isa::F f = column_result<Isa>(g, n, acc[p]);
    if (g.y_bf16) {
      Isa::store_bf16(static_cast<std::uint16_t*>(g.y) + base + 16 * p, f, mask);
    } else {
      Isa::store_f32(static_cast<float*>(g.y) + base + 16 * p, f, mask);
    }
  }
}

// Transposed: n even, so the columns (n, n + 1) are (dx = 0, dx = 1) of one (o, dy), stored
// interleaved.
template <class Isa, int NPX>
[[gnu::always_inline]] inline void store_column_pair(const Int8Gemm& g, std::int64_t b,
                                                     std::int64_t row, std::int64_t n,
                                                     std::int64_t x0,
                                                     const typename Isa::Acc (&even)[NPX],
                                                     const typename Isa::Acc (&odd)[NPX]) {
  const std::int64_t o = n / 4, dy = (n % 4) / 2;
  const std::int64_t base =
      ((b * g.out_planes + o) * g.out_height + 2 * row + dy) * g.out_width + 2 * x0;
#pragma GCC unroll 4
  for (int p = 0; p < NPX; ++p) {
    const std::int64_t left = g.row_pixels - (x0 + 16 * p);
    if (left <= 0) break;
    const std::uint32_t mask = int8_first_lanes(2 * (left < 16 ? left : 16));
    const typename Isa::F e = column_result<Isa>(g, n, even[p]),
                          d = column_result<Isa>(g, n + 1, odd[p]);
    if (g.y_bf16) {
      Isa::store_bf16_interleaved(static_cast<std::uint16_t*>(g.y) + base + 32 * p, e, d, mask);
    } else {
      Isa::store_f32_interleaved(static_cast<float*>(g.y) + base + 32 * p, e, d, mask);
    }
  }
}

// Whether the padded input columns [from, from + count) of a row's busy bits hold a busy pixel.
inline bool int8_any_busy(const std::uint64_t* words, std::int64_t from, std::int64_t count) {
  while (count > 0) {
    const std::int64_t shift = from % 64, n = count < 64 - shift ? count : 64 - shift;
    const std::uint64_t bits = n == 64 ? ~std::uint64_t{0} : ((std::uint64_t{1} << n) - 1) << shift;
    if ((words[from / 64] & bits) != 0) return true;
    from += n, count -= n;
  }
  return false;
}

// Which of the `vectors` 16-pixel vectors from x0 of `row` (those before row_pixels) have a busy
// pixel in their windows: bit p for the pixels [x0 + 16 p, x0 + 16 p + 16); all where g.busy is
// null.
inline std::uint32_t int8_busy_vectors(const Int8Gemm& g, std::int64_t b, std::int64_t row,
                                       std::int64_t x0, int vectors) {
  if (g.busy == nullptr) return (std::uint32_t{1} << vectors) - 1;
  std::uint32_t busy = 0;
  const std::uint64_t* first = g.busy + (b * g.padded_height + row - g.busy_origin) * g.busy_words;
  for (int p = 0; p < vectors; ++p) {
    const std::int64_t x = x0 + 16 * p, left = g.row_pixels - x;
    if (left <= 0) break;
    const std::int64_t count = (left < 16 ? left : 16) + g.window_cols - 1;
    for (std::int64_t ky = 0; ky < g.window_rows; ++ky) {
      if (int8_any_busy(first + ky * g.busy_words, x, count)) {
        busy |= std::uint32_t{1} << p;
        break;
      }
    }
  }
  return busy;
}

// One register tile: the 8 columns of group n0 / 8, pixels [x0, x0 + 16 NPX) of `row` (those
// before row_pixels) of batch b, over the channel quads from cq_begin on: 0, or for windows idle
// in the leading idle_quads the quads after them, on top of the idle accumulators.
template <class Isa, int NPX>
void vnni_tile(const Int8Gemm& g, std::int64_t b, std::int64_t row, std::int64_t n0,
               std::int64_t x0, std::int64_t cq_begin) {
  using Acc = typename Isa::Acc;
  using Bytes = typename Isa::Bytes;
  constexpr int kCols = static_cast<int>(kInt8GroupColumns);
  Acc acc[kCols][NPX];
#pragma GCC unroll 8
  for (int c = 0; c < kCols; ++c) {
    const std::int32_t start =
        cq_begin > 0 && n0 + c < g.columns ? g.idle[b * g.columns + n0 + c] : 0;
#pragma GCC unroll 4
    for (int p = 0; p < NPX; ++p) acc[c][p] = cq_begin > 0 ? Isa::set1(start) : Isa::zero();
  }
  const std::uint8_t* x_row = g.xq + (b * g.batch_stride + row * g.row_stride - g.origin) + 4 * x0;
  const std::int64_t quads = g.quads, quad_stride = g.quad_stride;
  const std::int8_t* w_group = g.w + n0 * g.taps * quads * 4;
  for (int t = 0; t < g.taps; ++t) {
    const std::uint8_t* x = x_row + g.tap_offsets[t] + cq_begin * quad_stride;
    const std::int8_t* w = w_group + (t * quads + cq_begin) * 4 * kCols;
    for (std::int64_t cq = cq_begin; cq < quads; ++cq, x += quad_stride, w += 4 * kCols) {
      Bytes a[NPX];
#pragma GCC unroll 4
      for (int p = 0; p < NPX; ++p) a[p] = Isa::load(x + 64 * p);
#pragma GCC unroll 8
      for (int c = 0; c < kCols; ++c) {
        const Bytes weights = Isa::broadcast4(w + 4 * c);
#pragma GCC unroll 4
        for (int p = 0; p < NPX; ++p) acc[c][p] = Isa::dot(acc[c][p], a[p], weights);
      }
    }
  }
#pragma GCC unroll 8
  for (int c = 0; c < kCols; ++c) {
    if (n0 + c >= g.columns) break;
    if (!g.transposed) {
      store_column<Isa, NPX>(g, b, row, n0 + c, x0, acc[c]);
    } else if (c % 2 == 0) {
      store_column_pair<Isa, NPX>(g, b, row, n0 + c, x0, acc[c], acc[c + 1]);
    }
  }
}

// vnni_tile over `vectors` (1 to 3) vectors of 16 pixels from x0.
template <class Isa>
void vnni_tiles(const Int8Gemm& g, std::int64_t b, std::int64_t row, std::int64_t n0,
                std::int64_t x0, int vectors, std::int64_t cq_begin) {
  if (vectors == 3) {
    vnni_tile<Isa, 3>(g, b, row, n0, x0, cq_begin);
  } else if (vectors == 2) {
    vnni_tile<Isa, 2>(g, b, row, n0, x0, cq_begin);
  } else {
    vnni_tile<Isa, 1>(g, b, row, n0, x0, cq_begin);
  }
}

template <class Isa>
void vnni_band(const Int8Gemm& g, std::int64_t b, std::int64_t row_begin, std::int64_t row_end) {
  for (std::int64_t block = 0; block < g.columns; block += kInt8ColumnBlock) {
    const std::int64_t n_end =
        block + kInt8ColumnBlock < g.columns ? block + kInt8ColumnBlock : g.columns;
    for (std::int64_t row = row_begin; row < row_end; ++row) {
      for (std::int64_t n0 = block; n0 < n_end; n0 += kInt8GroupColumns) {
        for (std::int64_t x0 = 0; x0 < g.row_pixels; x0 += 48) {
          const std::int64_t left = g.row_pixels - x0;
          const int vectors = left > 32 ? 3 : left > 16 ? 2 : 1;
          const std::uint32_t busy = int8_busy_vectors(g, b, row, x0, vectors);
          if (busy == (std::uint32_t{1} << vectors) - 1 || busy == 0) {
            vnni_tiles<Isa>(g, b, row, n0, x0, vectors, busy == 0 ? g.idle_quads : 0);
            continue;
          }
          // The busy vectors' span in one tile, the idle ones around it in tiles of their own.
          const int lo = __builtin_ctz(busy), hi = 31 - __builtin_clz(busy);
          for (int p = 0; p < vectors; ++p) {
            if (p < lo || p > hi) vnni_tile<Isa, 1>(g, b, row, n0, x0 + 16 * p, g.idle_quads);
          }
          vnni_tiles<Isa>(g, b, row, n0, x0 + 16 * lo, hi - lo + 1, 0);
        }
      }
    }
  }
}

}  // namespace
}  // namespace pillarseg::cpu
