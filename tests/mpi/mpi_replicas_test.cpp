// MpiReplicas under `mpirun -np R` (R >= 2; CTest runs 3, so that the gradient chunks are
// uneven): every sum is the replica-order sum v_0 + v_1 + ... computed here by each rank from
// the values every rank contributes (a function of rank and index), bit for bit, for sizes
// below, at and above R; the float sums are chosen so that another order gives other bits. The
// floats are summed in pieces that are in flight together, with blocking sums in between (the
// trainer's buckets and synchronised BatchNorm), and each size reuses the last one's pieces.
// Exits 1 with the first mismatch.
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <vector>

#include "engine/mpi/mpi_replicas.hpp"

namespace {

// Rank r's value at index i: magnitudes far apart, so that the order of the additions shows.
float contribution(int r, int64_t i) {
  const float scale[] = {1.0f, 3e-8f, 3e-8f, -1.0f, 0.5f};
  return scale[r % 5] * (1.0f + static_cast<float>(i % 7) * 0.125f);
}

int failures = 0;

void expect(bool ok, const char* what, int rank, int64_t n, int64_t i) {
  if (ok) return;
  if (failures++ < 5)
    std::fprintf(stderr, "rank %d: %s differs at n = %lld, i = %lld\n", rank, what,
                 static_cast<long long>(n), static_cast<long long>(i));
}

}  // namespace

int main() {
  pillarseg::MpiReplicas replicas;
  const int R = replicas.size(), me = replicas.rank();
  if (R < 2) {
    std::fprintf(stderr, "run under mpirun -np 2 or more (got %d process)\n", R);
    return 1;
  }
  for (const int64_t n :
       {int64_t{0}, int64_t{1}, int64_t{R - 1}, int64_t{R}, int64_t{1000}, int64_t{4099}}) {
    std::vector<float> floats(static_cast<size_t>(n));
    std::vector<double> doubles(static_cast<size_t>(n));
    std::vector<int64_t> counts(static_cast<size_t>(n));
    for (int64_t i = 0; i < n; ++i) {
      floats[static_cast<size_t>(i)] = contribution(me, i);
      doubles[static_cast<size_t>(i)] = static_cast<double>(contribution(me, i)) * 1e-3;
      counts[static_cast<size_t>(i)] = (int64_t{1} << 40) * me + i;
    }
    // The floats in three pieces begun one after another (the last first, as the backward does),
    // with the blocking sums and progress() in between and end_sums() after all of them.
    const int64_t cut1 = n / 3, cut2 = n - n / 4;
    replicas.begin_sum(floats.data() + cut2, n - cut2);
    replicas.progress();
    replicas.sum(doubles.data(), n);
    replicas.begin_sum(floats.data() + cut1, cut2 - cut1);
    replicas.progress();
    replicas.sum(counts.data(), n);
    replicas.progress();
    replicas.begin_sum(floats.data(), cut1);
    replicas.end_sums();
    for (int64_t i = 0; i < n; ++i) {
      float f = contribution(0, i);
      double d = static_cast<double>(contribution(0, i)) * 1e-3;
      int64_t c = i;
      for (int r = 1; r < R; ++r) {
        f += contribution(r, i);
        d += static_cast<double>(contribution(r, i)) * 1e-3;
        c += (int64_t{1} << 40) * r + i;
      }
      expect(std::memcmp(&f, &floats[static_cast<size_t>(i)], sizeof f) == 0, "the float sum", me,
             n, i);
      expect(std::memcmp(&d, &doubles[static_cast<size_t>(i)], sizeof d) == 0, "the double sum", me,
             n, i);
      expect(c == counts[static_cast<size_t>(i)], "the count sum", me, n, i);
    }
  }
  // The test's own premise: the order matters for these values (else a reordered sum passes).
  const float forward = (contribution(0, 0) + contribution(1, 0)) + contribution(2, 0);
  const float reordered = contribution(0, 0) + (contribution(1, 0) + contribution(2, 0));
  if (R >= 3 && forward == reordered) {
    std::fprintf(stderr, "the test values do not tell the order of the additions apart\n");
    return 1;
  }
  if (failures > 0) return 1;
  if (me == 0)
    std::printf("MpiReplicas: float, double and count sums in replica order on %d ranks\n", R);
  return 0;
}
