// What every kernel file and the CUDA backend share:
//   PS_CUDA_CHECK(call)      the one checking macro for CUDA runtime calls;
//   ceil_div(n, d)           grid sizes;
//   launch_kernel(kernel, grid, block, shared_bytes, stream, args...)
//                            the one way to launch a kernel (also in emulated builds, which have
//                            no <<<>>>), checked like a runtime call;
//   dynamic_shared<T>()      the block's dynamic shared memory (`extern __shared__` on a GPU).
// Compiles with nvcc, with the host compiler against real CUDA (without launch_kernel and
// dynamic_shared, which need device code), and against the emulation (PILLARSEG_CUDA_EMULATION).
#pragma once

#include <cstddef>
#include <source_location>
#include <string>
#include <string_view>
#include <type_traits>
#include <utility>

#include <fmt/core.h>

#include "core/error.hpp"
#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// Throws pillarseg::Error for a failed CUDA call, as
//   "CUDA call `<call>` failed at <file>:<line>: cudaErrorName (error string)[: what the emulation
//   found wrong]",
// and clears CUDA's last error so that later checks start clean.
[[noreturn]] inline void throw_cuda_error(cudaError_t error, std::string_view call,
                                          const char* file, int line) {
  std::string message = fmt::format("CUDA call `{}` failed at {}:{}: {} ({})", call, file, line,
                                    cudaGetErrorName(error), cudaGetErrorString(error));
#if defined(PILLARSEG_CUDA_EMULATION)
  if (!emu::last_error_detail().empty()) message += fmt::format(": {}", emu::last_error_detail());
#endif
  static_cast<void>(cudaGetLastError());
  throw Error(message);
}

// ceil(numerator / denominator) for numerator >= 0 and denominator > 0.
template <class A, class B>
__host__ __device__ constexpr std::common_type_t<A, B> ceil_div(A numerator, B denominator) {
  static_assert(std::is_integral_v<A> && std::is_integral_v<B>, "ceil_div is for integers");
  return (numerator + denominator - 1) / denominator;
}

}  // namespace pillarseg::cuda

// Evaluates a CUDA runtime call once; throws pillarseg::Error naming the call, file and line
// unless it returned cudaSuccess.
#define PS_CUDA_CHECK(call)                                                           \
  do {                                                                                \
    const cudaError_t ps_cuda_error_ = (call);                                        \
    if (ps_cuda_error_ != cudaSuccess) {                                              \
      ::pillarseg::cuda::throw_cuda_error(ps_cuda_error_, #call, __FILE__, __LINE__); \
    }                                                                                 \
  } while (0)

#if defined(__CUDACC__) || defined(PILLARSEG_CUDA_EMULATION)
namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// launch_kernel's work: kernel<<<grid, block, shared_bytes, stream>>>(args...) on a GPU, the
// emulated launch otherwise; a failed launch throws with the caller's file and line.
template <class... Params, class... Args>
void launch_kernel_at(const std::source_location& where, void (*kernel)(Params...), dim3 grid,
                      dim3 block, std::size_t shared_bytes, cudaStream_t stream, Args&&... args) {
#if defined(PILLARSEG_CUDA_EMULATION)
  const cudaError_t error = emu::launch(emu::bind_kernel(kernel, std::forward<Args>(args)...), grid,
                                        block, shared_bytes, stream);
#else
  // clang-format off
  kernel<<<grid, block, shared_bytes, stream>>>(std::forward<Args>(args)...);
  // clang-format on
  const cudaError_t error = cudaGetLastError();
#endif
  if (error != cudaSuccess) {
    const std::string call =
        fmt::format("kernel launch <<<({}, {}, {}), ({}, {}, {}), {}>>>", grid.x, grid.y, grid.z,
                    block.x, block.y, block.z, shared_bytes);
    throw_cuda_error(error, call, where.file_name(), static_cast<int>(where.line()));
  }
}

// launch_kernel(kernel, grid, block, shared_bytes, stream, args...): launches `kernel` with
// `args` converted to its parameter types. Used like a function; it is a class only so that it
// can take the caller's source location after the variadic arguments (the deduction guide below
// deduces Kernel and Args from the call).
template <class Kernel, class... Args>
struct launch_kernel {
  launch_kernel(Kernel kernel, dim3 grid, dim3 block, std::size_t shared_bytes, cudaStream_t stream,
                Args&&... args,
                const std::source_location& where = std::source_location::current()) {
    launch_kernel_at(where, kernel, grid, block, shared_bytes, stream, std::forward<Args>(args)...);
  }
};
template <class Kernel, class... Args>
launch_kernel(Kernel, dim3, dim3, std::size_t, cudaStream_t, Args&&...)
    -> launch_kernel<Kernel, Args...>;

// The block's dynamic shared memory (the launch's shared_bytes), at least 16-byte aligned.
template <class T>
__device__ __forceinline__ T* dynamic_shared() {
#if defined(PILLARSEG_CUDA_EMULATION)
  return reinterpret_cast<T*>(emu::dynamic_shared_memory());
#else
  extern __shared__ __align__(16) unsigned char ps_dynamic_shared_memory[];
  return reinterpret_cast<T*>(ps_dynamic_shared_memory);
#endif
}

}  // namespace pillarseg::cuda
#endif
