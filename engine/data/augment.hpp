// Training augmentation (DESIGN.md section 1 "Augmentation"), OpenPCDet's global augmentors in
// their usual order, composed into one affine map p -> A p + t of the LiDAR frame:
//   1. random_world_flip: "along x" negates y, "along y" negates x, each with probability 0.5;
//   2. random_world_rotation about z by U(-rotation_max, rotation_max), counter-clockwise
//      (x, y) -> (x cos a - y sin a, x sin a + y cos a), as OpenPCDet's rotate_points_along_z;
//   3. random_world_scaling by U(scale_min, scale_max);
//   4. random_world_translation by N(0, sigma^2) per axis (off by default: the paper found
//      that it hurts).
// So A = s R F and t = the translation. Labels are per point and move with the points; the
// sensor origin is moved with apply(origin) and an aggregated neighbour scan with
// as_matrix() * relative_pose, so every map is built from the same augmented data.
#pragma once

#include <numbers>
#include <vector>

#include "core/eigen.hpp"
#include "core/point.hpp"
#include "core/rng.hpp"

namespace pillarseg {

struct AugmentConfig {
  bool flip_x = true;  // flip along x: y -> -y
  bool flip_y = true;  // flip along y: x -> -x
  bool rotate = true;
  bool scale = true;
  bool translate = false;
  double rotation_max = std::numbers::pi / 4;  // radians, rotation in [-max, max)
  double scale_min = 0.95, scale_max = 1.05;
  Eigen::Vector3d translation_sigma{5.0, 5.0, 0.05};  // metres, per axis
};

// An affine map p -> linear * p + translation in the LiDAR frame, double precision.
struct AugmentTransform {
  Eigen::Matrix3d linear = Eigen::Matrix3d::Identity();
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();

  Eigen::Vector3d apply(const Eigen::Vector3d& p) const { return linear * p + translation; }
  // Moves x, y, z of every point (computed in double, stored as float); reflectance unchanged.
  void apply(std::vector<Point>& points) const;
  // The 4x4 homogeneous matrix [linear translation; 0 0 0 1]. With flips and scaling it is
  // affine, not rigid; compose it on the left of a pose: as_matrix() * relative_pose.
  Pose as_matrix() const;
  // Exactly the identity (every stage off, or every drawn value neutral).
  bool is_identity() const;
};

// Draws one transform from `rng`. Every stage draws its random numbers whether it is switched
// on or not (flip x, flip y, angle, scale, then the three translation normals), so switching
// one stage off leaves the values of the others unchanged for a given seed (ablations compare
// like with like); a stage switched off contributes the identity. Same seed, same transform.
AugmentTransform sample_augmentation(const AugmentConfig& cfg, Rng& rng);

}  // namespace pillarseg
