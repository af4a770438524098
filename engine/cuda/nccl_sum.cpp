#include "engine/cuda/nccl_sum.hpp"

#include <dlfcn.h>
#include <nccl.h>

#include <string>

namespace pillarseg {

namespace {

// The NCCL entry points these sums call, from the library dlopen() found.
struct NcclApi {
  ncclResult_t (*get_unique_id)(ncclUniqueId*) = nullptr;
  ncclResult_t (*comm_init_rank)(ncclComm_t*, int, ncclUniqueId, int) = nullptr;
  ncclResult_t (*comm_destroy)(ncclComm_t) = nullptr;
  ncclResult_t (*group_start)() = nullptr;
  ncclResult_t (*group_end)() = nullptr;
  ncclResult_t (*send)(const void*, size_t, ncclDataType_t, int, ncclComm_t,
                       cudaStream_t) = nullptr;
  ncclResult_t (*recv)(void*, size_t, ncclDataType_t, int, ncclComm_t, cudaStream_t) = nullptr;
  ncclResult_t (*all_gather)(const void*, void*, size_t, ncclDataType_t, ncclComm_t,
                             cudaStream_t) = nullptr;
  const char* (*error_string)(ncclResult_t) = nullptr;
};

// The loaded library, closed by the destructor.
class NcclLibrary {
 public:
  NcclLibrary() {
    handle_ = dlopen("libnccl.so.2", RTLD_NOW | RTLD_LOCAL);
    if (handle_ == nullptr) handle_ = dlopen("libnccl.so", RTLD_NOW | RTLD_LOCAL);
    PS_CHECK(handle_ != nullptr,
             "data-parallel training on the GPU needs NCCL, and libnccl.so.2 cannot be loaded "
             "({}); install NCCL "
             "(it comes with the CUDA toolkit's repositories) or put it on LD_LIBRARY_PATH",
             dlerror());
    bind(api.get_unique_id, "ncclGetUniqueId");
    bind(api.comm_init_rank, "ncclCommInitRank");
    bind(api.comm_destroy, "ncclCommDestroy");
    bind(api.group_start, "ncclGroupStart");
    bind(api.group_end, "ncclGroupEnd");
    bind(api.send, "ncclSend");
    bind(api.recv, "ncclRecv");
    bind(api.all_gather, "ncclAllGather");
    bind(api.error_string, "ncclGetErrorString");
  }
  ~NcclLibrary() {
    if (handle_ != nullptr) dlclose(handle_);
  }
  NcclLibrary(const NcclLibrary&) = delete;
  NcclLibrary& operator=(const NcclLibrary&) = delete;

  NcclApi api;

 private:
  template <class Fn>
  void bind(Fn& fn, const char* name) {
    fn = reinterpret_cast<Fn>(dlsym(handle_, name));
    PS_CHECK(fn != nullptr,
             "the NCCL library has no {} (NCCL 2.7 or later is needed for send / receive)", name);
  }
  void* handle_ = nullptr;
};

}  // namespace

// ---- the communicator ----

struct NcclCommunicator::State {
  NcclLibrary library;
  ncclComm_t comm = nullptr;
  int rank = 0, size = 1;

  void check(ncclResult_t result, const char* call) const {
    PS_CHECK(result == ncclSuccess, "{} failed: {}", call, library.api.error_string(result));
  }
  ~State() {
    if (comm != nullptr) library.api.comm_destroy(comm);  // before the library is closed
  }
};

NcclCommunicator::NcclCommunicator(Replicas& replicas) : state_(std::make_unique<State>()) {
  State& s = *state_;
  s.rank = replicas.rank(), s.size = replicas.size();
  ncclUniqueId id{};
  if (replicas.leader()) s.check(s.library.api.get_unique_id(&id), "ncclGetUniqueId");
  replicas.broadcast(&id, sizeof id);
  s.check(s.library.api.comm_init_rank(&s.comm, s.size, id, s.rank), "ncclCommInitRank");
}

NcclCommunicator::~NcclCommunicator() = default;

int NcclCommunicator::rank() const {
  return state_->rank;
}

int NcclCommunicator::size() const {
  return state_->size;
}

void NcclCommunicator::exchange_chunks(const float* send, float* receive, size_t chunk,
                                       cudaStream_t stream) {
  const State& s = *state_;
  const NcclApi& api = s.library.api;
  s.check(api.group_start(), "ncclGroupStart");
  for (int p = 0; p < s.size; ++p) {
    const size_t offset = static_cast<size_t>(p) * chunk;
    s.check(api.send(send + offset, chunk, ncclFloat, p, s.comm, stream), "ncclSend");
    s.check(api.recv(receive + offset, chunk, ncclFloat, p, s.comm, stream), "ncclRecv");
  }
  s.check(api.group_end(), "ncclGroupEnd");
}

void NcclCommunicator::all_gather(const float* mine, float* all, size_t count,
                                  cudaStream_t stream) {
  const State& s = *state_;
  s.check(s.library.api.all_gather(mine, all, count, ncclFloat, s.comm, stream), "ncclAllGather");
}

void NcclCommunicator::all_gather(const double* mine, double* all, size_t count,
                                  cudaStream_t stream) {
  const State& s = *state_;
  s.check(s.library.api.all_gather(mine, all, count, ncclDouble, s.comm, stream), "ncclAllGather");
}

// ---- the gradients ----

NcclGradientSum::NcclGradientSum(NcclCommunicator& communicator, cudaStream_t compute)
    : communicator_(communicator), compute_(compute) {}

void NcclGradientSum::begin(float* values, int64_t n) {
  if (n == 0) return;
  const auto R = static_cast<size_t>(communicator_.size());
  const size_t chunk = (static_cast<size_t>(n) + R - 1) / R;
  if (padded_.size() < R * chunk) {
    PS_CUDA_CHECK(cudaStreamSynchronize(stream_.get()));  // earlier pieces use the scratch
    padded_ = cuda::DeviceBuffer<float>(R * chunk);
    chunks_ = cuda::DeviceBuffer<float>(R * chunk);
  }
  PS_CUDA_CHECK(cudaEventRecord(reached_.get(), compute_));
  PS_CUDA_CHECK(cudaStreamWaitEvent(stream_.get(), reached_.get(), 0));
  cudaStream_t stream = stream_.get();
  const size_t bytes = static_cast<size_t>(n) * sizeof(float);
  PS_CUDA_CHECK(cudaMemsetAsync(padded_.data(), 0, R * chunk * sizeof(float), stream));
  PS_CUDA_CHECK(cudaMemcpyAsync(padded_.data(), values, bytes, cudaMemcpyDeviceToDevice, stream));
  // Chunk p of this replica to replica p; chunk `rank` of replica p into row p of chunks.
  communicator_.exchange_chunks(padded_.data(), chunks_.data(), chunk, stream);
  float* mine = padded_.data() + static_cast<size_t>(communicator_.rank()) * chunk;
  cuda::sum_replica_chunks(chunks_.data(), communicator_.size(), static_cast<int64_t>(chunk), mine,
                           stream);
  communicator_.all_gather(mine, padded_.data(), chunk, stream);
  PS_CUDA_CHECK(cudaMemcpyAsync(values, padded_.data(), bytes, cudaMemcpyDeviceToDevice, stream));
}

void NcclGradientSum::end() {
  PS_CUDA_CHECK(cudaEventRecord(summed_.get(), stream_.get()));
  PS_CUDA_CHECK(cudaStreamWaitEvent(compute_, summed_.get(), 0));
}

// ---- the BatchNorm statistics ----

NcclStatisticsSum::NcclStatisticsSum(NcclCommunicator& communicator, Replicas& replicas)
    : communicator_(communicator), replicas_(replicas) {}

void NcclStatisticsSum::sum(double* values, int64_t n) {
  replicas_.sum(values, n);
}

double* NcclStatisticsSum::scratch(int64_t n) {
  if (scratch_.size() < static_cast<size_t>(n)) {
    PS_CUDA_CHECK(cudaDeviceSynchronize());
    scratch_ = cuda::DeviceBuffer<double>();  // freed first: its values are scratch
    scratch_ = cuda::DeviceBuffer<double>(static_cast<size_t>(n));
  }
  return scratch_.data();
}

void NcclStatisticsSum::sum(double* values, int64_t n, cudaStream_t stream) {
  if (n == 0) return;
  const auto R = static_cast<size_t>(communicator_.size());
  const auto count = static_cast<size_t>(n);
  if (gathered_.size() < R * count) {
    PS_CUDA_CHECK(cudaDeviceSynchronize());  // earlier sums may still use it
    gathered_ = cuda::DeviceBuffer<double>();
    gathered_ = cuda::DeviceBuffer<double>(R * count);
  }
  communicator_.all_gather(values, gathered_.data(), count, stream);
  cuda::sum_replica_chunks(gathered_.data(), communicator_.size(), n, values, stream);
}

}  // namespace pillarseg
