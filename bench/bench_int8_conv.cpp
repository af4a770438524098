// The full-size U-Net's 3x3 convolutions on the CPU, layer by layer, in every precision this CPU
// runs, in one run: FP32 (the CPU backend's Winograd F(4x4, 3x3)), BF16 (Winograd F(2x2, 3x3) on
// AVX512_BF16, and with its products on AMX-BF16 tiles), INT8 (the direct convolution of
// engine/cpu/int8_conv.hpp on AVX512-VNNI, and on AMX-INT8 tiles). Each timed step runs every
// variant once, in turn; the table gives medians in ms, the INT8 rate in GOP/s (2 O I 9 h w
// operations), wall and CPU time, the sums over the U-Net's 3x3 layers and the INT8 output's
// relative RMS error against FP32 (x ~ N(0, 1) quantized with sx = max |x| / 127, weights ~ N(0,
// 0.05)). 16-bit and INT8 variants read and write BF16 activations, as the model stores them.
// Flags: --reps=R (timed steps per layer, default 5), --threads=T (default 2), --winograd (also
// what Winograd-domain INT8 would gain: see below), and Google Benchmark's
// (--benchmark_filter=REGEX).
#include <benchmark/benchmark.h>
#include <fmt/format.h>

#include <algorithm>
#include <array>
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
#include "engine/cpu/bf16_conv.hpp"
#include "engine/cpu/int8_conv.hpp"
#include "engine/model/backend.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "weights_io/half.hpp"

using namespace pillarseg;
using namespace pillarseg::bench;

namespace {

int g_reps = 5;

struct LayerResult {
  Layer layer;
  StepTimes fp32, bf16, bf16_amx, int8_vnni, int8_amx;
  double int8_rel_rms = 0.0;
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

  LayerResult r{l, {}, {}, {}, {}, {}, 0.0};
  for (auto _ : state) {
    state.SetIterationTime(time_once(r.fp32, [&] {
      backend->conv2d_forward(x_ref, w_ref, &bias_ref, 1, y_ref);
      benchmark::DoNotOptimize(y.data());
    }));
    if (bf16) {
      time_once(r.bf16, [&] {
        cpu::conv3x3_winograd_forward(cpu::Bf16Kernels::Avx512, x16_ref, w16_ref, u_avx512.data(),
                                      bias16_ref, weight, false, y16_act, bf16_workspace);
        benchmark::DoNotOptimize(y16.data());
      });
    }
    if (bf16_amx) {
      time_once(r.bf16_amx, [&] {
        cpu::conv3x3_winograd_forward(cpu::Bf16Kernels::Amx, x16_ref, w16_ref, u_amx.data(),
                                      bias16_ref, weight, false, y16_act, bf16_workspace);
        benchmark::DoNotOptimize(y16.data());
      });
    }
    if (vnni) {
      time_once(r.int8_vnni, [&] {
        cpu::int8_conv2d_forward(cpu::Int8Kernels::Vnni, x16_act, sx, q_vnni, 1, false, y16_act,
                                 int8_workspace);
        benchmark::DoNotOptimize(y16.data());
      });
    }
    if (int8_amx) {
      time_once(r.int8_amx, [&] {
        cpu::int8_conv2d_forward(cpu::Int8Kernels::Amx, x16_act, sx, q_amx, 1, false, y16_act,
                                 int8_workspace);
        benchmark::DoNotOptimize(y16.data());
      });
    }
  }
  // The last INT8 output (BF16) against the FP32 one (the FP32 input; the INT8 one read its BF16
  // rounding, as the model would).
  if (vnni || int8_amx) {
    double error2 = 0.0, signal2 = 0.0;
    for (size_t i = 0; i < y.size(); ++i) {
      const double d = static_cast<double>(weights::bf16_bits_to_float(y16[i])) - y[i];
      error2 += d * d;
      signal2 += static_cast<double>(y[i]) * y[i];
    }
    r.int8_rel_rms = std::sqrt(error2 / signal2);
  }
  state.counters["fp32_ms"] = r.fp32.wall_median() * 1e3;
  if (vnni) state.counters["int8_vnni_ms"] = r.int8_vnni.wall_median() * 1e3;
  if (int8_amx) state.counters["int8_amx_ms"] = r.int8_amx.wall_median() * 1e3;
  g_results.push_back(std::move(r));
}

// Every 3x3 convolution of the full-size U-Net (bilinear upsampling, the default), batch 1.
std::vector<Layer> unet_3x3_layers() {
  const std::unique_ptr<Backend> backend = make_cpu_backend();
  const PillarSegNet net(config_of("full", false), *backend);
  std::vector<Layer> layers;
  for (Layer l : forward_layers(net, 1, 0)) {
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
      "RMS of the int8 (amx, else vnni) BF16 output against fp32:\n",
      num_threads(), g_reps);
  fmt::print(
      "  {:<36} {:>20} {:>6} | {:>15} | {:>15} | {:>15} | {:>15} {:>5} | {:>15} {:>5} | {:>6}\n",
      "layer", "I -> O @ h x w", "GOP", "fp32 winograd", "bf16 wino avx", "bf16 wino amx",
      "int8 vnni", "GOP/s", "int8 amx", "GOP/s", "err %");
  const auto cell = [](const StepTimes& t) { return ms(t, false) + " / " + ms(t, true); };
  struct Sum {
    double wall = 0.0, cpu = 0.0;
    void add(const StepTimes& t) {
      if (t.wall.empty()) return;
      wall += t.wall_median(), cpu += t.cpu_median() / num_threads();
    }
    std::string str() const { return fmt::format("{:.0f} / {:.0f}", wall * 1e3, cpu * 1e3); }
  } fp32, bf16, bf16_amx, vnni, amx;
  double gop_sum = 0.0;
  for (const LayerResult& r : g_results) {
    const double gop = r.layer.flops() * 1e-9;
    const auto rate = [&](const StepTimes& t) {
      return t.wall.empty() ? std::string("-") : fmt::format("{:.0f}", gop / t.wall_median());
    };
    fmt::print(
        "  {:<36} {:>20} {:>6.1f} | {:>15} | {:>15} | {:>15} | {:>15} {:>5} | {:>15} {:>5} | "
        "{:>6.3f}\n",
        r.layer.name,
        fmt::format("{} -> {} @ {}x{}", r.layer.in, r.layer.out, r.layer.h, r.layer.w), gop,
        cell(r.fp32), cell(r.bf16), cell(r.bf16_amx), cell(r.int8_vnni), rate(r.int8_vnni),
        cell(r.int8_amx), rate(r.int8_amx), 100.0 * r.int8_rel_rms);
    gop_sum += gop;
    fp32.add(r.fp32), bf16.add(r.bf16), bf16_amx.add(r.bf16_amx), vnni.add(r.int8_vnni),
        amx.add(r.int8_amx);
  }
  fmt::print(
      "  sum over the U-Net's 3x3 layers ({:.0f} GOP), wall / CPU ms: fp32 winograd {}, bf16 "
      "winograd avx512_bf16 {}, bf16 winograd amx_bf16 {}, int8 direct avx512_vnni {} ({:.0f} "
      "GOP/s by CPU time), int8 direct amx_int8 {} ({:.0f} GOP/s by CPU time)\n{}",
      gop_sum, fp32.str(), bf16.str(), bf16_amx.str(), vnni.str(),
      vnni.cpu > 0 ? gop_sum / vnni.cpu : 0.0, amx.str(), amx.cpu > 0 ? gop_sum / amx.cpu : 0.0,
      g_notes);
}

// ---- Winograd-domain INT8 F(2x2, 3x3): what it would gain (--winograd) ----
//
// Not an implementation: its products are timed on the INT8 kernels as they stand, and its
// accuracy simulated in double. Products: the 16 GEMMs M_p (O x tiles) = U_p (O x I) V_p (I x
// tiles) of a layer, each an INT8 1x1 convolution of (1, I, h/2, w/2) with FP32 M out, through
// memory: each pass quantizes its V_p and writes its M_p in full, which a blocked implementation
// (V and M of a block of tiles in L2, as bf16_winograd.hpp keeps them) would not; the transforms
// are not counted. Their multiply-adds are the direct convolution's / 2.25.

struct WinogradResult {
  Layer layer;
  StepTimes vnni, amx;
};
std::vector<WinogradResult> g_winograd;

void BM_WinogradProducts(benchmark::State& state, const Layer& l) {
  const std::int64_t th = (l.h + 1) / 2, tw = (l.w + 1) / 2;
  const Shape v_shape{1, l.in, th, tw}, m_shape{1, l.out, th, tw}, u_shape{l.out, l.in, 1, 1};
  std::vector<float> u = normal_values(shape_numel(u_shape), 4, 0.05f),
                     zero(static_cast<size_t>(l.out));
  std::vector<std::uint16_t> v(static_cast<size_t>(shape_numel(v_shape)));
  for (size_t i = 0; i < v.size(); ++i)
    v[i] = weights::float_to_bf16_bits(static_cast<float>(i % 255) - 127.0f);
  std::vector<float> m(static_cast<size_t>(shape_numel(m_shape)));
  const Ref u_ref{u.data(), u_shape}, zero_ref{zero.data(), {l.out}};
  const bool vnni = cpu::avx512_vnni_available(), amx = cpu::amx_int8_available();
  cpu::Int8ConvWeights q_vnni, q_amx;
  if (vnni) cpu::prepare_int8_conv(cpu::Int8Kernels::Vnni, u_ref, zero_ref, q_vnni);
  if (amx) cpu::prepare_int8_conv(cpu::Int8Kernels::Amx, u_ref, zero_ref, q_amx);
  cpu::Int8ConvWorkspace workspace;
  WinogradResult r{l, {}, {}};
  const ActRef v_act{v.data(), v_shape, true}, m_act{m.data(), m_shape, false};
  for (auto _ : state) {
    double seconds = 0.0;
    for (const bool on_amx : {false, true}) {
      if (on_amx ? !amx : !vnni) continue;
      seconds = time_once(on_amx ? r.amx : r.vnni, [&] {
        for (int p = 0; p < 16; ++p) {
          cpu::int8_conv2d_forward(on_amx ? cpu::Int8Kernels::Amx : cpu::Int8Kernels::Vnni, v_act,
                                   1.0f, on_amx ? q_amx : q_vnni, 0, false, m_act, workspace);
        }
        benchmark::DoNotOptimize(m.data());
      });
    }
    state.SetIterationTime(seconds);
  }
  g_winograd.push_back(std::move(r));
}

// The accuracy of the choices on one layer in double: the exact convolution of x against direct
// INT8 (the kernels' rules) and Winograd-domain INT8, V_p = (B^T d B)_p quantized with one scale
// per tile position p (max |V_p| / 127 over the tensor, LoWino's per-position calibration) or one
// for all 16, U_p = (G g G^T)_p per output channel and position (max over the input channels /
// 127). Returns the relative RMS errors {direct, winograd per position, winograd one scale}.
std::array<double, 3> winograd_accuracy(std::int64_t in, std::int64_t out, std::int64_t h,
                                        std::int64_t w, bool relu_input) {
  std::vector<float> x = normal_values(in * h * w, 71, 1.0f);
  if (relu_input)
    for (float& v : x) v = std::max(v, 0.0f);
  const std::vector<float> wt = normal_values(out * in * 9, 72, 0.05f);
  const auto at = [&](std::int64_t c, std::int64_t y, std::int64_t xx) -> double {
    return y < 0 || y >= h || xx < 0 || xx >= w ? 0.0
                                                : x[static_cast<size_t>((c * h + y) * w + xx)];
  };
  const auto wv = [&](std::int64_t o, std::int64_t c, int ky, int kx) -> double {
    return wt[static_cast<size_t>(((o * in + c) * 3 + ky) * 3 + kx)];
  };
  const auto quantize = [](double v, double scale) {
    return scale > 0 ? std::clamp(std::nearbyint(v / scale), -127.0, 127.0) : 0.0;
  };
  double max_x = 0.0;
  for (float v : x) max_x = std::max(max_x, static_cast<double>(std::abs(v)));
  const double sx = max_x / 127.0;
  std::vector<double> sw(static_cast<size_t>(out), 0.0);
  for (std::int64_t o = 0; o < out; ++o) {
    for (std::int64_t c = 0; c < in; ++c)
      for (int t = 0; t < 9; ++t)
        sw[static_cast<size_t>(o)] =
            std::max(sw[static_cast<size_t>(o)], std::abs(wv(o, c, t / 3, t % 3)));
    sw[static_cast<size_t>(o)] /= 127.0;
  }
  // Winograd: U (O, I, 16), V (I, tiles, 16).
  const std::int64_t th = h / 2, tw = w / 2, tiles = th * tw;
  std::vector<double> u(static_cast<size_t>(out * in * 16)),
      v(static_cast<size_t>(in * tiles * 16));
  for (std::int64_t o = 0; o < out; ++o)
    for (std::int64_t c = 0; c < in; ++c) {
      double gg[4][3];
      for (int b = 0; b < 3; ++b) {
        gg[0][b] = wv(o, c, 0, b);
        gg[1][b] = 0.5 * (wv(o, c, 0, b) + wv(o, c, 1, b) + wv(o, c, 2, b));
        gg[2][b] = 0.5 * (wv(o, c, 0, b) - wv(o, c, 1, b) + wv(o, c, 2, b));
        gg[3][b] = wv(o, c, 2, b);
      }
      for (int i = 0; i < 4; ++i) {
        const double row[4] = {gg[i][0], 0.5 * (gg[i][0] + gg[i][1] + gg[i][2]),
                               0.5 * (gg[i][0] - gg[i][1] + gg[i][2]), gg[i][2]};
        for (int j = 0; j < 4; ++j) u[static_cast<size_t>((o * in + c) * 16 + 4 * i + j)] = row[j];
      }
    }
  for (std::int64_t c = 0; c < in; ++c)
    for (std::int64_t t = 0; t < tiles; ++t) {
      const std::int64_t y0 = 2 * (t / tw) - 1, x0 = 2 * (t % tw) - 1;
      double d[4][4], bd[4][4];
      for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j) d[i][j] = at(c, y0 + i, x0 + j);
      for (int j = 0; j < 4; ++j) {
        bd[0][j] = d[0][j] - d[2][j], bd[1][j] = d[1][j] + d[2][j];
        bd[2][j] = d[2][j] - d[1][j], bd[3][j] = d[1][j] - d[3][j];
      }
      for (int i = 0; i < 4; ++i) {
        const double row[4] = {bd[i][0] - bd[i][2], bd[i][1] + bd[i][2], bd[i][2] - bd[i][1],
                               bd[i][1] - bd[i][3]};
        for (int j = 0; j < 4; ++j)
          v[static_cast<size_t>((c * tiles + t) * 16 + 4 * i + j)] = row[j];
      }
    }
  double sv[16] = {}, sv_all = 0.0;
  for (size_t i = 0; i < v.size(); ++i) sv[i % 16] = std::max(sv[i % 16], std::abs(v[i]));
  for (double& s : sv) sv_all = std::max(sv_all, s), s /= 127.0;
  sv_all /= 127.0;
  std::vector<double> su(static_cast<size_t>(out * 16), 0.0);
  for (std::int64_t o = 0; o < out; ++o)
    for (std::int64_t c = 0; c < in; ++c)
      for (int p = 0; p < 16; ++p)
        su[static_cast<size_t>(o * 16 + p)] =
            std::max(su[static_cast<size_t>(o * 16 + p)],
                     std::abs(u[static_cast<size_t>((o * in + c) * 16 + p)]) / 127.0);
  double signal = 0.0, e_direct = 0.0, e_wino = 0.0, e_wino_one = 0.0;
  for (std::int64_t o = 0; o < out; ++o) {
    for (std::int64_t t = 0; t < tiles; ++t) {
      double m[2][16] = {};
      for (std::int64_t c = 0; c < in; ++c)
        for (int p = 0; p < 16; ++p) {
          const double uu = u[static_cast<size_t>((o * in + c) * 16 + p)],
                       s_u = su[static_cast<size_t>(o * 16 + p)];
          const double vv = v[static_cast<size_t>((c * tiles + t) * 16 + p)];
          const double qu = quantize(uu, s_u) * s_u;
          m[0][p] += qu * quantize(vv, sv[p]) * sv[p];
          m[1][p] += qu * quantize(vv, sv_all) * sv_all;
        }
      for (int dy = 0; dy < 2; ++dy)
        for (int dx = 0; dx < 2; ++dx) {
          const std::int64_t oy = 2 * (t / tw) + dy, ox = 2 * (t % tw) + dx;
          double exact = 0.0, direct = 0.0;
          for (std::int64_t c = 0; c < in; ++c)
            for (int ky = 0; ky < 3; ++ky)
              for (int kx = 0; kx < 3; ++kx) {
                const double xv = at(c, oy + ky - 1, ox + kx - 1), wgt = wv(o, c, ky, kx);
                exact += xv * wgt;
                direct += quantize(xv, sx) * sx * quantize(wgt, sw[static_cast<size_t>(o)]) *
                          sw[static_cast<size_t>(o)];
              }
          // Y = A^T M A, A^T = [1 1 1 0; 0 1 -1 -1].
          double y[2];
          for (int k = 0; k < 2; ++k) {
            double am[4];
            for (int j = 0; j < 4; ++j) {
              const double* mm = m[k];
              am[j] = dy == 0 ? mm[j] + mm[4 + j] + mm[8 + j] : mm[4 + j] - mm[8 + j] - mm[12 + j];
            }
            y[k] = dx == 0 ? am[0] + am[1] + am[2] : am[1] - am[2] - am[3];
          }
          signal += exact * exact;
          e_direct += (direct - exact) * (direct - exact);
          e_wino += (y[0] - exact) * (y[0] - exact);
          e_wino_one += (y[1] - exact) * (y[1] - exact);
        }
    }
  }
  return {std::sqrt(e_direct / signal), std::sqrt(e_wino / signal), std::sqrt(e_wino_one / signal)};
}

void print_winograd() {
  if (g_winograd.empty()) return;
  fmt::print(
      "\nWinograd-domain INT8 F(2x2, 3x3): its 16 product GEMMs per layer as 16 INT8 1x1 "
      "convolutions through memory (not blocked; transforms not counted), wall / CPU ms, against "
      "the direct INT8 convolution above:\n");
  double direct_vnni = 0, direct_amx = 0, wino_vnni = 0, wino_amx = 0;
  for (const WinogradResult& w : g_winograd) {
    const auto found = std::find_if(g_results.begin(), g_results.end(), [&](const LayerResult& r) {
      return r.layer.name == w.layer.name;
    });
    fmt::print(
        "  {:<36} int8 vnni products {:>15} (direct {:>15}) | int8 amx products {:>15} "
        "(direct {:>15})\n",
        w.layer.name, ms(w.vnni, false) + " / " + ms(w.vnni, true),
        found == g_results.end() ? "-"
                                 : ms(found->int8_vnni, false) + " / " + ms(found->int8_vnni, true),
        ms(w.amx, false) + " / " + ms(w.amx, true),
        found == g_results.end() ? "-"
                                 : ms(found->int8_amx, false) + " / " + ms(found->int8_amx, true));
    if (found != g_results.end() && !w.vnni.wall.empty()) {
      direct_vnni += found->int8_vnni.cpu_median(), wino_vnni += w.vnni.cpu_median();
    }
    if (found != g_results.end() && !w.amx.wall.empty()) {
      direct_amx += found->int8_amx.cpu_median(), wino_amx += w.amx.cpu_median();
    }
  }
  const double t = num_threads();
  fmt::print(
      "  sum, CPU ms: vnni direct {:.0f}, winograd products {:.0f}; amx direct {:.0f}, "
      "winograd products {:.0f}\n",
      direct_vnni / t * 1e3, wino_vnni / t * 1e3, direct_amx / t * 1e3, wino_amx / t * 1e3);
  fmt::print(
      "  accuracy (double simulation, 64 -> 64 channels @ 64 x 64, weights N(0, 0.05)), "
      "relative RMS error against the exact convolution:\n");
  for (const bool relu_input : {false, true}) {
    const std::array<double, 3> e = winograd_accuracy(64, 64, 64, 64, relu_input);
    fmt::print(
        "    x {}: direct int8 {:.3f}%, winograd int8 per-position scales {:.3f}%, one scale "
        "{:.3f}%\n",
        relu_input ? "ReLU(N(0, 1))" : "N(0, 1)     ", 100 * e[0], 100 * e[1], 100 * e[2]);
  }
}

}  // namespace

int main(int argc, char** argv) {
  int threads = 2;
  bool winograd = false;
  std::vector<char*> rest;
  for (int i = 0; i < argc; ++i) {
    const std::string a = argv[i];
    if (a.rfind("--reps=", 0) == 0) {
      g_reps = std::max(1, std::atoi(a.c_str() + 7));
    } else if (a == "--winograd") {
      winograd = true;
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
  if (winograd) {
    for (const Layer& l : unet_3x3_layers()) {
      benchmark::RegisterBenchmark(
          fmt::format("Int8WinogradProducts/{}/{}to{}/{}x{}", l.name, l.in, l.out, l.h, l.w)
              .c_str(),
          BM_WinogradProducts, l)
          ->Iterations(g_reps)
          ->UseManualTime()
          ->Unit(benchmark::kMillisecond);
    }
  }
  benchmark::RunSpecifiedBenchmarks();
  print_table();
  if (winograd) print_winograd();
  benchmark::Shutdown();
  return 0;
}
