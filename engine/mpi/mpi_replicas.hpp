// Data-parallel replicas over MPI (OpenMPI from Debian): `mpirun -np R pillarseg train ...`.
// One MpiReplicas per process, on MPI_COMM_WORLD; MPI is initialised by the constructor and
// finalised by the destructor. Every sum is in replica order, the same bits on every replica:
//   doubles and counts (BatchNorm statistics, confusion matrices; a few thousand values): all
//     gathered, then added 0, 1, ..., R - 1 by each replica;
//   gradients (pieces of the parameter arena, begun as the backward completes them): a
//     reduce-scatter by hand (replica r gathers chunk r of every replica's piece with one
//     nonblocking all-to-all and adds them in order) and a nonblocking all-gather of the summed
//     chunks; each value crosses the network twice, as in a ring all-reduce. The all-to-alls run
//     on one duplicate of MPI_COMM_WORLD and the all-gathers on another, each posted in the order
//     the pieces were begun (an all-gather only once every earlier piece's is posted), so that
//     the collectives match on every rank whatever the timing, and the statistics' blocking sums
//     on MPI_COMM_WORLD may come in between.
// MPI calls come from the training thread only (MPI_THREAD_FUNNELED).
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "core/replicas.hpp"

namespace pillarseg {

class MpiReplicas final : public Replicas {
 public:
  MpiReplicas();
  ~MpiReplicas() override;
  MpiReplicas(const MpiReplicas&) = delete;
  MpiReplicas& operator=(const MpiReplicas&) = delete;

  int rank() const override { return rank_; }
  int size() const override { return size_; }
  void sum(double* values, int64_t n) override;
  void sum(int64_t* values, int64_t n) override;
  void begin_sum(float* values, int64_t n) override;
  void progress() override;
  void end_sums() override;
  void broadcast(void* bytes, size_t n) override;
  [[noreturn]] void abort_all(const std::string& message) override;

 private:
  struct PieceSum;
  // Adds the piece's exchanged chunks in replica order and posts its all-gather.
  void gather(PieceSum& piece);

  int rank_ = 0, size_ = 1;
  std::vector<double> gathered_doubles_;
  std::vector<int64_t> gathered_counts_;
  // The communicators of the gradient sums' two halves (MPI_Comm, an int or a pointer by MPI's
  // choice, kept opaque here so that this header needs no mpi.h).
  struct Communicators;
  std::unique_ptr<Communicators> comms_;
  // The pieces begun since the last end_sums(), in order; their buffers are kept for the next
  // step's pieces (the same sizes every step).
  std::vector<std::unique_ptr<PieceSum>> pieces_;
  size_t begun_ = 0;      // pieces_[0, begun_) are in flight
  size_t gathering_ = 0;  // pieces_[0, gathering_) have their all-gather posted
};

}  // namespace pillarseg
