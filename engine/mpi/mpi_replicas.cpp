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

// One piece of the gradients on its way: the chunk bounds of every replica, this replica's
// received chunks (R x mine) and the request of the stage it is in.
struct MpiReplicas::PieceSum {
  float* values = nullptr;
  std::vector<int> counts, offsets, receive_counts, receive_offsets;
  std::vector<float> chunks;
  MPI_Request request = MPI_REQUEST_NULL;
};

struct MpiReplicas::Communicators {
  MPI_Comm exchange = MPI_COMM_NULL, gather = MPI_COMM_NULL;
};

MpiReplicas::MpiReplicas() {
  int initialised = 0;
  check_mpi(MPI_Initialized(&initialised), "MPI_Initialized");
  PS_CHECK(!initialised, "MPI is already initialised in this process: one MpiReplicas per process");
  int provided = 0;
  check_mpi(MPI_Init_thread(nullptr, nullptr, MPI_THREAD_FUNNELED, &provided), "MPI_Init_thread");
  check_mpi(MPI_Comm_set_errhandler(MPI_COMM_WORLD, MPI_ERRORS_RETURN), "MPI_Comm_set_errhandler");
  check_mpi(MPI_Comm_rank(MPI_COMM_WORLD, &rank_), "MPI_Comm_rank");
  check_mpi(MPI_Comm_size(MPI_COMM_WORLD, &size_), "MPI_Comm_size");
  comms_ = std::make_unique<Communicators>();
  check_mpi(MPI_Comm_dup(MPI_COMM_WORLD, &comms_->exchange), "MPI_Comm_dup");
  check_mpi(MPI_Comm_dup(MPI_COMM_WORLD, &comms_->gather), "MPI_Comm_dup");
}

MpiReplicas::~MpiReplicas() {
  pieces_.clear();
  if (comms_->exchange != MPI_COMM_NULL) MPI_Comm_free(&comms_->exchange);
  if (comms_->gather != MPI_COMM_NULL) MPI_Comm_free(&comms_->gather);
  MPI_Finalize();
}

void MpiReplicas::sum(double* values, int64_t n) {
  if (size_ > 1) gather_and_add(values, n, MPI_DOUBLE, size_, gathered_doubles_);
}

void MpiReplicas::sum(int64_t* values, int64_t n) {
  if (size_ > 1) gather_and_add(values, n, MPI_INT64_T, size_, gathered_counts_);
}

void MpiReplicas::begin_sum(float* values, int64_t n) {
  if (size_ <= 1) return;
  mpi_count(n, "gradients");
  if (begun_ == pieces_.size()) pieces_.push_back(std::make_unique<PieceSum>());
  PieceSum& p = *pieces_[begun_++];
  const auto R = static_cast<size_t>(size_);
  p.values = values;
  p.counts.resize(R), p.offsets.resize(R), p.receive_counts.resize(R), p.receive_offsets.resize(R);
  const auto begin = [&](int r) { return static_cast<int>(n * r / size_); };
  for (int r = 0; r < size_; ++r) {
    p.offsets[static_cast<size_t>(r)] = begin(r);
    p.counts[static_cast<size_t>(r)] = begin(r + 1) - begin(r);
  }
  // Replica r receives chunk r of every replica's piece, replica q's at q * mine.
  const int mine = p.counts[static_cast<size_t>(rank_)];
  for (int r = 0; r < size_; ++r) {
    p.receive_counts[static_cast<size_t>(r)] = mine;
    p.receive_offsets[static_cast<size_t>(r)] = r * mine;
  }
  p.chunks.resize(static_cast<size_t>(mine) * R);
  check_mpi(MPI_Ialltoallv(values, p.counts.data(), p.offsets.data(), MPI_FLOAT, p.chunks.data(),
                           p.receive_counts.data(), p.receive_offsets.data(), MPI_FLOAT,
                           comms_->exchange, &p.request),
            "MPI_Ialltoallv");
}

void MpiReplicas::gather(PieceSum& p) {
  const int mine = p.counts[static_cast<size_t>(rank_)];
  float* own = p.values + p.offsets[static_cast<size_t>(rank_)];
  for (int i = 0; i < mine; ++i) {
    float total = p.chunks[static_cast<size_t>(i)];
    for (int r = 1; r < size_; ++r)
      total += p.chunks[static_cast<size_t>(r) * static_cast<size_t>(mine) + static_cast<size_t>(i)];
    own[i] = total;
  }
  check_mpi(MPI_Iallgatherv(MPI_IN_PLACE, 0, MPI_DATATYPE_NULL, p.values, p.counts.data(),
                            p.offsets.data(), MPI_FLOAT, comms_->gather, &p.request),
            "MPI_Iallgatherv");
}

void MpiReplicas::progress() {
  // The all-gathers are posted in the order of the pieces: the first piece whose exchange has
  // not arrived stops the walk. Testing one request also moves the others along (MPI's
  // progress engine runs inside every call).
  while (gathering_ < begun_) {
    PieceSum& p = *pieces_[gathering_];
    int done = 0;
    check_mpi(MPI_Test(&p.request, &done, MPI_STATUS_IGNORE), "MPI_Test");
    if (done == 0) return;
    gather(p);
    ++gathering_;
  }
  if (begun_ > 0) {
    int done = 0;
    check_mpi(MPI_Test(&pieces_[begun_ - 1]->request, &done, MPI_STATUS_IGNORE), "MPI_Test");
  }
}

void MpiReplicas::end_sums() {
  for (; gathering_ < begun_; ++gathering_) {
    PieceSum& p = *pieces_[gathering_];
    check_mpi(MPI_Wait(&p.request, MPI_STATUS_IGNORE), "MPI_Wait");
    gather(p);
  }
  for (size_t i = 0; i < begun_; ++i)
    check_mpi(MPI_Wait(&pieces_[i]->request, MPI_STATUS_IGNORE), "MPI_Wait");
  begun_ = gathering_ = 0;
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
