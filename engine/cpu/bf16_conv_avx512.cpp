// The BF16 micro-kernel (bf16_microkernel.hpp) and the BF16 Winograd F(2x2, 3x3) convolution
// (bf16_winograd.hpp) on AVX512_BF16: VDPBF16PS for the dot products,
// VCVTNE(2)PS2BF16 for BF16 outputs, AVX512BW masked loads and stores for the image borders and
// row ends. This file alone is built with -mavx512f -mavx512bw -mavx512vl -mavx512bf16 and
// includes no library header: its functions are called only after the run-time check
// (avx512_bf16_available in bf16_conv.cpp), and nothing here may be shared with code that runs
// on other CPUs. Its instruction-for-instruction model is EmulatedBf16Isa (bf16_isa_emulated.hpp).
// Where the compiler has them (PILLARSEG_HAVE_AMX_BF16_KERNELS), it is also built with
// -mamx-tile -mamx-bf16 for the Winograd products on AMX tiles (bf16_amx.hpp; their model is
// EmulatedAmxTiles), called only after amx_bf16_available.
#include <immintrin.h>

#include <cstdint>

#include "engine/cpu/bf16_amx.hpp"
#include "engine/cpu/bf16_microkernel.hpp"
#include "engine/cpu/bf16_winograd.hpp"

namespace pillarseg::cpu {
namespace {

// Word 2 i of the result is word i of the source, word 2 i + 1 is word 16 + i.
alignas(64) constexpr std::uint16_t kInterleaveWords[32] = {
    0, 16, 1, 17, 2,  18, 3,  19, 4,  20, 5,  21, 6,  22, 7,  23,
    8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31};
// Dword 2 i of the first result is a[i], 2 i + 1 is b[i] (index 16 + i of permutex2var); the
// second result holds lanes 8..15.
alignas(64) constexpr std::uint32_t kInterleaveLow[16] = {0, 16, 1, 17, 2, 18, 3, 19,
                                                          4, 20, 5, 21, 6, 22, 7, 23};
alignas(64) constexpr std::uint32_t kInterleaveHigh[16] = {8,  24, 9,  25, 10, 26, 11, 27,
                                                           12, 28, 13, 29, 14, 30, 15, 31};

// base + index as an address; the lanes a zero mask bit names are never read or written, so the
// address of a row outside the image is formed but not dereferenced.
template <class T>
T* at(T* base, std::int64_t index) {
  return reinterpret_cast<T*>(reinterpret_cast<std::uintptr_t>(base) +
                              static_cast<std::uintptr_t>(index) * sizeof(T));
}

struct Avx512Bf16Isa {
  using Acc = __m512;
  using Pair = __m512i;

  static Acc zero() { return _mm512_setzero_ps(); }
  static Pair load_pairs(const std::uint16_t* base, std::int64_t first, std::uint32_t first_mask,
                         std::int64_t second, std::uint32_t second_mask) {
    const __m256i a = _mm256_maskz_loadu_epi16(static_cast<__mmask16>(first_mask), at(base, first));
    const __m256i b =
        _mm256_maskz_loadu_epi16(static_cast<__mmask16>(second_mask), at(base, second));
    const __m512i ab = _mm512_inserti64x4(_mm512_castsi256_si512(a), b, 1);
    return _mm512_permutexvar_epi16(_mm512_load_si512(kInterleaveWords), ab);
  }
  static Pair load_words(const std::uint16_t* words) { return _mm512_loadu_si512(words); }
  static Pair load_words_masked(const std::uint16_t* base, std::int64_t index, std::uint32_t mask) {
    return _mm512_maskz_loadu_epi16(static_cast<__mmask32>(mask), at(base, index));
  }
  static Acc even_words(Pair a) { return _mm512_castsi512_ps(_mm512_slli_epi32(a, 16)); }
  static Acc odd_words(Pair a) {
    return _mm512_castsi512_ps(
        _mm512_and_si512(a, _mm512_set1_epi32(static_cast<int>(0xFFFF0000u))));
  }
  static Acc load_f32(const float* y) { return _mm512_loadu_ps(y); }
  static Acc add(Acc a, Acc b) { return _mm512_add_ps(a, b); }
  static Acc sub(Acc a, Acc b) { return _mm512_sub_ps(a, b); }
  static Pair broadcast_pair(const std::uint16_t* two) {
    std::uint32_t bits;
    __builtin_memcpy(&bits, two, sizeof(bits));
    return _mm512_set1_epi32(static_cast<int>(bits));
  }
  static Acc dot(Acc acc, Pair a, Pair b) {
    return _mm512_dpbf16_ps(acc, reinterpret_cast<__m512bh>(a), reinterpret_cast<__m512bh>(b));
  }
  static Acc bias_act(Acc acc, float bias, bool relu) {
    const __m512 v = _mm512_add_ps(acc, _mm512_set1_ps(bias));
    return relu ? _mm512_max_ps(v, _mm512_setzero_ps()) : v;
  }
  static void store_f32(float* y, Acc acc, std::uint32_t mask) {
    _mm512_mask_storeu_ps(y, static_cast<__mmask16>(mask), acc);
  }
  static void store_bf16(std::uint16_t* y, Acc acc, std::uint32_t mask) {
    const __m256bh h = _mm512_cvtneps_pbh(acc);
    _mm256_mask_storeu_epi16(y, static_cast<__mmask16>(mask), reinterpret_cast<const __m256i&>(h));
  }
  static void store_f32_interleaved(float* y, Acc even, Acc odd, std::uint32_t mask) {
    const __m512 low = _mm512_permutex2var_ps(even, _mm512_load_si512(kInterleaveLow), odd);
    const __m512 high = _mm512_permutex2var_ps(even, _mm512_load_si512(kInterleaveHigh), odd);
    _mm512_mask_storeu_ps(y, static_cast<__mmask16>(mask & 0xFFFFu), low);
    _mm512_mask_storeu_ps(y + 16, static_cast<__mmask16>(mask >> 16), high);
  }
  static void store_bf16_interleaved(std::uint16_t* y, Acc even, Acc odd, std::uint32_t mask) {
    // Words 0..15: even, 16..31: odd; then interleaved.
    const __m512bh both = _mm512_cvtne2ps_pbh(odd, even);
    const __m512i words = _mm512_permutexvar_epi16(_mm512_load_si512(kInterleaveWords),
                                                   reinterpret_cast<const __m512i&>(both));
    _mm512_mask_storeu_epi16(y, static_cast<__mmask32>(mask), words);
  }
};

#if defined(PILLARSEG_HAVE_AMX_BF16_KERNELS)
// The tile instructions for bf16_amx.hpp. The intrinsics take tile numbers as literals (they are
// pasted into the instruction's text), hence one branch per tile the products use.
struct AmxTiles {
  static void configure(const AmxTileConfig& config) { _tile_loadconfig(&config); }
  static void release() { _tile_release(); }
  template <int T>
  static void zero() {
    static_assert(T >= 0 && T <= 2, "the accumulators are tmm0..tmm2");
    if constexpr (T == 0) _tile_zero(0);
    if constexpr (T == 1) _tile_zero(1);
    if constexpr (T == 2) _tile_zero(2);
  }
  template <int T>
  static void load(const void* base, std::int64_t stride_bytes) {
    static_assert(T >= 3 && T <= 6, "the operands are tmm3..tmm6");
    if constexpr (T == 3) _tile_loadd(3, base, stride_bytes);
    if constexpr (T == 4) _tile_loadd(4, base, stride_bytes);
    if constexpr (T == 5) _tile_loadd(5, base, stride_bytes);
    if constexpr (T == 6) _tile_loadd(6, base, stride_bytes);
  }
  template <int T>
  static void store(void* base, std::int64_t stride_bytes) {
    static_assert(T >= 0 && T <= 2, "the accumulators are tmm0..tmm2");
    if constexpr (T == 0) _tile_stored(0, base, stride_bytes);
    if constexpr (T == 1) _tile_stored(1, base, stride_bytes);
    if constexpr (T == 2) _tile_stored(2, base, stride_bytes);
  }
  template <int C, int A, int B>
  static void dot() {
    static_assert(A == 3 && B == C + 4 && C >= 0 && C <= 2, "C tmm0..2, A tmm3, B tmm4..6");
    if constexpr (C == 0) _tile_dpbf16ps(0, 3, 4);
    if constexpr (C == 1) _tile_dpbf16ps(1, 3, 5);
    if constexpr (C == 2) _tile_dpbf16ps(2, 3, 6);
  }
};
#endif

}  // namespace

void bf16_gemm_rows_avx512(const Bf16Gemm& g, std::int64_t begin, std::int64_t end) {
  gemm_rows<Avx512Bf16Isa>(g, begin, end);
}

void bf16_winograd_blocks_avx512(const Bf16Winograd& g, std::int64_t begin, std::int64_t end,
                                 int thread) {
  winograd_blocks<Avx512Bf16Isa>(g, begin, end, thread);
}

#if defined(PILLARSEG_HAVE_AMX_BF16_KERNELS)
void bf16_winograd_blocks_amx(const Bf16Winograd& g, std::int64_t begin, std::int64_t end,
                              int thread) {
  winograd_blocks_amx<Avx512Bf16Isa, AmxTiles>(g, begin, end, thread);
}
#endif

}  // namespace pillarseg::cpu
