// Augmentation: flips, rotation, scaling and translation follow OpenPCDet's conventions and
// order (checked stage by stage and composed), labels, origin and neighbour poses move with the
// points, seeds reproduce, switches turn stages off, flips happen half of the time. Domain
// randomisation: sensor tilt and height after the other stages, reflectance jitter and dropout,
// point dropout with the labels, the ground bend's heights by hand, bad settings rejected; a model without reflectance
// (model.reflectance: false) sees r = 0 on the host path and the backend pipeline.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <numbers>
#include <string>
#include <vector>

#include "core/eigen.hpp"
#include "core/error.hpp"
#include "engine/backend/backend.hpp"
#include "engine/data/augment.hpp"
#include "engine/model/run_config.hpp"
#include "engine/pipeline/scan_inputs.hpp"
#include "engine/pipeline/scan_pipeline.hpp"
#include "tests/support/tiny_model.hpp"

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

// ---- domain randomisation -------------------------------------------------------------------

TEST(Augment, TiltAndHeightAreSmallRotationsAndLiftsAfterTheOtherDraws) {
  AugmentConfig cfg = only(true, true, true, true, false);
  cfg.tilt = 0.02;
  cfg.height = 0.1;
  const AugmentConfig plain = only(true, true, true, true, false);
  AugmentConfig tilt_only = only(false, false, false, false, false);
  tilt_only.tilt = 0.02;
  const int trials = 3000;
  double sum_sq_angle = 0, sum_lift = 0, sum_sq_lift = 0;
  for (uint64_t seed = 0; seed < trials; ++seed) {
    const AugmentTransform full = sample(cfg, seed);
    const AugmentTransform without = sample(plain, seed);
    const AugmentTransform tilt = sample(tilt_only, seed);
    // A = s R F T: the other stages' values do not change when tilt and height are on.
    EXPECT_TRUE(full.linear.isApprox(without.linear * tilt.linear, 1e-14));
    EXPECT_EQ(full.translation.head<2>(), Eigen::Vector2d::Zero());
    // The tilt is a rotation about a horizontal axis: orthonormal, and it turns z by its angle.
    EXPECT_TRUE((tilt.linear * tilt.linear.transpose()).isIdentity(1e-12));
    EXPECT_NEAR(tilt.linear.determinant(), 1.0, 1e-12);
    const double angle = std::acos(std::clamp(tilt.linear(2, 2), -1.0, 1.0));
    sum_sq_angle += angle * angle;
    sum_lift += full.translation.z();
    sum_sq_lift += full.translation.z() * full.translation.z();
  }
  // Pitch and roll each N(0, 0.02^2): the angle of z is about sqrt(pitch^2 + roll^2), mean
  // square 2 * 0.02^2.
  EXPECT_NEAR(std::sqrt(sum_sq_angle / trials), std::sqrt(2.0) * 0.02, 0.002);
  const double mean = sum_lift / trials;
  EXPECT_NEAR(mean, 0.0, 5 * 0.1 / std::sqrt(trials));
  EXPECT_NEAR(std::sqrt(sum_sq_lift / trials - mean * mean), 0.1, 0.006);
}

TEST(Augment, RandomisationJittersReflectanceLinearlyPerScan) {
  AugmentConfig cfg;
  cfg.reflectance_jitter = true;
  cfg.reflectance_noise = 0.0;
  const std::vector<Point> original = random_points(400, 5);
  for (uint64_t seed = 0; seed < 20; ++seed) {
    Rng rng(seed);
    const ScanRandomisation r = sample_randomisation(cfg, rng);
    EXPECT_GE(r.scale, cfg.reflectance_scale_min);
    EXPECT_LE(r.scale, cfg.reflectance_scale_max);
    std::vector<Point> points = original;
    std::vector<uint32_t> labels;
    r.apply(points, labels);
    ASSERT_EQ(points.size(), original.size());
    for (size_t i = 0; i < points.size(); ++i) {
      EXPECT_EQ(xyz(points[i]), xyz(original[i]));
      const double expected = std::clamp(r.scale * original[i].r + r.offset, 0.0, 1.0);
      EXPECT_NEAR(points[i].r, expected, 1e-6);
    }
  }
  // With noise: r' - (a r + b) has the noise's spread where nothing is clipped.
  cfg.reflectance_noise = 0.05;
  Rng rng(77);
  const ScanRandomisation r = sample_randomisation(cfg, rng);
  std::vector<Point> points = original;
  std::vector<uint32_t> labels;
  r.apply(points, labels);
  double sum = 0, sum_sq = 0;
  int n = 0;
  for (size_t i = 0; i < points.size(); ++i) {
    const double clean = r.scale * original[i].r + r.offset;
    if (clean < 0.2 || clean > 0.8) continue;
    const double e = points[i].r - clean;
    sum += e, sum_sq += e * e, ++n;
  }
  ASSERT_GT(n, 100);
  EXPECT_NEAR(std::sqrt(sum_sq / n - (sum / n) * (sum / n)), 0.05, 0.01);
}

TEST(Augment, RandomisationDropsReflectanceAndPointsWithTheirLabels) {
  const std::vector<Point> original = random_points(2000, 8);
  std::vector<uint32_t> original_labels(original.size());
  for (size_t i = 0; i < original.size(); ++i) original_labels[i] = static_cast<uint32_t>(i);
  AugmentConfig cfg;
  cfg.reflectance_dropout = 1.0;
  cfg.point_dropout = 0.5;
  double dropped_share = 0;
  const int scans = 40;
  for (uint64_t seed = 0; seed < scans; ++seed) {
    Rng rng(seed);
    const ScanRandomisation r = sample_randomisation(cfg, rng);
    EXPECT_TRUE(r.zero_reflectance);
    EXPECT_GE(r.drop, 0.0);
    EXPECT_LT(r.drop, 0.5);
    std::vector<Point> points = original;
    std::vector<uint32_t> labels = original_labels;
    r.apply(points, labels);
    ASSERT_EQ(points.size(), labels.size());
    // The kept points are in their order, with their labels, and every r is 0.
    for (size_t i = 0; i < points.size(); ++i) {
      EXPECT_EQ(xyz(points[i]), xyz(original[labels[i]]));
      EXPECT_EQ(points[i].r, 0.0f);
      if (i > 0) {
        EXPECT_GT(labels[i], labels[i - 1]);
      }
    }
    const double share = 1.0 - static_cast<double>(points.size()) / original.size();
    EXPECT_NEAR(share, r.drop, 5 * std::sqrt(0.25 / original.size()) + 1e-9);
    dropped_share += share / scans;
    // Same randomisation, same result.
    std::vector<Point> again = original;
    std::vector<uint32_t> again_labels = original_labels;
    r.apply(again, again_labels);
    EXPECT_EQ(again_labels, labels);
  }
  EXPECT_NEAR(dropped_share, 0.25, 0.06) << "U(0, 0.5) per scan";
  // Switched off: nothing changes, and the draws are the same.
  AugmentConfig off;
  EXPECT_FALSE(off.randomises_points());
  EXPECT_TRUE(cfg.randomises_points());
  Rng a(3), b(3);
  const ScanRandomisation ra = sample_randomisation(off, a), rb = sample_randomisation(cfg, b);
  EXPECT_TRUE(ra.is_identity());
  EXPECT_EQ(ra.point_seed, rb.point_seed);
  std::vector<Point> points = original;
  std::vector<uint32_t> labels = original_labels;
  ra.apply(points, labels);
  EXPECT_EQ(labels, original_labels);
}

TEST(Augment, GroundBendRaisesThePointsBeyondItsLineByAVerticalCurve) {
  GroundBend bend;
  bend.direction = {0.6, 0.8};
  bend.start = 10.0;
  bend.length = 8.0;
  bend.grade = 0.05;
  // d = 0.6 x + 0.8 y - 10 beyond the line.
  std::vector<Point> points = {
      {0.0f, 0.0f, -1.7f, 0.3f},    // the origin: d = -10, unchanged
      {6.0f, 8.0f, -1.0f, 0.3f},    // d = 0: on the line, unchanged
      {-8.0f, 6.0f, 0.5f, 0.3f},    // across the direction: d = -10, unchanged
      {9.0f, 12.0f, -1.5f, 0.3f},   // d = 5: in the curve, 0.05 * 25 / 16 = 0.078125
      {12.0f, 16.0f, -1.5f, 0.3f},  // d = 10: beyond it, 0.05 * (10 - 4) = 0.3
      {24.0f, 32.0f, 0.0f, 0.3f},   // d = 30: 0.05 * 26 = 1.3
  };
  const std::vector<double> expected = {0.0, 0.0, 0.0, 0.078125, 0.3, 1.3};
  const std::vector<Point> original = points;
  bend.apply(points);
  for (size_t i = 0; i < points.size(); ++i) {
    EXPECT_NEAR(bend.offset(original[i].x, original[i].y), expected[i], 1e-12) << i;
    EXPECT_FLOAT_EQ(points[i].z, static_cast<float>(original[i].z + expected[i])) << i;
    EXPECT_EQ(points[i].x, original[i].x);
    EXPECT_EQ(points[i].y, original[i].y);
    EXPECT_EQ(points[i].r, original[i].r);
  }
  // Continuous with a continuous slope where the curve meets the grade (d = length = 8).
  const double h = 1e-6;
  const auto at = [&](double d) { return bend.offset(0.6 * (d + 10.0), 0.8 * (d + 10.0)); };
  EXPECT_NEAR(at(8.0 - h), at(8.0 + h), 3 * 0.05 * h);
  EXPECT_NEAR((at(8.0) - at(8.0 - h)) / h, 0.05, 1e-5);
  EXPECT_NEAR((at(8.0 + h) - at(8.0)) / h, 0.05, 1e-5);
  EXPECT_NEAR((at(h) - at(0.0)) / h, 0.0, 1e-5);
  // A dip: the opposite grade mirrors the heights.
  bend.grade = -0.05;
  EXPECT_NEAR(bend.offset(24.0, 32.0), -1.3, 1e-12);
}

TEST(Augment, GroundBendDrawsOnlyWhenOnAndSpreadsAsConfigured) {
  AugmentConfig off;
  Rng untouched(3), reference(3);
  EXPECT_TRUE(sample_ground_bend(off, untouched).is_identity());
  EXPECT_EQ(untouched.state(), reference.state()) << "a bend that is off draws nothing";

  AugmentConfig cfg;
  cfg.grade_change = 0.04;
  cfg.bend_start_min = 6.0;
  cfg.bend_start_max = 20.0;
  cfg.bend_length = 12.0;
  const int trials = 4000;
  double sum_grade = 0, sum_sq_grade = 0, sum_cos = 0, sum_sin = 0, low = 1e9, high = -1e9;
  for (uint64_t seed = 0; seed < trials; ++seed) {
    Rng rng(seed);
    const GroundBend b = sample_ground_bend(cfg, rng);
    EXPECT_NEAR(b.direction.norm(), 1.0, 1e-12);
    EXPECT_EQ(b.length, 12.0);
    low = std::min(low, b.start), high = std::max(high, b.start);
    sum_grade += b.grade, sum_sq_grade += b.grade * b.grade;
    sum_cos += b.direction.x(), sum_sin += b.direction.y();
    Rng again(seed);
    const GroundBend same = sample_ground_bend(cfg, again);
    EXPECT_EQ(same.grade, b.grade);
    EXPECT_EQ(same.start, b.start);
  }
  EXPECT_GE(low, 6.0);
  EXPECT_LT(high, 20.0);
  EXPECT_LT(low, 6.5);
  EXPECT_GT(high, 19.5);
  const double mean = sum_grade / trials;
  EXPECT_NEAR(mean, 0.0, 5 * 0.04 / std::sqrt(trials));
  EXPECT_NEAR(std::sqrt(sum_sq_grade / trials - mean * mean), 0.04, 0.003);
  // Directions uniform on the circle: the mean unit vector near 0.
  EXPECT_NEAR(sum_cos / trials, 0.0, 0.05);
  EXPECT_NEAR(sum_sin / trials, 0.0, 0.05);
}

TEST(Augment, RejectsBadRandomisation) {
  Rng rng(1);
  const auto rejects = [&](auto change) {
    AugmentConfig cfg;
    change(cfg);
    EXPECT_THROW(validate_augmentation(cfg), Error);
    EXPECT_THROW(sample_augmentation(cfg, rng), Error);
  };
  rejects([](AugmentConfig& c) { c.tilt = -0.01; });
  rejects([](AugmentConfig& c) { c.tilt = 0.6; });
  rejects([](AugmentConfig& c) { c.height = -1; });
  rejects([](AugmentConfig& c) { c.reflectance_scale_min = 0.0; });
  rejects([](AugmentConfig& c) { c.reflectance_scale_max = 0.5; });
  rejects([](AugmentConfig& c) { c.reflectance_noise = -0.1; });
  rejects([](AugmentConfig& c) { c.reflectance_dropout = 1.5; });
  rejects([](AugmentConfig& c) { c.point_dropout = 1.0; });
  rejects([](AugmentConfig& c) { c.grade_change = -0.01; });
  rejects([](AugmentConfig& c) { c.grade_change = 0.5; });
  rejects([](AugmentConfig& c) { c.bend_start_min = -1.0; });
  rejects([](AugmentConfig& c) { c.bend_start_max = 2.0; });
  rejects([](AugmentConfig& c) { c.bend_length = 0.0; });
  try {
    AugmentConfig c;
    c.point_dropout = 2.0;
    validate_augmentation(c);
    ADD_FAILURE() << "point_dropout 2 accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("point_dropout"), std::string::npos) << e.what();
  }
}

TEST(Augment, ModelWithoutReflectanceSeesZeroReflectance) {
  ModelConfig with = test::tiny_config(OccupancyInput::None, false, /*grid_map=*/true);
  ModelConfig without = with;
  without.reflectance = false;
  const GridSpec& g = with.grid;
  Rng rng(12);
  std::vector<Point> points(300);
  for (Point& p : points)
    p = {static_cast<float>(rng.uniform(g.x_min, g.x_max)),
         static_cast<float>(rng.uniform(g.y_min, g.y_max)),
         static_cast<float>(rng.uniform(g.z_min, g.z_max)),
         static_cast<float>(rng.uniform(0.1, 1))};
  std::vector<Point> dark = points;
  for (Point& p : dark) p.r = 0.0f;
  const Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  const ScanInputs seen =
      compute_scan_inputs(points, origin, without, host::SampleMode::Inference, nullptr);
  const ScanInputs expected =
      compute_scan_inputs(dark, origin, with, host::SampleMode::Inference, nullptr);
  const ScanInputs lit =
      compute_scan_inputs(points, origin, with, host::SampleMode::Inference, nullptr);
  ASSERT_GT(seen.pillar_points.numel(), 0);
  ASSERT_EQ(seen.pillar_points.numel(), expected.pillar_points.numel());
  for (int64_t i = 0; i < seen.pillar_points.numel(); ++i)
    EXPECT_EQ(seen.pillar_points[i], expected.pillar_points[i]);
  ASSERT_EQ(seen.grid_map.numel(), expected.grid_map.numel());
  for (int64_t i = 0; i < seen.grid_map.numel(); ++i)
    EXPECT_EQ(seen.grid_map[i], expected.grid_map[i]);
  double lit_sum = 0;
  for (int64_t i = 3; i < lit.pillar_points.numel(); i += 10) lit_sum += lit.pillar_points[i];
  EXPECT_GT(lit_sum, 1.0) << "with reflectance the decoration carries it";
  // The backend pipeline's points: r = 0 for the model without reflectance, the caller's intact.
  const std::unique_ptr<Backend> backend = make_cpu_backend();
  ScanPipeline pipeline(without, *backend);
  const Ref loaded = pipeline.load_points(points);
  ASSERT_EQ(loaded.dim(0), static_cast<int64_t>(points.size()));
  for (size_t i = 0; i < points.size(); ++i) {
    EXPECT_EQ(loaded.data[4 * i + 3], 0.0f);
    EXPECT_EQ(loaded.data[4 * i], points[i].x);
    EXPECT_GT(points[i].r, 0.0f);
  }
}

TEST(Augment, RunConfigReadsTheRandomisationKeys) {
  const RunConfig c = parse_run_config(
      "model: {reflectance: false}\n"
      "train:\n"
      "  augmentation: {tilt_deg: 2.0, height: 0.07, reflectance_jitter: true,\n"
      "                 reflectance_dropout: 0.25, point_dropout: 0.3, grade_change: 0.03}\n",
      "dr.yaml");
  EXPECT_FALSE(c.model.reflectance);
  const AugmentConfig& a = c.train.augmentation;
  EXPECT_NEAR(a.tilt, 2.0 * std::numbers::pi / 180.0, 1e-15);
  EXPECT_EQ(a.height, 0.07);
  EXPECT_TRUE(a.reflectance_jitter);
  EXPECT_EQ(a.reflectance_dropout, 0.25);
  EXPECT_EQ(a.point_dropout, 0.3);
  EXPECT_EQ(a.grade_change, 0.03);
  EXPECT_TRUE(parse_run_config("train: {epochs: 1}\n", "plain.yaml").model.reflectance);
  try {
    parse_run_config("train: {augmentation: {point_dropout: 1.5}}\n", "bad.yaml");
    ADD_FAILURE() << "point_dropout 1.5 accepted";
  } catch (const Error& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("bad.yaml"), std::string::npos) << what;
    EXPECT_NE(what.find("point_dropout"), std::string::npos) << what;
  }
}
