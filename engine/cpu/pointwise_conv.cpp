// The 1 x 1 FP32 convolution of pointwise_conv.hpp: per block of pixels, the block's inputs
// widened once into an FP32 panel of the thread (I x kBlock, in L2: the loads of a channel run
// along kBlock contiguous pixels, which the prefetchers follow), then register tiles of kTileOut
// outputs x kTilePixels pixels summed over the input channels, written with the bias and the
// activation.
#include "engine/cpu/pointwise_conv.hpp"

#include <algorithm>
#include <vector>

#include "core/error.hpp"
#include "core/ops.hpp"
#include "core/parallel.hpp"
#include "weights_io/half.hpp"

namespace pillarseg::cpu {
namespace {

constexpr int64_t kBlock = 512;  // pixels a panel holds
constexpr int kTilePixels = 32;  // two AVX-512 vectors of FP32
constexpr int kTileOut = 6;      // outputs a tile sums at once (12 accumulator vectors)

// The panel's pixels [0, n) of every input channel, FP32, zero beyond n.
template <class In>
void widen_panel(const In* x, int64_t channels, int64_t plane, int64_t n, float* panel) {
  for (int64_t c = 0; c < channels; ++c) {
    const In* src = x + c * plane;
    float* dst = panel + c * kBlock;
    if constexpr (std::is_same_v<In, float>) {
      std::copy_n(src, n, dst);
    } else {
      for (int64_t p = 0; p < n; ++p) dst[p] = weights::bf16_bits_to_float(src[p]);
    }
    std::fill(dst + n, dst + kBlock, 0.0f);
  }
}

template <class Out>
void store(float v, bool relu, Out* y) {
  if (relu) v = v > 0.0f ? v : 0.0f;
  if constexpr (std::is_same_v<Out, float>) {
    *y = v;
  } else {
    *y = weights::float_to_bf16_bits(v);
  }
}

// Outputs [o0, o0 + kOut) of the panel's pixels [p0, p0 + kTilePixels) (those before n) into y
// (at the panel's first pixel of plane 0; planes `plane` apart).
template <int kOut, class Out>
void tile(const float* panel, const float* w, const float* bias, int64_t channels, int64_t o0, int64_t p0,
          int64_t n, int64_t plane, bool relu, Out* y) {
  float acc[kOut][kTilePixels] = {};
  for (int64_t c = 0; c < channels; ++c) {
    const float* xr = panel + c * kBlock + p0;
    for (int j = 0; j < kOut; ++j) {
      const float wv = w[(o0 + j) * channels + c];
      for (int q = 0; q < kTilePixels; ++q) acc[j][q] += wv * xr[q];
    }
  }
  const int64_t valid = std::min<int64_t>(kTilePixels, n - p0);
  for (int j = 0; j < kOut; ++j) {
    Out* out = y + (o0 + j) * plane + p0;
    const float b = bias[o0 + j];
    if (valid == kTilePixels) {
      for (int q = 0; q < kTilePixels; ++q) store(acc[j][q] + b, relu, out + q);
    } else {
      for (int64_t q = 0; q < valid; ++q) store(acc[j][q] + b, relu, out + q);
    }
  }
}

template <class In, class Out>
void run(const In* x, const float* w, const float* bias, int64_t batch, int64_t in_channels, int64_t out_channels,
         int64_t plane, bool relu, Out* y) {
  const int64_t blocks = (plane + kBlock - 1) / kBlock;
  const int threads = std::max(num_threads(), 1);
  std::vector<float> panels(static_cast<size_t>(threads * in_channels * kBlock));
  parallel_chunks(batch * blocks, [&](int64_t begin, int64_t end, int thread) {
    float* panel = panels.data() + static_cast<int64_t>(thread) * in_channels * kBlock;
    for (int64_t item = begin; item < end; ++item) {
      const int64_t b = item / blocks, first = (item % blocks) * kBlock, n = std::min(kBlock, plane - first);
      widen_panel(x + b * in_channels * plane + first, in_channels, plane, n, panel);
      Out* out = y + b * out_channels * plane + first;
      for (int64_t p0 = 0; p0 < n; p0 += kTilePixels) {
        int64_t o0 = 0;
        for (; o0 + kTileOut <= out_channels; o0 += kTileOut)
          tile<kTileOut>(panel, w, bias, in_channels, o0, p0, n, plane, relu, out);
        for (; o0 < out_channels; ++o0) tile<1>(panel, w, bias, in_channels, o0, p0, n, plane, relu, out);
      }
    }
  });
}

}  // namespace

void pointwise_conv_forward(const char* op, const TensorRef& x, const Ref& w, const Ref& bias, bool relu,
                            const TensorRef& y) {
  PS_CHECK(x.shape.size() == 4, "{}: x must be (B, I, H, W), got {}", op, shape_str(x.shape));
  PS_CHECK(w.shape.size() == 4 && w.dim(1) == x.dim(1) && w.dim(2) == 1 && w.dim(3) == 1,
           "{}: a 1 x 1 convolution of x {} needs w ({}, {}, 1, 1)-shaped, got {}", op, shape_str(x.shape),
           w.shape.empty() ? 0 : w.dim(0), x.dim(1), shape_str(w.shape));
  require_shape(op, "bias", bias, {w.dim(0)});
  const Shape y_shape = op::conv2d(x.shape, w.shape, 0, nullptr, op);
  PS_CHECK(y.shape == y_shape, "{}: y must be {}, got {}", op, shape_str(y_shape), shape_str(y.shape));
  const auto width_ok = [](DType d) { return d == DType::F32 || d == DType::BF16; };
  PS_CHECK(width_ok(x.dtype) && width_ok(y.dtype), "{}: FP32 arithmetic takes f32 or bf16 x and y, got {} and {}",
           op, dtype_name(x.dtype), dtype_name(y.dtype));
  const int64_t batch = x.dim(0), in = x.dim(1), out = w.dim(0), plane = x.dim(2) * x.dim(3);
  const auto with_out = [&](const auto* in_data) {
    if (y.dtype == DType::F32) {
      run(in_data, w.data, bias.data, batch, in, out, plane, relu, static_cast<float*>(y.data));
    } else {
      run(in_data, w.data, bias.data, batch, in, out, plane, relu, static_cast<uint16_t*>(y.data));
    }
  };
  if (x.dtype == DType::F32) {
    with_out(static_cast<const float*>(x.data));
  } else {
    with_out(static_cast<const uint16_t*>(x.data));
  }
}

}  // namespace pillarseg::cpu
