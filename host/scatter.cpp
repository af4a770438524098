// Pillar scatter (P, C) -> (B, C, H, W) canvas and its backward, the gather (B, C, H, W) -> (P, C).
#include "host/scatter.hpp"

#include <vector>

namespace pillarseg::host {

namespace {

void check_cells_shape(const char* op, const Tensor<int32_t>& cells) {
  PS_CHECK(cells.rank() == 2 && cells.dim(1) == 3,
           "{}: expected cells of shape (P, 3) holding (batch index, iy, ix), given {}", op,
           shape_str(cells.shape()));
}

// Checks that every (b, iy, ix) of cells (P, 3) lies in a (batch_size, height, width) canvas
// and belongs to one pillar only.
void check_cells(const char* op, const Tensor<int32_t>& cells, int64_t batch_size, int64_t height,
                 int64_t width) {
  std::vector<int32_t> owner(static_cast<size_t>(batch_size * height * width), -1);
  for (int64_t p = 0; p < cells.dim(0); ++p) {
    const int32_t b = cells(p, 0), iy = cells(p, 1), ix = cells(p, 2);
    PS_CHECK(b >= 0 && b < batch_size && iy >= 0 && iy < height && ix >= 0 && ix < width,
             "{}: pillar {} has cell (batch {}, iy {}, ix {}) outside the canvas of batch size "
             "{}, height {}, width {}",
             op, p, b, iy, ix, batch_size, height, width);
    int32_t& cell_owner = owner[static_cast<size_t>((b * height + iy) * width + ix)];
    PS_CHECK(cell_owner < 0, "{}: pillars {} and {} have the same cell (batch {}, iy {}, ix {})",
             op, cell_owner, p, b, iy, ix);
    cell_owner = static_cast<int32_t>(p);
  }
}

}  // namespace

template <class T>
void scatter_forward(const Tensor<T>& features, const Tensor<int32_t>& cells, int64_t batch_size,
                     int64_t height, int64_t width, Tensor<T>& canvas) {
  const char* op = "scatter_forward";
  PS_CHECK(batch_size >= 0 && height >= 0 && width >= 0,
           "{}: expected a canvas size of zero or more, given batch size {}, height {}, width {}",
           op, batch_size, height, width);
  check_cells_shape(op, cells);
  PS_CHECK(features.rank() == 2 && features.dim(0) == cells.dim(0),
           "{}: expected features of shape (P, C) with P = {} (the rows of cells), given {}", op,
           cells.dim(0), shape_str(features.shape()));
  check_cells(op, cells, batch_size, height, width);
  const int64_t channels = features.dim(1);
  const int64_t plane = height * width;
  canvas.resize({batch_size, channels, height, width});
  for (int64_t p = 0; p < features.dim(0); ++p) {
    T* cell = canvas.data() + cells(p, 0) * channels * plane + cells(p, 1) * width + cells(p, 2);
    for (int64_t c = 0; c < channels; ++c) cell[c * plane] = features(p, c);
  }
}

template <class T>
void scatter_backward(const Tensor<T>& d_canvas, const Tensor<int32_t>& cells,
                      Tensor<T>& d_features) {
  const char* op = "scatter_backward";
  PS_CHECK(d_canvas.rank() == 4, "{}: expected d_canvas of shape (B, C, H, W), given {}", op,
           shape_str(d_canvas.shape()));
  const int64_t batch_size = d_canvas.dim(0), channels = d_canvas.dim(1);
  const int64_t height = d_canvas.dim(2), width = d_canvas.dim(3);
  check_cells_shape(op, cells);
  check_cells(op, cells, batch_size, height, width);
  const int64_t plane = height * width;
  d_features.resize({cells.dim(0), channels});
  for (int64_t p = 0; p < cells.dim(0); ++p) {
    const T* cell =
        d_canvas.data() + cells(p, 0) * channels * plane + cells(p, 1) * width + cells(p, 2);
    for (int64_t c = 0; c < channels; ++c) d_features(p, c) = cell[c * plane];
  }
}

template void scatter_forward<float>(const Tensor<float>&, const Tensor<int32_t>&, int64_t, int64_t,
                                     int64_t, Tensor<float>&);
template void scatter_forward<double>(const Tensor<double>&, const Tensor<int32_t>&, int64_t,
                                      int64_t, int64_t, Tensor<double>&);
template void scatter_backward<float>(const Tensor<float>&, const Tensor<int32_t>&, Tensor<float>&);
template void scatter_backward<double>(const Tensor<double>&, const Tensor<int32_t>&,
                                       Tensor<double>&);

void batch_cells(const Tensor<int32_t>& cell, int sample, Tensor<int32_t>& cells) {
  PS_CHECK(cell.rank() == 2 && cell.dim(1) == 2 && cells.shape() == (Shape{cell.dim(0), 3}),
           "batch_cells: expected cell (R, 2) and cells (R, 3), given {} and {}",
           shape_str(cell.shape()), shape_str(cells.shape()));
  PS_CHECK(sample >= 0, "batch_cells: the sample index must be >= 0, given {}", sample);
  for (int64_t r = 0; r < cell.dim(0); ++r) {
    const bool used = cell(r, 0) >= 0;
    cells(r, 0) = used ? sample : -1;
    cells(r, 1) = used ? cell(r, 0) : -1;
    cells(r, 2) = used ? cell(r, 1) : -1;
  }
}

}  // namespace pillarseg::host
