// The CUDA runtime API on the host (see emu_runtime.hpp): allocation registries that let copies
// check their pointers, streams that run work at once or record it while capturing, events on the
// host clock, graphs as recorded node lists, and the launch path into the block scheduler.
#include "kernels/emu/emu_runtime.hpp"

#include <omp.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <bit>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <exception>
#include <functional>
#include <map>
#include <mutex>
#include <new>
#include <thread>
#include <unordered_map>
#include <utility>
#include <vector>

#include <fmt/format.h>

namespace {

// Work recorded by stream capture; returns what the operation would have returned.
using GraphNode = std::function<cudaError_t()>;

}  // namespace

struct CUstream_st {
  unsigned int flags = 0;
  bool capturing = false;
  bool capture_invalidated = false;
  cudaStreamCaptureMode capture_mode = cudaStreamCaptureModeGlobal;
  std::thread::id capture_thread;
  std::vector<GraphNode> captured;
};

struct CUevent_st {
  unsigned int flags = 0;
  bool recorded = false;
  std::chrono::steady_clock::time_point time;
};

struct CUgraph_st {
  std::vector<GraphNode> nodes;
};

struct CUgraphExec_st {
  std::vector<GraphNode> nodes;
};

namespace pillarseg::emu {
namespace {

constexpr std::size_t kDeviceAlignment = 256;  // what cudaMalloc guarantees
constexpr int kMaxThreadsPerBlock = 1024;
constexpr std::size_t kDefaultSharedBytes = 48 * 1024;
constexpr std::size_t kMaxOptInSharedBytes =
    232448;  // 227 KiB: sm_90's cudaDevAttrMaxSharedMemoryPerBlockOptin

thread_local cudaError_t t_last_error = cudaSuccess;
thread_local std::string t_last_error_detail;

cudaError_t fail(cudaError_t error, std::string detail) {
  t_last_error = error;
  t_last_error_detail = std::move(detail);
  return error;
}

// Owns the objects behind handles; a handle not created here (or destroyed) is rejected.
template <class T>
class Registry {
 public:
  T* create() {
    auto object = std::make_unique<T>();
    T* handle = object.get();
    objects_.emplace(handle, std::move(object));
    return handle;
  }
  T* insert(std::unique_ptr<T> object) {
    T* handle = object.get();
    objects_.emplace(handle, std::move(object));
    return handle;
  }
  bool contains(const T* handle) const { return objects_.count(const_cast<T*>(handle)) != 0; }
  bool destroy(T* handle) { return objects_.erase(handle) != 0; }
  template <class Fn>
  void for_each(Fn&& fn) {
    for (auto& [handle, object] : objects_) fn(*object);
  }

 private:
  std::unordered_map<T*, std::unique_ptr<T>> objects_;
};

// Start address -> size of each live allocation.
class AllocationMap {
 public:
  void add(const void* pointer, std::size_t bytes) { sizes_[address(pointer)] = bytes; }
  bool remove(const void* pointer) { return sizes_.erase(address(pointer)) != 0; }
  // The allocation containing `pointer`, as (start, bytes), or (0, 0).
  std::pair<std::uintptr_t, std::size_t> find(const void* pointer) const {
    auto next = sizes_.upper_bound(address(pointer));
    if (next == sizes_.begin()) return {0, 0};
    --next;
    if (address(pointer) >= next->first + next->second) return {0, 0};
    return *next;
  }

 private:
  static std::uintptr_t address(const void* pointer) {
    return reinterpret_cast<std::uintptr_t>(pointer);
  }
  std::map<std::uintptr_t, std::size_t> sizes_;
};

struct Runtime {
  std::mutex mutex;
  AllocationMap device;
  AllocationMap pinned;
  Registry<CUstream_st> streams;
  Registry<CUevent_st> events;
  Registry<CUgraph_st> graphs;
  Registry<CUgraphExec_st> executables;
  std::unordered_map<const void*, std::size_t> shared_bytes_limit;  // set by cudaFuncSetAttribute
};

Runtime& runtime() {
  static Runtime state;
  return state;
}

bool is_default_stream(cudaStream_t stream) {
  return stream == nullptr || stream == cudaStreamLegacy || stream == cudaStreamPerThread;
}

// Checks a stream handle. Caller holds the runtime mutex.
cudaError_t check_stream(cudaStream_t stream, const char* call) {
  if (is_default_stream(stream) || runtime().streams.contains(stream)) return cudaSuccess;
  return fail(cudaErrorInvalidResourceHandle,
              fmt::format("{}: stream {} was not created by cudaStreamCreate or was destroyed",
                          call, static_cast<const void*>(stream)));
}

// The stream recording work, or nullptr if work on `stream` runs now. Caller holds the mutex.
CUstream_st* capturing_stream(cudaStream_t stream) {
  return !is_default_stream(stream) && stream->capturing ? stream : nullptr;
}

// Calls that synchronise or allocate are not allowed while a stream captures in global mode (any
// thread) or thread-local mode (this thread); like CUDA, they fail and invalidate the capture.
cudaError_t check_no_unsafe_capture(const char* call) {
  Runtime& state = runtime();
  const std::lock_guard lock(state.mutex);
  bool conflict = false;
  state.streams.for_each([&](CUstream_st& stream) {
    if (!stream.capturing) return;
    const bool applies = stream.capture_mode == cudaStreamCaptureModeGlobal ||
                         (stream.capture_mode == cudaStreamCaptureModeThreadLocal &&
                          stream.capture_thread == std::this_thread::get_id());
    if (!applies) return;
    stream.capture_invalidated = true;
    conflict = true;
  });
  if (!conflict) return cudaSuccess;
  return fail(
      cudaErrorStreamCaptureUnsupported,
      fmt::format("{} is not allowed while a stream captures (use the Async form on the capturing "
                  "stream, or allocate before the capture); the capture is now invalidated",
                  call));
}

std::string describe_range(const void* pointer, std::size_t bytes) {
  return fmt::format("[{}, +{} bytes)", pointer, bytes);
}

// Checks that [pointer, pointer + bytes) is inside one device allocation (want_device) or outside
// every device allocation (host memory). Caller holds the mutex.
cudaError_t check_side(const void* pointer, std::size_t bytes, bool want_device, const char* call,
                       const char* role) {
  const auto [start, size] = runtime().device.find(pointer);
  const auto address = reinterpret_cast<std::uintptr_t>(pointer);
  if (want_device) {
    if (size == 0) {
      return fail(cudaErrorInvalidValue,
                  fmt::format("{}: {} {} is not device memory (not inside any cudaMalloc "
                              "allocation)",
                              call, role, describe_range(pointer, bytes)));
    }
    if (address + bytes > start + size) {
      return fail(
          cudaErrorInvalidValue,
          fmt::format("{}: {} {} runs {} bytes past the end of its {}-byte device allocation", call,
                      role, describe_range(pointer, bytes), address + bytes - (start + size),
                      size));
    }
    return cudaSuccess;
  }
  if (size != 0) {
    return fail(cudaErrorInvalidValue,
                fmt::format("{}: {} {} is device memory, but the copy kind says host memory", call,
                            role, describe_range(pointer, bytes)));
  }
  return cudaSuccess;
}

struct CopyDigests {
  std::mutex mutex;
  std::atomic<bool> recording{false};
  std::vector<std::uint64_t> digests;
};
CopyDigests& copy_digests() {
  static CopyDigests digests;
  return digests;
}

// A 64-bit hash of the bytes: eight at a time, multiplied and rotated (not cryptographic: it only
// has to change when a bit changes).
std::uint64_t hash_bytes(const void* data, std::size_t bytes) {
  const auto* p = static_cast<const unsigned char*>(data);
  std::uint64_t h = 0x9E3779B97F4A7C15ull ^ bytes;
  std::size_t i = 0;
  for (; i + 8 <= bytes; i += 8) {
    std::uint64_t word;
    std::memcpy(&word, p + i, 8);
    h = std::rotl((h ^ word) * 0xBF58476D1CE4E5B9ull, 29);
  }
  std::uint64_t tail = 0;
  std::memcpy(&tail, p + i, bytes - i);
  h = std::rotl((h ^ tail) * 0x94D049BB133111EBull, 31);
  return h ^ (h >> 32);
}

void append_copy_digest(const void* data, std::size_t bytes) {
  CopyDigests& digests = copy_digests();
  if (!digests.recording.load(std::memory_order_relaxed)) return;
  const std::uint64_t digest = hash_bytes(data, bytes);
  const std::lock_guard lock(digests.mutex);
  digests.digests.push_back(digest);
}

cudaError_t copy_now(void* destination, const void* source, std::size_t bytes, cudaMemcpyKind kind,
                     const char* call) {
  if (bytes == 0) return cudaSuccess;
  if (kind < cudaMemcpyHostToHost || kind > cudaMemcpyDefault) {
    return fail(cudaErrorInvalidMemcpyDirection,
                fmt::format("{}: copy kind {} is not a cudaMemcpyKind (0 to 4)", call,
                            static_cast<int>(kind)));
  }
  if (destination == nullptr || source == nullptr) {
    return fail(cudaErrorInvalidValue,
                fmt::format("{}: the {} pointer is null with {} bytes to copy", call,
                            destination == nullptr ? "destination" : "source", bytes));
  }
  bool device_to_host = false;
  {
    const std::lock_guard lock(runtime().mutex);
    device_to_host =
        runtime().device.find(source).second != 0 && runtime().device.find(destination).second == 0;
    if (kind != cudaMemcpyDefault) {
      const bool device_destination =
          kind == cudaMemcpyHostToDevice || kind == cudaMemcpyDeviceToDevice;
      const bool device_source = kind == cudaMemcpyDeviceToHost || kind == cudaMemcpyDeviceToDevice;
      if (const cudaError_t error =
              check_side(destination, bytes, device_destination, call, "destination");
          error != cudaSuccess) {
        return error;
      }
      if (const cudaError_t error = check_side(source, bytes, device_source, call, "source");
          error != cudaSuccess) {
        return error;
      }
    }
  }
  std::memmove(destination, source, bytes);
  if (device_to_host) append_copy_digest(destination, bytes);
  return cudaSuccess;
}

cudaError_t fill_now(void* destination, int value, std::size_t bytes, const char* call) {
  if (bytes == 0) return cudaSuccess;
  if (destination == nullptr) {
    return fail(cudaErrorInvalidValue,
                fmt::format("{}: the destination is null with {} bytes to set", call, bytes));
  }
  {
    const std::lock_guard lock(runtime().mutex);
    if (const cudaError_t error = check_side(destination, bytes, true, call, "destination");
        error != cudaSuccess) {
      return error;
    }
  }
  std::memset(destination, value, bytes);
  return cudaSuccess;
}

cudaError_t record_now(cudaEvent_t event) {
  {
    const std::lock_guard lock(runtime().mutex);
    if (!runtime().events.contains(event)) {
      return fail(
          cudaErrorInvalidResourceHandle,
          fmt::format("cudaEventRecord: event {} was destroyed", static_cast<const void*>(event)));
    }
  }
  event->recorded = true;
  event->time = std::chrono::steady_clock::now();
  return cudaSuccess;
}

cudaError_t run_now(const BoundKernel& kernel, dim3 grid, dim3 block,
                    std::size_t dynamic_shared_bytes) {
  try {
    run_grid(
        GridLaunch{grid, block, dynamic_shared_bytes, kernel.arguments.get(), kernel.run_thread});
  } catch (const std::exception& e) {
    return fail(cudaErrorLaunchFailure, e.what());
  }
  return cudaSuccess;
}

cudaError_t replay(const std::vector<GraphNode>& nodes) {
  for (const GraphNode& node : nodes) {
    if (const cudaError_t error = node(); error != cudaSuccess) return error;
  }
  return cudaSuccess;
}

// Runs `work` now, or appends it to the stream's capture. Checks the stream handle first.
cudaError_t run_or_capture(cudaStream_t stream, const char* call, GraphNode work) {
  {
    const std::lock_guard lock(runtime().mutex);
    if (const cudaError_t error = check_stream(stream, call); error != cudaSuccess) return error;
    if (CUstream_st* capture = capturing_stream(stream)) {
      capture->captured.push_back(std::move(work));
      return cudaSuccess;
    }
  }
  return work();
}

std::size_t physical_memory_bytes(int pages_name) {
  const long pages = sysconf(pages_name);
  const long page_bytes = sysconf(_SC_PAGESIZE);
  return pages > 0 && page_bytes > 0
             ? static_cast<std::size_t>(pages) * static_cast<std::size_t>(page_bytes)
             : 0;
}

}  // namespace

const std::string& last_error_detail() {
  return t_last_error_detail;
}

cudaError_t launch(BoundKernel kernel, dim3 grid, dim3 block, std::size_t dynamic_shared_bytes,
                   cudaStream_t stream) {
  const unsigned long long threads = 1ull * block.x * block.y * block.z;
  if (block.x == 0 || block.y == 0 || block.z == 0 || block.x > 1024 || block.y > 1024 ||
      block.z > 64 || threads > kMaxThreadsPerBlock) {
    return fail(
        cudaErrorInvalidConfiguration,
        fmt::format(
            "kernel launch: block ({}, {}, {}) has {} threads; a block needs 1 to {} threads with "
            "x, y <= 1024 and z <= 64",
            block.x, block.y, block.z, threads, kMaxThreadsPerBlock));
  }
  if (grid.x == 0 || grid.y == 0 || grid.z == 0 || grid.x > 2147483647u || grid.y > 65535 ||
      grid.z > 65535) {
    return fail(cudaErrorInvalidConfiguration,
                fmt::format("kernel launch: grid ({}, {}, {}) is empty or too large; x must be 1 "
                            "to 2^31 - 1, y and z "
                            "1 to 65535",
                            grid.x, grid.y, grid.z));
  }
  {
    const std::lock_guard lock(runtime().mutex);
    const auto limit = runtime().shared_bytes_limit.find(kernel.kernel);
    const std::size_t allowed =
        limit == runtime().shared_bytes_limit.end() ? kDefaultSharedBytes : limit->second;
    if (dynamic_shared_bytes > allowed) {
      return fail(
          cudaErrorInvalidValue,
          fmt::format(
              "kernel launch: {} bytes of dynamic shared memory, but the kernel may use {} (raise "
              "it "
              "with cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, "
              "bytes), at most {})",
              dynamic_shared_bytes, allowed, kMaxOptInSharedBytes));
    }
  }
  return run_or_capture(stream, "kernel launch",
                        [kernel = std::move(kernel), grid, block, dynamic_shared_bytes] {
                          return run_now(kernel, grid, block, dynamic_shared_bytes);
                        });
}

void record_copy_digests(bool on) {
  copy_digests().recording.store(on, std::memory_order_relaxed);
}

std::vector<std::uint64_t> take_copy_digests() {
  CopyDigests& digests = copy_digests();
  const std::lock_guard lock(digests.mutex);
  return std::exchange(digests.digests, {});
}

}  // namespace pillarseg::emu

using pillarseg::emu::fail;
using pillarseg::emu::is_default_stream;
using pillarseg::emu::runtime;

// ---- device and errors ----

cudaError_t cudaGetDeviceCount(int* count) {
  if (count == nullptr) return fail(cudaErrorInvalidValue, "cudaGetDeviceCount: count is null");
  *count = 1;
  return cudaSuccess;
}

cudaError_t cudaGetDevice(int* device) {
  if (device == nullptr) return fail(cudaErrorInvalidValue, "cudaGetDevice: device is null");
  *device = 0;
  return cudaSuccess;
}

cudaError_t cudaSetDevice(int device) {
  if (device != 0) {
    return fail(
        cudaErrorInvalidDevice,
        fmt::format("cudaSetDevice: device {} does not exist; the emulation has device 0 only",
                    device));
  }
  return cudaSuccess;
}

cudaError_t cudaGetDeviceProperties(cudaDeviceProp* properties, int device) {
  if (properties == nullptr)
    return fail(cudaErrorInvalidValue, "cudaGetDeviceProperties: properties is null");
  if (device != 0) {
    return fail(cudaErrorInvalidDevice,
                fmt::format("cudaGetDeviceProperties: device {} does not exist", device));
  }
  *properties = cudaDeviceProp{};
  const int threads = omp_get_max_threads();
  const std::string name = fmt::format("pillarseg CUDA emulation (host CPU, {} threads)", threads);
  std::snprintf(properties->name, sizeof(properties->name), "%s", name.c_str());
  properties->totalGlobalMem = pillarseg::emu::physical_memory_bytes(_SC_PHYS_PAGES);
  properties->sharedMemPerBlock = pillarseg::emu::kDefaultSharedBytes;
  properties->sharedMemPerBlockOptin = pillarseg::emu::kMaxOptInSharedBytes;
  properties->warpSize = 32;
  properties->maxThreadsPerBlock = pillarseg::emu::kMaxThreadsPerBlock;
  properties->maxThreadsDim[0] = 1024;
  properties->maxThreadsDim[1] = 1024;
  properties->maxThreadsDim[2] = 64;
  properties->maxGridSize[0] = 2147483647;
  properties->maxGridSize[1] = 65535;
  properties->maxGridSize[2] = 65535;
  properties->multiProcessorCount = threads;
  properties->major = 9;
  properties->minor = 0;
  return cudaSuccess;
}

cudaError_t cudaDeviceSynchronize() {
  return pillarseg::emu::check_no_unsafe_capture("cudaDeviceSynchronize");
}

cudaError_t cudaGetLastError() {
  const cudaError_t error = pillarseg::emu::t_last_error;
  pillarseg::emu::t_last_error = cudaSuccess;
  pillarseg::emu::t_last_error_detail.clear();
  return error;
}

cudaError_t cudaPeekAtLastError() {
  return pillarseg::emu::t_last_error;
}

const char* cudaGetErrorName(cudaError_t error) {
  switch (error) {
    case cudaSuccess:
      return "cudaSuccess";
    case cudaErrorInvalidValue:
      return "cudaErrorInvalidValue";
    case cudaErrorMemoryAllocation:
      return "cudaErrorMemoryAllocation";
    case cudaErrorInvalidConfiguration:
      return "cudaErrorInvalidConfiguration";
    case cudaErrorInvalidDevicePointer:
      return "cudaErrorInvalidDevicePointer";
    case cudaErrorInvalidMemcpyDirection:
      return "cudaErrorInvalidMemcpyDirection";
    case cudaErrorInvalidDeviceFunction:
      return "cudaErrorInvalidDeviceFunction";
    case cudaErrorNoDevice:
      return "cudaErrorNoDevice";
    case cudaErrorInvalidDevice:
      return "cudaErrorInvalidDevice";
    case cudaErrorInvalidResourceHandle:
      return "cudaErrorInvalidResourceHandle";
    case cudaErrorIllegalState:
      return "cudaErrorIllegalState";
    case cudaErrorNotReady:
      return "cudaErrorNotReady";
    case cudaErrorLaunchFailure:
      return "cudaErrorLaunchFailure";
    case cudaErrorNotSupported:
      return "cudaErrorNotSupported";
    case cudaErrorStreamCaptureUnsupported:
      return "cudaErrorStreamCaptureUnsupported";
    case cudaErrorStreamCaptureInvalidated:
      return "cudaErrorStreamCaptureInvalidated";
    case cudaErrorStreamCaptureUnmatched:
      return "cudaErrorStreamCaptureUnmatched";
    case cudaErrorStreamCaptureImplicit:
      return "cudaErrorStreamCaptureImplicit";
    case cudaErrorStreamCaptureWrongThread:
      return "cudaErrorStreamCaptureWrongThread";
    case cudaErrorUnknown:
      return "cudaErrorUnknown";
  }
  return "cudaErrorUnknown";
}

const char* cudaGetErrorString(cudaError_t error) {
  switch (error) {
    case cudaSuccess:
      return "no error";
    case cudaErrorInvalidValue:
      return "invalid argument";
    case cudaErrorMemoryAllocation:
      return "out of memory";
    case cudaErrorInvalidConfiguration:
      return "invalid configuration argument";
    case cudaErrorInvalidDevicePointer:
      return "invalid device pointer";
    case cudaErrorInvalidMemcpyDirection:
      return "invalid copy direction for memcpy";
    case cudaErrorInvalidDeviceFunction:
      return "invalid device function";
    case cudaErrorNoDevice:
      return "no CUDA-capable device is detected";
    case cudaErrorInvalidDevice:
      return "invalid device ordinal";
    case cudaErrorInvalidResourceHandle:
      return "invalid resource handle";
    case cudaErrorIllegalState:
      return "the operation cannot be performed in the present state";
    case cudaErrorNotReady:
      return "device not ready";
    case cudaErrorLaunchFailure:
      return "unspecified launch failure";
    case cudaErrorNotSupported:
      return "operation not supported";
    case cudaErrorStreamCaptureUnsupported:
      return "operation not permitted when stream is capturing";
    case cudaErrorStreamCaptureInvalidated:
      return "operation failed due to a previous error during capture";
    case cudaErrorStreamCaptureUnmatched:
      return "capture was not initiated in this stream";
    case cudaErrorStreamCaptureImplicit:
      return "operation would make the legacy stream depend on a capturing blocking stream";
    case cudaErrorStreamCaptureWrongThread:
      return "attempt to terminate a thread-local capture sequence from another thread";
    case cudaErrorUnknown:
      return "unknown error";
  }
  return "unrecognized error code";
}

// ---- memory ----

namespace {

cudaError_t allocate(void** pointer, std::size_t bytes, bool device, const char* call) {
  if (pointer == nullptr)
    return fail(cudaErrorInvalidValue, fmt::format("{}: the output pointer is null", call));
  *pointer = nullptr;
  if (const cudaError_t error = pillarseg::emu::check_no_unsafe_capture(call); error != cudaSuccess)
    return error;
  if (bytes == 0) return cudaSuccess;
  void* memory =
      ::operator new (bytes, std::align_val_t{pillarseg::emu::kDeviceAlignment}, std::nothrow);
  if (memory == nullptr) {
    return fail(cudaErrorMemoryAllocation,
                fmt::format("{}: cannot allocate {} bytes", call, bytes));
  }
  // CUDA leaves new memory uninitialised; all-ones bytes (NaN as float) make kernels that read
  // before writing show it.
  std::memset(memory, 0xFF, bytes);
  {
    const std::lock_guard lock(runtime().mutex);
    (device ? runtime().device : runtime().pinned).add(memory, bytes);
  }
  *pointer = memory;
  return cudaSuccess;
}

cudaError_t release(void* pointer, bool device, const char* call) {
  if (pointer == nullptr) return cudaSuccess;
  if (const cudaError_t error = pillarseg::emu::check_no_unsafe_capture(call); error != cudaSuccess)
    return error;
  {
    const std::lock_guard lock(runtime().mutex);
    if (!(device ? runtime().device : runtime().pinned).remove(pointer)) {
      return fail(cudaErrorInvalidValue,
                  fmt::format("{}: {} is not the start of a live {} allocation", call, pointer,
                              device ? "cudaMalloc" : "cudaMallocHost"));
    }
  }
  ::operator delete (pointer, std::align_val_t{pillarseg::emu::kDeviceAlignment});
  return cudaSuccess;
}

}  // namespace

cudaError_t cudaMalloc(void** pointer, std::size_t bytes) {
  return allocate(pointer, bytes, true, "cudaMalloc");
}
cudaError_t cudaFree(void* pointer) {
  return release(pointer, true, "cudaFree");
}
cudaError_t cudaMallocHost(void** pointer, std::size_t bytes) {
  return allocate(pointer, bytes, false, "cudaMallocHost");
}
cudaError_t cudaFreeHost(void* pointer) {
  return release(pointer, false, "cudaFreeHost");
}

cudaError_t cudaMemGetInfo(std::size_t* free_bytes, std::size_t* total_bytes) {
  if (free_bytes == nullptr || total_bytes == nullptr) {
    return fail(cudaErrorInvalidValue, "cudaMemGetInfo: an output pointer is null");
  }
  *free_bytes = pillarseg::emu::physical_memory_bytes(_SC_AVPHYS_PAGES);
  *total_bytes = pillarseg::emu::physical_memory_bytes(_SC_PHYS_PAGES);
  return cudaSuccess;
}

cudaError_t cudaMemcpy(void* destination, const void* source, std::size_t bytes,
                       cudaMemcpyKind kind) {
  if (const cudaError_t error = pillarseg::emu::check_no_unsafe_capture("cudaMemcpy");
      error != cudaSuccess) {
    return error;
  }
  return pillarseg::emu::copy_now(destination, source, bytes, kind, "cudaMemcpy");
}

cudaError_t cudaMemcpyAsync(void* destination, const void* source, std::size_t bytes,
                            cudaMemcpyKind kind, cudaStream_t stream) {
  return pillarseg::emu::run_or_capture(stream, "cudaMemcpyAsync", [=] {
    return pillarseg::emu::copy_now(destination, source, bytes, kind, "cudaMemcpyAsync");
  });
}

cudaError_t cudaMemset(void* destination, int value, std::size_t bytes) {
  if (const cudaError_t error = pillarseg::emu::check_no_unsafe_capture("cudaMemset");
      error != cudaSuccess) {
    return error;
  }
  return pillarseg::emu::fill_now(destination, value, bytes, "cudaMemset");
}

cudaError_t cudaMemsetAsync(void* destination, int value, std::size_t bytes, cudaStream_t stream) {
  return pillarseg::emu::run_or_capture(stream, "cudaMemsetAsync", [=] {
    return pillarseg::emu::fill_now(destination, value, bytes, "cudaMemsetAsync");
  });
}

// ---- streams and events ----

cudaError_t cudaStreamCreate(cudaStream_t* stream) {
  return cudaStreamCreateWithFlags(stream, cudaStreamDefault);
}

cudaError_t cudaStreamCreateWithFlags(cudaStream_t* stream, unsigned int flags) {
  if (stream == nullptr)
    return fail(cudaErrorInvalidValue, "cudaStreamCreate: the output pointer is null");
  if ((flags & ~static_cast<unsigned int>(cudaStreamNonBlocking)) != 0) {
    return fail(cudaErrorInvalidValue,
                fmt::format("cudaStreamCreateWithFlags: unknown flags {:#x}", flags));
  }
  const std::lock_guard lock(runtime().mutex);
  *stream = runtime().streams.create();
  (*stream)->flags = flags;
  return cudaSuccess;
}

cudaError_t cudaStreamDestroy(cudaStream_t stream) {
  const std::lock_guard lock(runtime().mutex);
  if (is_default_stream(stream) || !runtime().streams.destroy(stream)) {
    return fail(cudaErrorInvalidResourceHandle,
                fmt::format("cudaStreamDestroy: {} is not a live stream",
                            static_cast<const void*>(stream)));
  }
  return cudaSuccess;
}

namespace {

// Synchronising with a stream that captures is an error that invalidates its capture.
cudaError_t check_not_capturing(cudaStream_t stream, const char* call) {
  const std::lock_guard lock(runtime().mutex);
  if (const cudaError_t error = pillarseg::emu::check_stream(stream, call); error != cudaSuccess)
    return error;
  if (CUstream_st* capture = pillarseg::emu::capturing_stream(stream)) {
    capture->capture_invalidated = true;
    return fail(
        cudaErrorStreamCaptureUnsupported,
        fmt::format(
            "{}: the stream is capturing a graph; end the capture first (the capture is now "
            "invalidated)",
            call));
  }
  return cudaSuccess;
}

}  // namespace

cudaError_t cudaStreamSynchronize(cudaStream_t stream) {
  return check_not_capturing(stream, "cudaStreamSynchronize");
}
cudaError_t cudaStreamQuery(cudaStream_t stream) {
  return check_not_capturing(stream, "cudaStreamQuery");
}

cudaError_t cudaStreamWaitEvent(cudaStream_t stream, cudaEvent_t event, unsigned int flags) {
  const std::lock_guard lock(runtime().mutex);
  if (const cudaError_t error = pillarseg::emu::check_stream(stream, "cudaStreamWaitEvent");
      error != cudaSuccess) {
    return error;
  }
  if (!runtime().events.contains(event)) {
    return fail(cudaErrorInvalidResourceHandle,
                "cudaStreamWaitEvent: the event is not a live event");
  }
  if (flags != 0)
    return fail(cudaErrorInvalidValue,
                fmt::format("cudaStreamWaitEvent: unknown flags {:#x}", flags));
  return cudaSuccess;  // work runs in issue order, so every recorded event has completed
}

cudaError_t cudaEventCreate(cudaEvent_t* event) {
  return cudaEventCreateWithFlags(event, cudaEventDefault);
}

cudaError_t cudaEventCreateWithFlags(cudaEvent_t* event, unsigned int flags) {
  if (event == nullptr)
    return fail(cudaErrorInvalidValue, "cudaEventCreate: the output pointer is null");
  if ((flags & ~static_cast<unsigned int>(cudaEventBlockingSync | cudaEventDisableTiming)) != 0) {
    return fail(cudaErrorInvalidValue,
                fmt::format("cudaEventCreateWithFlags: unknown flags {:#x}", flags));
  }
  const std::lock_guard lock(runtime().mutex);
  *event = runtime().events.create();
  (*event)->flags = flags;
  return cudaSuccess;
}

cudaError_t cudaEventDestroy(cudaEvent_t event) {
  const std::lock_guard lock(runtime().mutex);
  if (!runtime().events.destroy(event)) {
    return fail(
        cudaErrorInvalidResourceHandle,
        fmt::format("cudaEventDestroy: {} is not a live event", static_cast<const void*>(event)));
  }
  return cudaSuccess;
}

cudaError_t cudaEventRecord(cudaEvent_t event, cudaStream_t stream) {
  {
    const std::lock_guard lock(runtime().mutex);
    if (!runtime().events.contains(event)) {
      return fail(
          cudaErrorInvalidResourceHandle,
          fmt::format("cudaEventRecord: {} is not a live event", static_cast<const void*>(event)));
    }
  }
  return pillarseg::emu::run_or_capture(stream, "cudaEventRecord",
                                        [event] { return pillarseg::emu::record_now(event); });
}

cudaError_t cudaEventSynchronize(cudaEvent_t event) {
  const std::lock_guard lock(runtime().mutex);
  if (!runtime().events.contains(event)) {
    return fail(cudaErrorInvalidResourceHandle,
                "cudaEventSynchronize: the event is not a live event");
  }
  return cudaSuccess;
}

cudaError_t cudaEventQuery(cudaEvent_t event) {
  return cudaEventSynchronize(event);
}

cudaError_t cudaEventElapsedTime(float* milliseconds, cudaEvent_t start, cudaEvent_t end) {
  if (milliseconds == nullptr)
    return fail(cudaErrorInvalidValue, "cudaEventElapsedTime: the output pointer is null");
  const std::lock_guard lock(runtime().mutex);
  if (!runtime().events.contains(start) || !runtime().events.contains(end)) {
    return fail(cudaErrorInvalidResourceHandle,
                "cudaEventElapsedTime: an event is not a live event");
  }
  if (!start->recorded || !end->recorded) {
    return fail(cudaErrorInvalidResourceHandle,
                "cudaEventElapsedTime: an event has not been recorded");
  }
  if (((start->flags | end->flags) & cudaEventDisableTiming) != 0) {
    return fail(cudaErrorInvalidResourceHandle,
                "cudaEventElapsedTime: an event was created with cudaEventDisableTiming");
  }
  *milliseconds = std::chrono::duration<float, std::milli>(end->time - start->time).count();
  return cudaSuccess;
}

// ---- graphs ----

cudaError_t cudaStreamBeginCapture(cudaStream_t stream, cudaStreamCaptureMode mode) {
  const std::lock_guard lock(runtime().mutex);
  if (is_default_stream(stream)) {
    return fail(cudaErrorStreamCaptureUnsupported,
                "cudaStreamBeginCapture: the default stream cannot capture; create a stream");
  }
  if (const cudaError_t error = pillarseg::emu::check_stream(stream, "cudaStreamBeginCapture");
      error != cudaSuccess) {
    return error;
  }
  if (mode < cudaStreamCaptureModeGlobal || mode > cudaStreamCaptureModeRelaxed) {
    return fail(
        cudaErrorInvalidValue,
        fmt::format("cudaStreamBeginCapture: unknown capture mode {}", static_cast<int>(mode)));
  }
  if (stream->capturing)
    return fail(cudaErrorIllegalState, "cudaStreamBeginCapture: the stream already captures");
  stream->capturing = true;
  stream->capture_invalidated = false;
  stream->capture_mode = mode;
  stream->capture_thread = std::this_thread::get_id();
  stream->captured.clear();
  return cudaSuccess;
}

cudaError_t cudaStreamEndCapture(cudaStream_t stream, cudaGraph_t* graph) {
  if (graph == nullptr)
    return fail(cudaErrorInvalidValue, "cudaStreamEndCapture: the output pointer is null");
  const std::lock_guard lock(runtime().mutex);
  *graph = nullptr;
  if (is_default_stream(stream) || !runtime().streams.contains(stream) || !stream->capturing) {
    return fail(cudaErrorIllegalState, "cudaStreamEndCapture: the stream is not capturing");
  }
  if (stream->capture_mode != cudaStreamCaptureModeRelaxed &&
      stream->capture_thread != std::this_thread::get_id()) {
    return fail(cudaErrorStreamCaptureWrongThread,
                "cudaStreamEndCapture: the capture was begun by another thread");
  }
  stream->capturing = false;
  std::vector<GraphNode> nodes = std::move(stream->captured);
  stream->captured.clear();
  if (stream->capture_invalidated) {
    return fail(cudaErrorStreamCaptureInvalidated,
                "cudaStreamEndCapture: a call not allowed during capture invalidated this capture");
  }
  auto recorded = std::make_unique<CUgraph_st>();
  recorded->nodes = std::move(nodes);
  *graph = runtime().graphs.insert(std::move(recorded));
  return cudaSuccess;
}

cudaError_t cudaStreamIsCapturing(cudaStream_t stream, cudaStreamCaptureStatus* status) {
  if (status == nullptr)
    return fail(cudaErrorInvalidValue, "cudaStreamIsCapturing: the output pointer is null");
  const std::lock_guard lock(runtime().mutex);
  if (const cudaError_t error = pillarseg::emu::check_stream(stream, "cudaStreamIsCapturing");
      error != cudaSuccess) {
    return error;
  }
  const CUstream_st* capture = pillarseg::emu::capturing_stream(stream);
  *status = capture == nullptr             ? cudaStreamCaptureStatusNone
            : capture->capture_invalidated ? cudaStreamCaptureStatusInvalidated
                                           : cudaStreamCaptureStatusActive;
  return cudaSuccess;
}

cudaError_t cudaGraphInstantiate(cudaGraphExec_t* executable, cudaGraph_t graph,
                                 unsigned long long flags) {
  if (executable == nullptr)
    return fail(cudaErrorInvalidValue, "cudaGraphInstantiate: the output pointer is null");
  const std::lock_guard lock(runtime().mutex);
  *executable = nullptr;
  if (!runtime().graphs.contains(graph)) {
    return fail(cudaErrorInvalidResourceHandle,
                "cudaGraphInstantiate: the graph is not a live graph");
  }
  if (flags != 0) {
    return fail(cudaErrorInvalidValue,
                fmt::format("cudaGraphInstantiate: flags {:#x} are not emulated", flags));
  }
  auto instance = std::make_unique<CUgraphExec_st>();
  instance->nodes = graph->nodes;
  *executable = runtime().executables.insert(std::move(instance));
  return cudaSuccess;
}

cudaError_t cudaGraphLaunch(cudaGraphExec_t executable, cudaStream_t stream) {
  std::vector<GraphNode> nodes;
  {
    const std::lock_guard lock(runtime().mutex);
    if (!runtime().executables.contains(executable)) {
      return fail(cudaErrorInvalidResourceHandle,
                  "cudaGraphLaunch: the executable graph is not live");
    }
    nodes = executable->nodes;
  }
  return pillarseg::emu::run_or_capture(stream, "cudaGraphLaunch", [nodes = std::move(nodes)] {
    return pillarseg::emu::replay(nodes);
  });
}

cudaError_t cudaGraphDestroy(cudaGraph_t graph) {
  const std::lock_guard lock(runtime().mutex);
  if (!runtime().graphs.destroy(graph)) {
    return fail(cudaErrorInvalidResourceHandle, "cudaGraphDestroy: the graph is not a live graph");
  }
  return cudaSuccess;
}

cudaError_t cudaGraphExecDestroy(cudaGraphExec_t executable) {
  const std::lock_guard lock(runtime().mutex);
  if (!runtime().executables.destroy(executable)) {
    return fail(cudaErrorInvalidResourceHandle,
                "cudaGraphExecDestroy: the executable graph is not live");
  }
  return cudaSuccess;
}

// ---- kernel attributes ----

cudaError_t cudaFuncSetAttribute(const void* kernel, cudaFuncAttribute attribute, int value) {
  if (kernel == nullptr)
    return fail(cudaErrorInvalidDeviceFunction, "cudaFuncSetAttribute: the kernel is null");
  if (attribute != cudaFuncAttributeMaxDynamicSharedMemorySize) {
    return fail(cudaErrorInvalidValue,
                fmt::format("cudaFuncSetAttribute: attribute {} is not emulated",
                            static_cast<int>(attribute)));
  }
  if (value < 0 || static_cast<std::size_t>(value) > pillarseg::emu::kMaxOptInSharedBytes) {
    return fail(
        cudaErrorInvalidValue,
        fmt::format(
            "cudaFuncSetAttribute: {} bytes of dynamic shared memory; the device allows 0 to {}",
            value, pillarseg::emu::kMaxOptInSharedBytes));
  }
  const std::lock_guard lock(runtime().mutex);
  runtime().shared_bytes_limit[kernel] = static_cast<std::size_t>(value);
  return cudaSuccess;
}
