// The GPU's two ceilings, measured in the same call as our kernels (DESIGN.md section 6): the
// practical dense BF16 matrix rate, cuBLAS's 8192 x 8192 x 8192 GEMM (BF16 inputs, FP32
// accumulation and output, random data: zeros run faster than real data), and the device memory
// bandwidth, a 2 GiB device-to-device copy (bytes read plus bytes written). Our kernels' rates and
// the roofline bounds are read against these. Each is timed with CUDA events after a warm-up run.
//
// Without a CUDA device, and in the emulated build, it prints "skipped: ..." and times nothing.
#include <benchmark/benchmark.h>

#include <cstdint>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "bench/support/cuda_bench.hpp"
#include "core/rng.hpp"
#include "kernels/device_buffer.hpp"
#if !defined(PILLARSEG_CUDA_EMULATION)
#include <cublas_v2.h>
#include <cuda_bf16.h>
#endif

namespace {

using namespace pillarseg;

bool device_or_skip(benchmark::State& state) {
  const std::string missing = bench::missing_cuda_device();
  if (missing.empty()) return true;
  state.SkipWithError(("skipped: no CUDA device: " + missing).c_str());
  return false;
}

#if !defined(PILLARSEG_CUDA_EMULATION)
void check_cublas(cublasStatus_t status, const char* call) {
  PS_CHECK(status == CUBLAS_STATUS_SUCCESS, "{} failed: {} ({})", call, cublasGetStatusName(status),
           cublasGetStatusString(status));
}

// n x n BF16 values uniform in [-1, 1), from a fixed seed.
cuda::DeviceBuffer<__nv_bfloat16> random_bf16(std::int64_t n, std::uint64_t seed) {
  Rng rng(seed);
  std::vector<__nv_bfloat16> host(static_cast<std::size_t>(n));
  for (auto& v : host) v = __float2bfloat16(static_cast<float>(rng.uniform(-1.0, 1.0)));
  return cuda::DeviceBuffer<__nv_bfloat16>::from_host(host);
}
#endif

// C (n x n, FP32) = A (n x n, BF16) B (n x n, BF16) through cublasGemmEx with FP32 compute.
void CublasGemmBF16(benchmark::State& state) {
  if (!device_or_skip(state)) return;
#if !defined(PILLARSEG_CUDA_EMULATION)
  const std::int64_t n = state.range(0);
  auto a = random_bf16(n * n, 1);
  auto b = random_bf16(n * n, 2);
  cuda::DeviceBuffer<float> c(static_cast<std::size_t>(n * n));
  cublasHandle_t raw_handle = nullptr;
  check_cublas(cublasCreate(&raw_handle), "cublasCreate");
  const std::unique_ptr<cublasContext, decltype(&cublasDestroy)> owner(raw_handle, &cublasDestroy);
  cublasHandle_t handle = owner.get();
  const float one = 1.0f, zero = 0.0f;
  const int ni = static_cast<int>(n);
  const double ms = bench::time_iterations(state, [&](cudaStream_t stream) {
    check_cublas(cublasSetStream(handle, stream), "cublasSetStream");
    check_cublas(cublasGemmEx(handle, CUBLAS_OP_N, CUBLAS_OP_N, ni, ni, ni, &one, a.data(),
                              CUDA_R_16BF, ni, b.data(), CUDA_R_16BF, ni, &zero, c.data(),
                              CUDA_R_32F, ni, CUBLAS_COMPUTE_32F, CUBLAS_GEMM_DEFAULT),
                 "cublasGemmEx (BF16 x BF16 -> FP32)");
  });
  const double flops =
      2.0 * static_cast<double>(n) * static_cast<double>(n) * static_cast<double>(n);
  state.counters["ms"] = ms;
  state.counters["TFLOP/s"] = ms > 0 ? flops / (ms * 1e-3) / 1e12 : 0.0;
#endif
}
BENCHMARK(CublasGemmBF16)
    ->Arg(8192)
    ->UseManualTime()
    ->Unit(benchmark::kMillisecond)
    ->Iterations(10);

// A device-to-device copy of `bytes` (the argument, MiB): bandwidth counts the bytes read and the
// bytes written.
void DeviceCopy(benchmark::State& state) {
  if (!device_or_skip(state)) return;
  const auto bytes = static_cast<std::size_t>(state.range(0)) << 20;
  cuda::DeviceBuffer<std::uint8_t> source(bytes), destination(bytes);
  PS_CUDA_CHECK(cudaMemset(source.data(), 0x5A, bytes));
  const double ms = bench::time_iterations(state, [&](cudaStream_t stream) {
    PS_CUDA_CHECK(cudaMemcpyAsync(destination.data(), source.data(), bytes,
                                  cudaMemcpyDeviceToDevice, stream));
  });
  state.counters["ms"] = ms;
  state.counters["TB/s"] = ms > 0 ? 2.0 * static_cast<double>(bytes) / (ms * 1e-3) / 1e12 : 0.0;
}
BENCHMARK(DeviceCopy)->Arg(2048)->UseManualTime()->Unit(benchmark::kMillisecond)->Iterations(20);

}  // namespace

BENCHMARK_MAIN();
