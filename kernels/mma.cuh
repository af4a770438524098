// Tensor-core building blocks shared by the mixed-precision kernels, the same source for nvcc
// (inline PTX, sm_80 and later) and the emulation (kernels/emu/emu_mma.hpp, which documents the
// fragment layouts):
//   Half16                   which 16-bit float a kernel computes in: bfloat16 or IEEE half;
//   to_half16 / from_half16  conversions of one value, rounding to nearest even (the
//                            emulation's are exact bit manipulations; on a GPU the cvt.rn
//                            instructions, which round the same way);
//   mma_m16n8k16<H>          D = A B + C on one warp's fragments, FP32 accumulation;
//   mma_m16n8k32_i8<A>       D = A B + C with 8-bit integers, 32-bit integer accumulation
//                            (wrapping): B signed (s8), A signed (Int8A::S8) or unsigned
//                            (Int8A::U8: bytes 0..255, for non-negative activations); A and B
//                            fragments are those of m16n8k16 with each 16-bit element two 8-bit
//                            ones along K, so ldmatrix loads them, the same for both A types;
//   ldmatrix_x4/_x2<Trans>   one warp's fragments from shared memory (row addresses per lane);
//   cp_async_16, cp_async_commit, cp_async_wait<N>
//                            asynchronous 16-byte copies from global to shared memory (sm_80),
//                            zero-filled when not `fill`, in groups: wait<N> returns once all
//                            but the N newest committed groups have landed (a __syncthreads
//                            then makes them visible to the block).
#pragma once

#include <cstdint>
#include <cstring>
#include <type_traits>

#include "kernels/emu/cuda_compat.cuh"

#if defined(PILLARSEG_CUDA_EMULATION)
#include "kernels/emu/emu_mma.hpp"
#else
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#endif

// 1 where a compilation can hold the tensor-core kernels: the emulation, the host pass, and sm_80
// and later. Their launchers refuse devices before 8.0 (mma_supported), so for sm_75 the kernels'
// bodies are a trap: nvcc then spends no time on what never runs there (the INT8 file's sm_75 pass:
// 28 s before, 8 s after).
#if !defined(__CUDA_ARCH__) || __CUDA_ARCH__ >= 800
#define PILLARSEG_MMA_ARCH 1
#else
#define PILLARSEG_MMA_ARCH 0
#endif

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

enum class Half16 { BF16, F16 };

// How m16n8k32's A bytes read: signed (-128..127) or unsigned (0..255). B is always signed.
enum class Int8A { S8, U8 };

// Round to nearest even; NaN stays a (quiet) NaN, overflow goes to infinity.
__host__ __device__ inline std::uint16_t float_to_bf16_bits(float x) {
#if defined(__CUDA_ARCH__)
  return __bfloat16_as_ushort(__float2bfloat16_rn(x));
#else
  std::uint32_t u = 0;
  std::memcpy(&u, &x, 4);
  if ((u & 0x7FFFFFFFu) > 0x7F800000u) return static_cast<std::uint16_t>((u >> 16) | 0x0040u);
  u += 0x7FFFu + ((u >> 16) & 1u);
  return static_cast<std::uint16_t>(u >> 16);
#endif
}

__host__ __device__ inline std::uint16_t float_to_f16_bits(float x) {
#if defined(__CUDA_ARCH__)
  return __half_as_ushort(__float2half_rn(x));
#else
  std::uint32_t u = 0;
  std::memcpy(&u, &x, 4);
  const std::uint32_t sign = (u >> 16) & 0x8000u;
  const std::uint32_t magnitude = u & 0x7FFFFFFFu;
  if (magnitude > 0x7F800000u)
    return static_cast<std::uint16_t>(sign | 0x7E00u | ((magnitude >> 13) & 0x3FFu));
  if (magnitude >= 0x477FF000u)
    return static_cast<std::uint16_t>(sign | 0x7C00u);  // rounds past 65504
  if (magnitude < 0x38800000u) {
    // Below 2^-14: a subnormal half, magnitude * 2^24 rounded to an integer (nearest even).
    if (magnitude < 0x33000000u) return static_cast<std::uint16_t>(sign);  // below half of 2^-24
    const std::uint32_t exponent = magnitude >> 23, mantissa = (magnitude & 0x7FFFFFu) | 0x800000u;
    // value = mantissa * 2^(exponent - 150); the half's integer is value * 2^24.
    const std::uint32_t shift = 126 - exponent;
    const std::uint32_t kept = mantissa >> shift, rest = mantissa & ((1u << shift) - 1u);
    const std::uint32_t half_way = 1u << (shift - 1);
    const std::uint32_t rounded =
        kept + ((rest > half_way || (rest == half_way && (kept & 1u))) ? 1u : 0u);
    return static_cast<std::uint16_t>(sign | rounded);
  }
  std::uint32_t v = magnitude - (112u << 23);  // rebias 127 -> 15
  v += 0xFFFu + ((v >> 13) & 1u);
  return static_cast<std::uint16_t>(sign | (v >> 13));
#endif
}

__host__ __device__ inline float bf16_bits_to_float(std::uint16_t bits) {
#if defined(__CUDA_ARCH__)
  return __uint_as_float(static_cast<unsigned>(bits) << 16);
#else
  const std::uint32_t u = std::uint32_t{bits} << 16;
  float x;
  std::memcpy(&x, &u, 4);
  return x;
#endif
}

__host__ __device__ inline float f16_bits_to_float(std::uint16_t bits) {
#if defined(__CUDA_ARCH__)
  return __half2float(__ushort_as_half(bits));
#elif defined(PILLARSEG_CUDA_EMULATION)
  return emu::f16_bits_to_float(bits);
#else
  return __half2float(__ushort_as_half(bits));
#endif
}

// Calls f(std::integral_constant<Half16, type>{}): a launcher's one way from the run-time type to
// a kernel template's argument (decltype(h)::value inside f).
template <class F>
void with_half16(Half16 type, F&& f) {
  if (type == Half16::BF16)
    f(std::integral_constant<Half16, Half16::BF16>{});
  else
    f(std::integral_constant<Half16, Half16::F16>{});
}

template <Half16 H>
__host__ __device__ inline std::uint16_t to_half16(float x) {
  return H == Half16::BF16 ? float_to_bf16_bits(x) : float_to_f16_bits(x);
}
template <Half16 H>
__host__ __device__ inline float from_half16(std::uint16_t bits) {
  return H == Half16::BF16 ? bf16_bits_to_float(bits) : f16_bits_to_float(bits);
}

#if defined(__CUDACC__) || defined(PILLARSEG_CUDA_EMULATION)

template <Half16 H>
__device__ inline void mma_m16n8k16(float d[4], const std::uint32_t a[4], const std::uint32_t b[2],
                                    const float c[4]) {
#if defined(PILLARSEG_CUDA_EMULATION)
  emu::mma_m16n8k16_collective(H == Half16::BF16, d, a, b, c);
#elif defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  if constexpr (H == Half16::BF16) {
    asm volatile(
        "mma.sync.aligned.m16n8k16.row.col.f32.bf16.bf16.f32 {%0, %1, %2, %3}, {%4, %5, %6, %7}, "
        "{%8, %9}, {%10, %11, %12, %13};\n"
        : "=f"(d[0]), "=f"(d[1]), "=f"(d[2]), "=f"(d[3])
        : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b[0]), "r"(b[1]), "f"(c[0]), "f"(c[1]),
          "f"(c[2]), "f"(c[3]));
  } else {
    asm volatile(
        "mma.sync.aligned.m16n8k16.row.col.f32.f16.f16.f32 {%0, %1, %2, %3}, {%4, %5, %6, %7}, "
        "{%8, %9}, {%10, %11, %12, %13};\n"
        : "=f"(d[0]), "=f"(d[1]), "=f"(d[2]), "=f"(d[3])
        : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b[0]), "r"(b[1]), "f"(c[0]), "f"(c[1]),
          "f"(c[2]), "f"(c[3]));
  }
#else
  // Before sm_80 there is no m16n8k16 with these types; the launchers refuse such devices.
  __trap();
#endif
}

template <Int8A A>
__device__ inline void mma_m16n8k32_i8(std::int32_t d[4], const std::uint32_t a[4],
                                       const std::uint32_t b[2], const std::int32_t c[4]) {
#if defined(PILLARSEG_CUDA_EMULATION)
  emu::mma_m16n8k32_i8_collective(A == Int8A::U8, d, a, b, c);
#elif defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  if constexpr (A == Int8A::U8) {
    asm volatile(
        "mma.sync.aligned.m16n8k32.row.col.s32.u8.s8.s32 {%0, %1, %2, %3}, {%4, %5, %6, %7}, "
        "{%8, %9}, {%10, %11, %12, %13};\n"
        : "=r"(d[0]), "=r"(d[1]), "=r"(d[2]), "=r"(d[3])
        : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b[0]), "r"(b[1]), "r"(c[0]), "r"(c[1]),
          "r"(c[2]), "r"(c[3]));
  } else {
    asm volatile(
        "mma.sync.aligned.m16n8k32.row.col.s32.s8.s8.s32 {%0, %1, %2, %3}, {%4, %5, %6, %7}, "
        "{%8, %9}, {%10, %11, %12, %13};\n"
        : "=r"(d[0]), "=r"(d[1]), "=r"(d[2]), "=r"(d[3])
        : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b[0]), "r"(b[1]), "r"(c[0]), "r"(c[1]),
          "r"(c[2]), "r"(c[3]));
  }
#else
  // Before sm_80 there is no m16n8k32; the launchers refuse such devices.
  __trap();
#endif
}

template <bool Transposed>
__device__ inline void ldmatrix_x4(std::uint32_t r[4], const void* row_address) {
#if defined(PILLARSEG_CUDA_EMULATION)
  emu::ldmatrix_collective<4, Transposed>(r, row_address);
#elif defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 750
  const unsigned address = static_cast<unsigned>(__cvta_generic_to_shared(row_address));
  if constexpr (Transposed) {
    asm volatile("ldmatrix.sync.aligned.m8n8.x4.trans.shared.b16 {%0, %1, %2, %3}, [%4];\n"
                 : "=r"(r[0]), "=r"(r[1]), "=r"(r[2]), "=r"(r[3])
                 : "r"(address));
  } else {
    asm volatile("ldmatrix.sync.aligned.m8n8.x4.shared.b16 {%0, %1, %2, %3}, [%4];\n"
                 : "=r"(r[0]), "=r"(r[1]), "=r"(r[2]), "=r"(r[3])
                 : "r"(address));
  }
#else
  __trap();
#endif
}

template <bool Transposed>
__device__ inline void ldmatrix_x2(std::uint32_t r[2], const void* row_address) {
#if defined(PILLARSEG_CUDA_EMULATION)
  emu::ldmatrix_collective<2, Transposed>(r, row_address);
#elif defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 750
  const unsigned address = static_cast<unsigned>(__cvta_generic_to_shared(row_address));
  if constexpr (Transposed) {
    asm volatile("ldmatrix.sync.aligned.m8n8.x2.trans.shared.b16 {%0, %1}, [%2];\n"
                 : "=r"(r[0]), "=r"(r[1])
                 : "r"(address));
  } else {
    asm volatile("ldmatrix.sync.aligned.m8n8.x2.shared.b16 {%0, %1}, [%2];\n"
                 : "=r"(r[0]), "=r"(r[1])
                 : "r"(address));
  }
#else
  __trap();
#endif
}

// `source` must be a valid 16-byte aligned global address even when !fill (nothing is read then).
__device__ inline void cp_async_16(void* shared_destination, const void* source, bool fill) {
#if defined(PILLARSEG_CUDA_EMULATION)
  emu::cp_async_16(shared_destination, source, fill);
#elif defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  const unsigned address = static_cast<unsigned>(__cvta_generic_to_shared(shared_destination));
  asm volatile("cp.async.cg.shared.global [%0], [%1], 16, %2;\n" ::"r"(address), "l"(source),
               "r"(fill ? 16 : 0));
#else
  __trap();
#endif
}

__device__ inline void cp_async_commit() {
#if defined(PILLARSEG_CUDA_EMULATION)
  emu::cp_async_commit_group();
#elif defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  asm volatile("cp.async.commit_group;\n" ::);
#else
  __trap();
#endif
}

template <int Pending>
__device__ inline void cp_async_wait() {
#if defined(PILLARSEG_CUDA_EMULATION)
  emu::cp_async_wait_group(Pending);
#elif defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  asm volatile("cp.async.wait_group %0;\n" ::"n"(Pending));
#else
  __trap();
#endif
}

#endif  // __CUDACC__ || PILLARSEG_CUDA_EMULATION

}  // namespace pillarseg::cuda
