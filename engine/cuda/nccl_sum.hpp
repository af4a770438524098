// The data-parallel sums in device memory over NCCL (DESIGN.md section 8), for the CUDA backend on
// a GPU: the same replica-order sums as the host's MPI path (engine/mpi/), so that a run's bits
// do not depend on timing, NCCL's algorithm choice or the transport.
//   NcclCommunicator: one communicator over the replicas, the one a backend's sums share. NCCL is
//     loaded when it is made (dlopen of libnccl.so.2), so that libpillarseg and the command line
//     run where it is not installed; the unique id comes from replica 0 through the Replicas
//     (MPI), as llm.c does. Each replica uses its own GPU.
//   NcclGradientSum: the gradients, a reduce-scatter by hand (the gradients, padded to R chunks of
//     equal size, exchanged with grouped ncclSend / ncclRecv so that replica r holds chunk r of
//     every replica side by side; kernels/replica_sum.cuh adds them in replica order) and an
//     ncclAllGather of the summed chunks. The sums run on a stream of their own: begin() makes
//     it wait for the compute stream's work queued so far (an event), so that the backward's
//     later kernels run while NCCL moves the piece; end() makes the compute stream wait for every
//     sum begun. Pieces follow one another on that stream and share its scratch.
//   NcclStatisticsSum: synchronised BatchNorm's small vectors of doubles (kernels/batchnorm.cuh),
//     a DeviceReplicaSum: an ncclAllGather of every replica's vector and the replica-order add,
//     on the stream the op gives (the compute stream: the sums sit between the op's kernels), so
//     that no BatchNorm waits for the device.
// NCCL runs the operations of one communicator one after another in the order they were issued,
// whatever their streams: a statistics sum waits for the gradient pieces begun before it.
// One replica runs every path too (sending to and receiving from itself), so that a machine with
// one GPU checks them (tests/test_cuda_backend.cpp).
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>

#include "core/replicas.hpp"
#include "kernels/cuda_handles.hpp"
#include "kernels/device_buffer.hpp"
#include "kernels/emu/cuda_compat.cuh"
#include "kernels/replica_sum.cuh"

namespace pillarseg {

class NcclCommunicator {
 public:
  // Loads NCCL and creates the communicator of `replicas` on the current device (collective:
  // every replica constructs one). Throws pillarseg::Error when NCCL cannot be loaded or
  // initialised.
  explicit NcclCommunicator(Replicas& replicas);
  ~NcclCommunicator();
  NcclCommunicator(const NcclCommunicator&) = delete;
  NcclCommunicator& operator=(const NcclCommunicator&) = delete;

  int rank() const;
  int size() const;
  // Replica p gets send[p * chunk, (p + 1) * chunk) of every replica q into
  // receive[q * chunk, (q + 1) * chunk), queued on `stream` (grouped ncclSend / ncclRecv).
  void exchange_chunks(const float* send, float* receive, size_t chunk, cudaStream_t stream);
  // Every replica's mine[0, count) into all[q * count, (q + 1) * count), q its rank.
  void all_gather(const float* mine, float* all, size_t count, cudaStream_t stream);
  void all_gather(const double* mine, double* all, size_t count, cudaStream_t stream);

 private:
  struct State;
  std::unique_ptr<State> state_;
};

class NcclGradientSum {
 public:
  // The sums' stream; `communicator` and `compute` (the backend's stream) must outlive it.
  NcclGradientSum(NcclCommunicator& communicator, cudaStream_t compute);
  NcclGradientSum(const NcclGradientSum&) = delete;
  NcclGradientSum& operator=(const NcclGradientSum&) = delete;

  // values (n floats of device memory) summed over the replicas in replica order once the
  // compute stream's work queued so far is done; the result is there for the compute stream's
  // work queued after end().
  void begin(float* values, int64_t n);
  void end();

 private:
  NcclCommunicator& communicator_;
  cudaStream_t compute_;
  cuda::Stream stream_;           // the sums'
  cuda::Event reached_, summed_;  // compute reached a piece; the sums queued so far are done
  cuda::DeviceBuffer<float> padded_, chunks_;  // (R x chunk) each
};

class NcclStatisticsSum final : public cuda::DeviceReplicaSum {
 public:
  // `communicator` and `replicas` (whose host sums this sum's host-memory sum is) must outlive it.
  NcclStatisticsSum(NcclCommunicator& communicator, Replicas& replicas);

  void sum(double* values, int64_t n) override;  // host memory: the Replicas' sum
  // Grows, waiting for the device (queued work may still use the old memory), only when n
  // exceeds every n before: a training loop waits only in its first step.
  double* scratch(int64_t n) override;
  void sum(double* values, int64_t n, cudaStream_t stream) override;

 private:
  NcclCommunicator& communicator_;
  Replicas& replicas_;
  cuda::DeviceBuffer<double> scratch_, gathered_;  // gathered: (R x n)
};

}  // namespace pillarseg
