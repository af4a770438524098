// The INT8 tensor-core convolutions (kernels/conv2d_mma_s8.cuh) on the GPU at the U-Net's layer
// shapes (those of bench_kernels_conv: b = 64 on the 1000 x 500 grid, the transposed-convolution
// variant's upsamplings, a small model at batch 2), beside the BF16 tensor-core forward of the
// same layers (kernels/conv2d_mma.cuh) timed in the same process:
//   Conv2dForwardBF16/<layer>        FP32 in and out, BF16 multiplies (the reference);
//   Conv2dForwardINT8/<layer>        FP32 in and out, activations quantized as they are staged;
//   Conv2dForwardINT8_bf16io/<layer> BF16 in and out (activations stored in 16 bits between
//                                    layers);
//   Conv2dForwardINT8_s8io/<layer>   S8x32 in and out (activations stored in INT8 between layers:
//                                    staged by cp.async alone);
//   Conv2dForwardINT8_u8_bf16io/<layer>
//                                    BF16 in and out, x non-negative (ActivationsS8::non_negative:
//                                    quantized to u8, mma.sync .u8.s8), beside INT8_bf16io;
// and the same for ConvTranspose2dForward*. Weights prepared once, split K with its workspace as
// the CUDA backend would run it. Each pass is timed with CUDA events after one warm-up run and
// reported in ms and GFLOP/s (2 multiply-adds per weight tap and output pixel), with its share of
// the device's dense INT8 (or 16-bit) tensor-core peak, pct_of_peak, and for INT8 the BF16 pass's
// time over its own, bf16_ms/int8_ms (> 1: INT8 is faster).
//
// Without a CUDA device, and in the emulated build, it prints "skipped: no CUDA device" and runs
// nothing.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <functional>
#include <map>
#include <string>
#include <vector>

#include "bench/support/cuda_bench.hpp"
#include "core/ops.hpp"
#include "core/rng.hpp"
#include "kernels/common.cuh"
#include "kernels/conv2d_mma.cuh"
#include "kernels/conv2d_mma_s8.cuh"
#include "kernels/device_buffer.hpp"
#include "kernels/mma.cuh"

using namespace pillarseg;
using cuda::DeviceBuffer;

namespace {

// A layer as the GEMM runs it: a convolution {batch, I, H, W, O, k, pad}, or the transposed 2x2
// {batch, I, H, W, O, -, -} (y of 2H x 2W).
struct Layer {
  const char* name;
  cuda::Conv2dShape shape;
  bool transposed;
};

const Layer kLayers[] = {
    {"full_occupancy_20to16_500x1000", {1, 20, 500, 1000, 16, 3, 1}, false},
    {"full_inc_64to64_500x1000", {1, 64, 500, 1000, 64, 3, 1}, false},
    {"full_down1_64to128_250x500", {1, 64, 250, 500, 128, 3, 1}, false},
    {"full_down2_128to256_125x250", {1, 128, 125, 250, 256, 3, 1}, false},
    {"full_up1_512to256_62x125", {1, 512, 62, 125, 256, 3, 1}, false},
    {"full_deepest_1024to1024_31x62", {1, 1024, 31, 62, 1024, 3, 1}, false},
    {"small_down1_16to32_125x250_B2", {2, 16, 125, 250, 32, 3, 1}, false},
    {"full_up1_1024to512_31x62", {1, 1024, 31, 62, 512, 2, 0}, true},
    {"full_up4_128to64_250x500", {1, 128, 250, 500, 64, 2, 0}, true},
};

std::int64_t output_pixels(const Layer& l) {
  return l.transposed ? 4 * l.shape.height * l.shape.width
                      : l.shape.out_height() * l.shape.out_width();
}

double flops(const Layer& l) {
  const cuda::Conv2dShape& s = l.shape;
  const double taps = l.transposed ? 1.0 : static_cast<double>(s.kernel * s.kernel);
  return 2.0 * static_cast<double>(s.batch * s.out_channels * s.in_channels) * taps *
         static_cast<double>(output_pixels(l));
}

// The dense tensor-core rate in flops per clock per SM, 16-bit with FP32 accumulation: 2048 on
// sm_80 and sm_87, 1024 on sm_86 and sm_89, 4096 on sm_90; INT8 twice that.
double dense_peak_flops(bool int8) {
#if defined(PILLARSEG_CUDA_EMULATION)
  static_cast<void>(int8);
  return 0;  // no device, no peak
#else
  int device = 0, major = 0, minor = 0, sms = 0, khz = 0;
  PS_CUDA_CHECK(cudaGetDevice(&device));
  PS_CUDA_CHECK(cudaDeviceGetAttribute(&major, cudaDevAttrComputeCapabilityMajor, device));
  PS_CUDA_CHECK(cudaDeviceGetAttribute(&minor, cudaDevAttrComputeCapabilityMinor, device));
  PS_CUDA_CHECK(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device));
  PS_CUDA_CHECK(cudaDeviceGetAttribute(&khz, cudaDevAttrClockRate, device));
  const int sm = 10 * major + minor;
  const double half = sm >= 90 ? 4096 : (sm == 86 || sm == 89) ? 1024 : sm >= 80 ? 2048 : 0;
  return (int8 ? 2 : 1) * half * sms * khz * 1e3;
#endif
}

// The BF16 pass's time per layer, for bf16_ms/int8_ms.
std::map<std::string, double>& bf16_ms() {
  static std::map<std::string, double> times;
  return times;
}

// Uniform in [-spread, spread], or [0, spread] when non_negative.
DeviceBuffer<float> random_buffer(std::int64_t n, std::uint64_t seed, double spread,
                                  bool non_negative = false) {
  Rng rng(seed);
  std::vector<float> values(static_cast<size_t>(n));
  for (float& v : values) v = static_cast<float>(rng.uniform(non_negative ? 0.0 : -spread, spread));
  return DeviceBuffer<float>::from_host(values);
}

DeviceBuffer<std::uint16_t> random_bf16_buffer(std::int64_t n, std::uint64_t seed,
                                               bool non_negative) {
  Rng rng(seed);
  std::vector<std::uint16_t> values(static_cast<size_t>(n));
  for (auto& v : values)
    v = cuda::float_to_bf16_bits(static_cast<float>(rng.uniform(non_negative ? 0.0 : -1.0, 1.0)));
  return DeviceBuffer<std::uint16_t>::from_host(values);
}

bool tensor_cores_or_skip(benchmark::State& state) {
  std::string why;
  if (cuda::mma_supported(&why)) return true;
  state.SkipWithError(why.c_str());
  return false;
}

// Times `run`, sets GFLOP/s and pct_of_peak; returns the mean ms.
double time_layer(benchmark::State& state, const Layer& l, bool int8,
                  const std::function<void(cudaStream_t)>& run) {
  const double ms = bench::time_iterations(state, run);
  state.counters["GFLOP/s"] =
      benchmark::Counter(flops(l) * 1e-9, benchmark::Counter::kIsIterationInvariantRate);
  const double peak = dense_peak_flops(int8);
  if (ms > 0 && peak > 0) state.counters["pct_of_peak"] = 100.0 * flops(l) / (ms * 1e-3) / peak;
  return ms;
}

void BM_Bf16(benchmark::State& state, const Layer& l) {
  if (!tensor_cores_or_skip(state)) return;
  const cuda::Conv2dShape& s = l.shape;
  const std::int64_t taps = l.transposed ? 1 : s.kernel * s.kernel;
  const std::int64_t columns = l.transposed ? 4 * s.out_channels : s.out_channels;
  DeviceBuffer<float> x = random_buffer(s.batch * s.in_channels * s.height * s.width, 1, 1.0);
  DeviceBuffer<float> w =
      random_buffer(s.out_channels * s.in_channels * (l.transposed ? 4 : taps), 2, 0.1);
  DeviceBuffer<float> bias = random_buffer(s.out_channels, 3, 0.1);
  DeviceBuffer<std::uint16_t> w16(
      static_cast<size_t>(columns * op::half16_weight_k(s.in_channels, taps)));
  DeviceBuffer<float> bias_out(static_cast<size_t>(columns));
  DeviceBuffer<float> y(static_cast<size_t>(s.batch * s.out_channels * output_pixels(l)));
  const std::int64_t workspace_floats =
      l.transposed ? cuda::conv_transpose2d_mma_forward_workspace(s.batch, s.in_channels, s.height,
                                                                   s.width, s.out_channels)
                   : cuda::conv2d_mma_forward_workspace(s);
  DeviceBuffer<float> workspace(static_cast<size_t>(std::max<std::int64_t>(workspace_floats, 1)));
  float* ws = workspace_floats > 0 ? workspace.data() : nullptr;
  if (l.transposed)
    cuda::prepare_conv_transpose_weights(w.data(), bias.data(), s.in_channels, s.out_channels,
                                         cuda::Half16::BF16, w16.data(), bias_out.data(), nullptr);
  else
    cuda::prepare_conv_weights(w.data(), bias.data(), cuda::FoldedBatchNorm{}, s,
                               cuda::Half16::BF16, w16.data(), bias_out.data(), nullptr);
  bf16_ms()[l.name] = time_layer(state, l, false, [&](cudaStream_t stream) {
    if (l.transposed)
      cuda::conv_transpose2d_mma_forward(x.data(), false, w16.data(), bias_out.data(), s.batch,
                                          s.in_channels, s.height, s.width, s.out_channels,
                                          cuda::Half16::BF16, y.data(), false, stream, ws);
    else
      cuda::conv2d_mma_forward(x.data(), false, w16.data(), bias_out.data(), s, cuda::Half16::BF16,
                               false, y.data(), false, stream, ws);
  });
}

// x and y in `layout` (FP32, BF16, or S8x32: x quantized beforehand, untimed); non_negative: x
// in [0, 1] quantized to u8 (FP32 or BF16 only), otherwise x in [-1, 1] to s8.
void BM_Int8(benchmark::State& state, const Layer& l, cuda::ActivationLayout layout,
             bool non_negative) {
  if (!tensor_cores_or_skip(state)) return;
  using cuda::ActivationLayout;
  const cuda::Conv2dShape& s = l.shape;
  const std::int64_t taps = l.transposed ? 1 : s.kernel * s.kernel;
  const std::int64_t columns = l.transposed ? 4 * s.out_channels : s.out_channels;
  const std::int64_t x_count = s.batch * s.in_channels * s.height * s.width;
  const std::int64_t y_count = s.batch * s.out_channels * output_pixels(l);
  const std::int64_t y_height = l.transposed ? 2 * s.height : s.out_height(),
                     y_width = l.transposed ? 2 * s.width : s.out_width();
  const bool f32 = layout == ActivationLayout::F32, bf16 = layout == ActivationLayout::BF16,
             s8 = layout == ActivationLayout::S8x32;
  const float x_scale = non_negative ? 1.0f / 255.0f : 1.0f / 127.0f, y_scale = 4.0f / 127.0f;
  DeviceBuffer<float> x = random_buffer(bf16 ? 1 : x_count, 1, 1.0, non_negative);
  DeviceBuffer<std::uint16_t> x16 = random_bf16_buffer(bf16 ? x_count : 1, 1, non_negative);
  DeviceBuffer<std::int8_t> x8(static_cast<size_t>(
      s8 ? cuda::activations_s8_bytes(s.batch, s.in_channels, s.height, s.width) : 16));
  if (s8)
    cuda::quantize_activations_s8(x.data(), ActivationLayout::F32, x_scale, s.batch, s.in_channels,
                                  s.height, s.width, x8.data(), nullptr);
  DeviceBuffer<float> w =
      random_buffer(s.out_channels * s.in_channels * (l.transposed ? 4 : taps), 2, 0.1);
  DeviceBuffer<float> bias = random_buffer(s.out_channels, 3, 0.1);
  DeviceBuffer<std::int8_t> w8(
      static_cast<size_t>(columns * op::half16_weight_k(s.in_channels, taps)));
  DeviceBuffer<float> w_scale(static_cast<size_t>(columns)), bias_out(static_cast<size_t>(columns));
  DeviceBuffer<float> y(static_cast<size_t>(f32 ? y_count : 1));
  DeviceBuffer<std::uint16_t> y16(static_cast<size_t>(bf16 ? y_count : 1));
  DeviceBuffer<std::int8_t> y8(static_cast<size_t>(
      s8 ? cuda::activations_s8_bytes(s.batch, s.out_channels, y_height, y_width) : 16));
  const std::int64_t workspace_count =
      l.transposed ? cuda::conv_transpose2d_mma_s8_forward_workspace(
                         s.batch, s.in_channels, s.height, s.width, s.out_channels)
                   : cuda::conv2d_mma_s8_forward_workspace(s);
  DeviceBuffer<std::int32_t> workspace(
      static_cast<size_t>(std::max<std::int64_t>(workspace_count, 1)));
  std::int32_t* ws = workspace_count > 0 ? workspace.data() : nullptr;
  if (l.transposed)
    cuda::prepare_conv_transpose_weights_s8(w.data(), bias.data(), s.in_channels, s.out_channels,
                                            w8.data(), w_scale.data(), bias_out.data(), nullptr);
  else
    cuda::prepare_conv_weights_s8(w.data(), bias.data(), cuda::FoldedBatchNorm{}, s, w8.data(),
                                  w_scale.data(), bias_out.data(), nullptr);
  const void* x_data = s8     ? static_cast<const void*>(x8.data())
                       : bf16 ? static_cast<const void*>(x16.data())
                              : x.data();
  void* y_data = s8     ? static_cast<void*>(y8.data())
                 : bf16 ? static_cast<void*>(y16.data())
                        : y.data();
  const cuda::ActivationsS8 x_in{x_data, layout, x_scale, non_negative};
  const cuda::OutputS8 y_out{y_data, layout, y_scale};
  const double ms = time_layer(state, l, true, [&](cudaStream_t stream) {
    if (l.transposed)
      cuda::conv_transpose2d_mma_s8_forward(x_in, w8.data(), w_scale.data(), bias_out.data(),
                                             s.batch, s.in_channels, s.height, s.width,
                                             s.out_channels, false, y_out, stream, ws);
    else
      cuda::conv2d_mma_s8_forward(x_in, w8.data(), w_scale.data(), bias_out.data(), s, false, y_out,
                                  stream, ws);
  });
  const auto reference = bf16_ms().find(l.name);
  if (reference != bf16_ms().end() && ms > 0)
    state.counters["bf16_ms/int8_ms"] = reference->second / ms;
}

void register_benchmarks() {
  for (const Layer& l : kLayers) {
    const std::string kind = l.transposed ? "ConvTranspose2dForward" : "Conv2dForward";
    benchmark::RegisterBenchmark((kind + "BF16/" + l.name).c_str(), BM_Bf16, l)
        ->Unit(benchmark::kMillisecond)
        ->UseManualTime();
    struct Variant {
      const char* suffix;
      cuda::ActivationLayout layout;
      bool non_negative;
    };
    for (const Variant& v : {Variant{"INT8/", cuda::ActivationLayout::F32, false},
                             Variant{"INT8_bf16io/", cuda::ActivationLayout::BF16, false},
                             Variant{"INT8_u8_bf16io/", cuda::ActivationLayout::BF16, true},
                             Variant{"INT8_s8io/", cuda::ActivationLayout::S8x32, false}}) {
      benchmark::RegisterBenchmark((kind + v.suffix + l.name).c_str(), BM_Int8, l, v.layout,
                                   v.non_negative)
          ->Unit(benchmark::kMillisecond)
          ->UseManualTime();
    }
  }
}

}  // namespace

int main(int argc, char** argv) {
  const std::string missing = pillarseg::bench::missing_cuda_device();
  if (!missing.empty()) {
    std::printf("bench_kernels_int8 skipped: no CUDA device (%s)\n", missing.c_str());
    return 0;
  }
  register_benchmarks();
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
