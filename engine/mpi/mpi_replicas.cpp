#include "engine/mpi/mpi_replicas.hpp"

#include <mpi.h>

#include <cstdio>
#include <cstdlib>
#include <limits>
#include <string>

#include "core/error.hpp"

namespace pillarseg {

namespace {

// Every MPI call goes through here: MPI_ERRORS_RETURN is set on the communicator, so a failure
// becomes a pillarseg::Error naming the call and MPI's own message.
void check_mpi(int code, const char* call) {
  if (code == MPI_SUCCESS) return;
  char text[MPI_MAX_ERROR_STRING];
  int length = 0;
  MPI_Error_string(code, text, &length);
  PS_FAIL("{} failed: {}", call, std::string(text, static_cast<size_t>(length)));
}

int mpi_count(int64_t n, const char* what) {
  PS_CHECK(n >= 0 && n <= std::numeric_limits<int>::max(),
           "data-parallel sum of {}: {} values are more than MPI's int "
           "counts hold",
           what, n);
  return static_cast<int>(n);
}

// Gathers n values of every replica into gathered (R * n), then replaces values[i] by
// gathered[0 * n + i] + gathered[1 * n + i] + ... in that order.
template <class T>
void gather_and_add(T* values, int64_t n, MPI_Datatype type, int size, std::vector<T>& gathered) {
  const int count = mpi_count(n, "statistics");
  gathered.resize(static_cast<size_t>(n) * static_cast<size_t>(size));
  check_mpi(MPI_Allgather(values, count, type, gathered.data(), count, type, MPI_COMM_WORLD),
            "MPI_Allgather");
  for (int64_t i = 0; i < n; ++i) {
    T total = gathered[static_cast<size_t>(i)];
    for (int r = 1; r < size; ++r)
      total += gathered[static_cast<size_t>(r) * static_cast<size_t>(n) + static_cast<size_t>(i)];
    values[i] = total;
  }
}

}  // namespace

MpiReplicas::MpiReplicas() {
  int initialised = 0;
  check_mpi(MPI_Initialized(&initialised), "MPI_Initialized");
  PS_CHECK(!initialised, "MPI is already initialised in this process: one MpiReplicas per process");
  int provided = 0;
  check_mpi(MPI_Init_thread(nullptr, nullptr, MPI_THREAD_FUNNELED, &provided), "MPI_Init_thread");
  check_mpi(MPI_Comm_set_errhandler(MPI_COMM_WORLD, MPI_ERRORS_RETURN), "MPI_Comm_set_errhandler");
  check_mpi(MPI_Comm_rank(MPI_COMM_WORLD, &rank_), "MPI_Comm_rank");
  check_mpi(MPI_Comm_size(MPI_COMM_WORLD, &size_), "MPI_Comm_size");
}

MpiReplicas::~MpiReplicas() {
  MPI_Finalize();
}

void MpiReplicas::sum(double* values, int64_t n) {
  if (size_ > 1) gather_and_add(values, n, MPI_DOUBLE, size_, gathered_doubles_);
}

void MpiReplicas::sum(int64_t* values, int64_t n) {
  if (size_ > 1) gather_and_add(values, n, MPI_INT64_T, size_, gathered_counts_);
}

void MpiReplicas::sum(float* values, int64_t n) {
  if (size_ <= 1) return;
  mpi_count(n, "gradients");
  const auto begin = [&](int r) { return static_cast<int>(n * r / size_); };
  std::vector<int> counts(static_cast<size_t>(size_)), offsets(static_cast<size_t>(size_));
  for (int r = 0; r < size_; ++r) {
    offsets[static_cast<size_t>(r)] = begin(r);
    counts[static_cast<size_t>(r)] = begin(r + 1) - begin(r);
  }
  // Replica r receives chunk r of every replica's gradients, replica p's at p * mine.
  const int mine = counts[static_cast<size_t>(rank_)];
  std::vector<int> receive_counts(static_cast<size_t>(size_), mine),
      receive_offsets(static_cast<size_t>(size_));
  for (int r = 0; r < size_; ++r) receive_offsets[static_cast<size_t>(r)] = r * mine;
  chunks_.resize(static_cast<size_t>(mine) * static_cast<size_t>(size_));
  check_mpi(MPI_Alltoallv(values, counts.data(), offsets.data(), MPI_FLOAT, chunks_.data(),
                          receive_counts.data(), receive_offsets.data(), MPI_FLOAT, MPI_COMM_WORLD),
            "MPI_Alltoallv");
  float* own = values + offsets[static_cast<size_t>(rank_)];
  for (int i = 0; i < mine; ++i) {
    float total = chunks_[static_cast<size_t>(i)];
    for (int r = 1; r < size_; ++r)
      total += chunks_[static_cast<size_t>(r) * static_cast<size_t>(mine) + static_cast<size_t>(i)];
    own[i] = total;
  }
  check_mpi(MPI_Allgatherv(MPI_IN_PLACE, 0, MPI_DATATYPE_NULL, values, counts.data(),
                           offsets.data(), MPI_FLOAT, MPI_COMM_WORLD),
            "MPI_Allgatherv");
}

void MpiReplicas::broadcast(void* bytes, size_t n) {
  if (size_ > 1) check_mpi(MPI_Bcast(bytes, mpi_count(static_cast<int64_t>(n), "bytes"), MPI_BYTE, 0, MPI_COMM_WORLD), "MPI_Bcast");
}

void MpiReplicas::abort_all(const std::string& message) {
  std::fprintf(stderr, "pillarseg: error (rank %d of %d): %s\n", rank_, size_, message.c_str());
  std::fflush(stderr);
  MPI_Abort(MPI_COMM_WORLD, 1);
  std::abort();  // MPI_Abort does not return; this keeps [[noreturn]] honest if it ever did
}

}  // namespace pillarseg
