// The device side of the data-parallel gradient sum (engine/cuda/nccl_replicas.cpp): the R
// replicas' copies of one chunk of the gradients, received side by side, added in replica order,
// so that a GPU run sums exactly as the host's MPI path does (engine/mpi/mpi_replicas.cpp):
//   chunks (R, n) -> out (n), out[i] = chunks[0][i] + chunks[1][i] + ... + chunks[R - 1][i].
// Pointers are device memory; the work is queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

void sum_replica_chunks(const float* chunks, int replicas, std::int64_t n, float* out,
                        cudaStream_t stream);

}  // namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE
