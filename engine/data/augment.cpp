// Training augmentation: sampling of the flip / rotation / scaling / translation / tilt / height
// stages and their composition into one affine transform A = s R F T, t, and the per-point
// domain randomisation (see augment.hpp).
#include "engine/data/augment.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>

#include "core/error.hpp"

namespace pillarseg {

void AugmentTransform::apply(std::vector<Point>& points) const {
  for (Point& pt : points) {
    const Eigen::Vector3d moved = apply(Eigen::Vector3d(pt.x, pt.y, pt.z));
    pt.x = static_cast<float>(moved.x());
    pt.y = static_cast<float>(moved.y());
    pt.z = static_cast<float>(moved.z());
  }
}

Pose AugmentTransform::as_matrix() const {
  Pose m = Pose::Identity();
  m.topLeftCorner<3, 3>() = linear;
  m.topRightCorner<3, 1>() = translation;
  return m;
}

double GroundBend::offset(double x, double y) const {
  const double d = direction.x() * x + direction.y() * y - start;
  if (d <= 0.0) return 0.0;
  if (d < length) return grade * d * d / (2.0 * length);
  return grade * (d - 0.5 * length);
}

void GroundBend::apply(std::vector<Point>& points) const {
  if (is_identity()) return;
  for (Point& pt : points) pt.z = static_cast<float>(pt.z + offset(pt.x, pt.y));
}

bool AugmentTransform::is_identity() const {
  return linear == Eigen::Matrix3d::Identity() && translation == Eigen::Vector3d::Zero();
}

void validate_augmentation(const AugmentConfig& cfg) {
  PS_CHECK(std::isfinite(cfg.rotation_max) && cfg.rotation_max >= 0.0,
           "augmentation: rotation_max must be a finite angle >= 0 (radians), given {}",
           cfg.rotation_max);
  PS_CHECK(std::isfinite(cfg.scale_min) && std::isfinite(cfg.scale_max) && cfg.scale_min > 0.0 &&
               cfg.scale_min <= cfg.scale_max,
           "augmentation: scaling needs 0 < scale_min <= scale_max, given [{}, {}]", cfg.scale_min,
           cfg.scale_max);
  PS_CHECK(cfg.translation_sigma.allFinite() && (cfg.translation_sigma.array() >= 0.0).all(),
           "augmentation: translation_sigma must be finite and >= 0, given ({}, {}, {})",
           cfg.translation_sigma.x(), cfg.translation_sigma.y(), cfg.translation_sigma.z());

  PS_CHECK(std::isfinite(cfg.tilt) && cfg.tilt >= 0.0 && cfg.tilt < 0.5,
           "augmentation: tilt must be in [0, 0.5) radians (a sigma), given {}", cfg.tilt);
  PS_CHECK(std::isfinite(cfg.height) && cfg.height >= 0.0 && cfg.height <= 1.0,
           "augmentation: height must be in [0, 1] m (a sigma), given {}", cfg.height);
  PS_CHECK(std::isfinite(cfg.reflectance_scale_min) && std::isfinite(cfg.reflectance_scale_max) &&
               cfg.reflectance_scale_min > 0.0 &&
               cfg.reflectance_scale_min <= cfg.reflectance_scale_max,
           "augmentation: reflectance scale needs 0 < min <= max, given [{}, {}]",
           cfg.reflectance_scale_min, cfg.reflectance_scale_max);
  PS_CHECK(std::isfinite(cfg.reflectance_offset) && cfg.reflectance_offset >= 0.0 &&
               std::isfinite(cfg.reflectance_noise) && cfg.reflectance_noise >= 0.0,
           "augmentation: reflectance offset and noise must be sigmas >= 0, given {} and {}",
           cfg.reflectance_offset, cfg.reflectance_noise);
  PS_CHECK(cfg.reflectance_dropout >= 0.0 && cfg.reflectance_dropout <= 1.0,
           "augmentation: reflectance_dropout must be a probability in [0, 1], given {}",
           cfg.reflectance_dropout);
  PS_CHECK(cfg.point_dropout >= 0.0 && cfg.point_dropout < 1.0,
           "augmentation: point_dropout must be in [0, 1), given {}", cfg.point_dropout);
  PS_CHECK(std::isfinite(cfg.grade_change) && cfg.grade_change >= 0.0 && cfg.grade_change <= 0.2,
           "augmentation: grade_change must be in [0, 0.2] (a sigma, rise over run), given {}",
           cfg.grade_change);
  PS_CHECK(std::isfinite(cfg.bend_start_min) && std::isfinite(cfg.bend_start_max) &&
               cfg.bend_start_min >= 0.0 && cfg.bend_start_min <= cfg.bend_start_max,
           "augmentation: the ground bend's start needs 0 <= min <= max (m), given [{}, {}]",
           cfg.bend_start_min, cfg.bend_start_max);
  PS_CHECK(std::isfinite(cfg.bend_length) && cfg.bend_length > 0.0,
           "augmentation: bend_length must be > 0 m, given {}", cfg.bend_length);
}

AugmentTransform sample_augmentation(const AugmentConfig& cfg, Rng& rng) {
  validate_augmentation(cfg);

  // All draws first, in a fixed order, independent of the switches; the tilt and height after
  // the others', so that they leave the others' values as they were.
  const bool flip_along_x = rng.bernoulli(0.5);
  const bool flip_along_y = rng.bernoulli(0.5);
  const double angle = rng.uniform(-cfg.rotation_max, cfg.rotation_max);
  const double scale = rng.uniform(cfg.scale_min, cfg.scale_max);
  Eigen::Vector3d shift;
  for (int axis = 0; axis < 3; ++axis) shift[axis] = rng.normal(0.0, cfg.translation_sigma[axis]);
  const double pitch = rng.normal(0.0, cfg.tilt);
  const double roll = rng.normal(0.0, cfg.tilt);
  const double lift = rng.normal(0.0, cfg.height);

  AugmentTransform transform;
  Eigen::Matrix3d flip = Eigen::Matrix3d::Identity();
  if (cfg.flip_x && flip_along_x) flip(1, 1) = -1.0;
  if (cfg.flip_y && flip_along_y) flip(0, 0) = -1.0;
  transform.linear = flip;
  if (cfg.tilt > 0.0)
    transform.linear = flip * (Eigen::AngleAxisd(pitch, Eigen::Vector3d::UnitY()) *
                               Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitX()))
                                  .toRotationMatrix();
  if (cfg.rotate) {
    const double c = std::cos(angle), s = std::sin(angle);
    Eigen::Matrix3d rotation;
    rotation << c, -s, 0.0,  //
        s, c, 0.0,           //
        0.0, 0.0, 1.0;
    transform.linear = rotation * transform.linear;
  }
  if (cfg.scale) transform.linear *= scale;
  if (cfg.translate) transform.translation = shift;
  if (cfg.height > 0.0) transform.translation.z() += lift;
  return transform;
}

GroundBend sample_ground_bend(const AugmentConfig& cfg, Rng& rng) {
  validate_augmentation(cfg);
  GroundBend bend;
  if (cfg.grade_change == 0.0) return bend;
  const double angle = rng.uniform(0.0, 2.0 * std::numbers::pi);
  bend.direction = {std::cos(angle), std::sin(angle)};
  bend.start = rng.uniform(cfg.bend_start_min, cfg.bend_start_max);
  bend.length = cfg.bend_length;
  bend.grade = rng.normal(0.0, cfg.grade_change);
  return bend;
}

ScanRandomisation sample_randomisation(const AugmentConfig& cfg, Rng& rng) {
  validate_augmentation(cfg);
  const double scale = rng.uniform(cfg.reflectance_scale_min, cfg.reflectance_scale_max);
  const double offset = rng.normal(0.0, cfg.reflectance_offset);
  const bool zero = rng.bernoulli(cfg.reflectance_dropout);
  const double drop = rng.uniform(0.0, cfg.point_dropout);
  const uint64_t seed = rng.next_u64();
  ScanRandomisation r;
  r.jitter = cfg.reflectance_jitter;
  if (r.jitter) {
    r.scale = scale;
    r.offset = offset;
    r.noise = cfg.reflectance_noise;
  }
  r.zero_reflectance = zero;
  r.drop = drop;
  r.point_seed = seed;
  return r;
}

void ScanRandomisation::apply(std::vector<Point>& points, std::vector<uint32_t>& labels) const {
  PS_CHECK(labels.empty() || labels.size() == points.size(),
           "scan randomisation: {} labels for {} points", labels.size(), points.size());
  if (is_identity()) return;
  Rng rng(point_seed);
  size_t kept = 0;
  for (size_t i = 0; i < points.size(); ++i) {
    // Two draws a point whatever is on, so a point's fate does not depend on the switches.
    const double speckle = rng.normal();
    const bool dropped = rng.bernoulli(drop);
    if (dropped) continue;
    Point p = points[i];
    if (zero_reflectance) {
      p.r = 0.0f;
    } else if (jitter) {
      p.r = static_cast<float>(std::clamp(scale * p.r + offset + noise * speckle, 0.0, 1.0));
    }
    points[kept] = p;
    if (!labels.empty()) labels[kept] = labels[i];
    ++kept;
  }
  points.resize(kept);
  if (!labels.empty()) labels.resize(kept);
}

}  // namespace pillarseg
