// The CPU's BF16 convolutions and 16-bit data movement (bf16_conv.hpp): argument checks, the
// GEMM descriptions for the micro-kernel, the run-time choice of its instructions, threads.
#include "engine/cpu/bf16_conv.hpp"

#if defined(__x86_64__)
#include <cpuid.h>
#include <sys/syscall.h>
#include <unistd.h>
#endif

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

#include "core/error.hpp"
#include "core/bilinear_taps.hpp"
#include "core/ops.hpp"
#include "core/parallel.hpp"
#include "engine/cpu/bf16_amx.hpp"
#include "engine/cpu/bf16_isa_emulated.hpp"
#include "engine/cpu/bf16_microkernel.hpp"
#include "engine/cpu/bf16_winograd.hpp"
#include "weights_io/half.hpp"

namespace pillarseg::cpu {

namespace {

std::uint16_t to_bits(float v, Precision p) {
  return p == Precision::BF16 ? weights::float_to_bf16_bits(v) : weights::float_to_f16_bits(v);
}

// The 16-bit type as a compile-time value, so that its conversions inline into a loop: calls
// f(std::true_type) for BF16, f(std::false_type) for FP16; inside f, half_value<decltype(h)::
// value> and half_bits<...> convert.
template <class F>
void with_half_type(Precision p, F&& f) {
  if (p == Precision::BF16) {
    f(std::true_type{});
  } else {
    f(std::false_type{});
  }
}
template <bool kBf16>
float half_value(std::uint16_t bits) {
  return kBf16 ? weights::bf16_bits_to_float(bits) : weights::f16_bits_to_float(bits);
}
template <bool kBf16>
std::uint16_t half_bits(float v) {
  return kBf16 ? weights::float_to_bf16_bits(v) : weights::float_to_f16_bits(v);
}

void require_half(const char* op, Precision p) {
  PS_CHECK(p == Precision::BF16 || p == Precision::F16,
           "{}: 16-bit activations need bf16 or fp16, got {}", op, precision_name(p));
}

// K's elements (t, c) for the spatial taps t and the channels c < channels, tap-major, each in
// its column t Ip + c of the prepared weights, and a zero partner after a tap's last channel
// when their count is odd (bf16_microkernel.hpp).
std::vector<KTap> k_taps(std::int64_t channels, const std::vector<TapOffset>& offsets,
                         std::int64_t height, std::int64_t width) {
  const std::int64_t padded = op::half16_padded_channels(channels);
  const auto zero_tap = static_cast<std::int32_t>(offsets.size());
  std::vector<KTap> taps;
  taps.reserve(static_cast<size_t>(channels + 1) * offsets.size());
  for (size_t t = 0; t < offsets.size(); ++t) {
    const std::int64_t column0 = static_cast<std::int64_t>(t) * padded;
    for (std::int64_t c = 0; c < channels; ++c) {
      taps.push_back({c * height * width + offsets[t].dy * width + offsets[t].dx, column0 + c,
                      static_cast<std::int32_t>(t)});
    }
    if (channels % 2 == 1) taps.push_back({0, column0 + channels, zero_tap});
  }
  return taps;
}

// Whether `kernels` run the AVX-512 instructions (checked here) rather than their model.
bool native(Bf16Kernels kernels) {
  if (kernels == Bf16Kernels::Emulated || kernels == Bf16Kernels::AmxEmulated) return false;
  std::string why;
  PS_CHECK(avx512_bf16_available(&why), "BF16 convolutions on the CPU: {}", why);
  return true;
}

void run_gemm(Bf16Kernels kernels, const Bf16Gemm& g) {
  const bool on_avx512 = native(kernels);  // the AMX path's direct convolutions are AVX-512's
  parallel_chunks(gemm_items(g), [&](std::int64_t begin, std::int64_t end, int) {
#if defined(PILLARSEG_HAVE_AVX512_BF16_KERNELS)
    if (on_avx512) {
      bf16_gemm_rows_avx512(g, begin, end);
      return;
    }
#endif
    gemm_rows<EmulatedBf16Isa>(g, begin, end);
  });
}

// y's shape against the op's, and whether y is FP32 or BF16.
void require_output(const char* op, const TensorRef& y, const Shape& expected) {
  PS_CHECK(y.shape == expected, "{}: y must be {}, got {}", op, shape_str(expected),
           shape_str(y.shape));
  PS_CHECK(y.data != nullptr || y.numel() == 0, "{}: y has no memory", op);
  PS_CHECK(y.dtype == DType::F32 || y.dtype == DType::BF16, "{}: y must be f32 or bf16, got {}", op,
           dtype_name(y.dtype));
}

}  // namespace

bool avx512_bf16_available(std::string* why_not) {
#if defined(PILLARSEG_HAVE_AVX512_BF16_KERNELS)
  __builtin_cpu_init();
  // libgcc reports AVX-512 features only where the OS saves the ZMM registers (XCR0).
  std::string missing;
  const auto need = [&](bool present, const char* feature) {
    if (!present) missing += (missing.empty() ? "" : ", ") + std::string(feature);
  };
  need(__builtin_cpu_supports("avx512f") != 0, "AVX512F");
  need(__builtin_cpu_supports("avx512bw") != 0, "AVX512BW");
  need(__builtin_cpu_supports("avx512vl") != 0, "AVX512VL");
  need(__builtin_cpu_supports("avx512bf16") != 0, "AVX512_BF16");
  if (missing.empty()) return true;
  if (why_not != nullptr) *why_not = "this CPU (or its OS) lacks " + missing;
  return false;
#else
  if (why_not != nullptr) {
    *why_not =
        "this build has no AVX512_BF16 micro-kernel (not an x86-64 target, or the compiler lacks "
        "-mavx512bf16)";
  }
  return false;
#endif
}

namespace {

// The AMX check's answer, worked out once: "" where the AMX path runs, else what is missing.
std::string amx_missing() {
  std::string why;
  if (!avx512_bf16_available(&why)) return why;
#if defined(PILLARSEG_HAVE_AMX_BF16_KERNELS) && defined(__x86_64__) && defined(__linux__)
  unsigned eax = 0, ebx = 0, ecx = 0, edx = 0;
  if (__get_cpuid_count(7, 0, &eax, &ebx, &ecx, &edx) == 0) return "this CPU has no CPUID leaf 7";
  std::string missing;
  if (((edx >> 24) & 1u) == 0) missing = "AMX-TILE";
  if (((edx >> 22) & 1u) == 0) missing += missing.empty() ? "AMX-BF16" : ", AMX-BF16";
  if (!missing.empty()) return "this CPU lacks " + missing;
  unsigned xcr0_lo = 0, xcr0_hi = 0;
  __asm__ volatile("xgetbv" : "=a"(xcr0_lo), "=d"(xcr0_hi) : "c"(0));  // OSXSAVE: AVX-512 above
  if (((xcr0_lo >> 17) & 3u) != 3u)
    return "the OS does not enable the AMX tile state (XCR0 bits 17, 18)";
  constexpr long kArchReqXcompPerm = 0x1023, kXfeatureXtiledata = 18;  // <asm/prctl.h>
  if (::syscall(SYS_arch_prctl, kArchReqXcompPerm, kXfeatureXtiledata) != 0) {
    return std::string(
               "Linux did not grant this process the AMX tile state (arch_prctl "
               "ARCH_REQ_XCOMP_PERM: ") +
           std::strerror(errno) + "; Linux 5.16 or later grants it)";
  }
  return "";
#else
  return "this build has no AMX-BF16 tiles (not x86-64 Linux, or the compiler lacks -mamx-bf16)";
#endif
}

}  // namespace

bool amx_bf16_available(std::string* why_not) {
  static const std::string missing = amx_missing();
  if (missing.empty()) return true;
  if (why_not != nullptr) *why_not = missing;
  return false;
}

Bf16Kernels native_bf16_kernels() {
  const char* amx = std::getenv("PILLARSEG_CPU_AMX");
  if (amx != nullptr && std::string_view(amx) == "0") return Bf16Kernels::Avx512;
  return amx_bf16_available() ? Bf16Kernels::Amx : Bf16Kernels::Avx512;
}

const char* bf16_kernels_name(Bf16Kernels kernels) {
  switch (kernels) {
    case Bf16Kernels::Avx512:
      return "avx512_bf16";
    case Bf16Kernels::Emulated:
      return "emulated";
    case Bf16Kernels::Amx:
      return "amx_bf16";
    case Bf16Kernels::AmxEmulated:
      return "amx_bf16 (emulated)";
  }
  return "?";
}

void prepare_conv_weights(const Ref& w, const Ref* bias, const BatchNormRefs* bn, Precision p,
                          HRef& w16, Ref& bias_out) {
  const char* op = "CpuBackend::prepare_conv_weights";
  require_half(op, p);
  require_rank(op, "w", w, 4);
  const std::int64_t out = w.dim(0), k = w.dim(1) * w.dim(2) * w.dim(3);
  if (bias) require_shape(op, "bias", *bias, {out});
  require_shape(op, "w16", w16, op::half16_conv_weights(w.shape, false));
  require_shape(op, "bias_out", bias_out, {out});
  if (bn != nullptr) {
    for (const Ref* r : {&bn->gamma, &bn->beta, &bn->running_mean, &bn->running_var})
      require_shape(op, "BatchNorm", *r, {out});
  }
  const std::int64_t kp = w16.dim(1), in = w.dim(1), taps = w.dim(2) * w.dim(3), padded = kp / taps;
  parallel_for(out, [&](std::int64_t n) {
    // The CUDA backend's arithmetic (prepare_weights_kernel in kernels/conv2d_mma.cu).
    float scale = 1.0f, shift = 0.0f;
    if (bn != nullptr) {
      scale = bn->gamma.data[n] / std::sqrt(bn->running_var.data[n] + bn->eps);
      shift = bn->beta.data[n] - scale * bn->running_mean.data[n];
    }
    for (std::int64_t t = 0; t < taps; ++t) {
      for (std::int64_t c = 0; c < padded; ++c)
        w16.data[n * kp + t * padded + c] =
            to_bits(c < in ? w.data[n * k + c * taps + t] * scale : 0.0f, p);
    }
    bias_out.data[n] = scale * (bias != nullptr ? bias->data[n] : 0.0f) + shift;
  });
}

void prepare_conv_transpose_weights(const Ref& w, const Ref* bias, Precision p, HRef& w16,
                                    Ref& bias_out) {
  const char* op = "CpuBackend::prepare_conv_transpose_weights";
  require_half(op, p);
  require_rank(op, "w", w, 4);
  const std::int64_t in = w.dim(0), out = w.dim(1);
  PS_CHECK(w.dim(2) == 2 && w.dim(3) == 2, "{}: w must be (I, O, 2, 2), got {}", op,
           shape_str(w.shape));
  if (bias) require_shape(op, "bias", *bias, {out});
  require_shape(op, "w16", w16, op::half16_conv_weights(w.shape, true));
  require_shape(op, "bias_out", bias_out, {4 * out});
  const std::int64_t kp = w16.dim(1);
  parallel_for(4 * out, [&](std::int64_t n) {
    const std::int64_t o = n / 4, s = n % 4;
    for (std::int64_t i = 0; i < kp; ++i)
      w16.data[n * kp + i] = to_bits(i < in ? w.data[(i * out + o) * 4 + s] : 0.0f, p);
    bias_out.data[n] = bias != nullptr ? bias->data[o] : 0.0f;
  });
}

void conv2d_forward(Bf16Kernels kernels, const HRef& x, const HRef& w16, const Ref& bias_out,
                    const Shape& weight, int pad, bool relu, const TensorRef& y) {
  const char* op = "CpuBackend::conv2d_prepared_forward";
  const Shape y_shape = op::conv2d(x.shape, weight, pad, nullptr, op);
  require_output(op, y, y_shape);
  require_shape(op, "w16", w16, op::half16_conv_weights(weight, false));
  require_shape(op, "bias_out", bias_out, {weight[0]});
  const std::int64_t in = weight[1], kh = weight[2], kw = weight[3], h = x.dim(2), w = x.dim(3);
  PS_CHECK(kh * kw <= kMaxTaps, "{}: kernels up to 7 x 7, got {}", op, shape_str(weight));
  std::vector<TapOffset> offsets;
  for (std::int64_t ky = 0; ky < kh; ++ky) {
    for (std::int64_t kx = 0; kx < kw; ++kx)
      offsets.push_back({static_cast<std::int32_t>(ky - pad), static_cast<std::int32_t>(kx - pad)});
  }
  const std::vector<KTap> taps = k_taps(in, offsets, h, w);
  Bf16Gemm g;
  g.x = x.data, g.batch = x.dim(0), g.x_batch_stride = in * h * w, g.height = h, g.width = w;
  g.k_taps = taps.data(), g.k = static_cast<std::int64_t>(taps.size()), g.offsets = offsets.data(),
  g.taps = static_cast<int>(offsets.size());
  g.w = w16.data, g.kp = w16.dim(1), g.columns = weight[0], g.bias = bias_out.data, g.relu = relu;
  g.y = y.data, g.y_bf16 = y.dtype == DType::BF16;
  g.rows = y_shape[2], g.row_pixels = y_shape[3];
  g.out_height = y_shape[2], g.out_width = y_shape[3], g.out_planes = y_shape[1];
  run_gemm(kernels, g);
}

namespace {

// U's layout: U[p][o][c / 2][c % 2] for the 16 Winograd points p, `rows` output channels and
// `pairs` input channel pairs; AMX's tiles take 16 channel pairs and 16 output channels at a time,
// so there U is zero padded to those.
struct WinogradWeightLayout {
  std::int64_t pairs, rows;
  std::int64_t elements() const { return 16 * rows * pairs * 2; }
};

WinogradWeightLayout winograd_layout(Bf16Kernels kernels, const Shape& weight) {
  const bool amx = kernels == Bf16Kernels::Amx || kernels == Bf16Kernels::AmxEmulated;
  const auto round_up = [](std::int64_t n, std::int64_t to) { return (n + to - 1) / to * to; };
  const std::int64_t out = weight[0], in = weight[1];
  return {amx ? round_up((in + 1) / 2, kAmxPairs) : (in + 1) / 2,
          amx ? round_up(out, kAmxGroupColumns) : out};
}

void require_3x3(const char* op, const Shape& weight) {
  PS_CHECK(weight.size() == 4 && weight[2] == 3 && weight[3] == 3,
           "{}: needs a 3 x 3 kernel, got {}", op, shape_str(weight));
}

}  // namespace

std::int64_t winograd_weight_elements(Bf16Kernels kernels, const Shape& weight) {
  require_3x3("winograd_weight_elements", weight);
  return winograd_layout(kernels, weight).elements();
}

void winograd_transform_weights(Bf16Kernels kernels, const HRef& w16, const Shape& weight,
                                std::uint16_t* u) {
  const char* op = "winograd_transform_weights";
  require_3x3(op, weight);
  require_shape(op, "w16", w16, op::half16_conv_weights(weight, false));
  const std::int64_t out = weight[0], in = weight[1], kp = w16.dim(1);
  const WinogradWeightLayout l = winograd_layout(kernels, weight);
  // U[p][o][c / 2][c % 2] = (G g G^T)[p] of the prepared BF16 kernel g of (o, c), in double,
  // rounded once; zero for the channels past C (an odd count's partner, AMX's padding) and the
  // rows past O.
  parallel_for(l.rows, [&](std::int64_t o) {
    for (std::int64_t c = 0; c < 2 * l.pairs; ++c) {
      double gg[4][3] = {};  // G g
      if (c < in && o < out) {
        double k[3][3];
        for (int t = 0; t < 9; ++t)
          k[t / 3][t % 3] = weights::bf16_bits_to_float(w16.data[o * kp + t * (kp / 9) + c]);
        for (int b = 0; b < 3; ++b) {
          gg[0][b] = k[0][b];
          gg[1][b] = 0.5 * (k[0][b] + k[1][b] + k[2][b]);
          gg[2][b] = 0.5 * (k[0][b] - k[1][b] + k[2][b]);
          gg[3][b] = k[2][b];
        }
      }
      for (int i = 0; i < 4; ++i) {
        const double row[4] = {gg[i][0], 0.5 * (gg[i][0] + gg[i][1] + gg[i][2]),
                               0.5 * (gg[i][0] - gg[i][1] + gg[i][2]), gg[i][2]};
        for (int j = 0; j < 4; ++j) {
          u[((static_cast<std::int64_t>(4 * i + j) * l.rows + o) * l.pairs + c / 2) * 2 + c % 2] =
              EmulatedBf16Isa::float_to_bf16(static_cast<float>(row[j]));
        }
      }
    }
  });
}

void conv3x3_winograd_forward(Bf16Kernels kernels, const HRef& x, const HRef& w16,
                              const std::uint16_t* u, const Ref& bias_out, const Shape& weight,
                              bool relu, const TensorRef& y, Bf16WinogradWorkspace& workspace) {
  const char* op = "CpuBackend::conv2d_prepared_forward (Winograd)";
  require_3x3(op, weight);
  const Shape y_shape = op::conv2d(x.shape, weight, 1, nullptr, op);
  require_output(op, y, y_shape);
  require_shape(op, "w16", w16, op::half16_conv_weights(weight, false));
  require_shape(op, "bias_out", bias_out, {weight[0]});
  const bool on_native = native(kernels);
  const bool amx = kernels == Bf16Kernels::Amx || kernels == Bf16Kernels::AmxEmulated;
  if (kernels == Bf16Kernels::Amx) {
    std::string why;
    PS_CHECK(amx_bf16_available(&why), "BF16 convolutions on AMX tiles: {}", why);
  }
  const std::int64_t out = weight[0], in = weight[1];
  const WinogradWeightLayout l = winograd_layout(kernels, weight);
  const std::int64_t pairs = l.pairs, u_rows = l.rows;
  if (u == nullptr) {
    workspace.u.resize(static_cast<size_t>(l.elements()));
    winograd_transform_weights(kernels, w16, weight, workspace.u.data());
    u = workspace.u.data();
  }
  Bf16Winograd g;
  g.x = x.data, g.batch = x.dim(0), g.channels = in, g.height = x.dim(2), g.width = x.dim(3);
  g.channel_pairs = pairs, g.u = u, g.out_channels = out, g.u_rows = u_rows;
  g.bias = bias_out.data, g.relu = relu;
  g.y = y.data, g.y_bf16 = y.dtype == DType::BF16;
  g.tiles_h = (g.height + 1) / 2, g.tiles_w = (g.width + 1) / 2;
  // Blocks whose V (16 channel-pair rows of 4-byte pairs per tile) stays within 384 KiB of a
  // core's L2, at least one 48-tile group, at most an image.
  const std::int64_t tiles = g.tiles_h * g.tiles_w;
  const std::int64_t fit = (384 << 10) / (16 * pairs * 4) / kWinogradGroupTiles;
  g.block_tiles = std::min(std::max<std::int64_t>(fit, 1),
                           (tiles + kWinogradGroupTiles - 1) / kWinogradGroupTiles) *
                  kWinogradGroupTiles;
  const int threads = std::max(num_threads(), 1);
  g.v_stride = winograd_v_words(pairs, g.block_tiles);
  g.m_stride = winograd_m_floats(amx ? kAmxGroupColumns : kWinogradGroupColumns);
  workspace.v.resize(static_cast<size_t>(threads * g.v_stride));
  workspace.m.resize(static_cast<size_t>(threads * g.m_stride));
  g.v = workspace.v.data(), g.m = workspace.m.data();
  parallel_chunks(g.batch * winograd_blocks_per_image(g),
                  [&](std::int64_t begin, std::int64_t end, int thread) {
#if defined(PILLARSEG_HAVE_AMX_BF16_KERNELS)
                    if (on_native && amx) {
                      bf16_winograd_blocks_amx(g, begin, end, thread);
                      return;
                    }
#endif
#if defined(PILLARSEG_HAVE_AVX512_BF16_KERNELS)
                    if (on_native && !amx) {
                      bf16_winograd_blocks_avx512(g, begin, end, thread);
                      return;
                    }
#endif
                    if (amx) {
                      winograd_blocks_amx<EmulatedBf16Isa, EmulatedAmxTiles>(g, begin, end, thread);
                    } else {
                      winograd_blocks<EmulatedBf16Isa>(g, begin, end, thread);
                    }
                  });
}

void conv_transpose2d_forward(Bf16Kernels kernels, const HRef& x, const HRef& w16,
                               const Ref& bias_out, const Shape& weight, const TensorRef& y) {
  const char* op = "CpuBackend::conv_transpose2d_prepared_forward";
  const Shape y_shape = op::conv_transpose2d(x.shape, weight, nullptr, op);
  require_output(op, y, y_shape);
  require_shape(op, "w16", w16, op::half16_conv_weights(weight, true));
  require_shape(op, "bias_out", bias_out, {4 * weight[1]});
  const std::int64_t in = x.dim(1), h = x.dim(2), w = x.dim(3);
  const std::vector<TapOffset> offsets = {{0, 0}};
  const std::vector<KTap> taps = k_taps(in, offsets, h, w);
  Bf16Gemm g;
  g.x = x.data, g.batch = x.dim(0), g.x_batch_stride = in * h * w, g.height = h, g.width = w;
  g.k_taps = taps.data(), g.k = static_cast<std::int64_t>(taps.size()), g.offsets = offsets.data(),
  g.taps = 1;
  g.w = w16.data, g.kp = w16.dim(1), g.columns = 4 * weight[1], g.bias = bias_out.data;
  g.transposed = true;
  g.y = y.data, g.y_bf16 = y.dtype == DType::BF16;
  g.rows = h, g.row_pixels = w;
  g.out_height = y_shape[2], g.out_width = y_shape[3], g.out_planes = y_shape[1];
  run_gemm(kernels, g);
}

void to_half(const Ref& x, Precision p, HRef& y) {
  require_half("CpuBackend::to_half", p);
  require_shape("CpuBackend::to_half", "y", y, x.shape);
  const std::int64_t n = x.numel();
  parallel_chunks(n, [&](std::int64_t begin, std::int64_t end, int) {
    for (std::int64_t i = begin; i < end; ++i) y.data[i] = to_bits(x.data[i], p);
  });
}

void scatter_half(const Ref& features, const IRef& cells, int channel0, Precision p, HRef& canvas) {
  const char* op = "CpuBackend::scatter_forward_half";
  require_half(op, p);
  op::scatter(features.shape, cells.shape, canvas.shape, channel0, op);
  const std::int64_t batch = canvas.dim(0), channels = canvas.dim(1), height = canvas.dim(2),
                     width = canvas.dim(3), plane = height * width, c_band = features.dim(1);
  const std::int64_t rows = features.dim(0);
  // Each thread owns whole channels: it zeroes them, then writes every pillar's value in them in
  // pillar order, so a cell named twice keeps the last pillar's value as the serial loop did.
  parallel_chunks(c_band, [&](std::int64_t c_begin, std::int64_t c_end, int) {
    for (std::int64_t b = 0; b < batch; ++b)
      std::fill_n(canvas.data + (b * channels + channel0 + c_begin) * plane,
                  (c_end - c_begin) * plane, std::uint16_t{0});
    for (std::int64_t r = 0; r < rows; ++r) {
      const std::int32_t* cell = cells.data + 3 * r;
      if (cell[0] < 0 || cell[0] >= batch || cell[1] < 0 || cell[1] >= height || cell[2] < 0 ||
          cell[2] >= width)
        continue;
      std::uint16_t* out =
          canvas.data + (cell[0] * channels + channel0) * plane + cell[1] * width + cell[2];
      for (std::int64_t c = c_begin; c < c_end; ++c)
        out[c * plane] = to_bits(features.data[r * c_band + c], p);
    }
  });
}

void maxpool2d_half(const HRef& x, Precision p, HRef& y) {
  const char* op = "CpuBackend::maxpool2d_half";
  require_half(op, p);
  require_shape(op, "y", y, op::maxpool2d(x.shape, op));
  const std::int64_t h = x.dim(2), w = x.dim(3), oh = h / 2, ow = w / 2;
  with_half_type(p, [&](auto half) {
    constexpr bool kBf16 = decltype(half)::value;
    parallel_for(x.dim(0) * x.dim(1), [&](std::int64_t plane) {
      for (std::int64_t oy = 0; oy < oh; ++oy) {
        for (std::int64_t ox = 0; ox < ow; ++ox) {
          const std::uint16_t* in = x.data + plane * h * w + 2 * oy * w + 2 * ox;
          const std::uint16_t window[4] = {in[0], in[1], in[w], in[w + 1]};
          std::uint16_t best_bits = window[0];
          float best = half_value<kBf16>(window[0]);
          for (int k = 1; k < 4; ++k) {
            // The FP32 op's rule: a greater value, or NaN, replaces the best so far.
            const float value = half_value<kBf16>(window[k]);
            if (value > best || std::isnan(value)) best = value, best_bits = window[k];
          }
          y.data[(plane * oh + oy) * ow + ox] = best_bits;
        }
      }
    });
  });
}

void upsample_bilinear_half(const HRef& x, Precision p, HRef& y) {
  const char* op = "CpuBackend::upsample_bilinear_half";
  require_half(op, p);
  require_shape(op, "y", y, op::upsample_bilinear(x.shape, op));
  const std::int64_t in_h = x.dim(2), in_w = x.dim(3), out_h = 2 * in_h, out_w = 2 * in_w;
  // The taps of core/bilinear_taps.hpp, as the CUDA kernel weighs.
  using Tap = BilinearTap<float>;
  const auto taps = [](std::int64_t in, std::int64_t out) {
    std::vector<Tap> t(static_cast<size_t>(out));
    for (std::int64_t d = 0; d < out; ++d) t[static_cast<size_t>(d)] = bilinear_tap<float>(d, in, out);
    return t;
  };
  const std::vector<Tap> rows = taps(in_h, out_h), cols = taps(in_w, out_w);
  with_half_type(p, [&](auto half) {
    constexpr bool kBf16 = decltype(half)::value;
    // Per plane: each input row interpolated along x once into FP32 (h_rows, the two a output
    // row reads), then the rows along y, in the same expression tree as the CUDA kernel.
    const int threads = std::max(num_threads(), 1);
    std::vector<float> scratch(static_cast<size_t>(threads * 2 * out_w));
    parallel_chunks(x.dim(0) * x.dim(1), [&](std::int64_t begin, std::int64_t end, int thread) {
      float* h_top = scratch.data() + static_cast<std::int64_t>(thread) * 2 * out_w;
      float* h_bottom = h_top + out_w;
      const auto along_x = [&](const std::uint16_t* row, float* h) {
        for (std::int64_t ox = 0; ox < out_w; ++ox) {
          const Tap& c = cols[static_cast<size_t>(ox)];
          h[ox] = c.w0 * half_value<kBf16>(row[c.i0]) + c.w1 * half_value<kBf16>(row[c.i1]);
        }
      };
      for (std::int64_t plane = begin; plane < end; ++plane) {
        const std::uint16_t* in = x.data + plane * in_h * in_w;
        std::uint16_t* out = y.data + plane * out_h * out_w;
        std::int64_t top_row = -1, bottom_row = -1;
        for (std::int64_t oy = 0; oy < out_h; ++oy) {
          const Tap& r = rows[static_cast<size_t>(oy)];
          if (r.i0 != top_row) {
            if (r.i0 == bottom_row) {
              std::swap(h_top, h_bottom);
              bottom_row = -1;
            } else {
              along_x(in + r.i0 * in_w, h_top);
            }
            top_row = r.i0;
          }
          if (r.i1 != bottom_row) {
            along_x(in + r.i1 * in_w, h_bottom);
            bottom_row = r.i1;
          }
          std::uint16_t* o = out + oy * out_w;
          for (std::int64_t ox = 0; ox < out_w; ++ox) {
            const float value = r.w0 * h_top[ox] + r.w1 * h_bottom[ox];
            o[ox] = half_bits<kBf16>(value);
          }
        }
      }
    });
  });
}

void pad_concat_half(const HRef& skip, const HRef& up, HRef& y) {
  const char* op = "CpuBackend::pad_concat_half";
  require_shape(op, "y", y, op::pad_concat(skip.shape, up.shape, op));
  const std::int64_t cs = skip.dim(1), cu = up.dim(1), h = skip.dim(2), w = skip.dim(3),
                     uh = up.dim(2), uw = up.dim(3);
  const std::int64_t top = (h - uh) / 2, left = (w - uw) / 2, plane = h * w;
  parallel_for(skip.dim(0) * (cs + cu), [&](std::int64_t item) {
    const std::int64_t b = item / (cs + cu), c = item % (cs + cu);
    std::uint16_t* out = y.data + item * plane;
    if (c < cs) {
      std::copy_n(skip.data + (b * cs + c) * plane, plane, out);
      return;
    }
    // Zero only the border the up-sampled plane leaves, then copy its rows in.
    const std::uint16_t* in = up.data + (b * cu + c - cs) * uh * uw;
    std::fill_n(out, top * w, std::uint16_t{0});
    for (std::int64_t uy = 0; uy < uh; ++uy) {
      std::uint16_t* row = out + (uy + top) * w;
      std::fill_n(row, left, std::uint16_t{0});
      std::copy_n(in + uy * uw, uw, row + left);
      std::fill_n(row + left + uw, w - left - uw, std::uint16_t{0});
    }
    std::fill_n(out + (top + uh) * w, (h - top - uh) * w, std::uint16_t{0});
  });
}

void copy_channels_half(const HRef& x, int channel0, HRef& y) {
  op::channel_band(x.shape, y.shape, channel0, "CpuBackend::copy_channels_half");
  const std::int64_t channels = x.dim(1), inner = x.dim(2) * x.dim(3), wide = y.dim(1);
  parallel_for(x.dim(0) * channels, [&](std::int64_t item) {
    const std::int64_t b = item / channels, c = item % channels;
    std::copy_n(x.data + item * inner, inner, y.data + (b * wide + channel0 + c) * inner);
  });
}

}  // namespace pillarseg::cpu
