// The convolution kernels (kernels/conv2d.cu, kernels/conv_transpose2d.cu) on the GPU at the
// U-Net's layer shapes (b = 64 on the 1000 x 500 grid, the transposed-convolution variant's
// upsamplings, a small CPU-sized model): conv2d forward, input gradient and parameter gradients
// (dw + db), conv_transpose2d the same. Each pass is timed with CUDA events on its own stream
// after one warm-up run, and reported in ms and GFLOP/s (2 multiply-add flops per weight tap and
// output pixel: 2 B O I k k Ho Wo for every pass of conv2d, 2 B I 4O H W for conv_transpose2d).
// With CUDA, every conv2d pass also runs through the engines that CudaBackend selects with
// --conv (engine/cuda/vendor_conv.hpp, PILLARSEG_BENCH_VENDOR_CONV): cuDNN with FP32 FMA math and
// with cuDNN's default math (which may use TF32 tensor cores), both with the algorithms that
// cudnnFind* times fastest (cuDNN rows only where cuDNN is installed), and im2col / col2im +
// cuBLAS SGEMM in FP32; those rows add ours_ms/peer_ms, our pass's time over theirs (> 1: the
// peer is faster).
//
// Beside them, the BF16 and FP16 tensor-core forward (Conv2dForwardBF16/..., FP16), with its
// percentage of the device's dense 16-bit peak and its speed-up over our FP32 forward, and with
// CUDA cuDNN's 16-bit forward and cuBLAS's 16-bit GEMM of the same sizes (..._cudnn,
// ..._cublas_gemm) with the same share of the peak and ours_ms/peer_ms; and the tensor-core
// training gradients of 16-bit training (Conv2dBackwardDataBF16/..., Conv2dBackwardWeightsBF16/...,
// FP16, and ConvTranspose2dBackward{Data,Weights}{BF16,FP16}/...), with the same share of the peak
// and their speed-up over our FP32 pass (fp32_ms/half_ms).
//
// Without a CUDA device, and in the emulated build (whose times say nothing about a GPU), it
// prints "skipped: no CUDA device" and runs nothing.
#include <benchmark/benchmark.h>

#include <cstdint>
#include <cstdio>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "bench/support/cuda_bench.hpp"
#include "core/ops.hpp"
#include "core/rng.hpp"
#if defined(PILLARSEG_BENCH_VENDOR_CONV)
#include "engine/cuda/vendor_conv.hpp"
#endif
#include "kernels/common.cuh"
#include "kernels/conv2d.cuh"
#include "kernels/conv2d_mma.cuh"
#include "kernels/half_ops.cuh"
#include "kernels/conv_transpose2d.cuh"
#include "kernels/device_buffer.hpp"

using namespace pillarseg;
using cuda::DeviceBuffer;

namespace {

struct ConvLayer {
  const char* name;
  cuda::Conv2dShape shape;  // {batch, I, H, W, O, k, pad}
  bool bias;
};

// The full model (b = 64, I = 64, 1000 x 500 grid: images of 500 rows x 1000 columns), its
// occupancy convolution (20 -> 16, no bias) and head, and a small model (b = 16) at batch 2.
const ConvLayer kConvLayers[] = {
    {"full_occupancy_20to16_500x1000", {1, 20, 500, 1000, 16, 3, 1}, false},
    {"full_inc_64to64_500x1000", {1, 64, 500, 1000, 64, 3, 1}, true},
    {"full_down1_64to128_250x500", {1, 64, 250, 500, 128, 3, 1}, true},
    {"full_down2_128to256_125x250", {1, 128, 125, 250, 256, 3, 1}, true},
    {"full_up1_512to256_62x125", {1, 512, 62, 125, 256, 3, 1}, true},
    {"full_head_64to12_1x1_500x1000", {1, 64, 500, 1000, 12, 1, 0}, true},
    {"small_down1_16to32_125x250_B2", {2, 16, 125, 250, 32, 3, 1}, true},
};

struct ConvTransposeLayer {
  const char* name;
  cuda::ConvTranspose2dShape shape;  // {batch, I, H, W, O}
};

// The transposed-convolution variant (widths 2b .. 16b with b = 64) upsampling its deepest and
// its last level.
const ConvTransposeLayer kConvTransposeLayers[] = {
    {"full_up1_1024to512_31x62", {1, 1024, 31, 62, 512}},
    {"full_up4_128to64_250x500", {1, 128, 250, 500, 64}},
};

double conv_flops(const cuda::Conv2dShape& s) {
  return 2.0 * static_cast<double>(s.batch * s.out_channels * s.in_channels * s.kernel * s.kernel) *
         static_cast<double>(s.out_height() * s.out_width());
}

double conv_transpose_flops(const cuda::ConvTranspose2dShape& s) {
  return 2.0 * static_cast<double>(s.batch * s.in_channels * 4 * s.out_channels) *
         static_cast<double>(s.height * s.width);
}

DeviceBuffer<float> random_buffer(std::int64_t n, std::uint64_t seed) {
  Rng rng(seed);
  std::vector<float> values(static_cast<size_t>(n));
  for (float& v : values) v = static_cast<float>(rng.uniform(-1.0, 1.0));
  return DeviceBuffer<float>::from_host(values);
}

// bench::time_iterations, and the GFLOP/s counter. Returns the mean time in ms.
double time_pass(benchmark::State& state, double flops,
                 const std::function<void(cudaStream_t)>& run) {
  const double mean_ms = bench::time_iterations(state, run);
  state.counters["GFLOP/s"] =
      benchmark::Counter(flops * 1e-9, benchmark::Counter::kIsIterationInvariantRate);
  return mean_ms;
}

// Our conv2d time per pass and layer ("forward/<layer>", ...), for the peers' ratio.
std::map<std::string, double>& our_ms() {
  static std::map<std::string, double> times;
  return times;
}

// Device tensors of one conv2d layer.
struct ConvBuffers {
  explicit ConvBuffers(const cuda::Conv2dShape& s)
      : x(random_buffer(s.batch * s.in_channels * s.height * s.width, 1)),
        w(random_buffer(s.out_channels * s.in_channels * s.kernel * s.kernel, 2)),
        bias(random_buffer(s.out_channels, 3)),
        dy(random_buffer(s.batch * s.out_channels * s.out_height() * s.out_width(), 4)),
        y(dy.size()),
        dx(x.size()),
        dw(w.size()),
        db(bias.size()),
        workspace(cuda::conv2d_backward_weights_workspace(s)) {}
  DeviceBuffer<float> x, w, bias, dy, y, dx, dw, db, workspace;
};

void BM_Conv2dForward(benchmark::State& state, const ConvLayer& l) {
  ConvBuffers b(l.shape);
  const double ms = time_pass(state, conv_flops(l.shape), [&](cudaStream_t stream) {
    cuda::conv2d_forward(b.x.data(), b.w.data(), l.bias ? b.bias.data() : nullptr, b.y.data(),
                         l.shape, stream);
  });
  our_ms()[std::string("forward/") + l.name] = ms;
}

void BM_Conv2dBackwardData(benchmark::State& state, const ConvLayer& l) {
  ConvBuffers b(l.shape);
  our_ms()[std::string("backward_data/") + l.name] =
      time_pass(state, conv_flops(l.shape), [&](cudaStream_t stream) {
        cuda::conv2d_backward_data(b.dy.data(), b.w.data(), b.dx.data(), l.shape, stream);
      });
}

void BM_Conv2dBackwardWeights(benchmark::State& state, const ConvLayer& l) {
  ConvBuffers b(l.shape);
  our_ms()[std::string("backward_weights/") + l.name] =
      time_pass(state, conv_flops(l.shape), [&](cudaStream_t stream) {
        cuda::conv2d_backward_weights(b.x.data(), b.dy.data(), b.dw.data(),
                                      l.bias ? b.db.data() : nullptr, l.shape, b.workspace.data(),
                                      b.workspace.size(), stream);
      });
  state.counters["workspace_MiB"] = static_cast<double>(b.workspace.bytes()) / (1 << 20);
}

#if defined(PILLARSEG_BENCH_VENDOR_CONV)
enum class Pass { Forward, BackwardData, BackwardWeights };

const char* pass_name(Pass pass) {
  switch (pass) {
    case Pass::Forward:
      return "forward";
    case Pass::BackwardData:
      return "backward_data";
    case Pass::BackwardWeights:
      return "backward_weights";
  }
  return "";
}

// One pass of a vendor engine, made once (handle, descriptors, algorithm search and workspace in
// the warm-up run), then timed like ours.
void BM_Conv2dPeer(benchmark::State& state, const ConvLayer& l, ConvolutionImpl impl,
                   cuda::VendorConvOptions options, Pass pass) {
  ConvBuffers b(l.shape);
  const std::unique_ptr<cuda::Conv2dEngine> engine = cuda::make_vendor_conv2d(impl, options);
  const double ms = time_pass(state, conv_flops(l.shape), [&](cudaStream_t stream) {
    switch (pass) {
      case Pass::Forward:
        engine->forward(b.x.data(), b.w.data(), l.bias ? b.bias.data() : nullptr, b.y.data(),
                        l.shape, stream, /*capturing=*/false);
        break;
      case Pass::BackwardData:
        engine->backward_data(b.dy.data(), b.w.data(), b.dx.data(), l.shape, stream, false);
        break;
      case Pass::BackwardWeights:
        engine->backward_weights(b.x.data(), b.dy.data(), b.dw.data(),
                                 l.bias ? b.db.data() : nullptr, l.shape, stream, false);
        break;
    }
  });
  state.counters["workspace_MiB"] =
      static_cast<double>(engine->stats().workspace_bytes) / (1 << 20);
  const auto ours = our_ms().find(std::string(pass_name(pass)) + "/" + l.name);
  if (ours != our_ms().end() && ms > 0.0) state.counters["ours_ms/peer_ms"] = ours->second / ms;
}

// The peers of each pass, registered after ours.
void register_peers(const ConvLayer& l, Pass pass, const char* our_name) {
  struct Peer {
    const char* name;
    ConvolutionImpl impl;
    bool tensor_cores;
  };
  const Peer peers[] = {
#if defined(PILLARSEG_WITH_CUDNN)
    {"cudnn_fp32", ConvolutionImpl::Cudnn, false},
    {"cudnn_default_math", ConvolutionImpl::Cudnn, true},
#endif
    {"cublas_im2col", ConvolutionImpl::Cublas, false},
  };
  for (const Peer& peer : peers) {
    cuda::VendorConvOptions options;
    options.allow_tensor_cores = peer.tensor_cores;
    options.timed_search = true;
    benchmark::RegisterBenchmark((std::string(our_name) + "_" + peer.name + "/" + l.name).c_str(),
                                 BM_Conv2dPeer, l, peer.impl, options, pass)
        ->Unit(benchmark::kMillisecond)
        ->UseManualTime();
  }
}
#endif

struct ConvTransposeBuffers {
  explicit ConvTransposeBuffers(const cuda::ConvTranspose2dShape& s)
      : x(random_buffer(s.batch * s.in_channels * s.height * s.width, 5)),
        w(random_buffer(s.in_channels * s.out_channels * 4, 6)),
        bias(random_buffer(s.out_channels, 7)),
        dy(random_buffer(s.batch * s.out_channels * s.out_height() * s.out_width(), 8)),
        y(dy.size()),
        dx(x.size()),
        dw(w.size()),
        db(bias.size()),
        workspace(cuda::conv_transpose2d_backward_weights_workspace(s)) {}
  DeviceBuffer<float> x, w, bias, dy, y, dx, dw, db, workspace;
};

void BM_ConvTranspose2dForward(benchmark::State& state, const ConvTransposeLayer& l) {
  ConvTransposeBuffers b(l.shape);
  time_pass(state, conv_transpose_flops(l.shape), [&](cudaStream_t stream) {
    cuda::conv_transpose2d_forward(b.x.data(), b.w.data(), b.bias.data(), b.y.data(), l.shape,
                                   stream);
  });
}

void BM_ConvTranspose2dBackwardData(benchmark::State& state, const ConvTransposeLayer& l) {
  ConvTransposeBuffers b(l.shape);
  our_ms()[std::string("transpose_backward_data/") + l.name] =
      time_pass(state, conv_transpose_flops(l.shape), [&](cudaStream_t stream) {
        cuda::conv_transpose2d_backward_data(b.dy.data(), b.w.data(), b.dx.data(), l.shape, stream);
      });
}

void BM_ConvTranspose2dBackwardWeights(benchmark::State& state, const ConvTransposeLayer& l) {
  ConvTransposeBuffers b(l.shape);
  our_ms()[std::string("transpose_backward_weights/") + l.name] =
      time_pass(state, conv_transpose_flops(l.shape), [&](cudaStream_t stream) {
        cuda::conv_transpose2d_backward_weights(b.x.data(), b.dy.data(), b.dw.data(), b.db.data(),
                                                l.shape, b.workspace.data(), b.workspace.size(),
                                                stream);
      });
  state.counters["workspace_MiB"] = static_cast<double>(b.workspace.bytes()) / (1 << 20);
}

// The tensor-core evaluation convolutions (kernels/conv2d_mma.cuh): the 16-bit weights prepared
// once, then the forward (FP32 activations in and out, BF16 or FP16 multiplies, FP32 sums) timed
// like ours above, with its share of the device's dense 16-bit tensor-core peak: SMs x clock x
// the architecture's dense FP16/BF16 rate with FP32 accumulation (flops per clock per SM: 2048
// on sm_80 and sm_87, 1024 on sm_86 and sm_89, 4096 on sm_90).
double dense_half_peak_flops() {
#if defined(PILLARSEG_CUDA_EMULATION)
  return 0;  // no device, no peak
#else
  int device = 0, major = 0, minor = 0, sms = 0, khz = 0;
  PS_CUDA_CHECK(cudaGetDevice(&device));
  PS_CUDA_CHECK(cudaDeviceGetAttribute(&major, cudaDevAttrComputeCapabilityMajor, device));
  PS_CUDA_CHECK(cudaDeviceGetAttribute(&minor, cudaDevAttrComputeCapabilityMinor, device));
  PS_CUDA_CHECK(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device));
  PS_CUDA_CHECK(cudaDeviceGetAttribute(&khz, cudaDevAttrClockRate, device));
  const int sm = 10 * major + minor;
  const double per_clock = sm >= 90 ? 4096 : (sm == 86 || sm == 89) ? 1024 : sm >= 80 ? 2048 : 0;
  return per_clock * sms * khz * 1e3;
#endif
}

// A 16-bit pass's share of the dense 16-bit peak, and our FP32 pass's time (our_ms()[fp32_key],
// when it ran before in this process) over its own.
void half_counters(benchmark::State& state, double flops, double ms, const std::string& fp32_key) {
  const double peak = dense_half_peak_flops();
  if (ms > 0 && peak > 0) state.counters["pct_of_peak"] = 100.0 * flops / (ms * 1e-3) / peak;
  const auto ours = our_ms().find(fp32_key);
  if (ours != our_ms().end() && ms > 0.0) state.counters["fp32_ms/half_ms"] = ours->second / ms;
}

// Whether the device runs the tensor-core kernels; otherwise the benchmark is skipped, saying
// why.
bool tensor_cores_or_skip(benchmark::State& state) {
  std::string why;
  if (cuda::mma_supported(&why)) return true;
  state.SkipWithError(why.c_str());
  return false;
}

void BM_Conv2dForwardHalf(benchmark::State& state, const ConvLayer& l, cuda::Half16 type) {
  if (!tensor_cores_or_skip(state)) return;
  ConvBuffers b(l.shape);
  DeviceBuffer<std::uint16_t> w16(static_cast<size_t>(
      l.shape.out_channels *
      op::half16_weight_k(l.shape.in_channels, l.shape.kernel * l.shape.kernel)));
  DeviceBuffer<float> bias(static_cast<size_t>(l.shape.out_channels));
  cuda::prepare_conv_weights(b.w.data(), l.bias ? b.bias.data() : nullptr, cuda::FoldedBatchNorm{}, l.shape, type,
                             w16.data(), bias.data(), nullptr);
  const double flops = conv_flops(l.shape);
  const double ms = time_pass(state, flops, [&](cudaStream_t stream) {
    cuda::conv2d_mma_forward(b.x.data(), false, w16.data(), bias.data(), l.shape, type, false, b.y.data(), false,
                             stream);
  });
  half_counters(state, flops, ms, std::string("forward/") + l.name);
  our_ms()[std::string(type == cuda::Half16::BF16 ? "forward_bf16/" : "forward_fp16/") + l.name] = ms;
}

// The flipped 16-bit weights of the input gradients, in halves: (I, Kp(O k k)) for a convolution,
// (I, Kp(4 O)) for the transposed 2x2, as CudaBackend's 16-bit backward sizes them.
std::int64_t data_weight_halves(const cuda::Conv2dShape& s) {
  return s.in_channels * op::half16_weight_k(s.out_channels, s.kernel * s.kernel);
}

std::int64_t data_weight_halves(const cuda::ConvTranspose2dShape& s) {
  return s.in_channels * op::half16_weight_k(s.out_channels, 4);
}

// The training gradients on the tensor cores, timed as a 16-bit training step runs them: the
// input gradient with its flipped 16-bit weights prepared in every run (the weights change every
// step), the weight gradient (dw, and db where the layer has a bias) with its partial sums over
// the pixels in its workspace. The same FLOPs as the forward's.
void BM_Conv2dBackwardDataHalf(benchmark::State& state, const ConvLayer& l, cuda::Half16 type) {
  if (!tensor_cores_or_skip(state)) return;
  const cuda::Conv2dShape& s = l.shape;
  ConvBuffers b(s);
  DeviceBuffer<std::uint16_t> w16t(static_cast<size_t>(data_weight_halves(s)));
  const double flops = conv_flops(s);
  const double ms = time_pass(state, flops, [&](cudaStream_t stream) {
    cuda::prepare_conv_data_weights(b.w.data(), s, type, w16t.data(), stream);
    cuda::conv2d_mma_backward_data(b.dy.data(), w16t.data(), s, type, b.dx.data(), stream);
  });
  half_counters(state, flops, ms, std::string("backward_data/") + l.name);
}

void BM_Conv2dBackwardWeightsHalf(benchmark::State& state, const ConvLayer& l, cuda::Half16 type) {
  if (!tensor_cores_or_skip(state)) return;
  const cuda::Conv2dShape& s = l.shape;
  ConvBuffers b(s);
  DeviceBuffer<float> workspace(
      static_cast<size_t>(cuda::conv2d_mma_backward_weights_workspace(s)));
  const double flops = conv_flops(s);
  const double ms = time_pass(state, flops, [&](cudaStream_t stream) {
    cuda::conv2d_mma_backward_weights(b.x.data(), b.dy.data(), s, type, b.dw.data(),
                                      l.bias ? b.db.data() : nullptr, workspace.data(), stream);
  });
  half_counters(state, flops, ms, std::string("backward_weights/") + l.name);
  state.counters["workspace_MiB"] = static_cast<double>(workspace.bytes()) / (1 << 20);
}

// The transposed 2x2's gradients on the tensor cores, as above: the input gradient with its
// 16-bit weights (rows of w, (I, 4 O)) prepared in every run, and dw, db.
void BM_ConvTranspose2dBackwardDataHalf(benchmark::State& state, const ConvTransposeLayer& l,
                                        cuda::Half16 type) {
  if (!tensor_cores_or_skip(state)) return;
  const cuda::ConvTranspose2dShape& s = l.shape;
  ConvTransposeBuffers b(s);
  DeviceBuffer<std::uint16_t> w16t(static_cast<size_t>(data_weight_halves(s)));
  const double flops = conv_transpose_flops(s);
  const double ms = time_pass(state, flops, [&](cudaStream_t stream) {
    cuda::prepare_conv_transpose_data_weights(b.w.data(), s, type, w16t.data(), stream);
    cuda::conv_transpose2d_mma_backward_data(b.dy.data(), w16t.data(), s, type, b.dx.data(),
                                              stream);
  });
  half_counters(state, flops, ms, std::string("transpose_backward_data/") + l.name);
}

void BM_ConvTranspose2dBackwardWeightsHalf(benchmark::State& state, const ConvTransposeLayer& l,
                                           cuda::Half16 type) {
  if (!tensor_cores_or_skip(state)) return;
  const cuda::ConvTranspose2dShape& s = l.shape;
  ConvTransposeBuffers b(s);
  DeviceBuffer<float> workspace(
      static_cast<size_t>(cuda::conv_transpose2d_mma_backward_weights_workspace(s)));
  const double flops = conv_transpose_flops(s);
  const double ms = time_pass(state, flops, [&](cudaStream_t stream) {
    cuda::conv_transpose2d_mma_backward_weights(b.x.data(), b.dy.data(), s, type, b.dw.data(),
                                                 b.db.data(), workspace.data(), stream);
  });
  half_counters(state, flops, ms, std::string("transpose_backward_weights/") + l.name);
  state.counters["workspace_MiB"] = static_cast<double>(workspace.bytes()) / (1 << 20);
}

#if defined(PILLARSEG_BENCH_VENDOR_CONV)
// cuDNN's and cuBLAS's 16-bit forward (engine/cuda/vendor_conv.hpp) on the same layer, with the
// same share of the peak and ours_ms/peer_ms against our tensor-core forward.
void BM_Conv2dForwardHalfPeer(benchmark::State& state, const ConvLayer& l, ConvolutionImpl impl, bool bf16) {
  const cuda::Conv2dShape& s = l.shape;
  const auto half_buffer = [](std::int64_t n, std::uint64_t seed, cuda::Half16 type) {
    const DeviceBuffer<float> values = random_buffer(n, seed);
    DeviceBuffer<std::uint16_t> bits(static_cast<size_t>(n));
    cuda::to_half16(values.data(), n, type, bits.data(), nullptr);
    PS_CUDA_CHECK(cudaDeviceSynchronize());
    return bits;
  };
  const cuda::Half16 type = bf16 ? cuda::Half16::BF16 : cuda::Half16::F16;
  const DeviceBuffer<std::uint16_t> x = half_buffer(s.batch * s.in_channels * s.height * s.width, 1, type);
  const DeviceBuffer<std::uint16_t> w = half_buffer(s.out_channels * s.in_channels * s.kernel * s.kernel, 2, type);
  DeviceBuffer<std::uint16_t> y(static_cast<size_t>(s.batch * s.out_channels * s.out_height() * s.out_width()));
  const std::unique_ptr<cuda::HalfConvPeer> peer = cuda::make_vendor_half_conv(impl, bf16);
  const double flops = conv_flops(s);
  const double ms = time_pass(state, flops, [&](cudaStream_t stream) { peer->forward(x.data(), w.data(), y.data(), s, stream); });
  const double peak = dense_half_peak_flops();
  if (ms > 0 && peak > 0) state.counters["pct_of_peak"] = 100.0 * flops / (ms * 1e-3) / peak;
  const auto ours = our_ms().find(std::string(bf16 ? "forward_bf16/" : "forward_fp16/") + l.name);
  if (ours != our_ms().end() && ms > 0.0) state.counters["ours_ms/peer_ms"] = ours->second / ms;
}
#endif

template <class Function, class Layer>
void register_pass(const std::string& name, Function function, const Layer& layer) {
  benchmark::RegisterBenchmark(name.c_str(), function, layer)
      ->Unit(benchmark::kMillisecond)
      ->UseManualTime();
}

template <class Function, class Layer>
void register_half_pass(const std::string& name, Function function, const Layer& layer,
                        cuda::Half16 type) {
  benchmark::RegisterBenchmark(name.c_str(), function, layer, type)
      ->Unit(benchmark::kMillisecond)
      ->UseManualTime();
}

void register_benchmarks() {
  for (const ConvLayer& l : kConvLayers) {
    register_pass(std::string("Conv2dForward/") + l.name, BM_Conv2dForward, l);
    register_pass(std::string("Conv2dBackwardData/") + l.name, BM_Conv2dBackwardData, l);
    register_pass(std::string("Conv2dBackwardWeights/") + l.name, BM_Conv2dBackwardWeights, l);
    for (const auto& [type_name, type] : {std::pair{"BF16", cuda::Half16::BF16}, std::pair{"FP16", cuda::Half16::F16}}) {
      benchmark::RegisterBenchmark((std::string("Conv2dForward") + type_name + "/" + l.name).c_str(),
                                   BM_Conv2dForwardHalf, l, type)
          ->Unit(benchmark::kMillisecond)
          ->UseManualTime();
      register_half_pass(std::string("Conv2dBackwardData") + type_name + "/" + l.name,
                         BM_Conv2dBackwardDataHalf, l, type);
      register_half_pass(std::string("Conv2dBackwardWeights") + type_name + "/" + l.name,
                         BM_Conv2dBackwardWeightsHalf, l, type);
#if defined(PILLARSEG_BENCH_VENDOR_CONV)
      const bool bf16 = type == cuda::Half16::BF16;
      std::vector<std::pair<const char*, ConvolutionImpl>> peers = {{"cublas_gemm", ConvolutionImpl::Cublas}};
#if defined(PILLARSEG_WITH_CUDNN)
      peers.insert(peers.begin(), {"cudnn", ConvolutionImpl::Cudnn});
#endif
      for (const auto& [peer_name, impl] : peers) {
        benchmark::RegisterBenchmark(
            (std::string("Conv2dForward") + type_name + "_" + peer_name + "/" + l.name).c_str(),
            BM_Conv2dForwardHalfPeer, l, impl, bf16)
            ->Unit(benchmark::kMillisecond)
            ->UseManualTime();
      }
#endif
    }
#if defined(PILLARSEG_BENCH_VENDOR_CONV)
    register_peers(l, Pass::Forward, "Conv2dForward");
    register_peers(l, Pass::BackwardData, "Conv2dBackwardData");
    register_peers(l, Pass::BackwardWeights, "Conv2dBackwardWeights");
#endif
  }
  for (const ConvTransposeLayer& l : kConvTransposeLayers) {
    register_pass(std::string("ConvTranspose2dForward/") + l.name, BM_ConvTranspose2dForward, l);
    register_pass(std::string("ConvTranspose2dBackwardData/") + l.name,
                  BM_ConvTranspose2dBackwardData, l);
    register_pass(std::string("ConvTranspose2dBackwardWeights/") + l.name,
                  BM_ConvTranspose2dBackwardWeights, l);
    for (const auto& [type_name, type] :
         {std::pair{"BF16", cuda::Half16::BF16}, std::pair{"FP16", cuda::Half16::F16}}) {
      register_half_pass(std::string("ConvTranspose2dBackwardData") + type_name + "/" + l.name,
                         BM_ConvTranspose2dBackwardDataHalf, l, type);
      register_half_pass(std::string("ConvTranspose2dBackwardWeights") + type_name + "/" + l.name,
                         BM_ConvTranspose2dBackwardWeightsHalf, l, type);
    }
  }
}

}  // namespace

int main(int argc, char** argv) {
  const std::string missing = pillarseg::bench::missing_cuda_device();
  if (!missing.empty()) {
    std::printf("bench_kernels_conv skipped: no CUDA device (%s)\n", missing.c_str());
    return 0;
  }
  register_benchmarks();
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
