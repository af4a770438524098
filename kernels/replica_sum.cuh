// The device side of the data-parallel sums (DESIGN.md section 8), so that a GPU run sums exactly
// as the host's MPI path does (engine/mpi/mpi_replicas.cpp), in replica order:
//   sum_replica_chunks: the R replicas' copies of n values, received side by side, added in
//     replica order: chunks (R, n) -> out (n), out[i] = chunks[0][i] + chunks[1][i] + ... +
//     chunks[R - 1][i]; floats (the gradients, engine/cuda/nccl_sum.cpp) and doubles (the
//     BatchNorm statistics). Pointers are device memory; the work is queued on `stream`.
//   DeviceReplicaSum: a ReplicaSum (core/replicas.hpp) that also sums vectors in device memory
//     as work queued on a stream, so that an op in the middle of the forward or backward (the
//     synchronised BatchNorm of kernels/batchnorm.cu) never waits for the device. The CUDA
//     backend's implementation is NCCL's (engine/cuda/nccl_sum.hpp); an op given a ReplicaSum
//     that is one takes the device path.
#pragma once

#include <cstdint>

#include "core/replicas.hpp"
#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

void sum_replica_chunks(const float* chunks, int replicas, std::int64_t n, float* out,
                        cudaStream_t stream);
void sum_replica_chunks(const double* chunks, int replicas, std::int64_t n, double* out,
                        cudaStream_t stream);

class DeviceReplicaSum : public ReplicaSum {
 public:
  using ReplicaSum::sum;
  // Device memory for at least n doubles, this sum's own: where a caller keeps the vectors it
  // sums and what it computes from one sum for the next, so that an op whose workspace is sized
  // for one process needs no more. The same memory, holding what the caller left there, as long
  // as n does not exceed the largest n asked before; a larger n may move it and lose its values.
  virtual double* scratch(std::int64_t n) = 0;
  // Replaces values[0, n) (device memory) with their sums over all replicas, added in replica
  // order, by work queued on `stream` after the work queued there so far; the host does not
  // wait. Every replica calls it with the same n at the same point of the same op.
  virtual void sum(double* values, std::int64_t n, cudaStream_t stream) = 0;
};

}  // namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE
