// The full-size U-Net's 3x3 convolutions on the CPU, layer by layer, in every precision this CPU
// runs, in one run: FP32 (the CPU backend's Winograd F(4x4, 3x3)), BF16 (Winograd F(2x2, 3x3) on
// AVX512_BF16, and with its products on AMX-BF16 tiles), INT8 (the direct convolution of
// engine/cpu/int8_conv.hpp on AVX512-VNNI, and on AMX-INT8 tiles; and Winograd-domain INT8 F(2x2,
// 3x3) on AVX512-VNNI, its 16 input scales the maxima of the layer's own V). Each timed step runs
// every variant once, in turn; the table gives medians in ms, the INT8 rate in GOP/s (2 O I 9 h w
// operations), wall and CPU time, the sums over the U-Net's 3x3 layers and the INT8 output's
// relative RMS error against FP32 (x ~ N(0, 1) quantized with sx = max |x| / 127, weights ~ N(0,
// 0.05)). And the direct INT8 (amx, else vnni) on the non-negative input max(x, 0) in both modes:
// the time of the non-negative mode (sx = max x / 255), and both modes' errors against FP32 on that
// input. 16-bit and INT8 variants read and write BF16 activations, as the model stores them.
// Flags: --reps=R (timed steps per layer, default 5), --threads=T (default 2), and Google
// Benchmark's (--benchmark_filter=REGEX).
#include <benchmark/benchmark.h>
#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "bench/support/model_inputs.hpp"
#include "bench/support/model_layers.hpp"
#include "bench/support/step_timing.hpp"
#include "core/ops.hpp"
#include "core/parallel.hpp"
#include "engine/backend/backend.hpp"
#include "engine/cpu/bf16_conv.hpp"
#include "engine/cpu/int8_conv.hpp"
#include "weights_io/half.hpp"

using namespace pillarseg;
using namespace pillarseg::bench;

namespace {

int g_reps = 5;

struct LayerResult {
  Layer layer;
  StepTimes fp32, bf16, bf16_amx, int8_vnni, int8_amx, int8_winograd, int8_non_negative;
  double int8_rel_rms = 0.0, winograd_rel_rms = 0.0;
  double relu_signed_rel_rms = 0.0, relu_non_negative_rel_rms = 0.0;  // on max(x, 0)
};
std::vector<LayerResult> g_results;
std::string g_notes;

std::vector<float> normal_values(std::int64_t n, std::uint32_t seed, float sigma) {
  std::mt19937 gen(seed);
  std::normal_distribution<float> d(0.0f, sigma);
  std::vector<float> v(static_cast<size_t>(n));
  for (float& x : v) x = d(gen);
  return v;
}

void BM_Layer(benchmark::State& state, const Layer& l) {
  const Shape x_shape{1, l.in, l.h, l.w}, y_shape{1, l.out, l.h, l.w}, weight{l.out, l.in, 3, 3};
  std::vector<float> x = normal_values(shape_numel(x_shape), 1, 1.0f);
  std::vector<float> w = normal_values(shape_numel(weight), 2, 0.05f);
  std::vector<float> bias = normal_values(l.out, 3, 0.1f);
  std::vector<float> y(static_cast<size_t>(shape_numel(y_shape)));
  const Ref x_ref{x.data(), x_shape}, w_ref{w.data(), weight}, bias_ref{bias.data(), {l.out}};
  Ref y_ref{y.data(), y_shape};
  const std::unique_ptr<Backend> backend = make_cpu_backend();

  std::vector<std::uint16_t> x16(x.size()), y16(y.size());
  for (size_t i = 0; i < x.size(); ++i) x16[i] = weights::float_to_bf16_bits(x[i]);
  const ActRef x16_act{x16.data(), x_shape, true}, y16_act{y16.data(), y_shape, true};
  const TensorRef y16_bf16{y16.data(), y_shape, DType::BF16};

  const bool bf16 = cpu::avx512_bf16_available();
  const bool bf16_amx = cpu::amx_bf16_available();
  const Shape w16_shape = op::half16_conv_weights(weight, false);
  std::vector<std::uint16_t> w16(static_cast<size_t>(shape_numel(w16_shape))), u_avx512, u_amx;
  std::vector<float> bias16(static_cast<size_t>(l.out));
  HRef w16_ref{w16.data(), w16_shape};
  Ref bias16_ref{bias16.data(), {l.out}};
  cpu::Bf16WinogradWorkspace bf16_workspace;
  if (bf16) {
    cpu::prepare_conv_weights(w_ref, &bias_ref, nullptr, Precision::BF16, w16_ref, bias16_ref);
    u_avx512.resize(
        static_cast<size_t>(cpu::winograd_weight_elements(cpu::Bf16Kernels::Avx512, weight)));
    cpu::winograd_transform_weights(cpu::Bf16Kernels::Avx512, w16_ref, weight, u_avx512.data());
  }
  if (bf16_amx) {
    u_amx.resize(static_cast<size_t>(cpu::winograd_weight_elements(cpu::Bf16Kernels::Amx, weight)));
    cpu::winograd_transform_weights(cpu::Bf16Kernels::Amx, w16_ref, weight, u_amx.data());
  }
  const HRef x16_ref{x16.data(), x_shape};

  const bool vnni = cpu::avx512_vnni_available();
  const bool int8_amx = cpu::amx_int8_available();
  cpu::Int8ConvWeights q_vnni, q_amx;
  if (vnni) cpu::prepare_int8_conv(cpu::Int8Kernels::Vnni, w_ref, bias_ref, q_vnni);
  if (int8_amx) cpu::prepare_int8_conv(cpu::Int8Kernels::Amx, w_ref, bias_ref, q_amx);
  float max_abs = 0.0f;
  for (float v : x) max_abs = std::max(max_abs, std::abs(v));
  const float sx = max_abs / 127.0f;
  cpu::Int8ConvWorkspace int8_workspace;
  cpu::Int8WinogradWeights q_winograd;
  cpu::Int8WinogradWorkspace winograd_workspace;
  float sv[16];
  if (vnni) {
    cpu::prepare_int8_winograd(w_ref, bias_ref, q_winograd);
    cpu::int8_winograd_input_absmax(x16_act, sv);
    for (float& v : sv) v = std::max(v, 1e-6f) / 127.0f;
  }

  // The non-negative input: max(x, 0) in BF16, on the native direct kernels.
  std::vector<float> x_relu(x.size());
  std::vector<std::uint16_t> x16_relu(x.size());
  for (size_t i = 0; i < x.size(); ++i) {
    x_relu[i] = std::max(x[i], 0.0f);
    x16_relu[i] = weights::float_to_bf16_bits(x_relu[i]);
  }
  const ActRef x16_relu_act{x16_relu.data(), x_shape, true};
  const cpu::Int8Kernels native_kernels = int8_amx ? cpu::Int8Kernels::Amx : cpu::Int8Kernels::Vnni;
  const cpu::Int8ConvWeights& q_native = int8_amx ? q_amx : q_vnni;
  const float relu_max = *std::max_element(x_relu.begin(), x_relu.end());

  LayerResult r{l, {}, {}, {}, {}, {}, {}, {}, 0.0, 0.0, 0.0, 0.0};
  for (auto _ : state) {
    state.SetIterationTime(time_once(r.fp32, [&] {
      backend->conv2d_forward(x_ref, w_ref, &bias_ref, 1, y_ref);
      benchmark::DoNotOptimize(y.data());
    }));
    if (bf16) {
      time_once(r.bf16, [&] {
        cpu::conv3x3_winograd_forward(cpu::Bf16Kernels::Avx512, x16_ref, w16_ref, u_avx512.data(),
                                      bias16_ref, weight, false, y16_bf16, bf16_workspace);
        benchmark::DoNotOptimize(y16.data());
      });
    }
    if (bf16_amx) {
      time_once(r.bf16_amx, [&] {
        cpu::conv3x3_winograd_forward(cpu::Bf16Kernels::Amx, x16_ref, w16_ref, u_amx.data(),
                                      bias16_ref, weight, false, y16_bf16, bf16_workspace);
        benchmark::DoNotOptimize(y16.data());
      });
    }
    if (vnni) {
      time_once(r.int8_vnni, [&] {
        cpu::int8_conv2d_forward(cpu::Int8Kernels::Vnni, x16_act, sx, false, q_vnni, 1, false,
                                 y16_act, int8_workspace);
        benchmark::DoNotOptimize(y16.data());
      });
    }
    if (int8_amx) {
      time_once(r.int8_amx, [&] {
        cpu::int8_conv2d_forward(cpu::Int8Kernels::Amx, x16_act, sx, false, q_amx, 1, false,
                                 y16_act, int8_workspace);
        benchmark::DoNotOptimize(y16.data());
      });
    }
    if (vnni || int8_amx) {
      time_once(r.int8_non_negative, [&] {
        cpu::int8_conv2d_forward(native_kernels, x16_relu_act, relu_max / 255.0f, true, q_native, 1,
                                 false, y16_act, int8_workspace);
        benchmark::DoNotOptimize(y16.data());
      });
    }
    if (vnni) {
      time_once(r.int8_winograd, [&] {
        cpu::int8_winograd_forward(cpu::Int8Kernels::Vnni, x16_act, sv, q_winograd, false, y16_act,
                                   winograd_workspace);
        benchmark::DoNotOptimize(y16.data());
      });
    }
  }
  // The INT8 outputs (BF16) against the FP32 one (from the FP32 input; INT8 read its BF16
  // rounding, as the model would).
  const auto rel_rms = [&] {
    double error2 = 0.0, signal2 = 0.0;
    for (size_t i = 0; i < y.size(); ++i) {
      const double d = static_cast<double>(weights::bf16_bits_to_float(y16[i])) - y[i];
      error2 += d * d;
      signal2 += static_cast<double>(y[i]) * y[i];
    }
    return std::sqrt(error2 / signal2);
  };
  if (vnni || int8_amx) {
    const cpu::Int8Kernels k = int8_amx ? cpu::Int8Kernels::Amx : cpu::Int8Kernels::Vnni;
    cpu::int8_conv2d_forward(k, x16_act, sx, false, int8_amx ? q_amx : q_vnni, 1, false, y16_act,
                             int8_workspace);
    r.int8_rel_rms = rel_rms();
  }
  if (vnni) {
    cpu::int8_winograd_forward(cpu::Int8Kernels::Vnni, x16_act, sv, q_winograd, false, y16_act,
                               winograd_workspace);
    r.winograd_rel_rms = rel_rms();
  }
  if (vnni || int8_amx) {
    const Ref x_relu_ref{x_relu.data(), x_shape};
    backend->conv2d_forward(x_relu_ref, w_ref, &bias_ref, 1, y_ref);
    for (const bool non_negative : {false, true}) {
      cpu::int8_conv2d_forward(native_kernels, x16_relu_act,
                               relu_max / (non_negative ? 255.0f : 127.0f), non_negative, q_native,
                               1, false, y16_act, int8_workspace);
      (non_negative ? r.relu_non_negative_rel_rms : r.relu_signed_rel_rms) = rel_rms();
    }
  }
  state.counters["fp32_ms"] = r.fp32.wall_median() * 1e3;
  if (vnni) state.counters["int8_vnni_ms"] = r.int8_vnni.wall_median() * 1e3;
  if (int8_amx) state.counters["int8_amx_ms"] = r.int8_amx.wall_median() * 1e3;
  if (vnni || int8_amx)
    state.counters["int8_non_negative_ms"] = r.int8_non_negative.wall_median() * 1e3;
  g_results.push_back(std::move(r));
}

// Every 3x3 convolution of the full-size U-Net (bilinear upsampling, the default), batch 1.
std::vector<Layer> unet_3x3_layers() {
  std::vector<Layer> layers;
  for (Layer l : forward_layers(config_of("full", false), 1, 0)) {
    if (l.kind != Layer::Kind::Conv || l.k != 3) continue;
    l.name = l.name.substr(l.name.find('.') + 1);  // drop segmentation_head.
    layers.push_back(l);
  }
  return layers;
}

// A variant's median wall ms and CPU ms (all threads' CPU seconds / threads: what the wall time
// would be with the cores to itself, on a machine that others load).
std::string ms(const StepTimes& t, bool cpu) {
  if (t.wall.empty()) return "-";
  return fmt::format("{:.1f}", (cpu ? t.cpu_median() / num_threads() : t.wall_median()) * 1e3);
}

void print_table() {
  if (g_results.empty()) return;
  std::string why;
  if (!cpu::avx512_bf16_available(&why)) g_notes += "  bf16: not run: " + why + "\n";
  if (!cpu::amx_bf16_available(&why)) g_notes += "  bf16 amx: not run: " + why + "\n";
  if (!cpu::avx512_vnni_available(&why)) g_notes += "  int8 vnni: not run: " + why + "\n";
  if (!cpu::amx_int8_available(&why)) g_notes += "  int8 amx: not run: " + why + "\n";
  fmt::print(
      "\nU-Net 3x3 convolutions, full size, batch 1, {} threads, median of {} steps: wall ms / CPU "
      "ms (process CPU time / threads); GOP/s of int8 by wall (2 O I 9 h w / time); err: relative "
      "RMS of the int8 direct (amx, else vnni) and int8 Winograd (vnni) BF16 outputs against "
      "fp32, %; on max(x, 0): the int8 direct's non-negative mode (u8), and both modes' errors, "
      "%:\n",
      num_threads(), g_reps);
  fmt::print(
      "  {:<36} {:>20} {:>6} | {:>15} | {:>15} | {:>15} | {:>15} {:>5} | {:>15} {:>5} | {:>15} | "
      "{:>5} {:>5} | {:>15} {:>6} {:>6}\n",
      "layer", "I -> O @ h x w", "GOP", "fp32 winograd", "bf16 wino avx", "bf16 wino amx",
      "int8 vnni", "GOP/s", "int8 amx", "GOP/s", "int8 wino vnni", "err", "wino", "u8 on relu",
      "err s8", "err u8");
  const auto cell = [](const StepTimes& t) { return ms(t, false) + " / " + ms(t, true); };
  struct Sum {
    double wall = 0.0, cpu = 0.0;
    void add(const StepTimes& t) {
      if (t.wall.empty()) return;
      wall += t.wall_median(), cpu += t.cpu_median() / num_threads();
    }
    std::string str() const { return fmt::format("{:.0f} / {:.0f}", wall * 1e3, cpu * 1e3); }
  } fp32, bf16, bf16_amx, vnni, amx, winograd, non_negative;
  double gop_sum = 0.0;
  for (const LayerResult& r : g_results) {
    const double gop = r.layer.flops * 1e-9;
    const auto rate = [&](const StepTimes& t) {
      return t.wall.empty() ? std::string("-") : fmt::format("{:.0f}", gop / t.wall_median());
    };
    fmt::print(
        "  {:<36} {:>20} {:>6.1f} | {:>15} | {:>15} | {:>15} | {:>15} {:>5} | {:>15} {:>5} | "
        "{:>15} | {:>5.2f} {:>5.2f} | {:>15} {:>6.2f} {:>6.2f}\n",
        r.layer.name,
        fmt::format("{} -> {} @ {}x{}", r.layer.in, r.layer.out, r.layer.h, r.layer.w), gop,
        cell(r.fp32), cell(r.bf16), cell(r.bf16_amx), cell(r.int8_vnni), rate(r.int8_vnni),
        cell(r.int8_amx), rate(r.int8_amx), cell(r.int8_winograd), 100.0 * r.int8_rel_rms,
        100.0 * r.winograd_rel_rms, cell(r.int8_non_negative), 100.0 * r.relu_signed_rel_rms,
        100.0 * r.relu_non_negative_rel_rms);
    gop_sum += gop;
    fp32.add(r.fp32), bf16.add(r.bf16), bf16_amx.add(r.bf16_amx), vnni.add(r.int8_vnni),
        amx.add(r.int8_amx), winograd.add(r.int8_winograd), non_negative.add(r.int8_non_negative);
  }
  fmt::print(
      "  sum over the U-Net's 3x3 layers ({:.0f} GOP), wall / CPU ms: fp32 winograd {}, bf16 "
      "winograd avx512_bf16 {}, bf16 winograd amx_bf16 {}, int8 direct avx512_vnni {} ({:.0f} "
      "GOP/s by CPU time), int8 direct amx_int8 {} ({:.0f} GOP/s by CPU time), int8 Winograd "
      "F(2x2, 3x3) avx512_vnni {}, int8 direct non-negative mode on max(x, 0) {}\n{}",
      gop_sum, fp32.str(), bf16.str(), bf16_amx.str(), vnni.str(),
      vnni.cpu > 0 ? gop_sum / vnni.cpu : 0.0, amx.str(), amx.cpu > 0 ? gop_sum / amx.cpu : 0.0,
      winograd.str(), non_negative.str(), g_notes);
}

}  // namespace

int main(int argc, char** argv) {
  int threads = 2;
  std::vector<char*> rest;
  for (int i = 0; i < argc; ++i) {
    const std::string a = argv[i];
    if (a.rfind("--reps=", 0) == 0) {
      g_reps = std::max(1, std::atoi(a.c_str() + 7));
    } else if (a.rfind("--threads=", 0) == 0) {
      threads = std::atoi(a.c_str() + 10);
    } else {
      rest.push_back(argv[i]);
    }
  }
  int rest_count = static_cast<int>(rest.size());
  set_num_threads(threads);
  benchmark::Initialize(&rest_count, rest.data());
  for (const Layer& l : unet_3x3_layers()) {
    benchmark::RegisterBenchmark(
        fmt::format("Int8Conv3x3/{}/{}to{}/{}x{}", l.name, l.in, l.out, l.h, l.w).c_str(), BM_Layer,
        l)
        ->Iterations(g_reps)
        ->UseManualTime()
        ->Unit(benchmark::kMillisecond);
  }
  benchmark::RunSpecifiedBenchmarks();
  print_table();
  benchmark::Shutdown();
  return 0;
}
