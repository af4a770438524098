// Conv2d, stride 1, square kernel k, zero padding: im2col + Eigen GEMM.
//   forward:  x (B, I, H, W), w (O, I, k, k), bias (O) -> y (B, O, Ho, Wo),
//             Ho = H + 2 pad - k + 1, Wo = W + 2 pad - k + 1.
//   backward: dy (B, O, Ho, Wo) -> dx (B, I, H, W), dw (O, I, k, k), db (O).
//
// An image's im2col matrix has one row per (i, ky, kx) and one column per output pixel, so
// y[b] (O, Ho Wo) = w (O, I k k) * cols. The matrix is built for a tile of whole output rows at a
// time, which bounds its memory at full resolution (I k k x Ho Wo would be gigabytes).
//   dx: a stride-1 convolution's input gradient is the convolution of dy with the kernel
//       flipped in y and x and its channel axes swapped, padded by k - 1 - pad: the forward
//       code again, with no scatter-add.
//   dw: dw (O, I k k) = sum over images and tiles of dy_tile (O, pixels) * cols_tile^T.
#include "host/conv2d.hpp"

#include <algorithm>
#include <cstdint>
#include <type_traits>

#include "core/eigen.hpp"
#include "core/error.hpp"
#include "core/ops.hpp"
#include "core/parallel.hpp"

namespace pillarseg::host {
namespace {

template <class T>
using RowMajorMatrix = Eigen::Matrix<T, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
template <class T>
using MatrixView = Eigen::Map<RowMajorMatrix<T>, Eigen::Unaligned, Eigen::OuterStride<>>;
template <class T>
using ConstMatrixView = Eigen::Map<const RowMajorMatrix<T>, Eigen::Unaligned, Eigen::OuterStride<>>;
template <class T>
using ConstVectorView = Eigen::Map<const Eigen::Matrix<T, Eigen::Dynamic, 1>>;

// Upper bound on the elements of one tile's im2col matrix (2 MiB in float): large enough that the
// GEMM runs at full speed, small enough to be still in cache when the GEMM reads what im2col wrote.
constexpr int64_t kTileColumnElements = int64_t{1} << 19;
// The weight gradient is split into this many blocks of input channels, computed in parallel.
constexpr int64_t kWeightGradientBlocks = 8;

// Sizes of one correlation. pad may be negative (a crop): the dx pass uses k - 1 - pad.
struct ConvShape {
  int64_t batch = 0;
  int64_t in_channels = 0;
  int64_t height = 0;
  int64_t width = 0;
  int64_t out_channels = 0;
  int64_t kernel = 0;
  int64_t pad = 0;

  int64_t out_height() const { return height + 2 * pad - kernel + 1; }
  int64_t out_width() const { return width + 2 * pad - kernel + 1; }
  // A 1x1 kernel without padding: the im2col matrix is the image itself.
  bool pointwise() const { return kernel == 1 && pad == 0; }
};

// Below this many multiply-adds in all, an OpenMP region costs more than it saves; Eigen also
// runs GEMMs this small (under 1e5 multiply-adds) on one thread by its own rule.
constexpr int64_t kMinParallelWork = int64_t{1} << 16;

// Runs body(item) for every item in [0, count), which together do `work` multiply-adds, on
// num_threads() threads. Items write disjoint parts of the output. A parallel loop is an OpenMP
// region even when it has a single item, because Eigen runs a GEMM inside a region on one thread
// with a blocking that depends on the matrix sizes alone: every output element is then summed in
// the same order whatever the thread count. (Outside a region, Eigen would split a large GEMM
// over threads itself, with a blocking that depends on their number. With num_threads() = 1,
// set_num_threads has set OpenMP's count to 1 too, so Eigen stays on one thread as well.)
template <class Body>
void for_each_work_item(int64_t count, int64_t work, const Body& body) {
  if (work < kMinParallelWork) {
    for (int64_t item = 0; item < count; ++item) body(item);
    return;
  }
#pragma omp parallel for schedule(dynamic, 1) num_threads(num_threads())
  for (int64_t item = 0; item < count; ++item) body(item);
}

// Output rows per tile when the im2col matrix has `depth` rows.
int64_t tile_rows(int64_t depth, const ConvShape& s) {
  const int64_t pixels_per_row = std::max<int64_t>(1, depth * s.out_width());
  return std::clamp<int64_t>(kTileColumnElements / pixels_per_row, 1,
                             std::max<int64_t>(1, s.out_height()));
}

// im2col of channels [c0, c1) of one image (I, H, W) for output rows [row0, row0 + rows):
//   cols((c - c0) k k + ky k + kx, r Wo + ox) = image(c, row0 + r + ky - pad, ox + kx - pad),
// zero where that position lies outside the image. cols: ((c1 - c0) k k, rows Wo).
template <class T>
void im2col(const T* image, const ConvShape& s, int64_t c0, int64_t c1, int64_t row0, int64_t rows,
            RowMajorMatrix<T>& cols) {
  const int64_t k = s.kernel;
  const int64_t out_w = s.out_width();
  cols.resize((c1 - c0) * k * k, rows * out_w);
  for (int64_t c = c0; c < c1; ++c) {
    for (int64_t ky = 0; ky < k; ++ky) {
      for (int64_t kx = 0; kx < k; ++kx) {
        T* dst = cols.row(((c - c0) * k + ky) * k + kx).data();
        // Output columns ox whose input column ox + kx - pad lies in [0, W).
        const int64_t shift = kx - s.pad;
        const int64_t ox_begin = std::clamp<int64_t>(-shift, 0, out_w);
        const int64_t ox_end = std::clamp<int64_t>(s.width - shift, ox_begin, out_w);
        for (int64_t r = 0; r < rows; ++r, dst += out_w) {
          const int64_t iy = row0 + r + ky - s.pad;
          if (iy < 0 || iy >= s.height) {
            std::fill(dst, dst + out_w, T{0});
            continue;
          }
          const T* src_row = image + (c * s.height + iy) * s.width;
          std::fill(dst, dst + ox_begin, T{0});
          std::copy(src_row + ox_begin + shift, src_row + ox_end + shift, dst + ox_begin);
          std::fill(dst + ox_end, dst + out_w, T{0});
        }
      }
    }
  }
}

// y (B, O, Ho, Wo) = correlation of x (B, I, H, W) with w (O, I, k, k), plus bias (O) if given.
template <class T>
void correlate(const T* x, const T* w, const std::type_identity_t<T>* bias, const ConvShape& s,
               T* y) {
  const int64_t depth = s.in_channels * s.kernel * s.kernel;
  const int64_t out_h = s.out_height();
  const int64_t out_w = s.out_width();
  const int64_t out_pixels = out_h * out_w;
  const int64_t in_pixels = s.height * s.width;
  const ConstMatrixView<T> weights(w, s.out_channels, depth, Eigen::OuterStride<>(depth));
  const int64_t rows_per_tile = tile_rows(depth, s);
  const int64_t tiles = (out_h + rows_per_tile - 1) / rows_per_tile;

  const int64_t work = s.batch * s.out_channels * depth * out_pixels;
  for_each_work_item(s.batch * tiles, work, [&](int64_t item) {
    const int64_t b = item / tiles;
    const int64_t row0 = (item % tiles) * rows_per_tile;
    const int64_t rows = std::min(rows_per_tile, out_h - row0);
    const T* image = x + b * s.in_channels * in_pixels;
    MatrixView<T> out(y + b * s.out_channels * out_pixels + row0 * out_w, s.out_channels,
                      rows * out_w, Eigen::OuterStride<>(out_pixels));
    if (s.pointwise()) {
      out.noalias() = weights * ConstMatrixView<T>(image + row0 * s.width, s.in_channels,
                                                   rows * s.width, Eigen::OuterStride<>(in_pixels));
    } else {
      RowMajorMatrix<T> cols;
      im2col(image, s, 0, s.in_channels, row0, rows, cols);
      out.noalias() = weights * cols;
    }
    if (bias != nullptr) out.colwise() += ConstVectorView<T>(bias, s.out_channels);
  });
}

// dw (O, I, k, k) = sum over b of the correlation of x[b] with dy[b], as GEMMs per block of
// input channels; each block sums its images and tiles in a fixed order.
template <class T>
void weight_gradient(const T* x, const T* dy, const ConvShape& s, T* dw) {
  const int64_t kk = s.kernel * s.kernel;
  const int64_t depth = s.in_channels * kk;
  const int64_t out_h = s.out_height();
  const int64_t out_w = s.out_width();
  const int64_t out_pixels = out_h * out_w;
  const int64_t in_pixels = s.height * s.width;
  const int64_t blocks = std::min(s.in_channels, kWeightGradientBlocks);

  const int64_t work = s.batch * s.out_channels * depth * out_pixels;
  for_each_work_item(blocks, work, [&](int64_t block) {
    const int64_t c0 = s.in_channels * block / blocks;
    const int64_t c1 = s.in_channels * (block + 1) / blocks;
    MatrixView<T> dw_block(dw + c0 * kk, s.out_channels, (c1 - c0) * kk,
                           Eigen::OuterStride<>(depth));
    dw_block.setZero();
    const int64_t rows_per_tile = tile_rows((c1 - c0) * kk, s);
    RowMajorMatrix<T> cols;
    for (int64_t b = 0; b < s.batch; ++b) {
      const T* image = x + b * s.in_channels * in_pixels;
      for (int64_t row0 = 0; row0 < out_h; row0 += rows_per_tile) {
        const int64_t rows = std::min(rows_per_tile, out_h - row0);
        const ConstMatrixView<T> dy_tile(dy + b * s.out_channels * out_pixels + row0 * out_w,
                                         s.out_channels, rows * out_w,
                                         Eigen::OuterStride<>(out_pixels));
        if (s.pointwise()) {
          const ConstMatrixView<T> x_tile(image + c0 * in_pixels + row0 * s.width, c1 - c0,
                                          rows * s.width, Eigen::OuterStride<>(in_pixels));
          dw_block.noalias() += dy_tile * x_tile.transpose();
        } else {
          im2col(image, s, c0, c1, row0, rows, cols);
          dw_block.noalias() += dy_tile * cols.transpose();
        }
      }
    }
  });
}

// Checks x, w, bias and pad (op::conv2d) and returns the sizes; `caller` names the op in messages.
template <class T>
ConvShape check_conv_args(const char* caller, const Tensor<T>& x, const Tensor<T>& w,
                          const std::type_identity_t<Tensor<T>>* bias, int pad) {
  op::conv2d(x.shape(), w.shape(), pad, bias != nullptr ? &bias->shape() : nullptr, caller);
  ConvShape s;
  s.batch = x.dim(0);
  s.in_channels = x.dim(1);
  s.height = x.dim(2);
  s.width = x.dim(3);
  s.out_channels = w.dim(0);
  s.kernel = w.dim(2);
  s.pad = pad;
  return s;
}

}  // namespace

template <class T>
void conv2d_forward(const Tensor<T>& x, const Tensor<T>& w,
                    const std::type_identity_t<Tensor<T>>* bias, int pad, Tensor<T>& y) {
  const ConvShape s = check_conv_args("conv2d_forward", x, w, bias, pad);
  PS_CHECK(&y != &x && &y != &w && &y != bias,
           "conv2d_forward: the output y must be a different tensor from x, w and bias");
  y.resize({s.batch, s.out_channels, s.out_height(), s.out_width()});
  correlate(x.data(), w.data(), bias != nullptr ? bias->data() : nullptr, s, y.data());
}

template <class T>
void conv2d_backward(const Tensor<T>& x, const Tensor<T>& w, const Tensor<T>& dy, int pad,
                     std::type_identity_t<Tensor<T>>* dx, std::type_identity_t<Tensor<T>>* dw,
                     std::type_identity_t<Tensor<T>>* db) {
  const ConvShape s = check_conv_args("conv2d_backward", x, w, nullptr, pad);
  const Shape y_shape = {s.batch, s.out_channels, s.out_height(), s.out_width()};
  PS_CHECK(dy.shape() == y_shape, "conv2d_backward: dy must have the output shape {}, got {}",
           shape_str(y_shape), shape_str(dy.shape()));
  for (const Tensor<T>* grad : {dx, dw, db}) {
    PS_CHECK(grad == nullptr || (grad != &x && grad != &w && grad != &dy),
             "conv2d_backward: the gradients dx, dw, db must be different tensors from x, w, dy");
  }
  const int64_t out_pixels = s.out_height() * s.out_width();

  if (db != nullptr) {
    db->resize({s.out_channels});
    Eigen::Map<Eigen::Matrix<T, Eigen::Dynamic, 1>> bias_grad(db->data(), s.out_channels);
    for (int64_t b = 0; b < s.batch; ++b) {
      bias_grad += ConstMatrixView<T>(dy.data() + b * s.out_channels * out_pixels, s.out_channels,
                                      out_pixels, Eigen::OuterStride<>(out_pixels))
                       .rowwise()
                       .sum();
    }
  }
  if (dw != nullptr) {
    dw->resize(w.shape());
    weight_gradient(x.data(), dy.data(), s, dw->data());
  }
  if (dx != nullptr) {
    // Flipped kernel with swapped channel axes: flipped[i, o, ky, kx] = w[o, i, k-1-ky, k-1-kx].
    const int64_t k = s.kernel;
    Tensor<T> flipped({s.in_channels, s.out_channels, k, k});
    for (int64_t o = 0; o < s.out_channels; ++o)
      for (int64_t i = 0; i < s.in_channels; ++i)
        for (int64_t ky = 0; ky < k; ++ky)
          for (int64_t kx = 0; kx < k; ++kx)
            flipped(i, o, ky, kx) = w(o, i, k - 1 - ky, k - 1 - kx);
    ConvShape transposed;
    transposed.batch = s.batch;
    transposed.in_channels = s.out_channels;
    transposed.height = s.out_height();
    transposed.width = s.out_width();
    transposed.out_channels = s.in_channels;
    transposed.kernel = k;
    transposed.pad = k - 1 - s.pad;
    dx->resize(x.shape());
    correlate(dy.data(), flipped.data(), nullptr, transposed, dx->data());
  }
}

template void conv2d_forward<float>(const Tensor<float>&, const Tensor<float>&,
                                    const Tensor<float>*, int, Tensor<float>&);
template void conv2d_forward<double>(const Tensor<double>&, const Tensor<double>&,
                                     const Tensor<double>*, int, Tensor<double>&);
template void conv2d_backward<float>(const Tensor<float>&, const Tensor<float>&,
                                     const Tensor<float>&, int, Tensor<float>*, Tensor<float>*,
                                     Tensor<float>*);
template void conv2d_backward<double>(const Tensor<double>&, const Tensor<double>&,
                                      const Tensor<double>&, int, Tensor<double>*, Tensor<double>*,
                                      Tensor<double>*);

}  // namespace pillarseg::host
