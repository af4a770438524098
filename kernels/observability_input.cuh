// The 2D occupancy input (host/observability_input.hpp is the spec): out (n) = log(1 + t + d) of
// the transmissions and detections (n) of each cell (their sum in uint32), in double, rounded to
// float once. The GPU's log1p may differ from the host's by an ulp of the double, and so the float
// by one ulp in rare cells; the emulation uses the host's. Pointers are device memory; the work is
// queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

void observability_input(const std::uint32_t* transmissions, const std::uint32_t* detections,
                         std::int64_t n, float* out, cudaStream_t stream);

}  // namespace pillarseg::cuda
