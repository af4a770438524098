// Sum of squares of a float array, accumulated in double: *result = sum_i x[i]^2 over x (n); the
// gradient norm is its square root. Deterministic: the same x gives the same bits on every run,
// thread count and GPU, and in the emulation (each square is exact in double, and the additions
// happen in an order fixed by n alone). Pointers are device memory; the work is queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// The size, in doubles, of the scratch buffer sum_of_squares needs.
inline constexpr int kSumOfSquaresPartials = 1024;

// x (n) -> *result (1 double); partials: scratch of kSumOfSquaresPartials doubles. n = 0 gives 0.
void sum_of_squares(const float* x, std::int64_t n, double* partials, double* result,
                    cudaStream_t stream);

}  // namespace pillarseg::cuda
