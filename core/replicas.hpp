// The replicas of a data-parallel training run (DESIGN.md section 8): R processes, each training
// on its share of every global batch, kept identical by summing what they computed in a fixed
// order (replica 0, 1, ..., R - 1), so that the results depend on R but never on timing and
// every replica holds the same bits.
//   ReplicaSum: the sums an op needs inside itself (synchronised BatchNorm's statistics); an op
//     given one calls it where its per-channel sums over its own values are complete; without one
//     (nullptr) it is the single-process op.
//   Replicas: a process's place in the run and every sum the trainer needs, the gradients' in
//     pieces that may be summed while the backward goes on (begin_sum ... end_sums). SingleProcess
//     is the run of one; the MPI implementation (engine/mpi/) is linked into the command line
//     only, so that MPI never reaches libpillarseg.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

#include "core/error.hpp"

namespace pillarseg {

class ReplicaSum {
 public:
  virtual ~ReplicaSum() = default;
  // Replaces values[0, n) with their sums over all replicas, added in replica order
  // (v_0 + v_1 + ... + v_{R-1}), so that every replica gets the same bits whatever the timing.
  // Every replica calls it with the same n at the same point of the same op.
  virtual void sum(double* values, int64_t n) = 0;
};

class Replicas : public ReplicaSum {
 public:
  virtual int rank() const = 0;
  virtual int size() const = 0;
  bool leader() const { return rank() == 0; }  // writes the checkpoints and logs
  using ReplicaSum::sum;
  // Exact sums of counts (the validation's confusion matrix, labelled cells).
  virtual void sum(int64_t* values, int64_t n) = 0;
  // n floats in host memory (a piece of the parameter gradients) summed in replica order, begun
  // now and complete when end_sums() returns; values must stay untouched until then. Every
  // replica begins the same pieces in the same order, and may make other sums in between (they
  // do not wait for the pieces begun). progress() lets begun sums advance (the trainer calls it
  // between the backward's ops); end_sums() completes every piece begun since the last call.
  virtual void begin_sum(float* values, int64_t n) = 0;
  virtual void progress() = 0;
  virtual void end_sums() = 0;
  // Replica 0's bytes[0, n) to every replica (e.g. a communicator's id).
  virtual void broadcast(void* bytes, size_t n) = 0;
  // Stops every replica after this one failed with `message`; does not return.
  [[noreturn]] virtual void abort_all(const std::string& message) = 0;
};

class SingleProcess final : public Replicas {
 public:
  int rank() const override { return 0; }
  int size() const override { return 1; }
  void sum(double*, int64_t) override {}
  void sum(int64_t*, int64_t) override {}
  void begin_sum(float*, int64_t) override {}
  void progress() override {}
  void end_sums() override {}
  void broadcast(void*, size_t) override {}
  [[noreturn]] void abort_all(const std::string& message) override { throw Error(message); }
};

}  // namespace pillarseg
