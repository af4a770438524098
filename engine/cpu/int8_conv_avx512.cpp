// The INT8 micro-kernel and quantization (int8_microkernel.hpp) on AVX512-VNNI: VPDPBUSD for the
// products, VCVTPS2DQ {rn-sae} for the quantization, integer rounding for BF16 outputs (so that
// VNNI CPUs without AVX512_BF16, Cascade Lake and Ice Lake, run it too), AVX512BW masked loads and
// stores for the row ends. This file alone is built with -mavx512f -mavx512bw -mavx512vl
// -mavx512vnni and includes no library header: its functions are called only after the run-time
// check (avx512_vnni_available in int8_conv.cpp), and nothing here may be shared with code that
// runs on other CPUs. Its instruction-for-instruction model is EmulatedVnniIsa
// (int8_isa_emulated.hpp). Where the compiler has them (PILLARSEG_HAVE_AMX_INT8_KERNELS), it is
// also built with -mamx-tile -mamx-int8 for the products on tiles (int8_amx.hpp; their model is
// EmulatedAmxInt8Tiles), called only after amx_int8_available.
#include <immintrin.h>

#include <cstdint>

#include "engine/cpu/int8_amx.hpp"
#include "engine/cpu/int8_microkernel.hpp"
#include "engine/cpu/int8_winograd.hpp"

namespace pillarseg::cpu {
namespace {

alignas(64) constexpr std::uint32_t kInt8InterleaveLow[16] = {0, 16, 1, 17, 2, 18, 3, 19,
                                                              4, 20, 5, 21, 6, 22, 7, 23};
alignas(64) constexpr std::uint32_t kInt8InterleaveHigh[16] = {8,  24, 9,  25, 10, 26, 11, 27,
                                                               12, 28, 13, 29, 14, 30, 15, 31};

// Lane i of the permutation: 2 i (even) or 2 i + 1 (odd) of the pair (lo, hi), indices 16.. in hi.
alignas(64) constexpr std::uint32_t kInt8EvenLanes[16] = {0,  2,  4,  6,  8,  10, 12, 14,
                                                          16, 18, 20, 22, 24, 26, 28, 30};
alignas(64) constexpr std::uint32_t kInt8OddLanes[16] = {1,  3,  5,  7,  9,  11, 13, 15,
                                                         17, 19, 21, 23, 25, 27, 29, 31};

// base + index as an address; the lanes a zero mask bit names are never read, so the address of
// a column outside the image is formed but not dereferenced.
template <class T>
T* at(T* base, std::int64_t index) {
  return reinterpret_cast<T*>(reinterpret_cast<std::uintptr_t>(base) +
                              static_cast<std::uintptr_t>(index) * sizeof(T));
}

struct Avx512VnniIsa {
  using Acc = __m512i;
  using Bytes = __m512i;
  using F = __m512;

  static Acc zero() { return _mm512_setzero_si512(); }
  static Bytes load(const std::uint8_t* p) { return _mm512_loadu_si512(p); }
  static Bytes broadcast4(const std::int8_t* w) {
    std::int32_t bits;
    __builtin_memcpy(&bits, w, sizeof(bits));
    return _mm512_set1_epi32(bits);
  }
  static Acc dot(Acc acc, Bytes a, Bytes b) { return _mm512_dpbusd_epi32(acc, a, b); }
  static Acc load_acc(const std::int32_t* p) { return _mm512_loadu_si512(p); }
  static F epilogue(Acc acc, std::int32_t comp, float scale, float bias, bool relu) {
    // (The zero-masked form: GCC's unmasked one reads an undefined register, which it warns about.)
    const __m512 v =
        _mm512_maskz_cvtepi32_ps(0xFFFF, _mm512_sub_epi32(acc, _mm512_set1_epi32(comp)));
    const __m512 y = _mm512_fmadd_ps(v, _mm512_set1_ps(scale), _mm512_set1_ps(bias));
    return relu ? _mm512_max_ps(y, _mm512_setzero_ps()) : y;
  }
  // Each lane's BF16 bits in its low word: nearest even, NaN quiet.
  static __m512i bf16_dwords(F f) {
    const __m512i bits = _mm512_castps_si512(f);
    const __m512i lsb = _mm512_and_si512(_mm512_srli_epi32(bits, 16), _mm512_set1_epi32(1));
    const __m512i rounded = _mm512_srli_epi32(
        _mm512_add_epi32(_mm512_add_epi32(bits, _mm512_set1_epi32(0x7FFF)), lsb), 16);
    const __m512i quiet = _mm512_or_si512(_mm512_srli_epi32(bits, 16), _mm512_set1_epi32(0x40));
    return _mm512_mask_mov_epi32(rounded, _mm512_cmp_ps_mask(f, f, _CMP_UNORD_Q), quiet);
  }
  static void store_f32(float* y, F f, std::uint32_t mask) {
    _mm512_mask_storeu_ps(y, static_cast<__mmask16>(mask), f);
  }
  static void store_bf16(std::uint16_t* y, F f, std::uint32_t mask) {
    _mm256_mask_storeu_epi16(y, static_cast<__mmask16>(mask),
                             _mm512_cvtepi32_epi16(bf16_dwords(f)));
  }
  static void store_f32_interleaved(float* y, F even, F odd, std::uint32_t mask) {
    const __m512 low = _mm512_permutex2var_ps(even, _mm512_load_si512(kInt8InterleaveLow), odd);
    const __m512 high = _mm512_permutex2var_ps(even, _mm512_load_si512(kInt8InterleaveHigh), odd);
    _mm512_mask_storeu_ps(y, static_cast<__mmask16>(mask & 0xFFFFu), low);
    _mm512_mask_storeu_ps(y + 16, static_cast<__mmask16>(mask >> 16), high);
  }
  static void store_bf16_interleaved(std::uint16_t* y, F even, F odd, std::uint32_t mask) {
    // Dword i: even[i]'s bits in the low word, odd[i]'s in the high one: words 2 i, 2 i + 1.
    const __m512i words =
        _mm512_or_si512(bf16_dwords(even), _mm512_slli_epi32(bf16_dwords(odd), 16));
    _mm512_mask_storeu_epi16(y, static_cast<__mmask32>(mask), words);
  }

  static F load_f32(const float* x, std::uint32_t mask) {
    return _mm512_maskz_loadu_ps(static_cast<__mmask16>(mask), x);
  }
  static F load_bf16(const std::uint16_t* x, std::uint32_t mask) {
    const __m256i words = _mm256_maskz_loadu_epi16(static_cast<__mmask16>(mask), x);
    return _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_cvtepu16_epi32(words), 16));
  }
  static Acc quantize_u8(F x, float reciprocal) {
    __m512 r = _mm512_mul_ps(x, _mm512_set1_ps(reciprocal));
    r = _mm512_maskz_mov_ps(_mm512_cmp_ps_mask(r, r, _CMP_ORD_Q), r);  // NaN -> 0
    r = _mm512_min_ps(_mm512_max_ps(r, _mm512_set1_ps(-127.0f)), _mm512_set1_ps(127.0f));
    const __m512i q = _mm512_cvt_roundps_epi32(r, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    return _mm512_add_epi32(q, _mm512_set1_epi32(128));
  }
  static Acc quantize_unsigned(F x, float reciprocal) {
    __m512 r = _mm512_mul_ps(x, _mm512_set1_ps(reciprocal));
    r = _mm512_maskz_mov_ps(_mm512_cmp_ps_mask(r, r, _CMP_ORD_Q), r);  // NaN -> 0
    r = _mm512_min_ps(_mm512_max_ps(r, _mm512_setzero_ps()), _mm512_set1_ps(255.0f));
    return _mm512_cvt_roundps_epi32(r, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  }
  static Bytes pack_quads(Acc c0, Acc c1, Acc c2, Acc c3) {
    const __m512i byte = _mm512_set1_epi32(0xFF);
    __m512i v = _mm512_and_si512(c0, byte);
    v = _mm512_or_si512(v, _mm512_slli_epi32(_mm512_and_si512(c1, byte), 8));
    v = _mm512_or_si512(v, _mm512_slli_epi32(_mm512_and_si512(c2, byte), 16));
    return _mm512_or_si512(v, _mm512_slli_epi32(c3, 24));
  }
  static Acc set1(std::int32_t v) { return _mm512_set1_epi32(v); }
  static std::uint32_t differing_dwords(Bytes a, Bytes b) { return _mm512_cmpneq_epi32_mask(a, b); }
  static void store_quads(std::uint8_t* p, Bytes b, std::uint32_t mask) {
    _mm512_mask_storeu_epi32(p, static_cast<__mmask16>(mask), b);
  }

  static void prefetch_for_write(const void* p) { __builtin_prefetch(p, 1, 3); }

  static void prefetch_for_read(const void* p) { __builtin_prefetch(p, 0, 3); }
  static F even(F lo, F hi) {
    return _mm512_permutex2var_ps(lo, _mm512_load_si512(kInt8EvenLanes), hi);
  }
  static F odd(F lo, F hi) {
    return _mm512_permutex2var_ps(lo, _mm512_load_si512(kInt8OddLanes), hi);
  }
  static F add(F a, F b) { return _mm512_add_ps(a, b); }
  static F sub(F a, F b) { return _mm512_sub_ps(a, b); }
  static F bias_act(F a, float bias, bool relu) {
    const __m512 y = _mm512_add_ps(a, _mm512_set1_ps(bias));
    return relu ? _mm512_max_ps(y, _mm512_setzero_ps()) : y;
  }
  static F load_f(const float* p) { return _mm512_load_ps(p); }
  static void store_f(float* p, F f) { _mm512_store_ps(p, f); }

  using I16 = __m512i;
  static __m512i quantize_x16(F x, __m512 r) {
    const __m512 v = _mm512_mul_ps(x, r);
    const __mmask16 ordered = _mm512_cmp_ps_mask(v, v, _CMP_ORD_Q);
    const __m512 clamped =
        _mm512_min_ps(_mm512_max_ps(v, _mm512_set1_ps(-8191.0f)), _mm512_set1_ps(8191.0f));
    return _mm512_maskz_cvt_roundps_epi32(ordered, clamped,
                                          _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  }
  // One value (the columns after a block's last step), in scalar SSE arithmetic: the same
  // product, clamp and rounding (MXCSR's nearest even) as the vectors'.
  static std::int16_t quantize_x16_f32(float x, float r) {
    const float v = x * r;
    if (v != v) return 0;
    const float clamped = v < -8191.0f ? -8191.0f : v > 8191.0f ? 8191.0f : v;
    return static_cast<std::int16_t>(_mm_cvtss_si32(_mm_set_ss(clamped)));
  }
  static std::int16_t quantize_x16_bf16(std::uint16_t x, float r) {
    return quantize_x16_f32(__builtin_bit_cast(float, static_cast<std::uint32_t>(x) << 16), r);
  }
  // Two vectors of 16 int32 (lanes 0..15 and 16..31) as 32 int16 in lane order: VPACKSSDW
  // interleaves them by 64-bit quarters of each 128-bit lane, VPERMQ puts the quarters back.
  static I16 narrow(__m512i lo, __m512i hi) {
    return _mm512_permutexvar_epi64(_mm512_set_epi64(7, 5, 3, 1, 6, 4, 2, 0),
                                    _mm512_packs_epi32(lo, hi));
  }
  static void quantize_x16_pairs_bf16(const std::uint16_t* base, std::int64_t index,
                                      std::uint64_t mask, float r, I16& even, I16& odd) {
    const __m512 rv = _mm512_set1_ps(r);
    const __m512i high = _mm512_set1_epi32(static_cast<std::int32_t>(0xFFFF0000u));
    __m512i e[2], o[2];
    for (int k = 0; k < 2; ++k) {
      const __m512i words = _mm512_maskz_loadu_epi16(static_cast<__mmask32>(mask >> (32 * k)),
                                                     at(base, index + 32 * k));
      e[k] = quantize_x16(_mm512_castsi512_ps(_mm512_slli_epi32(words, 16)), rv);
      o[k] = quantize_x16(_mm512_castsi512_ps(_mm512_and_si512(words, high)), rv);
    }
    even = narrow(e[0], e[1]), odd = narrow(o[0], o[1]);
  }
  static void quantize_x16_pairs_f32(const float* base, std::int64_t index, std::uint64_t mask,
                                     float r, I16& even, I16& odd) {
    const __m512 rv = _mm512_set1_ps(r);
    __m512i e[2], o[2];
    for (int k = 0; k < 2; ++k) {
      const __m512 lo =
          _mm512_maskz_loadu_ps(static_cast<__mmask16>(mask >> (32 * k)), at(base, index + 32 * k));
      const __m512 hi = _mm512_maskz_loadu_ps(static_cast<__mmask16>(mask >> (32 * k + 16)),
                                              at(base, index + 32 * k + 16));
      e[k] = quantize_x16(Avx512VnniIsa::even(lo, hi), rv);
      o[k] = quantize_x16(Avx512VnniIsa::odd(lo, hi), rv);
    }
    even = narrow(e[0], e[1]), odd = narrow(o[0], o[1]);
  }
  static I16 zero_i16() { return _mm512_setzero_si512(); }
  static I16 load_i16(const std::int16_t* p) { return _mm512_loadu_si512(p); }
  static void store_i16(std::int16_t* p, I16 a) { _mm512_storeu_si512(p, a); }
  static I16 add_i16(I16 a, I16 b) { return _mm512_add_epi16(a, b); }
  static I16 sub_i16(I16 a, I16 b) { return _mm512_sub_epi16(a, b); }
  static I16 requantize(I16 a, std::int16_t m) {
    return _mm512_mulhrs_epi16(a, _mm512_set1_epi16(m));
  }
  // VPACKSSWB (c0, c2) and (c1, c3): per 128-bit lane L the bytes of 8 tiles 8 L.. of two
  // channels; VPUNPCK{L,H}BW pair the channels 0, 1 and 2, 3 a word per tile, VPUNPCK{L,H}WD
  // make the dwords of tiles 8 L..8 L + 3 and 8 L + 4..8 L + 7, VPERMT2Q puts the tiles in order.
  static void store_quads_i16(std::uint8_t* out, I16 c0, I16 c1, I16 c2, I16 c3, int tiles) {
    const __m512i floor = _mm512_set1_epi8(-127), flip = _mm512_set1_epi8(-128);
    const __m512i p = _mm512_xor_si512(_mm512_max_epi8(_mm512_packs_epi16(c0, c2), floor), flip);
    const __m512i q = _mm512_xor_si512(_mm512_max_epi8(_mm512_packs_epi16(c1, c3), floor), flip);
    const __m512i x = _mm512_unpacklo_epi8(p, q), y = _mm512_unpackhi_epi8(p, q);
    const __m512i z0 = _mm512_unpacklo_epi16(x, y), z1 = _mm512_unpackhi_epi16(x, y);
    _mm512_storeu_si512(
        out, _mm512_permutex2var_epi64(z0, _mm512_set_epi64(11, 10, 3, 2, 9, 8, 1, 0), z1));
    if (tiles > 16) {
      _mm512_storeu_si512(out + 64, _mm512_permutex2var_epi64(
                                        z0, _mm512_set_epi64(15, 14, 7, 6, 13, 12, 5, 4), z1));
    }
  }
};

#if defined(PILLARSEG_HAVE_AMX_INT8_KERNELS)
// The tile instructions for int8_amx.hpp. The intrinsics take tile numbers as literals, hence one
// branch per tile.
struct AmxInt8Tiles {
  static void configure(const AmxInt8TileConfig& config) { _tile_loadconfig(&config); }
  static void release() { _tile_release(); }
  template <int T>
  static void zero() {
    static_assert(T >= 0 && T <= 3, "the accumulators are tmm0..tmm3");
    if constexpr (T == 0) _tile_zero(0);
    if constexpr (T == 1) _tile_zero(1);
    if constexpr (T == 2) _tile_zero(2);
    if constexpr (T == 3) _tile_zero(3);
  }
  template <int T>
  static void load(const void* base, std::int64_t stride_bytes) {
    static_assert(T >= 0 && T <= 7, "the tiles are tmm0..tmm7");
    if constexpr (T == 0) _tile_loadd(0, base, stride_bytes);
    if constexpr (T == 1) _tile_loadd(1, base, stride_bytes);
    if constexpr (T == 2) _tile_loadd(2, base, stride_bytes);
    if constexpr (T == 3) _tile_loadd(3, base, stride_bytes);
    if constexpr (T == 4) _tile_loadd(4, base, stride_bytes);
    if constexpr (T == 5) _tile_loadd(5, base, stride_bytes);
    if constexpr (T == 6) _tile_loadd(6, base, stride_bytes);
    if constexpr (T == 7) _tile_loadd(7, base, stride_bytes);
  }
  template <int T>
  static void store(void* base, std::int64_t stride_bytes) {
    static_assert(T >= 0 && T <= 3, "the accumulators are tmm0..tmm3");
    if constexpr (T == 0) _tile_stored(0, base, stride_bytes);
    if constexpr (T == 1) _tile_stored(1, base, stride_bytes);
    if constexpr (T == 2) _tile_stored(2, base, stride_bytes);
    if constexpr (T == 3) _tile_stored(3, base, stride_bytes);
  }
  template <int C, int A, int B>
  static void dot() {
    static_assert(C == (A - 4) * 2 + (B - 6), "C (A, B): 0 (4, 6), 1 (4, 7), 2 (5, 6), 3 (5, 7)");
    if constexpr (C == 0) _tile_dpbsud(0, 4, 6);
    if constexpr (C == 1) _tile_dpbsud(1, 4, 7);
    if constexpr (C == 2) _tile_dpbsud(2, 5, 6);
    if constexpr (C == 3) _tile_dpbsud(3, 5, 7);
  }
};
#endif

}  // namespace

void int8_quantize_rows_avx512(const Int8Quantize& q, std::int64_t begin, std::int64_t end) {
  quantize_rows<Avx512VnniIsa>(q, begin, end);
}

void int8_gemm_band_vnni(const Int8Gemm& g, std::int64_t b, std::int64_t row_begin,
                         std::int64_t row_end) {
  vnni_band<Avx512VnniIsa>(g, b, row_begin, row_end);
}

void int8_winograd_blocks_vnni(const Int8Winograd& g, std::int64_t begin, std::int64_t end,
                               int thread) {
  int8_winograd_blocks<Avx512VnniIsa>(g, begin, end, thread);
}

#if defined(PILLARSEG_HAVE_AMX_INT8_KERNELS)
void int8_gemm_band_amx(const Int8Gemm& g, std::int64_t b, std::int64_t row_begin,
                        std::int64_t row_end) {
  amx_band<Avx512VnniIsa, AmxInt8Tiles>(g, b, row_begin, row_end);
}
#endif

}  // namespace pillarseg::cpu
