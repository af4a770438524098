// The data-parallel gradient sum in device memory over NCCL (DESIGN.md section 8), for the CUDA
// backend on a GPU: the same replica-order sum as the host's MPI path (engine/mpi/), so that a
// run's bits do not depend on timing, NCCL's algorithm choice or the transport:
//   a reduce-scatter by hand: the gradients, padded to R chunks of equal size, are exchanged with
//   grouped ncclSend / ncclRecv so that replica r holds chunk r of every replica side by side;
//   kernels/replica_sum.cuh adds them in replica order; an ncclAllGather of the summed chunks.
// NCCL is loaded when the first sum needs it (dlopen of libnccl.so.2), so that libpillarseg and
// the command line run where it is not installed; the communicator's unique id comes from replica
// 0 through the Replicas (MPI), as llm.c does. Each replica uses its own GPU.
// The sums run on a stream of their own: begin() makes it wait for the compute stream's work
// queued so far (an event), so that the backward's later kernels run while NCCL moves the piece;
// end() makes the compute stream wait for every sum begun. Pieces follow one another on that
// stream and share its scratch. One replica runs the whole path too (sending to and receiving
// from itself), so that a machine with one GPU checks it (tests/test_cuda_backend.cpp).
#pragma once

#include <cstdint>
#include <memory>

#include "core/replicas.hpp"
#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg {

class NcclGradientSum {
 public:
  // Creates the communicator of `replicas` on the current device (collective: every replica
  // constructs one) and the sums' stream. Throws pillarseg::Error when NCCL cannot be loaded or
  // initialised.
  NcclGradientSum(Replicas& replicas, cudaStream_t compute);
  ~NcclGradientSum();
  NcclGradientSum(const NcclGradientSum&) = delete;
  NcclGradientSum& operator=(const NcclGradientSum&) = delete;

  // values (n floats of device memory) summed over the replicas in replica order once the
  // compute stream's work queued so far is done; the result is there for the compute stream's
  // work queued after end().
  void begin(float* values, int64_t n);
  void end();

 private:
  struct State;
  std::unique_ptr<State> state_;
};

}  // namespace pillarseg
