// Masking of unobserved cells (host/mask_unobserved.hpp is the spec): where transmissions + detections
// is 0 (no ray touched the cell), labels (n) = 0 and, when probabilities is not null, each of its
// `planes` planes of n values = 0. Exact; one writer per element. Pointers are device memory; the
// work is queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

void mask_unobserved(const std::uint32_t* transmissions, const std::uint32_t* detections,
                     std::int64_t n, std::uint8_t* labels, float* probabilities,
                     std::int64_t planes, cudaStream_t stream);

}  // namespace pillarseg::cuda
