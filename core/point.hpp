// Point, Scan and pose types shared by the data pipeline. A Point is one 16-byte record of a
// SemanticKITTI .bin file: x y z reflectance, float32, in the LiDAR frame.
#pragma once

#include <cstdint>
#include <vector>

#include "core/eigen.hpp"

namespace pillarseg {

struct Point {
  float x = 0, y = 0, z = 0, r = 0;
};
static_assert(sizeof(Point) == 16, "Point must match the 16-byte .bin record");

// The largest reflectance magnitude the network takes: FP16's largest value (SemanticKITTI's
// remission is in [0, 1], 8-bit sensors give 0..255). A point beyond it, or with a NaN one, is
// left out of the pillars and the grid map (pillar_gather, grid_map_features; the kernels
// alike), so that no input can overflow the network into NaN.
inline constexpr float kMaxAbsReflectance = 65504.0f;

struct Scan {
  std::vector<Point> points;
  std::vector<uint32_t> labels;  // raw .label words, one per point, or empty when unlabelled
  size_t dropped_nonfinite = 0;  // points removed on reading because a coordinate was NaN/Inf
  bool labelled() const { return !labels.empty() || points.empty(); }
};

// 4x4 rigid transform, double precision.
using Pose = Eigen::Matrix4d;

}  // namespace pillarseg
