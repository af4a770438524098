// CUDA device code for the host compiler: the qualifiers, the built-in index variables, the block
// barrier, warp shuffles and votes, atomics, and the few intrinsics the kernels use. Included by
// kernels/emu/cuda_compat.cuh when PILLARSEG_CUDA_EMULATION is defined.
//
// Semantics (emu_scheduler.hpp): threads of a block are fibers on one OS thread, so
// `__shared__` (a static thread_local) is shared by the threads of a block and private to it;
// CUDA leaves shared memory uninitialised, so kernels must not rely on its content at block start:
// every `__shared__` variable lives in the TLS section pillarseg_emu_shared, which the scheduler
// fills with 0xFF bytes at the start of every block (a kernel reading what it never wrote reads
// NaN or -1).
// threadIdx is the current fiber's, blockIdx/blockDim/gridDim the current block's. Shuffles and
// votes return once every lane of their mask has called them. Atomics are relaxed, as in CUDA.
#pragma once

#include <atomic>
#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>

#include "kernels/emu/emu_scheduler.hpp"
#include "kernels/emu/emu_types.hpp"

#define __global__
#define __device__
#define __host__
#define __forceinline__ inline
#define __launch_bounds__(...)
#define __align__(n) __attribute__((aligned(n)))
#define __shared__ static thread_local __attribute__((section("pillarseg_emu_shared")))

// ---- built-in variables ----
inline thread_local uint3 threadIdx{0, 0, 0};
inline thread_local uint3 blockIdx{0, 0, 0};
inline thread_local dim3 blockDim{};
inline thread_local dim3 gridDim{};
inline constexpr int warpSize = 32;

// ---- block barrier ----
inline void __syncthreads() {
  pillarseg::emu::block_barrier(1);
}
inline int __syncthreads_count(int predicate) {
  return pillarseg::emu::block_barrier(predicate);
}
inline int __syncthreads_and(int predicate) {
  return pillarseg::emu::block_barrier(predicate) ==
         static_cast<int>(blockDim.x * blockDim.y * blockDim.z);
}
inline int __syncthreads_or(int predicate) {
  return pillarseg::emu::block_barrier(predicate) != 0;
}

// ---- warp votes and shuffles ----
inline void __syncwarp(unsigned mask = 0xffffffffu) {
  pillarseg::emu::warp_vote(pillarseg::emu::WarpOp::Sync, mask, 0);
}
inline unsigned __ballot_sync(unsigned mask, int predicate) {
  return pillarseg::emu::warp_vote(pillarseg::emu::WarpOp::Ballot, mask, predicate);
}
inline int __any_sync(unsigned mask, int predicate) {
  return pillarseg::emu::warp_vote(pillarseg::emu::WarpOp::Any, mask, predicate) != 0;
}
inline int __all_sync(unsigned mask, int predicate) {
  return pillarseg::emu::warp_vote(pillarseg::emu::WarpOp::All, mask, predicate) == mask;
}

namespace pillarseg::emu {
// A shuffle of any arithmetic type of up to 8 bytes, carried as the low bytes of a 64-bit word.
template <class T>
T shuffle_value(WarpOp op, unsigned mask, T value, int lane_argument, int width) {
  static_assert(std::is_arithmetic_v<T> && sizeof(T) <= sizeof(std::uint64_t),
                "CUDA shuffles exchange arithmetic values of up to 8 bytes");
  std::uint64_t bits = 0;
  std::memcpy(&bits, &value, sizeof(T));
  bits = warp_shuffle(op, mask, bits, lane_argument, width);
  T result;
  std::memcpy(&result, &bits, sizeof(T));
  return result;
}

// Read-modify-write by compare-and-swap, for the atomics std::atomic_ref lacks (min, max, inc,
// dec).
template <class T, class Update>
T atomic_update(T* address, Update update) {
  std::atomic_ref<T> target(*address);
  T old = target.load(std::memory_order_relaxed);
  while (!target.compare_exchange_weak(old, update(old), std::memory_order_relaxed)) {
  }
  return old;
}
}  // namespace pillarseg::emu

template <class T>
inline T __shfl_sync(unsigned mask, T var, int src_lane, int width = warpSize) {
  return pillarseg::emu::shuffle_value(pillarseg::emu::WarpOp::ShuffleIndex, mask, var, src_lane,
                                       width);
}
template <class T>
inline T __shfl_up_sync(unsigned mask, T var, unsigned delta, int width = warpSize) {
  return pillarseg::emu::shuffle_value(pillarseg::emu::WarpOp::ShuffleUp, mask, var,
                                       static_cast<int>(delta), width);
}
template <class T>
inline T __shfl_down_sync(unsigned mask, T var, unsigned delta, int width = warpSize) {
  return pillarseg::emu::shuffle_value(pillarseg::emu::WarpOp::ShuffleDown, mask, var,
                                       static_cast<int>(delta), width);
}
template <class T>
inline T __shfl_xor_sync(unsigned mask, T var, int lane_mask, int width = warpSize) {
  return pillarseg::emu::shuffle_value(pillarseg::emu::WarpOp::ShuffleXor, mask, var, lane_mask,
                                       width);
}

// ---- atomics: return the old value, relaxed ordering ----
#define PS_EMU_ATOMIC_FETCH(name, type, method)                                      \
  inline type name(type* address, type value) {                                      \
    return std::atomic_ref<type>(*address).method(value, std::memory_order_relaxed); \
  }
PS_EMU_ATOMIC_FETCH(atomicAdd, int, fetch_add)
PS_EMU_ATOMIC_FETCH(atomicAdd, unsigned int, fetch_add)
PS_EMU_ATOMIC_FETCH(atomicAdd, unsigned long long, fetch_add)
PS_EMU_ATOMIC_FETCH(atomicAdd, float, fetch_add)
PS_EMU_ATOMIC_FETCH(atomicAdd, double, fetch_add)
PS_EMU_ATOMIC_FETCH(atomicSub, int, fetch_sub)
PS_EMU_ATOMIC_FETCH(atomicSub, unsigned int, fetch_sub)
PS_EMU_ATOMIC_FETCH(atomicExch, int, exchange)
PS_EMU_ATOMIC_FETCH(atomicExch, unsigned int, exchange)
PS_EMU_ATOMIC_FETCH(atomicExch, unsigned long long, exchange)
PS_EMU_ATOMIC_FETCH(atomicExch, float, exchange)
PS_EMU_ATOMIC_FETCH(atomicAnd, int, fetch_and)
PS_EMU_ATOMIC_FETCH(atomicAnd, unsigned int, fetch_and)
PS_EMU_ATOMIC_FETCH(atomicAnd, unsigned long long, fetch_and)
PS_EMU_ATOMIC_FETCH(atomicOr, int, fetch_or)
PS_EMU_ATOMIC_FETCH(atomicOr, unsigned int, fetch_or)
PS_EMU_ATOMIC_FETCH(atomicOr, unsigned long long, fetch_or)
PS_EMU_ATOMIC_FETCH(atomicXor, int, fetch_xor)
PS_EMU_ATOMIC_FETCH(atomicXor, unsigned int, fetch_xor)
PS_EMU_ATOMIC_FETCH(atomicXor, unsigned long long, fetch_xor)
#undef PS_EMU_ATOMIC_FETCH

#define PS_EMU_ATOMIC_MIN_MAX(type)                                                                \
  inline type atomicMin(type* address, type value) {                                               \
    return pillarseg::emu::atomic_update(address,                                                  \
                                         [value](type old) { return value < old ? value : old; }); \
  }                                                                                                \
  inline type atomicMax(type* address, type value) {                                               \
    return pillarseg::emu::atomic_update(address,                                                  \
                                         [value](type old) { return value > old ? value : old; }); \
  }
PS_EMU_ATOMIC_MIN_MAX(int)
PS_EMU_ATOMIC_MIN_MAX(unsigned int)
PS_EMU_ATOMIC_MIN_MAX(long long)
PS_EMU_ATOMIC_MIN_MAX(unsigned long long)
#undef PS_EMU_ATOMIC_MIN_MAX

#define PS_EMU_ATOMIC_CAS(type)                                                         \
  inline type atomicCAS(type* address, type compare, type value) {                      \
    std::atomic_ref<type>(*address).compare_exchange_strong(compare, value,             \
                                                            std::memory_order_relaxed); \
    return compare;                                                                     \
  }
PS_EMU_ATOMIC_CAS(int)
PS_EMU_ATOMIC_CAS(unsigned int)
PS_EMU_ATOMIC_CAS(unsigned long long)
#undef PS_EMU_ATOMIC_CAS

// atomicInc: old >= limit ? 0 : old + 1; atomicDec: old == 0 || old > limit ? limit : old - 1.
inline unsigned int atomicInc(unsigned int* address, unsigned int limit) {
  return pillarseg::emu::atomic_update(
      address, [limit](unsigned int old) { return old >= limit ? 0u : old + 1u; });
}
inline unsigned int atomicDec(unsigned int* address, unsigned int limit) {
  return pillarseg::emu::atomic_update(
      address, [limit](unsigned int old) { return old == 0u || old > limit ? limit : old - 1u; });
}

inline void __threadfence() {
  std::atomic_thread_fence(std::memory_order_seq_cst);
}
inline void __threadfence_block() {
  std::atomic_thread_fence(std::memory_order_seq_cst);
}

// ---- loads and intrinsics ----
template <class T>
inline T __ldg(const T* address) {
  return *address;
}

inline float rsqrtf(float x) {
  return 1.0f / std::sqrt(x);
}
inline double rsqrt(double x) {
  return 1.0 / std::sqrt(x);
}
inline float __expf(float x) {
  return std::exp(x);
}
inline float __logf(float x) {
  return std::log(x);
}
inline float __fdividef(float a, float b) {
  return a / b;
}
inline float __saturatef(float x) {
  return x > 0.0f ? (x < 1.0f ? x : 1.0f) : 0.0f;
}  // NaN -> 0
inline float __fmaf_rn(float a, float b, float c) {
  return std::fma(a, b, c);
}
inline float __fadd_rn(float a, float b) {
  return a + b;
}
inline float __fmul_rn(float a, float b) {
  return a * b;
}
inline int __float_as_int(float x) {
  return std::bit_cast<int>(x);
}
inline unsigned int __float_as_uint(float x) {
  return std::bit_cast<unsigned int>(x);
}
inline float __int_as_float(int x) {
  return std::bit_cast<float>(x);
}
inline float __uint_as_float(unsigned int x) {
  return std::bit_cast<float>(x);
}

// CUDA's integer and floating min/max, which device code calls unqualified.
#define PS_EMU_MIN_MAX(type)        \
  inline type min(type a, type b) { \
    return b < a ? b : a;           \
  }                                 \
  inline type max(type a, type b) { \
    return a < b ? b : a;           \
  }
PS_EMU_MIN_MAX(int)
PS_EMU_MIN_MAX(unsigned int)
PS_EMU_MIN_MAX(long)
PS_EMU_MIN_MAX(unsigned long)
PS_EMU_MIN_MAX(long long)
PS_EMU_MIN_MAX(unsigned long long)
#undef PS_EMU_MIN_MAX
inline float min(float a, float b) {
  return std::fmin(a, b);
}
inline float max(float a, float b) {
  return std::fmax(a, b);
}
inline double min(double a, double b) {
  return std::fmin(a, b);
}
inline double max(double a, double b) {
  return std::fmax(a, b);
}
