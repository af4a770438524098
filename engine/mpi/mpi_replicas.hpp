// Data-parallel replicas over MPI (OpenMPI from Debian): `mpirun -np R pillarseg train ...`.
// One MpiReplicas per process, on MPI_COMM_WORLD; MPI is initialised by the constructor and
// finalised by the destructor. Every sum is in replica order, the same bits on every replica:
//   doubles and counts (BatchNorm statistics, confusion matrices; a few thousand values): all
//     gathered, then added 0, 1, ..., R - 1 by each replica;
//   gradients (the whole parameter arena): a reduce-scatter by hand (replica r gathers chunk r
//     of every replica's gradients with one all-to-all and adds them in order) and an all-gather
//     of the summed chunks; each value crosses the network twice, as in a ring all-reduce.
// MPI calls come from the training thread only (MPI_THREAD_FUNNELED).
#pragma once

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
  void sum(float* values, int64_t n) override;
  void broadcast(void* bytes, size_t n) override;
  [[noreturn]] void abort_all(const std::string& message) override;

 private:
  int rank_ = 0, size_ = 1;
  std::vector<double> gathered_doubles_;
  std::vector<int64_t> gathered_counts_;
  std::vector<float> chunks_;
};

}  // namespace pillarseg
