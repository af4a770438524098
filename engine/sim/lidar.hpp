// The simulated spinning LiDAR, HDL-64E-like: 64 beams (upper block of 32 from +2.0 to
// -8.33 deg, lower block of 32 from -8.83 to -24.9 deg), azimuth_steps pulses per beam and
// revolution, mounted 1.73 m above the road. Each pulse is cast against the city's ground,
// its static scene and the moving agents of the scan's time; the model adds range noise,
// dropouts (per beam, grazing, weak far returns, glass), pulses through foliage and wire mesh,
// a few outliers, and an intensity from the surface's albedo and incidence angle, the sensor's
// and each beam's gain, speckle, and a floor below which it reads 0.
// Returns are written in the LiDAR frame (x forward, y left, z up) in KITTI's order: beam by
// beam from the top beam down, each beam by azimuth from -180 deg (behind) counter-clockwise.
// Motion within a sweep is ignored.
#pragma once

#include <cstdint>
#include <vector>

#include "core/eigen.hpp"
#include "core/point.hpp"
#include "engine/sim/city.hpp"
#include "engine/sim/scene.hpp"

namespace pillarseg::sim {

struct LidarModel {
  std::vector<double> elevation_deg;  // per beam, top beam first
  int azimuth_steps = 2048;           // pulses per beam and revolution
  double max_range = 100.0;           // m
  double range_noise = 0.02;          // sigma of the range error, m
  double dropout = 0.02;              // probability that a pulse is lost regardless of the target
  double outlier_rate = 3e-4;         // probability of a spurious return (raw label 1)
  double gain = 1.0;                  // the sensor's intensity gain
  // Per beam (empty: gain 1 and `dropout` for every beam): the HDL-64E's lasers differ in
  // intensity and some lose many more pulses than others.
  std::vector<double> beam_gains, beam_dropouts;
  // The ego car's body in the LiDAR frame, which hides the near ground behind and beside it.
  Eigen::Vector3d body_min{-2.4, -0.95, -1.5}, body_max{1.0, 0.95, -0.73};

  // The HDL-64E-like sensor with the given pulses per revolution (>= 360).
  static LidarModel hdl64e(int azimuth_steps);
  // Pulses per revolution for about points_per_scan returns in a typical simulated street.
  static int azimuth_steps_for(int64_t points_per_scan);
  int beams() const { return static_cast<int>(elevation_deg.size()); }
  // A sensor of its own: the gain in [0.8, 1.2], each beam's gain in [0.85, 1.15], and each
  // beam's dropout in [0.005, 0.03], or [0.05, 0.2] for one beam in ten, and [0.3, 0.55] for
  // the beams below -20 deg; from seed.
  void vary(uint64_t seed);
  double beam_gain(int b) const {
    return beam_gains.empty() ? 1.0 : beam_gains[static_cast<size_t>(b)];
  }
  double beam_dropout(int b) const {
    return beam_dropouts.empty() ? dropout : beam_dropouts[static_cast<size_t>(b)];
  }
  // Azimuth (radians) of pulse k of a revolution, in [-pi, pi).
  double azimuth(int k) const;
};

struct SimScan {
  std::vector<Point> points;     // LiDAR frame
  std::vector<uint32_t> labels;  // raw SemanticKITTI words, one per point
};

// One revolution from the sensor pose lidar_to_world (4x4), against the city's ground and
// static scene and the primitives in `moving` (the moving agents at this scan's time).
// Deterministic in seed and independent of the thread count: pulse (beam b, step k) draws from
// its own stream Rng::derive(seed, b, k).
SimScan cast_scan(const LidarModel& lidar, const City& city, const SceneGrid& moving,
                  const Eigen::Matrix4d& lidar_to_world, uint64_t seed);

}  // namespace pillarseg::sim
