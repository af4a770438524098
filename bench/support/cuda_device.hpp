// Whether the kernel benchmarks (bench_kernels_*) can time anything: they run only on a real
// CUDA device and skip, saying why, on the emulation or without one.
#pragma once

#include <string>

#if !defined(PILLARSEG_CUDA_EMULATION)
#include <cuda_runtime.h>
#endif

namespace pillarseg::bench {

// Empty when a CUDA device can run the kernels, else why not.
inline std::string missing_cuda_device() {
#if defined(PILLARSEG_CUDA_EMULATION)
  return "this build runs the kernels on the CPU emulation";
#else
  int devices = 0;
  const cudaError_t error = cudaGetDeviceCount(&devices);
  if (error != cudaSuccess) {
    static_cast<void>(cudaGetLastError());
    return std::string(cudaGetErrorName(error)) + ": " + cudaGetErrorString(error);
  }
  if (devices == 0) return "cudaGetDeviceCount found none";
  return "";
#endif
}

}  // namespace pillarseg::bench
