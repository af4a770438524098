#include "engine/cuda/nccl_sum.hpp"

#include <dlfcn.h>
#include <nccl.h>

#include <string>

#include "kernels/cuda_handles.hpp"
#include "kernels/device_buffer.hpp"
#include "kernels/replica_sum.cuh"

namespace pillarseg {

namespace {

// The NCCL entry points this sum calls, from the library dlopen() found.
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

struct NcclGradientSum::State {
  NcclLibrary library;
  ncclComm_t comm = nullptr;
  int rank = 0, size = 1;
  cudaStream_t compute = nullptr;  // the backend's
  cuda::Stream stream;             // the sums'
  cuda::Event reached, summed;     // compute reached a piece; the sums queued so far are done
  cuda::DeviceBuffer<float> padded, chunks;  // (R x chunk) each

  void check(ncclResult_t result, const char* call) const {
    PS_CHECK(result == ncclSuccess, "{} failed: {}", call, library.api.error_string(result));
  }
  ~State() {
    // The communicator before the members (buffers, events, stream, the library) go.
    if (comm != nullptr) library.api.comm_destroy(comm);
  }
};

NcclGradientSum::NcclGradientSum(Replicas& replicas, cudaStream_t compute)
    : state_(std::make_unique<State>()) {
  State& s = *state_;
  s.rank = replicas.rank(), s.size = replicas.size(), s.compute = compute;
  ncclUniqueId id{};
  if (replicas.leader()) s.check(s.library.api.get_unique_id(&id), "ncclGetUniqueId");
  replicas.broadcast(&id, sizeof id);
  s.check(s.library.api.comm_init_rank(&s.comm, s.size, id, s.rank), "ncclCommInitRank");
}

NcclGradientSum::~NcclGradientSum() = default;

void NcclGradientSum::begin(float* values, int64_t n) {
  State& s = *state_;
  if (n == 0) return;
  const NcclApi& api = s.library.api;
  const auto R = static_cast<size_t>(s.size);
  const size_t chunk = (static_cast<size_t>(n) + R - 1) / R;
  if (s.padded.size() < R * chunk) {
    PS_CUDA_CHECK(cudaStreamSynchronize(s.stream.get()));  // earlier pieces use the scratch
    s.padded = cuda::DeviceBuffer<float>(R * chunk);
    s.chunks = cuda::DeviceBuffer<float>(R * chunk);
  }
  PS_CUDA_CHECK(cudaEventRecord(s.reached.get(), s.compute));
  PS_CUDA_CHECK(cudaStreamWaitEvent(s.stream.get(), s.reached.get(), 0));
  cudaStream_t stream = s.stream.get();
  const size_t bytes = static_cast<size_t>(n) * sizeof(float);
  PS_CUDA_CHECK(cudaMemsetAsync(s.padded.data(), 0, R * chunk * sizeof(float), stream));
  PS_CUDA_CHECK(cudaMemcpyAsync(s.padded.data(), values, bytes, cudaMemcpyDeviceToDevice, stream));
  // Chunk p of this replica to replica p; chunk `rank` of replica p into row p of chunks.
  s.check(api.group_start(), "ncclGroupStart");
  for (size_t p = 0; p < R; ++p) {
    s.check(api.send(s.padded.data() + p * chunk, chunk, ncclFloat, static_cast<int>(p), s.comm,
                     stream),
            "ncclSend");
    s.check(api.recv(s.chunks.data() + p * chunk, chunk, ncclFloat, static_cast<int>(p), s.comm,
                     stream),
            "ncclRecv");
  }
  s.check(api.group_end(), "ncclGroupEnd");
  float* mine = s.padded.data() + static_cast<size_t>(s.rank) * chunk;
  cuda::sum_replica_chunks(s.chunks.data(), s.size, static_cast<int64_t>(chunk), mine, stream);
  s.check(api.all_gather(mine, s.padded.data(), chunk, ncclFloat, s.comm, stream), "ncclAllGather");
  PS_CUDA_CHECK(cudaMemcpyAsync(values, s.padded.data(), bytes, cudaMemcpyDeviceToDevice, stream));
}

void NcclGradientSum::end() {
  State& s = *state_;
  PS_CUDA_CHECK(cudaEventRecord(s.summed.get(), s.stream.get()));
  PS_CUDA_CHECK(cudaStreamWaitEvent(s.compute, s.summed.get(), 0));
}

}  // namespace pillarseg
