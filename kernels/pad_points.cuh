// Point padding (host/pad_points.hpp is the spec): rows [M, capacity) of points (capacity, 4)
// become quiet NaN, M = *num_points read on the device, so that one recorded graph serves every
// scan of up to `capacity` points (padding rows belong to no pillar and cast no ray). M outside
// [0, capacity] is clamped to it (a kernel cannot throw). Pointers are device memory; the work is
// queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// points (capacity, 4), num_points (1 int32).
void pad_points(const std::int32_t* num_points, std::int64_t capacity, float* points,
                cudaStream_t stream);

}  // namespace pillarseg::cuda
