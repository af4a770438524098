// GridSpec: the top-view grid (DESIGN.md section 1). Cell (ix, iy) of a point is
// floor((p - min) / cell), always computed in double precision; W cells along x, H along y,
// Z voxel layers of height voxel_z over [z_min, z_max).
#pragma once

#include <cmath>
#include <cstdint>

namespace pillarseg {

struct GridSpec {
  double x_min = -50.0, x_max = 50.0;
  double y_min = -25.0, y_max = 25.0;
  double z_min = -2.5, z_max = 1.5;
  double cell = 0.1;     // xy size of a cell, pillar and voxel
  double voxel_z = 0.2;  // z size of an occupancy voxel

  int width() const { return static_cast<int>(std::llround((x_max - x_min) / cell)); }   // W
  int height() const { return static_cast<int>(std::llround((y_max - y_min) / cell)); }  // H
  int layers() const { return static_cast<int>(std::llround((z_max - z_min) / voxel_z)); }  // Z
  int64_t cells() const { return int64_t{width()} * height(); }

  // Index along x / y / z; may be outside [0, W) etc. for points outside the range.
  int64_t ix(double x) const { return static_cast<int64_t>(std::floor((x - x_min) / cell)); }
  int64_t iy(double y) const { return static_cast<int64_t>(std::floor((y - y_min) / cell)); }
  int64_t iz(double z) const { return static_cast<int64_t>(std::floor((z - z_min) / voxel_z)); }

  // Inside the cropped volume: x in [x_min, x_max), y likewise, z in [z_min, z_max), and
  // the cell index in range (guards rounding at the upper edges).
  bool contains(double x, double y, double z) const {
    if (!(x >= x_min && x < x_max && y >= y_min && y < y_max && z >= z_min && z < z_max)) return false;
    const int64_t cx = ix(x), cy = iy(y);
    return cx >= 0 && cx < width() && cy >= 0 && cy < height();
  }
  bool contains_xy(double x, double y) const {
    if (!(x >= x_min && x < x_max && y >= y_min && y < y_max)) return false;
    const int64_t cx = ix(x), cy = iy(y);
    return cx >= 0 && cx < width() && cy >= 0 && cy < height();
  }
  // Flat cell index iy * W + ix of a point known to be inside.
  int64_t cell_index(double x, double y) const { return iy(y) * width() + ix(x); }

  bool operator==(const GridSpec&) const = default;
};

}  // namespace pillarseg
