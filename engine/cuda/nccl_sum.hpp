// The data-parallel gradient sum in device memory over NCCL (DESIGN.md section 8), for the CUDA
// backend on a GPU: the same replica-order sum as the host's MPI path (engine/mpi/), so that a
// run's bits do not depend on timing, NCCL's algorithm choice or the transport:
//   a reduce-scatter by hand: the gradients, padded to R chunks of equal size, are exchanged with
//   grouped ncclSend / ncclRecv so that replica r holds chunk r of every replica side by side;
//   kernels/replica_sum.cuh adds them in replica order; an ncclAllGather of the summed chunks.
// NCCL is loaded when the first sum needs it (dlopen of libnccl.so.2), so that libpillarseg and
// the command line run where it is not installed; the communicator's unique id comes from replica
// 0 through the Replicas (MPI), as llm.c does. Each replica uses its own GPU.
#pragma once

#include <cstdint>
#include <memory>

#include "core/replicas.hpp"
#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg {

class NcclGradientSum {
 public:
  // Creates the communicator of `replicas` on the current device (collective: every replica
  // constructs one). Throws pillarseg::Error when NCCL cannot be loaded or initialised.
  NcclGradientSum(Replicas& replicas, cudaStream_t stream);
  ~NcclGradientSum();
  NcclGradientSum(const NcclGradientSum&) = delete;
  NcclGradientSum& operator=(const NcclGradientSum&) = delete;

  // values (n floats of device memory) summed over the replicas in replica order, queued on the
  // stream given to the constructor.
  void sum(float* values, int64_t n);

 private:
  struct State;
  std::unique_ptr<State> state_;
};

}  // namespace pillarseg
