// The 2x2 max-pool, bilinear x2 upsampling and pillar scatter of half_ops_avx512.hpp on AVX512F,
// BW and VL, bit for bit the scalar loops of half_ops.cpp. This file alone is built with
// -mavx512f -mavx512bw -mavx512vl and -ffp-contract=off (the upsampling's products and sums stay
// separate roundings, as in the scalar loop) and includes no library header: its functions run
// only after the run-time check (avx512_half_ops_available), and nothing here may be shared with
// code that runs on other CPUs.
//
// Conversions. BF16 -> FP32 is the word shifted to the top half; FP16 -> FP32 is VCVTPH2PS, exact
// (it quiets a signalling NaN, which changes no result below: the max-pool copies the winner's
// bits, and the first arithmetic on a NaN quiets it in the scalar loop too). FP32 -> BF16 is
// float_to_bf16_bits's integer rounding (not VCVTNEPS2BF16, which flushes denormals); FP32 -> FP16
// is VCVTPS2PH with round to nearest even, which rounds subnormals, overflow and NaN payloads as
// float_to_f16_bits does.
#include "engine/cpu/half_ops_avx512.hpp"

#include <immintrin.h>

#include <cstdint>

namespace pillarseg::cpu {
namespace {

constexpr std::int64_t kLanes = 16;

std::int64_t round_up_16(std::int64_t n) { return (n + kLanes - 1) / kLanes * kLanes; }

// The low n lanes of a 16- or 32-lane mask: none for n <= 0, all from 16 or 32 on.
__mmask16 first_lanes(std::int64_t n) {
  return static_cast<__mmask16>(n <= 0 ? 0u : n >= kLanes ? 0xFFFFu : (1u << n) - 1u);
}
__mmask32 first_words(std::int64_t n) {
  return static_cast<__mmask32>(n <= 0 ? 0u : n >= 2 * kLanes ? 0xFFFFFFFFu : (1u << n) - 1u);
}

// Word i of the result is word 2 i of a:b (the low halves of their dwords), or word 2 i + 1 (the
// high halves).
alignas(64) constexpr std::uint16_t kLowHalves[32] = {0,  2,  4,  6,  8,  10, 12, 14, 16, 18, 20,
                                                      22, 24, 26, 28, 30, 32, 34, 36, 38, 40, 42,
                                                      44, 46, 48, 50, 52, 54, 56, 58, 60, 62};
alignas(64) constexpr std::uint16_t kHighHalves[32] = {1,  3,  5,  7,  9,  11, 13, 15, 17, 19, 21,
                                                       23, 25, 27, 29, 31, 33, 35, 37, 39, 41, 43,
                                                       45, 47, 49, 51, 53, 55, 57, 59, 61, 63};

// 16 words as FP32.
template <bool kBf16>
__m512 half_values(__m256i words) {
  if constexpr (kBf16) {
    return _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_cvtepu16_epi32(words), 16));
  } else {
    return _mm512_cvtph_ps(words);
  }
}

// 16 FP32 values rounded to nearest even to BF16, each word in the high half of its dword:
// float_to_bf16_bits's (bits + 0x7FFF + lsb) >> 16; a NaN keeps its top half, made quiet.
__m512i bf16_in_high_halves(__m512 v) {
  const __m512i bits = _mm512_castps_si512(v);
  const __mmask16 odd = _mm512_test_epi32_mask(bits, _mm512_set1_epi32(0x10000));  // the kept lsb
  const __m512i half_down = _mm512_add_epi32(bits, _mm512_set1_epi32(0x7FFF));
  const __m512i rounded = _mm512_mask_add_epi32(half_down, odd, half_down, _mm512_set1_epi32(1));
  const __mmask16 nan = _mm512_cmp_ps_mask(v, v, _CMP_UNORD_Q);
  return _mm512_mask_or_epi32(rounded, nan, bits, _mm512_set1_epi32(0x00400000));
}

// 16 FP32 values rounded to nearest even to 16-bit words.
template <bool kBf16>
__m256i half_words(__m512 v) {
  if constexpr (kBf16) {
    return _mm512_cvtepi32_epi16(_mm512_srli_epi32(bf16_in_high_halves(v), 16));
  } else {
    return _mm512_cvtps_ph(v, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  }
}

// 32 FP32 values (lo: words 0..15, hi: 16..31) rounded to nearest even to 16-bit words.
template <bool kBf16>
__m512i half_words32(__m512 lo, __m512 hi) {
  if constexpr (kBf16) {
    return _mm512_permutex2var_epi16(bf16_in_high_halves(lo), _mm512_load_si512(kHighHalves),
                                     bf16_in_high_halves(hi));
  } else {
    return _mm512_inserti64x4(
        _mm512_castsi256_si512(_mm512_cvtps_ph(lo, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC)),
        _mm512_cvtps_ph(hi, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC), 1);
  }
}

// ---- max-pool ----

// The FP32 op's rule for the next value of the window: a greater value, or NaN, replaces the best
// so far.
__mmask16 replaces(__m512 value, __m512 best) {
  return _mm512_cmp_ps_mask(value, best, _CMP_GT_OQ) | _mm512_cmp_ps_mask(value, value, _CMP_UNORD_Q);
}

// The two cache lines of each input row a 32-output step will read kPrefetchBytes on (the rows
// run on into the next ones, so the lines are those of later steps wherever the row ends). The
// hardware prefetchers alone leave the loads waiting on memory: at full size (64 planes of 500 x
// 1000) the pool took 4.4 ms without, 3.1 ms with 4 KiB ahead (1 and 2 KiB: 3.4-3.8 ms).
constexpr std::int64_t kPrefetchBytes = 4096;
void prefetch_row_ahead(const std::uint16_t* row) {
  const char* line = reinterpret_cast<const char*>(row) + kPrefetchBytes;
  _mm_prefetch(line, _MM_HINT_T0);
  _mm_prefetch(line + 64, _MM_HINT_T0);
}
void prefetch_ahead(const std::uint16_t* top, const std::uint16_t* bottom) {
  prefetch_row_ahead(top);
  prefetch_row_ahead(bottom);
}

// One output row, 32 outputs a step. BF16: each output's two-word pairs of the two input rows
// read as one dword lane (the first word the low half), the words widened in place (a BF16 value
// is its word in the high half), the best kept as FP32, whose high halves are its words.
void maxpool_row_bf16(const std::uint16_t* top, const std::uint16_t* bottom, std::int64_t ow,
                      std::uint16_t* out) {
  const __m512i high = _mm512_set1_epi32(static_cast<int>(0xFFFF0000u));
  for (std::int64_t ox = 0; ox < ow; ox += 2 * kLanes) {
    prefetch_ahead(top + 2 * ox, bottom + 2 * ox);
    __m512 best[2];
    for (int half = 0; half < 2; ++half) {
      const std::int64_t at = ox + half * kLanes;
      const __mmask16 lanes = first_lanes(ow - at);
      const __m512i pairs[2] = {_mm512_maskz_loadu_epi32(lanes, top + 2 * at),
                                _mm512_maskz_loadu_epi32(lanes, bottom + 2 * at)};
      // The window in the scalar loop's order: (0, 0), (0, 1), (1, 0), (1, 1).
      const __m512 window[4] = {_mm512_castsi512_ps(_mm512_slli_epi32(pairs[0], 16)),
                                _mm512_castsi512_ps(_mm512_and_si512(pairs[0], high)),
                                _mm512_castsi512_ps(_mm512_slli_epi32(pairs[1], 16)),
                                _mm512_castsi512_ps(_mm512_and_si512(pairs[1], high))};
      best[half] = window[0];
      for (int k = 1; k < 4; ++k)
        best[half] = _mm512_mask_mov_ps(best[half], replaces(window[k], best[half]), window[k]);
    }
    const __m512i words = _mm512_permutex2var_epi16(_mm512_castps_si512(best[0]), _mm512_load_si512(kHighHalves),
                                                    _mm512_castps_si512(best[1]));
    _mm512_mask_storeu_epi16(out + ox, first_words(ow - ox), words);
  }
}

// FP16: the two rows' 64 words split into the windows' first and second words (32 each), widened
// by VCVTPH2PS, the winners' words blended beside their values.
void maxpool_row_f16(const std::uint16_t* top, const std::uint16_t* bottom, std::int64_t ow,
                     std::uint16_t* out) {
  const __m512i low_halves = _mm512_load_si512(kLowHalves), high_halves = _mm512_load_si512(kHighHalves);
  for (std::int64_t ox = 0; ox < ow; ox += 2 * kLanes) {
    prefetch_ahead(top + 2 * ox, bottom + 2 * ox);
    const std::int64_t words = 2 * (ow - ox);  // of each input row from 2 ox on
    __m512i window[4];
    for (int r = 0; r < 2; ++r) {
      const std::uint16_t* row = (r == 0 ? top : bottom) + 2 * ox;
      const __m512i a = _mm512_maskz_loadu_epi16(first_words(words), row);
      const __m512i b = _mm512_maskz_loadu_epi16(first_words(words - 2 * kLanes), row + 2 * kLanes);
      window[2 * r] = _mm512_permutex2var_epi16(a, low_halves, b);
      window[2 * r + 1] = _mm512_permutex2var_epi16(a, high_halves, b);
    }
    __m512i best_words = window[0];
    __m512 best_lo = _mm512_cvtph_ps(_mm512_castsi512_si256(window[0]));
    __m512 best_hi = _mm512_cvtph_ps(_mm512_extracti64x4_epi64(window[0], 1));
    for (int k = 1; k < 4; ++k) {
      const __m512 lo = _mm512_cvtph_ps(_mm512_castsi512_si256(window[k]));
      const __m512 hi = _mm512_cvtph_ps(_mm512_extracti64x4_epi64(window[k], 1));
      const __mmask16 take_lo = replaces(lo, best_lo), take_hi = replaces(hi, best_hi);
      best_lo = _mm512_mask_mov_ps(best_lo, take_lo, lo);
      best_hi = _mm512_mask_mov_ps(best_hi, take_hi, hi);
      best_words = _mm512_mask_mov_epi16(best_words, _mm512_kunpackw(take_hi, take_lo), window[k]);
    }
    _mm512_mask_storeu_epi16(out + ox, first_words(ow - ox), best_words);
  }
}

template <bool kBf16>
void maxpool_planes(const std::uint16_t* x, std::int64_t planes, std::int64_t h, std::int64_t w,
                    std::uint16_t* y) {
  const std::int64_t oh = h / 2, ow = w / 2;
  for (std::int64_t plane = 0; plane < planes; ++plane) {
    for (std::int64_t oy = 0; oy < oh; ++oy) {
      const std::uint16_t* top = x + (plane * h + 2 * oy) * w;
      std::uint16_t* out = y + (plane * oh + oy) * ow;
      if constexpr (kBf16) {
        maxpool_row_bf16(top, top + w, ow, out);
      } else {
        maxpool_row_f16(top, top + w, ow, out);
      }
    }
  }
}

// ---- bilinear upsampling ----

// h (2 in_w FP32 values, then up to the next multiple of 16) = the input row interpolated along x:
// each block of 16 outputs widens the 16 words from its first column and picks its two taps.
template <bool kBf16>
void upsample_along_x(const std::uint16_t* row, std::int64_t in_w, const UpsampleTaps& t, float* h) {
  const std::int64_t blocks = round_up_16(2 * in_w) / kLanes;
  const std::int64_t* first = t.first;
  const std::int32_t *index0 = t.index0, *index1 = t.index1;
  const float *w0 = t.w0, *w1 = t.w1;
  for (std::int64_t k = 0; k < blocks; ++k) {
    const std::int64_t from = first[k];
    const __m256i words = from + kLanes <= in_w
                              ? _mm256_loadu_si256(reinterpret_cast<const __m256i*>(row + from))
                              : _mm256_maskz_loadu_epi16(first_lanes(in_w - from), row + from);
    const __m512 source = half_values<kBf16>(words);
    const __m512 a = _mm512_permutexvar_ps(_mm512_loadu_si512(index0 + k * kLanes), source);
    const __m512 b = _mm512_permutexvar_ps(_mm512_loadu_si512(index1 + k * kLanes), source);
    const __m512 value = _mm512_add_ps(_mm512_mul_ps(_mm512_loadu_ps(w0 + k * kLanes), a),
                                       _mm512_mul_ps(_mm512_loadu_ps(w1 + k * kLanes), b));
    _mm512_storeu_ps(h + k * kLanes, value);
  }
}

template <bool kBf16>
void upsample_planes(const std::uint16_t* x, std::int64_t planes, std::int64_t in_h,
                     std::int64_t in_w, const UpsampleTaps& t, float* scratch, std::uint16_t* y) {
  const std::int64_t out_h = 2 * in_h, out_w = 2 * in_w;
  // Two rows of FP32 values padded to a multiple of 32 (the padding zero, read, never stored).
  const std::int64_t padded_w = (out_w + 2 * kLanes - 1) / (2 * kLanes) * (2 * kLanes);
  float* h_top = scratch;
  float* h_bottom = h_top + padded_w;
  for (std::int64_t i = round_up_16(out_w); i < padded_w; i += kLanes) {
    _mm512_storeu_ps(h_top + i, _mm512_setzero_ps());
    _mm512_storeu_ps(h_bottom + i, _mm512_setzero_ps());
  }
  for (std::int64_t plane = 0; plane < planes; ++plane) {
    const std::uint16_t* in = x + plane * in_h * in_w;
    std::uint16_t* out = y + plane * out_h * out_w;
    // The two rows output row oy blends, each interpolated once (as the scalar loop keeps them).
    std::int64_t top_row = -1, bottom_row = -1;
    for (std::int64_t oy = 0; oy < out_h; ++oy) {
      const std::int64_t i0 = t.row_i0[oy], i1 = t.row_i1[oy];
      if (i0 != top_row) {
        if (i0 == bottom_row) {
          float* swap = h_top;
          h_top = h_bottom;
          h_bottom = swap;
          bottom_row = -1;
        } else {
          upsample_along_x<kBf16>(in + i0 * in_w, in_w, t, h_top);
        }
        top_row = i0;
      }
      if (i1 != bottom_row) {
        upsample_along_x<kBf16>(in + i1 * in_w, in_w, t, h_bottom);
        bottom_row = i1;
      }
      const __m512 w0 = _mm512_set1_ps(t.row_w0[oy]), w1 = _mm512_set1_ps(t.row_w1[oy]);
      const auto blend = [&](std::int64_t ox) {
        return _mm512_add_ps(_mm512_mul_ps(w0, _mm512_loadu_ps(h_top + ox)),
                             _mm512_mul_ps(w1, _mm512_loadu_ps(h_bottom + ox)));
      };
      std::uint16_t* o = out + oy * out_w;
      for (std::int64_t ox = 0; ox < out_w; ox += 2 * kLanes) {
        const __m512i words = half_words32<kBf16>(blend(ox), blend(ox + kLanes));
        if (ox + 2 * kLanes <= out_w) {
          _mm512_storeu_si512(o + ox, words);
        } else {
          _mm512_mask_storeu_epi16(o + ox, first_words(out_w - ox), words);
        }
      }
    }
  }
}

// ---- pillar scatter ----

// A 16 x 16 block of words (16 pillars' 16 channels) transposed in three levels of VPERMT2W.
// Level 0, 8 vectors: vector p holds pillars 2p, 2p + 1 (16 words each, channels in order). Level 1
// merges vectors p and p + 4 into one vector a channel half h: pillars 2p, 2p + 1, 2p + 8, 2p + 9
// by 8 channels. Level 2 merges level-1 vectors p and p + 2 into one a channel quarter: 8 pillars
// (2p, 2p + 1, 2p + 8, 2p + 9, 2p + 4, 2p + 5, 2p + 12, 2p + 13) by 4 channels. Level 3 merges
// the two level-2 vectors into one a channel pair: 2 channels by pillars 0 .. 15 in order.
struct alignas(64) WordIndex {
  std::uint16_t v[32];
};
constexpr WordIndex level1_index(int h) {  // word s: pillar s / 8 of the four, channel 8 h + s % 8
  WordIndex r{};
  for (int s = 0; s < 32; ++s) {
    const int j = s / 8, c = 8 * h + s % 8;
    r.v[s] = static_cast<std::uint16_t>(j < 2 ? 16 * j + c : 32 + 16 * (j - 2) + c);
  }
  return r;
}
constexpr WordIndex level2_index(int g) {  // word s: pillar s / 4 of the eight, channel 4 g + s % 4
  WordIndex r{};
  for (int s = 0; s < 32; ++s) {
    const int j = s / 4, c = 4 * g + s % 4;
    r.v[s] = static_cast<std::uint16_t>(j < 4 ? 8 * j + c : 32 + 8 * (j - 4) + c);
  }
  return r;
}
constexpr WordIndex level3_index(int e) {  // word s: channel 2 e + s / 16, pillar s % 16
  WordIndex r{};
  for (int s = 0; s < 32; ++s) {
    const int q = s % 16, a = q / 8, b = q / 4 % 2, p = q / 2 % 2, odd = q % 2;
    const int j = 4 * b + 2 * a + odd;  // q's place among its level-2 vector's eight pillars
    r.v[s] = static_cast<std::uint16_t>(32 * p + 4 * j + 2 * e + s / 16);
  }
  return r;
}
constexpr WordIndex kLevel1[2] = {level1_index(0), level1_index(1)};
constexpr WordIndex kLevel2[2] = {level2_index(0), level2_index(1)};
constexpr WordIndex kLevel3[2] = {level3_index(0), level3_index(1)};

__m512i merge(__m512i a, const WordIndex& index, __m512i b) {
  return _mm512_permutex2var_epi16(a, _mm512_load_si512(index.v), b);
}

template <bool kBf16>
void scatter_columns(const float* features, std::int64_t channels, const std::int64_t* rows,
                     std::int64_t count, std::int64_t stride, std::uint16_t* columns) {
  for (std::int64_t k0 = 0; k0 < count; k0 += kLanes) {
    const std::int64_t pillars = count - k0 < kLanes ? count - k0 : kLanes;
    for (std::int64_t c0 = 0; c0 < channels; c0 += kLanes) {
      const __mmask16 lanes = first_lanes(channels - c0);
      const auto words = [&](std::int64_t q) {  // pillar k0 + q's channels c0 .. c0 + 15 (0 past the ends)
        return q < pillars ? half_words<kBf16>(_mm512_maskz_loadu_ps(lanes, features + rows[k0 + q] * channels + c0))
                           : _mm256_setzero_si256();
      };
      __m512i level0[8];
      for (int p = 0; p < 8; ++p)
        level0[p] = _mm512_inserti64x4(_mm512_castsi256_si512(words(2 * p)), words(2 * p + 1), 1);
      __m512i level1[2][4];
      for (int h = 0; h < 2; ++h)
        for (int p = 0; p < 4; ++p) level1[h][p] = merge(level0[p], kLevel1[h], level0[p + 4]);
      const __mmask16 store = first_lanes(pillars);
      for (int h = 0; h < 2; ++h) {
        for (int g = 0; g < 2; ++g) {
          const __m512i level2[2] = {merge(level1[h][0], kLevel2[g], level1[h][2]),
                                     merge(level1[h][1], kLevel2[g], level1[h][3])};
          for (int e = 0; e < 2; ++e) {
            const __m512i pair = merge(level2[0], kLevel3[e], level2[1]);
            const std::int64_t c = c0 + 8 * h + 4 * g + 2 * e;
            if (c < channels)
              _mm256_mask_storeu_epi16(columns + c * stride + k0, store, _mm512_castsi512_si256(pair));
            if (c + 1 < channels)
              _mm256_mask_storeu_epi16(columns + (c + 1) * stride + k0, store, _mm512_extracti64x4_epi64(pair, 1));
          }
        }
      }
    }
  }
}

}  // namespace

void maxpool2d_half_avx512(const std::uint16_t* x, std::int64_t planes, std::int64_t h,
                           std::int64_t w, bool bf16, std::uint16_t* y) {
  if (bf16) {
    maxpool_planes<true>(x, planes, h, w, y);
  } else {
    maxpool_planes<false>(x, planes, h, w, y);
  }
}

std::int64_t upsample_scratch_floats(std::int64_t in_w) {
  return 2 * ((2 * in_w + 2 * kLanes - 1) / (2 * kLanes) * (2 * kLanes));
}

void upsample_bilinear_half_avx512(const std::uint16_t* x, std::int64_t planes, std::int64_t in_h,
                                   std::int64_t in_w, const UpsampleTaps& taps, bool bf16,
                                   float* scratch, std::uint16_t* y) {
  if (bf16) {
    upsample_planes<true>(x, planes, in_h, in_w, taps, scratch, y);
  } else {
    upsample_planes<false>(x, planes, in_h, in_w, taps, scratch, y);
  }
}

void scatter_columns_half_avx512(const float* features, std::int64_t channels,
                                 const std::int64_t* rows, std::int64_t count, bool bf16,
                                 std::int64_t stride, std::uint16_t* columns) {
  if (bf16) {
    scatter_columns<true>(features, channels, rows, count, stride, columns);
  } else {
    scatter_columns<false>(features, channels, rows, count, stride, columns);
  }
}

void scatter_plane_half_avx512(const std::uint16_t* column, const std::int32_t* cells,
                               const std::int64_t* tile_start, std::int64_t tiles,
                               std::int64_t tile_length, std::int64_t plane, std::uint16_t* out) {
  for (std::int64_t t = 0; t < tiles; ++t) {
    std::uint16_t* segment = out + t * tile_length;
    const std::int64_t length = plane - t * tile_length < tile_length ? plane - t * tile_length : tile_length;
    for (std::int64_t i = 0; i < length; i += 2 * kLanes)
      _mm512_mask_storeu_epi16(segment + i, first_words(length - i), _mm512_setzero_si512());
    for (std::int64_t k = tile_start[t]; k < tile_start[t + 1]; ++k) segment[cells[k]] = column[k];
  }
}

}  // namespace pillarseg::cpu
