// What the kernel benchmarks (bench_kernels_*) share: whether they can time anything (they run
// only on a real CUDA device and skip, saying why, on the emulation or without one), and the
// timing of a pass with CUDA events after one warm-up run.
#pragma once

#include <benchmark/benchmark.h>

#include <cstdint>
#include <functional>
#include <string>

#include "kernels/common.cuh"
#include "kernels/cuda_handles.hpp"

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

// A stream and two events: times what `run` queues on the stream.
class EventTimer {
 public:
  // Milliseconds between the events recorded around run(stream).
  double milliseconds(const std::function<void(cudaStream_t)>& run) {
    PS_CUDA_CHECK(cudaEventRecord(start_.get(), stream_.get()));
    run(stream_.get());
    PS_CUDA_CHECK(cudaEventRecord(stop_.get(), stream_.get()));
    PS_CUDA_CHECK(cudaEventSynchronize(stop_.get()));
    float ms = 0.0f;
    PS_CUDA_CHECK(cudaEventElapsedTime(&ms, start_.get(), stop_.get()));
    return ms;
  }

 private:
  cuda::Stream stream_;
  cuda::Event start_, stop_;
};

// One warm-up run, then each iteration's event time as the benchmark's (manual) time. Returns
// the mean time in ms (0 when no iteration ran).
inline double time_iterations(benchmark::State& state,
                              const std::function<void(cudaStream_t)>& run) {
  EventTimer timer;
  timer.milliseconds(run);
  double total_ms = 0.0;
  std::int64_t runs = 0;
  for (auto _ : state) {
    const double ms = timer.milliseconds(run);
    state.SetIterationTime(ms * 1e-3);
    total_ms += ms;
    ++runs;
  }
  return runs > 0 ? total_ms / static_cast<double>(runs) : 0.0;
}

}  // namespace pillarseg::bench
