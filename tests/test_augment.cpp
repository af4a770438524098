// Augmentation: flips, rotation, scaling and translation follow OpenPCDet's conventions and
// order (checked stage by stage and composed), labels, origin and neighbour poses move with the
// points, seeds reproduce, switches turn stages off, flips happen half of the time.
#include <gtest/gtest.h>

#include <cmath>
#include <numbers>
#include <vector>

#include "core/eigen.hpp"
#include "core/error.hpp"
#include "engine/data/augment.hpp"

using namespace pillarseg;

namespace {

AugmentConfig only(bool flip_x, bool flip_y, bool rotate, bool scale, bool translate) {
  AugmentConfig cfg;
  cfg.flip_x = flip_x, cfg.flip_y = flip_y, cfg.rotate = rotate, cfg.scale = scale;
  cfg.translate = translate;
  return cfg;
}

AugmentTransform sample(const AugmentConfig& cfg, uint64_t seed) {
  Rng rng(seed);
  return sample_augmentation(cfg, rng);
}

std::vector<Point> random_points(int count, uint64_t seed) {
  Rng rng(seed);
  std::vector<Point> points(static_cast<size_t>(count));
  for (Point& p : points) {
    p = {static_cast<float>(rng.uniform(-50, 50)), static_cast<float>(rng.uniform(-25, 25)),
         static_cast<float>(rng.uniform(-2.5, 1.5)), static_cast<float>(rng.uniform())};
  }
  return points;
}

Eigen::Vector3d xyz(const Point& p) {
  return {p.x, p.y, p.z};
}

}  // namespace

TEST(Augment, FlipTwiceIsIdentity) {
  const AugmentConfig flips = only(true, true, false, false, false);
  int both_flipped = 0;
  for (uint64_t seed = 0; seed < 64; ++seed) {
    const AugmentTransform t = sample(flips, seed);
    const Eigen::Vector3d diagonal = t.linear.diagonal();
    EXPECT_TRUE(t.linear.isDiagonal(0.0));
    EXPECT_EQ(std::abs(diagonal.x()), 1.0);
    EXPECT_EQ(std::abs(diagonal.y()), 1.0);
    EXPECT_EQ(diagonal.z(), 1.0);
    both_flipped += diagonal.x() < 0 && diagonal.y() < 0;

    const std::vector<Point> original = random_points(50, seed);
    std::vector<Point> points = original;
    t.apply(points);
    t.apply(points);
    for (size_t i = 0; i < points.size(); ++i) {
      ASSERT_EQ(xyz(points[i]), xyz(original[i])) << "seed " << seed << " point " << i;
    }
  }
  EXPECT_GT(both_flipped, 0) << "no seed flipped both axes";
}

TEST(Augment, FlipAlongXNegatesYAndAlongYNegatesX) {
  for (uint64_t seed = 0; seed < 32; ++seed) {
    const AugmentTransform along_x = sample(only(true, false, false, false, false), seed);
    const AugmentTransform along_y = sample(only(false, true, false, false, false), seed);
    EXPECT_EQ(along_x.linear(0, 0), 1.0);
    EXPECT_EQ(along_y.linear(1, 1), 1.0);
    if (!along_x.is_identity()) {
      EXPECT_EQ(along_x.apply({1, 2, 3}), Eigen::Vector3d(1, -2, 3));
    }
    if (!along_y.is_identity()) {
      EXPECT_EQ(along_y.apply({1, 2, 3}), Eigen::Vector3d(-1, 2, 3));
    }
  }
}

TEST(Augment, RotationIsCounterClockwiseAboutZAndKeepsRadiusAndHeight) {
  const AugmentConfig rotate = only(false, false, true, false, false);
  const std::vector<Point> original = random_points(200, 5);
  double largest_angle = 0;
  for (uint64_t seed = 0; seed < 50; ++seed) {
    const AugmentTransform t = sample(rotate, seed);
    const double angle = std::atan2(t.linear(1, 0), t.linear(0, 0));
    EXPECT_LE(std::abs(angle), std::numbers::pi / 4);
    largest_angle = std::max(largest_angle, std::abs(angle));
    // OpenPCDet's rotate_points_along_z: (x, y) -> (x cos a - y sin a, x sin a + y cos a).
    EXPECT_TRUE(t.apply({1, 0, 0}).isApprox(Eigen::Vector3d(std::cos(angle), std::sin(angle), 0)));
    EXPECT_TRUE(t.apply({0, 1, 0}).isApprox(Eigen::Vector3d(-std::sin(angle), std::cos(angle), 0)));
    EXPECT_NEAR(t.linear.determinant(), 1.0, 1e-12);

    std::vector<Point> points = original;
    t.apply(points);
    for (size_t i = 0; i < points.size(); ++i) {
      EXPECT_NEAR(std::hypot(points[i].x, points[i].y), std::hypot(original[i].x, original[i].y),
                  1e-4);
      EXPECT_EQ(points[i].z, original[i].z);
      EXPECT_EQ(points[i].r, original[i].r);
    }
  }
  EXPECT_GT(largest_angle, 0.6) << "angles should spread over [-pi/4, pi/4]";
}

TEST(Augment, ScalingIsUniformWithinRange) {
  const AugmentConfig scale = only(false, false, false, true, false);
  double smallest = 2, largest = 0;
  for (uint64_t seed = 0; seed < 200; ++seed) {
    const AugmentTransform t = sample(scale, seed);
    const double s = t.linear(0, 0);
    EXPECT_TRUE(t.linear.isApprox(s * Eigen::Matrix3d::Identity()));
    EXPECT_GE(s, 0.95);
    EXPECT_LE(s, 1.05);
    smallest = std::min(smallest, s), largest = std::max(largest, s);
    for (const Point& p : random_points(20, seed)) {
      EXPECT_NEAR(t.apply(xyz(p)).norm(), s * xyz(p).norm(), 1e-12);
    }
  }
  EXPECT_LT(smallest, 0.96);
  EXPECT_GT(largest, 1.04);
}

TEST(Augment, TranslationOffByDefaultAndNormalWhenOn) {
  for (uint64_t seed = 0; seed < 100; ++seed) {
    EXPECT_EQ(sample(AugmentConfig{}, seed).translation, Eigen::Vector3d::Zero());
  }
  const AugmentConfig translate = only(false, false, false, false, true);
  const int trials = 4000;
  Eigen::Vector3d sum = Eigen::Vector3d::Zero(), sum_sq = Eigen::Vector3d::Zero();
  for (uint64_t seed = 0; seed < trials; ++seed) {
    const AugmentTransform t = sample(translate, seed);
    EXPECT_EQ(t.linear, Eigen::Matrix3d::Identity());
    sum += t.translation;
    sum_sq += t.translation.cwiseProduct(t.translation);
  }
  const Eigen::Vector3d sigma{5, 5, 0.05};
  for (int a = 0; a < 3; ++a) {
    const double mean = sum[a] / trials;
    const double sd = std::sqrt(sum_sq[a] / trials - mean * mean);
    EXPECT_NEAR(mean, 0.0, 5 * sigma[a] / std::sqrt(trials)) << "axis " << a;
    EXPECT_NEAR(sd, sigma[a], 0.05 * sigma[a]) << "axis " << a;
  }
}

TEST(Augment, StagesComposeInOpenPCDetOrder) {
  // flip, then rotate, then scale, then translate: A = s R F; every stage draws its numbers
  // even when off, so the one-stage transforms of a seed are the factors of the full one.
  AugmentConfig all;
  all.translate = true;
  for (uint64_t seed = 0; seed < 50; ++seed) {
    const AugmentTransform full = sample(all, seed);
    const AugmentTransform flip = sample(only(true, true, false, false, false), seed);
    const AugmentTransform rotation = sample(only(false, false, true, false, false), seed);
    const AugmentTransform scale = sample(only(false, false, false, true, false), seed);
    const AugmentTransform shift = sample(only(false, false, false, false, true), seed);
    EXPECT_TRUE(full.linear.isApprox(scale.linear * rotation.linear * flip.linear, 1e-14));
    EXPECT_EQ(full.translation, shift.translation);
  }
}

TEST(Augment, LabelsStayAlignedWithPoints) {
  // Labels are a parallel array: after apply(), the point that carries label L is A p + t of
  // the point that carried it before, for every L.
  AugmentConfig cfg;
  cfg.translate = true;
  const std::vector<Point> original = random_points(500, 9);
  std::vector<uint32_t> labels(original.size());
  for (size_t i = 0; i < labels.size(); ++i) labels[i] = static_cast<uint32_t>(1000 + 7 * i);
  for (uint64_t seed = 0; seed < 10; ++seed) {
    const AugmentTransform t = sample(cfg, seed);
    std::vector<Point> points = original;
    t.apply(points);
    ASSERT_EQ(points.size(), labels.size());
    for (size_t i = 0; i < points.size(); ++i) {
      const uint32_t label = labels[i];
      const size_t before = (label - 1000) / 7;
      const Eigen::Vector3d expected = t.linear * xyz(original[before]) + t.translation;
      EXPECT_NEAR(points[i].x, expected.x(), 1e-5 * (1 + std::abs(expected.x())));
      EXPECT_NEAR(points[i].y, expected.y(), 1e-5 * (1 + std::abs(expected.y())));
      EXPECT_NEAR(points[i].z, expected.z(), 1e-5 * (1 + std::abs(expected.z())));
      EXPECT_EQ(points[i].r, original[before].r);
    }
  }
}

TEST(Augment, OriginAndNeighbourPosesMoveLikeThePoints) {
  AugmentConfig cfg;
  cfg.translate = true;
  const AugmentTransform t = sample(cfg, 17);
  ASSERT_FALSE(t.is_identity());
  // The sensor origin goes to t; rays keep their direction relative to it.
  const Eigen::Vector3d origin = t.apply(Eigen::Vector3d::Zero());
  EXPECT_EQ(origin, t.translation);
  const Pose m = t.as_matrix();
  EXPECT_EQ(m.row(3), Eigen::RowVector4d(0, 0, 0, 1));
  // A neighbour scan in this scan's frame: relative_pose maps its points here.
  Pose relative_pose = Pose::Identity();
  relative_pose.topLeftCorner<3, 3>() =
      Eigen::AngleAxisd(0.3, Eigen::Vector3d(0.1, 0.2, 1.0).normalized()).toRotationMatrix();
  relative_pose.topRightCorner<3, 1>() = Eigen::Vector3d(4.0, -1.5, 0.2);
  const Pose moved_pose = m * relative_pose;
  for (const Point& p : random_points(20, 3)) {
    const Eigen::Vector3d q = xyz(p);
    EXPECT_TRUE(t.apply(q).isApprox((m * q.homogeneous()).head<3>(), 1e-14));
    EXPECT_TRUE(t.apply(q).isApprox(origin + t.linear * q, 1e-14));
    const Eigen::Vector3d neighbour_here = (relative_pose * q.homogeneous()).head<3>();
    EXPECT_TRUE(t.apply(neighbour_here).isApprox((moved_pose * q.homogeneous()).head<3>(), 1e-12));
  }
}

TEST(Augment, SameSeedSameTransformDifferentSeedDifferent) {
  AugmentConfig cfg;
  cfg.translate = true;
  Rng a(123), b(123), c(124);
  for (int i = 0; i < 20; ++i) {
    const AugmentTransform ta = sample_augmentation(cfg, a);
    const AugmentTransform tb = sample_augmentation(cfg, b);
    const AugmentTransform tc = sample_augmentation(cfg, c);
    EXPECT_EQ(ta.linear, tb.linear);
    EXPECT_EQ(ta.translation, tb.translation);
    EXPECT_NE(ta.translation, tc.translation);
  }
}

TEST(Augment, EverySwitchOffIsIdentity) {
  const AugmentConfig none = only(false, false, false, false, false);
  for (uint64_t seed = 0; seed < 100; ++seed) {
    const AugmentTransform t = sample(none, seed);
    EXPECT_TRUE(t.is_identity());
    const std::vector<Point> original = random_points(10, seed);
    std::vector<Point> points = original;
    t.apply(points);
    for (size_t i = 0; i < points.size(); ++i) EXPECT_EQ(xyz(points[i]), xyz(original[i]));
  }
  EXPECT_TRUE(AugmentTransform{}.is_identity());
  EXPECT_EQ(AugmentTransform{}.as_matrix(), Pose::Identity());
}

TEST(Augment, EachFlipHappensHalfOfTheTime) {
  const AugmentConfig flips = only(true, true, false, false, false);
  const int trials = 4000;
  int along_x = 0, along_y = 0, both = 0;
  for (int i = 0; i < trials; ++i) {
    Rng rng = Rng::derive(2024, static_cast<uint64_t>(i));
    const AugmentTransform t = sample_augmentation(flips, rng);
    const bool x = t.linear(1, 1) < 0, y = t.linear(0, 0) < 0;
    along_x += x, along_y += y, both += x && y;
  }
  // Binomial(4000, 0.5): sd 31.6; Binomial(4000, 0.25): sd 27.4; 5 sd.
  EXPECT_NEAR(along_x, trials / 2, 158);
  EXPECT_NEAR(along_y, trials / 2, 158);
  EXPECT_NEAR(both, trials / 4, 137) << "the two flips should be independent";
}

TEST(Augment, RejectsBadConfig) {
  Rng rng(1);
  AugmentConfig negative_rotation;
  negative_rotation.rotation_max = -0.1;
  EXPECT_THROW(sample_augmentation(negative_rotation, rng), Error);
  AugmentConfig reversed_scale;
  reversed_scale.scale_min = 1.1;
  EXPECT_THROW(sample_augmentation(reversed_scale, rng), Error);
  AugmentConfig zero_scale;
  zero_scale.scale_min = 0.0;
  EXPECT_THROW(sample_augmentation(zero_scale, rng), Error);
  AugmentConfig negative_sigma;
  negative_sigma.translation_sigma.z() = -1.0;
  EXPECT_THROW(sample_augmentation(negative_sigma, rng), Error);
}
