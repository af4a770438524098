// Test-time flips: a pass's probabilities over a mirrored copy of the scan, mirrored back and added
// to the running sum (host/mirror_add.hpp is the spec). x and sum are (planes, height, width):
//   sum[p, iy, ix] += x[p, mirror_y ? height - 1 - iy : iy, mirror_x ? width - 1 - ix : ix],
// one float addition per element (the sum's value, then x's), so the result is the host's bit for
// bit. One grid-stride loop over the sum's elements; each has one writer. Pointers are device
// memory; the work is queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// x, sum (planes, height, width); sum must not overlap x.
void mirror_add(const float* x, std::int64_t planes, std::int64_t height, std::int64_t width,
                bool mirror_y, bool mirror_x, float* sum, cudaStream_t stream);

}  // namespace pillarseg::cuda
