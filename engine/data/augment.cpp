// Training augmentation: sampling of the flip / rotation / scaling / translation stages and
// their composition into one affine transform A = s R F, t (see augment.hpp).
#include "engine/data/augment.hpp"

#include <cmath>

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

bool AugmentTransform::is_identity() const {
  return linear == Eigen::Matrix3d::Identity() && translation == Eigen::Vector3d::Zero();
}

AugmentTransform sample_augmentation(const AugmentConfig& cfg, Rng& rng) {
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

  // All draws first, in a fixed order, independent of the switches.
  const bool flip_along_x = rng.bernoulli(0.5);
  const bool flip_along_y = rng.bernoulli(0.5);
  const double angle = rng.uniform(-cfg.rotation_max, cfg.rotation_max);
  const double scale = rng.uniform(cfg.scale_min, cfg.scale_max);
  Eigen::Vector3d shift;
  for (int axis = 0; axis < 3; ++axis) shift[axis] = rng.normal(0.0, cfg.translation_sigma[axis]);

  AugmentTransform transform;
  Eigen::Matrix3d flip = Eigen::Matrix3d::Identity();
  if (cfg.flip_x && flip_along_x) flip(1, 1) = -1.0;
  if (cfg.flip_y && flip_along_y) flip(0, 0) = -1.0;
  transform.linear = flip;
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
  return transform;
}

}  // namespace pillarseg
