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
//
// Domain randomisation (each off by default), so that a model trained on simulated scans does
// not lean on what differs between sensors and mountings:
//   5. sensor tilt: pitch and roll by N(0, tilt^2) before the stages above (A = s R F T), and
//      sensor height: z shifted by N(0, height^2) (added to t);
//   6. per scan, on the points (ScanRandomisation): reflectance jitter r -> a r + b + noise
//      (a ~ U(reflectance_scale), b ~ N(0, reflectance_offset^2), per point
//      N(0, reflectance_noise^2), clipped to [0, 1]); reflectance dropout, every r -> 0 with
//      probability reflectance_dropout (a sensor without intensities); point dropout, each point
//      removed with probability U(0, point_dropout) drawn per scan, with its label;
//   7. ground bend (GroundBend), after the affine stages: beyond a line at U(bend_start_min,
//      bend_start_max) m from the origin, in a direction drawn uniformly, the ground's grade
//      changes by N(0, grade_change^2) over a parabolic vertical curve of bend_length m, so that
//      far buildings, cars and grass stand on a climb or a dip while the near ground keeps its
//      heights (a rigid tilt moves the near heights too). It draws only when it is on, after the
//      affine stages' draws: configurations without it keep their streams.
#pragma once

#include <cstdint>
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
  double tilt = 0.0;    // radians, sigma of the sensor's pitch and roll; 0: off
  double height = 0.0;  // metres, sigma of the sensor's height; 0: off
  bool reflectance_jitter = false;
  double reflectance_scale_min = 0.75, reflectance_scale_max = 1.3;
  double reflectance_offset = 0.03, reflectance_noise = 0.03;  // sigmas
  double reflectance_dropout = 0.0;  // probability that a scan's reflectance is all 0
  double point_dropout = 0.0;        // largest share of points a scan loses
  double grade_change = 0.0;         // sigma of the ground bend's change of grade; 0: off
  double bend_start_min = 5.0, bend_start_max = 25.0;  // metres, the bend's line from the origin
  double bend_length = 10.0;                           // metres, its vertical curve

  // Any per-point randomisation on (only then does a scan draw one).
  bool randomises_points() const {
    return reflectance_jitter || reflectance_dropout > 0.0 || point_dropout > 0.0;
  }
};

// The per-point part of one scan's domain randomisation, drawn by sample_randomisation.
struct ScanRandomisation {
  bool jitter = false;
  double scale = 1.0, offset = 0.0, noise = 0.0;  // r -> scale r + offset + N(0, noise^2)
  bool zero_reflectance = false;
  double drop = 0.0;        // probability of removing a point
  uint64_t point_seed = 0;  // the per-point draws' stream

  bool is_identity() const { return !jitter && !zero_reflectance && drop == 0.0; }
  // Changes the reflectance and removes points (and the labels at the same index; labels may
  // be empty). Same randomisation, same result.
  void apply(std::vector<Point>& points, std::vector<uint32_t>& labels) const;
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

// A change of the ground's grade along one horizontal direction u: with d = u . (x, y) a point's
// distance along u, every point's z moves by
//   offset = 0                                  d <= start
//          = grade (d - start)^2 / (2 length)   start < d < start + length
//          = grade (d - start - length / 2)     d >= start + length,
// a parabolic vertical curve (continuous, with a continuous slope) into the grade change.
struct GroundBend {
  Eigen::Vector2d direction{1.0, 0.0};  // unit
  double start = 0.0;                   // metres along direction; >= 0, so the origin stays
  double length = 1.0;                  // metres, > 0
  double grade = 0.0;                   // rise over run beyond the curve; 0: the identity

  bool is_identity() const { return grade == 0.0; }
  double offset(double x, double y) const;
  // Moves z of every point (computed in double, stored as float).
  void apply(std::vector<Point>& points) const;
};

// Throws pillarseg::Error naming the first setting out of its range.
void validate_augmentation(const AugmentConfig& cfg);

// Draws one transform from `rng`. Every stage draws its random numbers whether it is switched
// on or not (flip x, flip y, angle, scale, then the three translation normals), so switching
// one stage off leaves the values of the others unchanged for a given seed (ablations compare
// like with like); a stage switched off contributes the identity. Same seed, same transform.
AugmentTransform sample_augmentation(const AugmentConfig& cfg, Rng& rng);

// Draws one scan's ground bend from `rng` (direction angle, start, grade), after
// sample_augmentation; nothing is drawn and the identity returned when grade_change is 0.
GroundBend sample_ground_bend(const AugmentConfig& cfg, Rng& rng);

// Draws the per-point randomisation of one scan from `rng`, after sample_augmentation: always
// the same draws (scale, offset, the reflectance dropout's, the drop share's, the points'
// seed), whatever is switched on.
ScanRandomisation sample_randomisation(const AugmentConfig& cfg, Rng& rng);

}  // namespace pillarseg
