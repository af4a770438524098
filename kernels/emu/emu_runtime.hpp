// The CUDA runtime API for the host compiler: device memory is aligned host memory, streams run
// their work at once in the calling thread (so every call is also synchronous), events stamp the
// host clock, and stream capture records launches, copies, fills and event records into a graph
// that cudaGraphLaunch replays in order. One emulated device, with the limits of an sm_90 GPU.
//
// Calls validate their arguments like CUDA does and return the same error codes; the emulation
// also keeps a sentence saying what was wrong (pillarseg::emu::last_error_detail()), which
// PS_CUDA_CHECK appends to its message. Kernel launches go through pillarseg::emu::launch (the
// launch helper of kernels/common.cuh calls it); misuse inside a kernel (a divergent barrier, a bad
// warp mask) fails the launch with cudaErrorLaunchFailure and a detail naming block and thread.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include "kernels/emu/emu_scheduler.hpp"
#include "kernels/emu/emu_types.hpp"

// ---- device and errors ----
cudaError_t cudaGetDeviceCount(int* count);
cudaError_t cudaGetDevice(int* device);
cudaError_t cudaSetDevice(int device);
cudaError_t cudaGetDeviceProperties(cudaDeviceProp* properties, int device);
cudaError_t cudaDeviceSynchronize();
cudaError_t cudaGetLastError();
cudaError_t cudaPeekAtLastError();
const char* cudaGetErrorName(cudaError_t error);
const char* cudaGetErrorString(cudaError_t error);

// ---- memory ----
cudaError_t cudaMalloc(void** pointer, std::size_t bytes);
cudaError_t cudaFree(void* pointer);
cudaError_t cudaMallocHost(void** pointer, std::size_t bytes);
cudaError_t cudaFreeHost(void* pointer);
cudaError_t cudaMemGetInfo(std::size_t* free_bytes, std::size_t* total_bytes);
cudaError_t cudaMemcpy(void* destination, const void* source, std::size_t bytes,
                       cudaMemcpyKind kind);
cudaError_t cudaMemcpyAsync(void* destination, const void* source, std::size_t bytes,
                            cudaMemcpyKind kind, cudaStream_t stream = nullptr);
cudaError_t cudaMemset(void* destination, int value, std::size_t bytes);
cudaError_t cudaMemsetAsync(void* destination, int value, std::size_t bytes,
                            cudaStream_t stream = nullptr);

template <class T>
cudaError_t cudaMalloc(T** pointer, std::size_t bytes) {
  return cudaMalloc(reinterpret_cast<void**>(pointer), bytes);
}
template <class T>
cudaError_t cudaMallocHost(T** pointer, std::size_t bytes) {
  return cudaMallocHost(reinterpret_cast<void**>(pointer), bytes);
}

// ---- streams and events ----
cudaError_t cudaStreamCreate(cudaStream_t* stream);
cudaError_t cudaStreamCreateWithFlags(cudaStream_t* stream, unsigned int flags);
cudaError_t cudaStreamDestroy(cudaStream_t stream);
cudaError_t cudaStreamSynchronize(cudaStream_t stream);
cudaError_t cudaStreamQuery(cudaStream_t stream);
cudaError_t cudaStreamWaitEvent(cudaStream_t stream, cudaEvent_t event, unsigned int flags = 0);
cudaError_t cudaEventCreate(cudaEvent_t* event);
cudaError_t cudaEventCreateWithFlags(cudaEvent_t* event, unsigned int flags);
cudaError_t cudaEventDestroy(cudaEvent_t event);
cudaError_t cudaEventRecord(cudaEvent_t event, cudaStream_t stream = nullptr);
cudaError_t cudaEventSynchronize(cudaEvent_t event);
cudaError_t cudaEventQuery(cudaEvent_t event);
cudaError_t cudaEventElapsedTime(float* milliseconds, cudaEvent_t start, cudaEvent_t end);

// ---- graphs (stream capture) ----
cudaError_t cudaStreamBeginCapture(cudaStream_t stream, cudaStreamCaptureMode mode);
cudaError_t cudaStreamEndCapture(cudaStream_t stream, cudaGraph_t* graph);
cudaError_t cudaStreamIsCapturing(cudaStream_t stream, cudaStreamCaptureStatus* status);
cudaError_t cudaGraphInstantiate(cudaGraphExec_t* executable, cudaGraph_t graph,
                                 unsigned long long flags = 0);
cudaError_t cudaGraphLaunch(cudaGraphExec_t executable, cudaStream_t stream);
cudaError_t cudaGraphDestroy(cudaGraph_t graph);
cudaError_t cudaGraphExecDestroy(cudaGraphExec_t executable);

// ---- kernel attributes ----
cudaError_t cudaFuncSetAttribute(const void* kernel, cudaFuncAttribute attribute, int value);
template <class... Params>
cudaError_t cudaFuncSetAttribute(void (*kernel)(Params...), cudaFuncAttribute attribute,
                                 int value) {
  return cudaFuncSetAttribute(reinterpret_cast<const void*>(kernel), attribute, value);
}

namespace pillarseg::emu {

// What the last failing runtime call of this host thread found wrong (empty after success or
// after cudaGetLastError()).
const std::string& last_error_detail();

// A kernel with its arguments converted to the kernel's parameter types and copied, as a CUDA
// launch copies them; run_thread calls the kernel for the current emulated thread.
struct BoundKernel {
  const void* kernel = nullptr;  // identity, for the per-kernel attributes
  std::shared_ptr<const void> arguments;
  void (*run_thread)(const void* arguments) = nullptr;
};

template <class... Params>
struct KernelArguments {
  void (*kernel)(Params...);
  std::tuple<Params...> values;
  static void run_thread(const void* self) {
    const auto& bound = *static_cast<const KernelArguments*>(self);
    std::apply(bound.kernel, bound.values);
  }
};

template <class... Params, class... Args>
BoundKernel bind_kernel(void (*kernel)(Params...), Args&&... args) {
  static_assert(sizeof...(Params) == sizeof...(Args),
                "the kernel takes a different number of arguments");
  auto arguments = std::make_shared<const KernelArguments<Params...>>(
      KernelArguments<Params...>{kernel, std::tuple<Params...>(std::forward<Args>(args)...)});
  return BoundKernel{reinterpret_cast<const void*>(kernel), std::move(arguments),
                     &KernelArguments<Params...>::run_thread};
}

// Launches `kernel` on `stream` (runs it now, or records it while the stream captures). Checks
// the configuration like CUDA: cudaErrorInvalidConfiguration for a zero or too large grid or
// block, cudaErrorInvalidValue for more dynamic shared memory than the kernel may use (48 KiB, or
// what cudaFuncSetAttribute allowed, at most 227 KiB); cudaErrorLaunchFailure if the kernel
// misused barriers or warp operations. Sets the last error as CUDA does.
cudaError_t launch(BoundKernel kernel, dim3 grid, dim3 block, std::size_t dynamic_shared_bytes,
                   cudaStream_t stream);

// What came down from the device: while recording, every device-to-host copy appends a 64-bit
// hash of its bytes, so that a test can compare all it read back under two schedules (a race
// that a tolerance would hide still changes a bit). Copies from several host threads append in
// the order they happen.
void record_copy_digests(bool on);
std::vector<std::uint64_t> take_copy_digests();

}  // namespace pillarseg::emu
