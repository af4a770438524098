// The CPU's 16-bit data movement (half_ops.hpp): threads over channels or rows, each op the
// arithmetic of its kernel in kernels/half_ops.cu; the max-pool, upsampling and scatter also on
// AVX-512 (half_ops_avx512.hpp), whose work this file lays out and shares among the threads.
#include "engine/cpu/half_ops.hpp"

#include <algorithm>
#include <memory>
#include <string>
#include <type_traits>
#include <vector>

#include "core/bilinear_taps.hpp"
#include "core/error.hpp"
#include "core/ops.hpp"
#include "core/parallel.hpp"
#include "engine/cpu/cpu_features.hpp"
#include "engine/cpu/half_ops_avx512.hpp"
#include "weights_io/half.hpp"

namespace pillarseg::cpu {

std::uint16_t to_bits(float v, Precision p) {
  return p == Precision::BF16 ? weights::float_to_bf16_bits(v) : weights::float_to_f16_bits(v);
}

void require_half(const char* op, Precision p) {
  PS_CHECK(p == Precision::BF16 || p == Precision::F16,
           "{}: 16-bit activations need bf16 or fp16, got {}", op, precision_name(p));
}

namespace {

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

// Whether a pillar's cell (sample, iy, ix) lies on a (batch, ., height, width) canvas.
bool on_canvas(const std::int32_t* cell, std::int64_t batch, std::int64_t height, std::int64_t width) {
  return cell[0] >= 0 && cell[0] < batch && cell[1] >= 0 && cell[1] < height && cell[2] >= 0 &&
         cell[2] < width;
}

// Whether `kernels` runs the AVX-512 forms; asking for them where they cannot run is an error.
bool on_avx512(HalfOpsKernels kernels, const char* op) {
  if (kernels == HalfOpsKernels::Scalar) return false;
  std::string why;
  PS_CHECK(avx512_half_ops_available(&why), "{}: the AVX-512 kernels cannot run here: {}", op, why);
  return true;
}

// The AVX-512 forms' work laid out and shared among the threads (half_ops_avx512.hpp).
#if defined(PILLARSEG_HAVE_AVX512_HALF_OPS)
// Cells of a scatter tile on AVX-512: each tile of a plane (2 KiB) is zeroed, then written while
// in L1.
constexpr std::int64_t kScatterTile = 1024;

void scatter_avx512(const Ref& features, const IRef& cells, int channel0, Precision p, HRef& canvas) {
  const std::int64_t batch = canvas.dim(0), channels = canvas.dim(1), height = canvas.dim(2),
                     width = canvas.dim(3), plane = height * width, c_band = features.dim(1);
  const std::int64_t rows = features.dim(0);
  const auto inside = [&](const std::int32_t* cell) { return on_canvas(cell, batch, height, width); };
  // The rows on each tile of kScatterTile cells of a sample's planes, listed in row order (a
  // stable counting sort), so that the later row's values win at a cell named twice.
  const std::int64_t tiles_per_plane = (plane + kScatterTile - 1) / kScatterTile,
                     tiles = batch * tiles_per_plane;
  std::vector<std::int64_t> start(static_cast<size_t>(tiles + 1), 0);
  const auto tile_of = [&](const std::int32_t* cell) {
    return cell[0] * tiles_per_plane + (cell[1] * width + cell[2]) / kScatterTile;
  };
  for (std::int64_t r = 0; r < rows; ++r) {
    const std::int32_t* cell = cells.data + 3 * r;
    if (inside(cell)) ++start[static_cast<size_t>(tile_of(cell) + 1)];
  }
  for (std::int64_t t = 0; t < tiles; ++t) start[static_cast<size_t>(t + 1)] += start[static_cast<size_t>(t)];
  std::vector<std::int64_t> next(start.begin(), start.end() - 1);
  std::vector<std::int64_t> listed_rows(static_cast<size_t>(start.back()));
  std::vector<std::int32_t> listed_cells(listed_rows.size());
  for (std::int64_t r = 0; r < rows; ++r) {
    const std::int32_t* cell = cells.data + 3 * r;
    if (!inside(cell)) continue;
    const std::int64_t t = tile_of(cell), at = next[static_cast<size_t>(t)]++;
    listed_rows[static_cast<size_t>(at)] = r;
    listed_cells[static_cast<size_t>(at)] =
        static_cast<std::int32_t>((cell[1] * width + cell[2]) % kScatterTile);
  }
  // The listed pillars' features as 16-bit columns, one a channel; then each (sample, channel)
  // plane written front to back by one thread, from its column. The columns lie a cache line
  // more than a multiple of 64 bytes apart, so that a pillar's words fall in different L1 sets.
  const std::int64_t listed = start.back(), stride = (listed + 31) / 32 * 32 + 32;
  const auto columns = std::make_unique_for_overwrite<std::uint16_t[]>(static_cast<size_t>(c_band * stride));
  parallel_chunks(listed, [&](std::int64_t begin, std::int64_t end, int) {
    scatter_columns_half_avx512(features.data, c_band, listed_rows.data() + begin, end - begin,
                                p == Precision::BF16, stride, columns.get() + begin);
  });
  parallel_for(batch * c_band, [&](std::int64_t item) {
    const std::int64_t b = item / c_band, c = item % c_band;
    scatter_plane_half_avx512(columns.get() + c * stride, listed_cells.data(),
                              start.data() + b * tiles_per_plane, tiles_per_plane, kScatterTile, plane,
                              canvas.data + (b * channels + channel0 + c) * plane);
  });
}

void maxpool_avx512(const HRef& x, Precision p, HRef& y) {
  const std::int64_t h = x.dim(2), w = x.dim(3), oh = h / 2, ow = w / 2;
  parallel_chunks(x.dim(0) * x.dim(1), [&](std::int64_t begin, std::int64_t end, int) {
    maxpool2d_half_avx512(x.data + begin * h * w, end - begin, h, w, p == Precision::BF16,
                          y.data + begin * oh * ow);
  });
}

void upsample_avx512(const HRef& x, Precision p, const std::vector<BilinearTap<float>>& rows,
                     const std::vector<BilinearTap<float>>& cols, const char* op, HRef& y) {
  using Tap = BilinearTap<float>;
  const std::int64_t in_h = x.dim(2), in_w = x.dim(3), out_h = 2 * in_h, out_w = 2 * in_w;
  // The column taps by blocks of 16 outputs, each block's taps as lanes of the 16 input
  // columns from its first: 16 outputs span at most 15 (in - 1) / (2 in - 1) + 1 < 9 columns.
  // Lanes past the row keep index 0 and weight 0.
  const std::int64_t lanes = (out_w + 15) / 16 * 16;
  std::vector<std::int64_t> first(static_cast<size_t>(lanes / 16));
  std::vector<std::int32_t> index(static_cast<size_t>(2 * lanes));  // index0, then index1
  std::vector<float> weight(index.size());                           // w0, then w1
  for (std::int64_t ox = 0; ox < out_w; ++ox) {
    const Tap& c = cols[static_cast<size_t>(ox)];
    if (ox % 16 == 0) first[static_cast<size_t>(ox / 16)] = c.i0;
    const std::int64_t from = first[static_cast<size_t>(ox / 16)];
    PS_CHECK(c.i0 >= from && c.i1 < from + 16, "{}: column tap {} outside its block", op, ox);
    index[static_cast<size_t>(ox)] = static_cast<std::int32_t>(c.i0 - from);
    index[static_cast<size_t>(lanes + ox)] = static_cast<std::int32_t>(c.i1 - from);
    weight[static_cast<size_t>(ox)] = c.w0;
    weight[static_cast<size_t>(lanes + ox)] = c.w1;
  }
  std::vector<std::int64_t> row_index(static_cast<size_t>(2 * out_h));  // i0, then i1
  std::vector<float> row_weight(row_index.size());                      // w0, then w1
  for (std::int64_t oy = 0; oy < out_h; ++oy) {
    const Tap& r = rows[static_cast<size_t>(oy)];
    row_index[static_cast<size_t>(oy)] = r.i0, row_index[static_cast<size_t>(out_h + oy)] = r.i1;
    row_weight[static_cast<size_t>(oy)] = r.w0, row_weight[static_cast<size_t>(out_h + oy)] = r.w1;
  }
  const UpsampleTaps t{first.data(),          index.data(),      index.data() + lanes,
                       weight.data(),         weight.data() + lanes, row_index.data(),
                       row_index.data() + out_h, row_weight.data(), row_weight.data() + out_h};
  const std::int64_t scratch_floats = upsample_scratch_floats(in_w);
  std::vector<float> scratch(static_cast<size_t>(std::max(num_threads(), 1) * scratch_floats));
  parallel_chunks(x.dim(0) * x.dim(1), [&](std::int64_t begin, std::int64_t end, int thread) {
    upsample_bilinear_half_avx512(x.data + begin * in_h * in_w, end - begin, in_h, in_w, t,
                                  p == Precision::BF16, scratch.data() + thread * scratch_floats,
                                  y.data + begin * out_h * out_w);
  });
}
#endif

}  // namespace

HalfOpsKernels native_half_ops_kernels() {
  static const bool avx512 = avx512_half_ops_available();
  return avx512 ? HalfOpsKernels::Avx512 : HalfOpsKernels::Scalar;
}

void to_half(const Ref& x, Precision p, HRef& y) {
  require_half("CpuBackend::to_half", p);
  require_shape("CpuBackend::to_half", "y", y, x.shape);
  const std::int64_t n = x.numel();
  parallel_chunks(n, [&](std::int64_t begin, std::int64_t end, int) {
    for (std::int64_t i = begin; i < end; ++i) y.data[i] = to_bits(x.data[i], p);
  });
}

void scatter_half(const Ref& features, const IRef& cells, int channel0, Precision p, HRef& canvas,
                  HalfOpsKernels kernels) {
  const char* op = "CpuBackend::scatter_forward_half";
  require_half(op, p);
  op::scatter(features.shape, cells.shape, canvas.shape, channel0, op);
  const std::int64_t batch = canvas.dim(0), channels = canvas.dim(1), height = canvas.dim(2),
                     width = canvas.dim(3), plane = height * width, c_band = features.dim(1);
  const std::int64_t rows = features.dim(0);
  const auto inside = [&](const std::int32_t* cell) { return on_canvas(cell, batch, height, width); };
  if (on_avx512(kernels, op)) {  // (it throws where this build has no AVX-512 forms)
#if defined(PILLARSEG_HAVE_AVX512_HALF_OPS)
    scatter_avx512(features, cells, channel0, p, canvas);
    return;
#endif
  }
  // Each thread owns whole channels: it zeroes them, then writes every pillar's value in them in
  // pillar order, so a cell named twice keeps the last pillar's value as the serial loop did.
  parallel_chunks(c_band, [&](std::int64_t c_begin, std::int64_t c_end, int) {
    for (std::int64_t b = 0; b < batch; ++b)
      std::fill_n(canvas.data + (b * channels + channel0 + c_begin) * plane,
                  (c_end - c_begin) * plane, std::uint16_t{0});
    for (std::int64_t r = 0; r < rows; ++r) {
      const std::int32_t* cell = cells.data + 3 * r;
      if (!inside(cell)) continue;
      std::uint16_t* out =
          canvas.data + (cell[0] * channels + channel0) * plane + cell[1] * width + cell[2];
      for (std::int64_t c = c_begin; c < c_end; ++c)
        out[c * plane] = to_bits(features.data[r * c_band + c], p);
    }
  });
}

void maxpool2d_half(const HRef& x, Precision p, HRef& y, HalfOpsKernels kernels) {
  const char* op = "CpuBackend::maxpool2d_half";
  require_half(op, p);
  require_shape(op, "y", y, op::maxpool2d(x.shape, op));
  const std::int64_t h = x.dim(2), w = x.dim(3), oh = h / 2, ow = w / 2;
  if (on_avx512(kernels, op)) {  // (it throws where this build has no AVX-512 forms)
#if defined(PILLARSEG_HAVE_AVX512_HALF_OPS)
    maxpool_avx512(x, p, y);
    return;
#endif
  }
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

void upsample_bilinear_half(const HRef& x, Precision p, HRef& y, HalfOpsKernels kernels) {
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
  if (on_avx512(kernels, op)) {  // (it throws where this build has no AVX-512 forms)
#if defined(PILLARSEG_HAVE_AVX512_HALF_OPS)
    upsample_avx512(x, p, rows, cols, op, y);
    return;
#endif
  }
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
