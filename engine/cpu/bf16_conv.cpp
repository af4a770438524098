// The CPU's BF16 convolutions (bf16_conv.hpp): argument checks, the
// GEMM descriptions for the micro-kernel, the run-time choice of its instructions, threads.
#include "engine/cpu/bf16_conv.hpp"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "core/error.hpp"
#include "core/ops.hpp"
#include "core/parallel.hpp"
#include "engine/cpu/bf16_amx.hpp"
#include "engine/cpu/bf16_isa_emulated.hpp"
#include "engine/cpu/bf16_microkernel.hpp"
#include "engine/cpu/bf16_winograd.hpp"
#include "engine/cpu/half_ops.hpp"
#include "weights_io/half.hpp"

namespace pillarseg::cpu {

namespace {

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

// On the AMX tiles, and on AMD's AVX512_BF16, the BF16 products take at most 0.7x the FP32
// F(4x4)'s time at every U-Net shape, so the BF16 path always pays. On Intel's AVX512_BF16
// alone, VDPBF16PS's 32 products a cycle are no more than FP32's two 16-wide FMAs, and F(2x2)
// needs 4 products an output per channel pair to F(4x4)'s 2.25: the BF16 path pays only where
// its half-size data outweighs that, the channel-doubling convolutions of up to 128 input
// channels (the measured split: docs/benchmarks.md, "BF16 on the CPU, and OpenVINO").
bool bf16_winograd_pays(Bf16Kernels kernels, bool dot_outpaces_fma, const Shape& weight) {
  if (kernels == Bf16Kernels::Amx || kernels == Bf16Kernels::AmxEmulated || dot_outpaces_fma) return true;
  const std::int64_t out = weight[0], in = weight[1];
  return in <= 128 && out >= 2 * in;
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

}  // namespace pillarseg::cpu
