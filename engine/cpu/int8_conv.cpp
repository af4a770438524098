// The CPU's INT8 convolutions (int8_conv.hpp): weight quantization and packing,
// argument checks, the quantized input's layout, the run-time choice of instructions, threads.
#include "engine/cpu/int8_conv.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "core/error.hpp"
#include "core/ops.hpp"
#include "core/parallel.hpp"
#include "engine/cpu/int8_amx.hpp"
#include "engine/cpu/int8_isa_emulated.hpp"
#include "engine/cpu/int8_microkernel.hpp"
#include "engine/cpu/int8_winograd.hpp"
#include "host/winograd_f2_stats.hpp"
#include "weights_io/half.hpp"

namespace pillarseg::cpu {

bool int8_amx_family(Int8Kernels kernels) {
  return kernels == Int8Kernels::Amx || kernels == Int8Kernels::AmxEmulated;
}

std::int8_t quantize_int8(float x, float reciprocal) {
  float r = x * reciprocal;
  if (std::isnan(r)) return 0;
  r = std::clamp(r, -127.0f, 127.0f);
  return static_cast<std::int8_t>(std::nearbyint(r));
}

std::uint8_t quantize_uint8(float x, float reciprocal) {
  float r = x * reciprocal;
  if (std::isnan(r)) return 0;
  r = std::clamp(r, 0.0f, 255.0f);
  return static_cast<std::uint8_t>(std::nearbyint(r));
}

float int8_weight_scale(float max_abs) {
  return max_abs / 127.0f;
}

namespace {

// Channel quads the input is stored in: every quad of the channels, and for AMX a multiple of 16.
std::int64_t int8_quads(Int8Kernels kernels, std::int64_t channels) {
  const std::int64_t quads = (channels + 3) / 4;
  return int8_amx_family(kernels) ? int8_round_up(quads, kInt8AmxQuads) : quads;
}

// q[(n, tap, c)] of GEMM column n -> the packing of `kernels`: Vnni w[n / 8][tap][cq][n % 8][i],
// Amx w[n][tap][cq][i] (int8_microkernel.hpp, int8_amx.hpp), zero where c >= channels or n >=
// columns. qw(n, tap, c) gives the value.
template <class Qw>
void pack_weights(Int8Kernels kernels, std::int64_t columns, std::int64_t taps,
                  std::int64_t channels, Qw&& qw, AlignedVector<std::int8_t>& packed) {
  const std::int64_t quads = int8_quads(kernels, channels);
  const bool amx = int8_amx_family(kernels);
  const std::int64_t padded = int8_round_up(columns, amx ? kInt8AmxColumns : kInt8GroupColumns);
  packed.assign(static_cast<size_t>(padded * taps * quads * 4), 0);
  parallel_for(columns, [&](std::int64_t n) {
    for (std::int64_t t = 0; t < taps; ++t) {
      for (std::int64_t c = 0; c < channels; ++c) {
        const std::int64_t cq = c / 4, i = c % 4;
        const std::int64_t at =
            amx ? ((n * taps + t) * quads + cq) * 4 + i
                : (((n / kInt8GroupColumns * taps + t) * quads + cq) * kInt8GroupColumns +
                   n % kInt8GroupColumns) *
                          4 +
                      i;
        packed[static_cast<size_t>(at)] = qw(n, t, c);
      }
    }
  });
}

// sw[o] and qw for the FP32 weights of output channel o at `index(o, j)`, j < per_channel.
template <class Index>
void quantize_weights(const float* w, std::int64_t out, std::int64_t per_channel, Index&& index,
                      std::vector<float>& scale, std::vector<std::int8_t>& q) {
  scale.assign(static_cast<size_t>(out), 0.0f);
  parallel_for(out, [&](std::int64_t o) {
    float max_abs = 0.0f;
    for (std::int64_t j = 0; j < per_channel; ++j)
      max_abs = std::max(max_abs, std::abs(w[index(o, j)]));
    const float s = int8_weight_scale(max_abs);
    scale[static_cast<size_t>(o)] = s;
    for (std::int64_t j = 0; j < per_channel; ++j) {
      const std::int64_t at = index(o, j);
      q[static_cast<size_t>(at)] =
          s > 0.0f
              ? static_cast<std::int8_t>(std::clamp(std::nearbyint(w[at] / s), -127.0f, 127.0f))
              : std::int8_t{0};
    }
  });
}

void require_finite(const char* op, const Ref& r, const char* what) {
  for (std::int64_t i = 0; i < r.numel(); ++i)
    PS_CHECK(std::isfinite(r.data[i]), "{}: {} must be finite, got {} at element {}", op, what,
             r.data[i], i);
}

}  // namespace

void prepare_int8_conv(Int8Kernels kernels, const Ref& w, const Ref& bias, Int8ConvWeights& out) {
  const char* op = "prepare_int8_conv";
  require_rank(op, "w", w, 4);
  const std::int64_t o_count = w.dim(0), in = w.dim(1), taps = w.dim(2) * w.dim(3);
  PS_CHECK(taps <= kInt8MaxTaps, "{}: kernels up to 7 x 7, got {}", op, shape_str(w.shape));
  require_shape(op, "bias", bias, {o_count});
  require_finite(op, w, "w");
  require_finite(op, bias, "bias");
  out.packed_for = int8_amx_family(kernels) ? Int8Kernels::Amx : Int8Kernels::Vnni;
  out.weight = w.shape, out.transposed = false, out.columns = o_count;
  out.q.assign(static_cast<size_t>(w.numel()), 0);
  const std::int64_t k = in * taps;
  quantize_weights(
      w.data, o_count, k, [&](std::int64_t o, std::int64_t j) { return o * k + j; }, out.scale,
      out.q);
  out.bias.assign(bias.data, bias.data + o_count);
  out.compensation.assign(static_cast<size_t>(o_count), 0);
  for (std::int64_t o = 0; o < o_count; ++o) {
    std::int32_t sum = 0;
    for (std::int64_t j = 0; j < k; ++j) sum += out.q[static_cast<size_t>(o * k + j)];
    out.compensation[static_cast<size_t>(o)] = 128 * sum;
  }
  pack_weights(
      kernels, o_count, taps, in,
      [&](std::int64_t n, std::int64_t t, std::int64_t c) {
        return out.q[static_cast<size_t>((n * in + c) * taps + t)];
      },
      out.packed);
}

void prepare_int8_conv_transpose(Int8Kernels kernels, const Ref& w, const Ref& bias,
                                 Int8ConvWeights& out) {
  const char* op = "prepare_int8_conv_transpose";
  require_rank(op, "w", w, 4);
  const std::int64_t in = w.dim(0), o_count = w.dim(1);
  PS_CHECK(w.dim(2) == 2 && w.dim(3) == 2, "{}: w must be (I, O, 2, 2), got {}", op,
           shape_str(w.shape));
  require_shape(op, "bias", bias, {o_count});
  require_finite(op, w, "w");
  require_finite(op, bias, "bias");
  out.packed_for = int8_amx_family(kernels) ? Int8Kernels::Amx : Int8Kernels::Vnni;
  out.weight = w.shape, out.transposed = true, out.columns = 4 * o_count;
  out.q.assign(static_cast<size_t>(w.numel()), 0);
  // Output channel o's weights: w[i][o][s] for every input channel i and sub-pixel s.
  quantize_weights(
      w.data, o_count, 4 * in,
      [&](std::int64_t o, std::int64_t j) { return ((j / 4) * o_count + o) * 4 + j % 4; },
      out.scale, out.q);
  out.bias.resize(static_cast<size_t>(4 * o_count));
  out.compensation.assign(static_cast<size_t>(4 * o_count), 0);
  for (std::int64_t n = 0; n < 4 * o_count; ++n) {
    const std::int64_t o = n / 4, s = n % 4;
    out.bias[static_cast<size_t>(n)] = bias.data[o];
    std::int32_t sum = 0;
    for (std::int64_t i = 0; i < in; ++i)
      sum += out.q[static_cast<size_t>((i * o_count + o) * 4 + s)];
    out.compensation[static_cast<size_t>(n)] = 128 * sum;
  }
  pack_weights(
      kernels, 4 * o_count, 1, in,
      [&](std::int64_t n, std::int64_t, std::int64_t c) {
        return out.q[static_cast<size_t>((c * o_count + n / 4) * 4 + n % 4)];
      },
      out.packed);
}

namespace {

// Whether `kernels` run the native instructions (checked here) rather than their models.
bool native(Int8Kernels kernels) {
  if (kernels == Int8Kernels::Emulated || kernels == Int8Kernels::AmxEmulated) return false;
  std::string why;
  if (kernels == Int8Kernels::Amx) {
    PS_CHECK(amx_int8_available(&why), "INT8 convolutions on AMX tiles: {}", why);
  } else {
    PS_CHECK(avx512_vnni_available(&why), "INT8 convolutions on the CPU: {}", why);
  }
  return true;
}

void require_activation(const char* op, const char* what, const ActRef& r) {
  PS_CHECK(r.shape.size() == 4, "{}: {} must be (B, C, H, W), got {}", op, what,
           shape_str(r.shape));
  PS_CHECK(r.data != nullptr || r.numel() == 0, "{}: {} has no memory", op, what);
}

// The quantization's fields for x (`pad` columns and rows of padding around it: u = 128, or 0 for
// a non-negative input) and the GEMM's input fields.
Int8Quantize input_layout(Int8Kernels kernels, const ActRef& x, float sx, bool non_negative,
                          int pad, Int8Gemm& g) {
  Int8Quantize q;
  q.x = x.data, q.x_bf16 = x.half;
  q.channels = x.dim(1), q.height = x.dim(2), q.width = x.dim(3);
  q.reciprocal = 1.0f / sx;
  q.non_negative = non_negative;
  q.pad = pad;
  q.quads = int8_quads(kernels, q.channels);
  // Rows of whole cache lines (16 quads), so that a tap with kx = 0 loads aligned.
  q.padded_height = q.height + 2 * pad, q.padded_width = int8_round_up(q.width + 2 * pad, 16);
  g.quad_stride = q.padded_width * 4;
  g.row_stride = q.quads * g.quad_stride;
  g.batch_stride = q.padded_height * g.row_stride;
  g.quads = q.quads;
  g.sx = sx;
  g.batch = x.dim(0);
  return q;
}

// The reference pixel of the idle windows (int8_microkernel.hpp): of the four pixels 8 rows and
// columns in from the image's corners (or its last row or column where it has fewer), the one
// whose quads most of the pixels sampled along its row share. In a BEV grid centred on the sensor
// the corners are the far ends of the area, empty in most scans, though not all four in every
// one (the real SemanticKITTI scan in ../shared has points near one), and 8 pixels in, the first
// layers' outputs there are not those of the border (whose padding changes them).
constexpr std::int64_t kInt8ReferenceInset = 8;
// Pixels of a candidate's row sampled to judge it.
constexpr std::int64_t kInt8IdleSamples = 64;

// Pixel (row, col) of image b: its channel quad cq's four u bytes as one dword (byte i: channel 4
// cq + i; the padding's u past the channels).
std::uint32_t quad_at(const ActRef& x, const Int8Quantize& q, std::int64_t b, std::int64_t cq,
                      std::int64_t row, std::int64_t col) {
  std::uint32_t quad = 0;
  for (std::int64_t i = 0; i < 4; ++i) {
    const std::int64_t c = 4 * cq + i;
    std::uint32_t code = q.non_negative ? 0u : 128u;
    if (c < q.channels) {
      const std::int64_t at = ((b * q.channels + c) * q.height + row) * q.width + col;
      const float v =
          x.half ? weights::bf16_bits_to_float(static_cast<const std::uint16_t*>(x.data)[at])
                 : static_cast<const float*>(x.data)[at];
      code = q.non_negative ? quantize_uint8(v, q.reciprocal)
                            : static_cast<std::uint32_t>(quantize_int8(v, q.reciprocal) + 128);
    }
    quad |= code << (8 * i);
  }
  return quad;
}

// The idle windows' set-up, into the workspace and the fields of q and g: each image's reference
// quads; the leading quads most of whose sampled reference-row pixels equal the reference's
// (idle_quads: every quad of a scan's canvas, the canvas's of the first up-sampling block's
// concatenation, none of a layer deep in the U-Net, which then keeps no busy bits), a multiple of
// 16 on the AMX family (its quad block); whether each image's padding differs from its reference
// in them; and the idle accumulators idle[b][n] = sum over (tap, channel c < 4 idle_quads) of
// u_ref[c] qw(n, tap, c).
template <class Qw>
void idle_windows(Int8Kernels kernels, const ActRef& x, Int8Quantize& q, Int8Gemm& g,
                  std::int64_t columns, int taps, Qw&& qw, Int8ConvWorkspace& workspace) {
  const std::int64_t batch = x.dim(0);
  q.idle_quads = g.idle_quads = 0;
  if (q.height == 0 || q.width == 0) return;  // an empty input padded to a non-empty output
  const std::int64_t ry = std::min(kInt8ReferenceInset, q.height - 1);
  const std::int64_t rx = std::min(kInt8ReferenceInset, q.width - 1);
  const std::int64_t rows[4] = {ry, ry, q.height - 1 - ry, q.height - 1 - ry};
  const std::int64_t cols[4] = {rx, q.width - 1 - rx, rx, q.width - 1 - rx};
  const std::int64_t samples = std::min(kInt8IdleSamples, q.width);
  workspace.reference.resize(static_cast<size_t>(batch * q.quads));
  std::int64_t idle_quads = q.quads;
  for (std::int64_t b = 0; b < batch; ++b) {
    // Each candidate's leading quads shared by at least half the samples, and its matches in them.
    int best = 0;
    std::int64_t best_quads = -1, best_matches = -1;
    for (int k = 0; k < 4; ++k) {
      std::int64_t shared = 0, matches = 0;
      for (; shared < q.quads; ++shared) {
        const std::uint32_t reference = quad_at(x, q, b, shared, rows[k], cols[k]);
        std::int64_t equal = 0;
        for (std::int64_t j = 0; j < samples; ++j)
          equal += quad_at(x, q, b, shared, rows[k], j * q.width / samples) == reference ? 1 : 0;
        if (2 * equal < samples) break;
        matches += equal;
      }
      if (shared > best_quads || (shared == best_quads && matches > best_matches))
        best = k, best_quads = shared, best_matches = matches;
    }
    std::uint32_t* reference = workspace.reference.data() + b * q.quads;
    for (std::int64_t cq = 0; cq < q.quads; ++cq)
      reference[cq] = quad_at(x, q, b, cq, rows[best], cols[best]);
    idle_quads = std::min(idle_quads, best_quads);
  }
  if (int8_amx_family(kernels)) idle_quads = idle_quads / kInt8AmxQuads * kInt8AmxQuads;
  q.idle_quads = g.idle_quads = idle_quads;
  if (idle_quads == 0) return;
  const std::uint32_t padding = q.non_negative ? 0u : 0x80808080u;
  workspace.padding_busy.assign(static_cast<size_t>(batch), 0);
  workspace.idle.assign(static_cast<size_t>(batch * columns), 0);
  const std::int64_t idle_channels = std::min(4 * idle_quads, q.channels);
  for (std::int64_t b = 0; b < batch; ++b) {
    const std::uint32_t* reference = workspace.reference.data() + b * q.quads;
    for (std::int64_t cq = 0; cq < idle_quads; ++cq) {
      if (reference[cq] != padding) workspace.padding_busy[static_cast<size_t>(b)] = 1;
    }
    for (std::int64_t n = 0; n < columns; ++n) {
      std::int64_t sum = 0;
      for (int t = 0; t < taps; ++t) {
        for (std::int64_t c = 0; c < idle_channels; ++c) {
          const auto u = static_cast<std::int64_t>((reference[c / 4] >> (8 * (c % 4))) & 0xFFu);
          sum += u * qw(n, t, c);
        }
      }
      // Wrapped to 32 bits as the accumulators wrap.
      workspace.idle[static_cast<size_t>(b * columns + n)] =
          static_cast<std::int32_t>(static_cast<std::uint32_t>(static_cast<std::uint64_t>(sum)));
    }
  }
  q.reference = workspace.reference.data(), q.padding_busy = workspace.padding_busy.data();
  g.idle = workspace.idle.data();
}

// Padded input rows [begin, end) (r = b Hp + padded row) into q.xq.
void quantize([[maybe_unused]] bool on_native, const Int8Quantize& q, std::int64_t begin,
              std::int64_t end) {
#if defined(PILLARSEG_HAVE_AVX512_VNNI_KERNELS)
  if (on_native) {
    int8_quantize_rows_avx512(q, begin, end);
    return;
  }
#endif
  quantize_rows<EmulatedVnniIsa>(q, begin, end);
}

// The products and the epilogue of output rows [row_begin, row_end) of image b.
void gemm_band(Int8Kernels kernels, [[maybe_unused]] bool on_native, const Int8Gemm& g,
               std::int64_t b, std::int64_t row_begin, std::int64_t row_end) {
  const bool amx = int8_amx_family(kernels);
#if defined(PILLARSEG_HAVE_AMX_INT8_KERNELS)
  if (on_native && amx) {
    int8_gemm_band_amx(g, b, row_begin, row_end);
    return;
  }
#endif
#if defined(PILLARSEG_HAVE_AVX512_VNNI_KERNELS)
  if (on_native && !amx) {
    int8_gemm_band_vnni(g, b, row_begin, row_end);
    return;
  }
#endif
  if (amx) {
    amx_band<EmulatedVnniIsa, EmulatedAmxInt8Tiles>(g, b, row_begin, row_end);
  } else {
    vnni_band<EmulatedVnniIsa>(g, b, row_begin, row_end);
  }
}

// Quantized input rows a thread holds for one band: about half of a core's L2 cache (2 MiB on
// Sapphire Rapids), the rest left to a column group's weights and the outputs.
constexpr std::int64_t kInt8BandBytes = std::int64_t{1} << 20;

// The convolution, whose output row `row` reads the padded input rows [row, row + reach) (reach =
// kh; 1 for the transposed one, whose rows are input rows). Each thread takes a contiguous run of
// the (image, output row) pairs and walks it in bands of rows whose input fits kInt8BandBytes: it
// quantizes the band's input rows into its own slice of the workspace, then runs the band's
// products while they are still in its cache. The reach - 1 rows the next band shares are moved
// to the slice's front instead of being quantized again.
void run_conv(Int8Kernels kernels, bool on_native, const Int8Quantize& q, const Int8Gemm& g,
              std::int64_t reach, Int8ConvWorkspace& workspace) {
  const std::int64_t row_bytes = g.row_stride;
  const std::int64_t band = std::max<std::int64_t>(kInt8BandBytes / row_bytes - (reach - 1), 1);
  const std::int64_t slice = int8_round_up((band + reach - 1) * row_bytes + kInt8Slack, 64);
  const int threads = std::max(num_threads(), 1);
  if (workspace.x.size() < static_cast<size_t>(threads * slice))
    workspace.x.resize(static_cast<size_t>(threads * slice));
  const std::int64_t busy_words = int8_busy_words(q.padded_width);
  const std::int64_t busy_slice = (band + reach - 1) * busy_words;
  if (workspace.busy.size() < static_cast<size_t>(threads * busy_slice))
    workspace.busy.resize(static_cast<size_t>(threads * busy_slice));
  parallel_chunks(g.batch * g.rows, [&](std::int64_t begin, std::int64_t end, int thread) {
    std::uint8_t* buffer = workspace.x.data() + thread * slice;
    std::uint64_t* busy = workspace.busy.data() + thread * busy_slice;
    Int8Quantize band_q = q;
    Int8Gemm band_g = g;
    band_q.xq = buffer, band_g.xq = buffer;
    if (q.idle_quads > 0) band_q.busy = busy, band_g.busy = busy;
    band_q.busy_words = band_g.busy_words = busy_words;
    band_g.padded_height = q.padded_height;
    std::int64_t held_first = 0, held_end = 0;  // the input rows in the buffer (r = b Hp + row)
    for (std::int64_t at = begin; at < end;) {
      const std::int64_t b = at / g.rows, row = at % g.rows;
      const std::int64_t rows = std::min({band, g.rows - row, end - at});
      const std::int64_t first = b * q.padded_height + row, last = first + rows + reach - 1;
      std::int64_t from = first;
      if (held_first < first && first < held_end) {  // the same image's next band
        std::memmove(buffer, buffer + (first - held_first) * row_bytes,
                     static_cast<size_t>((held_end - first) * row_bytes));
        if (band_q.busy != nullptr)
          std::memmove(
              busy, busy + (first - held_first) * busy_words,
              static_cast<size_t>((held_end - first) * busy_words) * sizeof(std::uint64_t));
        from = held_end;
      }
      band_q.origin = band_g.origin = first * row_bytes;
      band_q.busy_origin = band_g.busy_origin = first;
      quantize(on_native, band_q, from, last);
      gemm_band(kernels, on_native, band_g, b, row, row + rows);
      held_first = first, held_end = last;
      at += rows;
    }
  });
}

void check_common(const char* op, Int8Kernels kernels, const ActRef& x, float sx,
                  const Int8ConvWeights& w, const ActRef& y) {
  require_activation(op, "x", x);
  require_activation(op, "y", y);
  PS_CHECK(std::isfinite(sx) && sx > 0.0f && std::isfinite(1.0f / sx),
           "{}: the input scale must be positive and finite with a finite reciprocal, got {}", op,
           sx);
  PS_CHECK(int8_amx_family(kernels) == int8_amx_family(w.packed_for),
           "{}: the weights were packed for {}, not for {}: prepare them for the kernels that run",
           op, int8_kernels_name(w.packed_for), int8_kernels_name(kernels));
}

// The weights' fields; the compensation only for the shifted (signed) input.
void fill_weights(const Int8ConvWeights& w, bool non_negative, Int8Gemm& g) {
  g.w = w.packed.data();
  g.columns = w.columns;
  g.sw = w.scale.data();
  g.bias = w.bias.data();
  g.compensation = non_negative ? nullptr : w.compensation.data();
}

}  // namespace

void int8_conv2d_forward(Int8Kernels kernels, const ActRef& x, float sx, bool non_negative,
                         const Int8ConvWeights& w, int pad, bool relu, const ActRef& y,
                         Int8ConvWorkspace& workspace) {
  const char* op = "int8_conv2d_forward";
  check_common(op, kernels, x, sx, w, y);
  PS_CHECK(!w.transposed, "{}: the weights are a transposed convolution's", op);
  const Shape y_shape = op::conv2d(x.shape, w.weight, pad, nullptr, op);
  PS_CHECK(y.shape == y_shape, "{}: y must be {}, got {}", op, shape_str(y_shape),
           shape_str(y.shape));
  const bool on_native = native(kernels);
  Int8Gemm g;
  Int8Quantize q = input_layout(kernels, x, sx, non_negative, pad, g);
  const std::int64_t kh = w.weight[2], kw = w.weight[3];
  g.taps = static_cast<int>(kh * kw);
  g.window_rows = kh, g.window_cols = kw;
  const std::int64_t in = w.weight[1];
  for (std::int64_t ky = 0; ky < kh; ++ky) {
    for (std::int64_t kx = 0; kx < kw; ++kx)
      g.tap_offsets[ky * kw + kx] = ky * g.row_stride + 4 * kx;
  }
  fill_weights(w, non_negative, g);
  g.relu = relu, g.transposed = false;
  g.y = y.data, g.y_bf16 = y.half;
  g.rows = y_shape[2], g.row_pixels = y_shape[3];
  g.out_height = y_shape[2], g.out_width = y_shape[3], g.out_planes = y_shape[1];
  if (y.numel() == 0) return;
  idle_windows(
      kernels, x, q, g, w.columns, g.taps,
      [&](std::int64_t n, int t, std::int64_t c) {
        return w.q[static_cast<size_t>((n * in + c) * g.taps + t)];
      },
      workspace);
  run_conv(kernels, on_native, q, g, kh, workspace);
}

void int8_conv_transpose2d_forward(Int8Kernels kernels, const ActRef& x, float sx,
                                   bool non_negative, const Int8ConvWeights& w, const ActRef& y,
                                   Int8ConvWorkspace& workspace) {
  const char* op = "int8_conv_transpose2d_forward";
  check_common(op, kernels, x, sx, w, y);
  PS_CHECK(w.transposed, "{}: the weights are a plain convolution's", op);
  const Shape y_shape = op::conv_transpose2d(x.shape, w.weight, nullptr, op);
  PS_CHECK(y.shape == y_shape, "{}: y must be {}, got {}", op, shape_str(y_shape),
           shape_str(y.shape));
  const bool on_native = native(kernels);
  Int8Gemm g;
  Int8Quantize q = input_layout(kernels, x, sx, non_negative, 0, g);
  g.taps = 1;
  g.tap_offsets[0] = 0;
  fill_weights(w, non_negative, g);
  g.relu = false, g.transposed = true;
  g.y = y.data, g.y_bf16 = y.half;
  g.rows = x.dim(2), g.row_pixels = x.dim(3);
  g.out_height = y_shape[2], g.out_width = y_shape[3], g.out_planes = y_shape[1];
  if (y.numel() == 0) return;
  const std::int64_t out_channels = w.weight[1];
  idle_windows(
      kernels, x, q, g, w.columns, 1,
      [&](std::int64_t n, int, std::int64_t c) {
        return w.q[static_cast<size_t>((c * out_channels + n / 4) * 4 + n % 4)];
      },
      workspace);
  run_conv(kernels, on_native, q, g, 1, workspace);
}

void prepare_int8_winograd(const Ref& w, const Ref& bias, Int8WinogradWeights& out) {
  const char* op = "prepare_int8_winograd";
  require_shape(op, "w", w, {w.dim(0), w.dim(1), 3, 3});
  const std::int64_t o_count = w.dim(0), in = w.dim(1);
  require_shape(op, "bias", bias, {o_count});
  require_finite(op, w, "w");
  require_finite(op, bias, "bias");
  out.weight = w.shape;
  std::vector<double> u(static_cast<size_t>(16 * o_count * in));  // (16, O, I)
  parallel_for(o_count, [&](std::int64_t o) {
    for (std::int64_t c = 0; c < in; ++c) {
      const float* g = w.data + (o * in + c) * 9;
      double gg[4][3];  // G g
      for (int b = 0; b < 3; ++b) {
        gg[0][b] = g[b];
        gg[1][b] = 0.5 * (static_cast<double>(g[b]) + g[3 + b] + g[6 + b]);
        gg[2][b] = 0.5 * (static_cast<double>(g[b]) - g[3 + b] + g[6 + b]);
        gg[3][b] = g[6 + b];
      }
      for (int i = 0; i < 4; ++i) {
        const double row[4] = {gg[i][0], 0.5 * (gg[i][0] + gg[i][1] + gg[i][2]),
                               0.5 * (gg[i][0] - gg[i][1] + gg[i][2]), gg[i][2]};
        for (int j = 0; j < 4; ++j)
          u[static_cast<size_t>(((4 * i + j) * o_count + o) * in + c)] = row[j];
      }
    }
  });
  const std::int64_t groups = (o_count + kInt8GroupColumns - 1) / kInt8GroupColumns;
  const std::int64_t o_padded = groups * kInt8GroupColumns, quads = (in + 3) / 4;
  out.q.assign(u.size(), 0);
  out.scale.assign(static_cast<size_t>(16 * o_count), 0.0f);
  out.compensation.assign(static_cast<size_t>(16 * o_padded), 0);
  out.packed.assign(static_cast<size_t>(16 * o_padded * quads * 4), 0);
  for (std::int64_t row = 0; row < 16 * o_count; ++row) {  // row = p O + o
    const std::int64_t p = row / o_count, o = row % o_count;
    const double* ur = u.data() + row * in;
    double max_abs = 0.0;
    for (std::int64_t c = 0; c < in; ++c) max_abs = std::max(max_abs, std::abs(ur[c]));
    const float s = static_cast<float>(max_abs / 127.0);
    out.scale[static_cast<size_t>(row)] = s;
    std::int32_t sum = 0;
    for (std::int64_t c = 0; c < in; ++c) {
      const auto q = static_cast<std::int8_t>(
          s > 0.0f ? std::clamp(std::nearbyint(ur[c] / s), -127.0, 127.0) : 0.0);
      out.q[static_cast<size_t>(row * in + c)] = q;
      sum += q;
      out.packed[static_cast<size_t>(
          (((p * groups + o / kInt8GroupColumns) * quads + c / 4) * kInt8GroupColumns +
           o % kInt8GroupColumns) *
              4 +
          c % 4)] = q;
    }
    out.compensation[static_cast<size_t>(p * o_padded + o)] = 128 * sum;
  }
  out.bias.assign(bias.data, bias.data + o_count);
}

Int8WinogradInputScales int8_winograd_input_scales(const float* sv) {
  const float largest = *std::max_element(sv, sv + 16), smallest = *std::min_element(sv, sv + 16);
  const float s16 = std::min(largest / 64.0f, smallest);
  Int8WinogradInputScales out;
  out.r16 = 1.0f / s16;
  for (int p = 0; p < 16; ++p) {
    const double m = std::clamp(std::nearbyint(32768.0 * s16 / sv[p]), 1.0, 32767.0);
    out.multiplier[p] = static_cast<std::int16_t>(m);
    out.sv_eff[p] = static_cast<float>(32768.0 * s16 / m);
  }
  return out;
}

void int8_winograd_forward(Int8Kernels kernels, const ActRef& x, const float* sv,
                           const Int8WinogradWeights& w, bool relu, const ActRef& y,
                           Int8WinogradWorkspace& workspace) {
  const char* op = "int8_winograd_forward";
  require_activation(op, "x", x);
  require_activation(op, "y", y);
  PS_CHECK(!int8_amx_family(kernels), "{}: runs on avx512_vnni or its model, not {}", op,
           int8_kernels_name(kernels));
  const Shape y_shape = op::conv2d(x.shape, w.weight, 1, nullptr, op);
  PS_CHECK(y.shape == y_shape, "{}: y must be {}, got {}", op, shape_str(y_shape),
           shape_str(y.shape));
  for (int p = 0; p < 16; ++p) {
    PS_CHECK(std::isfinite(sv[p]) && sv[p] > 0.0f && std::isfinite(1.0f / sv[p]),
             "{}: the input scale of position {} must be positive and finite, got {}", op, p,
             sv[p]);
  }
  const Int8WinogradInputScales scales = int8_winograd_input_scales(sv);
  const bool on_native = native(kernels);
  Int8Winograd g;
  g.x = x.data, g.x_bf16 = x.half;
  g.batch = x.dim(0), g.channels = x.dim(1), g.height = x.dim(2), g.width = x.dim(3);
  g.r16 = scales.r16, g.multiplier = scales.multiplier, g.sv = scales.sv_eff;
  g.quads = (g.channels + 3) / 4;
  g.u = w.packed.data(), g.su = w.scale.data(), g.compensation = w.compensation.data();
  g.bias = w.bias.data();
  g.out_channels = w.weight[0];
  g.column_groups = (g.out_channels + kInt8GroupColumns - 1) / kInt8GroupColumns;
  g.relu = relu, g.y = y.data, g.y_bf16 = y.half;
  g.tiles_h = (g.height + 1) / 2, g.tiles_w = (g.width + 1) / 2;
  // Blocks whose V (64 quads bytes a tile) stays within 512 KiB of a core's L2, a multiple of 16
  // tiles, at most a tile row.
  const std::int64_t fit = (512 << 10) / (64 * g.quads) / 16 * 16;
  g.block_tiles = std::min(std::max<std::int64_t>(fit, 16), int8_round_up(g.tiles_w, 16));
  g.blocks_per_row = (g.tiles_w + g.block_tiles - 1) / g.block_tiles;
  const int threads = std::max(num_threads(), 1);
  g.v_stride = 16 * g.quads * g.block_tiles * 4;
  g.m_stride = 16 * kInt8GroupColumns * kInt8WinogradGroupTiles;
  g.x16_tiles = int8_round_up(g.block_tiles, 32) + 32;
  g.x16_stride = 4 * 4 * 2 * g.x16_tiles;  // 4 channels x 4 rows x (even, odd), 64-byte multiple
  if (workspace.v.size() < static_cast<size_t>(threads * g.v_stride))
    workspace.v.resize(static_cast<size_t>(threads * g.v_stride));
  if (workspace.m.size() < static_cast<size_t>(threads * g.m_stride))
    workspace.m.resize(static_cast<size_t>(threads * g.m_stride));
  if (workspace.x16.size() < static_cast<size_t>(threads * g.x16_stride))
    workspace.x16.resize(static_cast<size_t>(threads * g.x16_stride));
  g.v = workspace.v.data(), g.m = workspace.m.data(), g.x16 = workspace.x16.data();
  if (y.numel() == 0) return;
  parallel_chunks(g.batch * g.tiles_h * g.blocks_per_row,
                  [&](std::int64_t begin, std::int64_t end, int thread) {
#if defined(PILLARSEG_HAVE_AVX512_VNNI_KERNELS)
                    if (on_native) {
                      int8_winograd_blocks_vnni(g, begin, end, thread);
                      return;
                    }
#endif
                    int8_winograd_blocks<EmulatedVnniIsa>(g, begin, end, thread);
                  });
}

void int8_winograd_input_absmax(const ActRef& x, float* absmax) {
  require_activation("int8_winograd_input_absmax", "x", x);
  // The transform and its order are host/winograd_f2_stats's (the calibration's); BF16 widens to
  // FP32 exactly, so the maxima are those of the values the kernel transforms.
  std::vector<float> widened;
  const float* values = static_cast<const float*>(x.data);
  if (x.half) {
    const auto* bits = static_cast<const std::uint16_t*>(x.data);
    widened.resize(static_cast<size_t>(x.numel()));
    parallel_for(x.numel(), [&](std::int64_t i) {
      widened[static_cast<size_t>(i)] = weights::bf16_bits_to_float(bits[i]);
    });
    values = widened.data();
  }
  const std::array<float, 16> maxima = host::winograd_f2_input_absmax(values, x.shape);
  std::copy(maxima.begin(), maxima.end(), absmax);
}

}  // namespace pillarseg::cpu
