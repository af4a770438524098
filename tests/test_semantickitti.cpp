// SemanticKITTI files: round trips of every format, the real scan, and bad input.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <limits>

#include "core/classes.hpp"
#include "core/eigen.hpp"
#include "core/grid.hpp"
#include "core/io.hpp"
#include "engine/data/semantickitti.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
namespace fs = std::filesystem;

using pillarseg::test::error_of;

namespace {

void write_text(const fs::path& path, const std::string& text) {
  fs::create_directories(path.parent_path());
  std::ofstream(path) << text;
}

// The error message of f(), or "" if it did not throw pillarseg::Error.
const char* kCalibText =
    "P0: 7.188560000000e+02 0 6.071928000000e+02 0 0 7.188560000000e+02 1.852157000000e+02 0 0 0 1 0\n"
    "P1: 1 0 0 0 0 1 0 0 0 0 1 0\nP2: 1 0 0 0 0 1 0 0 0 0 1 0\nP3: 1 0 0 0 0 1 0 0 0 0 1 0\n"
    "Tr: 4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 "
    "-7.210626507497e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 "
    "9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01\n";

}  // namespace

TEST(SemanticKitti, BinAndLabelRoundTrip) {
  const auto dir = test::temp_dir();
  std::vector<Point> pts = {{1.5f, -2.25f, 0.125f, 0.5f}, {-49.9f, 24.9f, -2.4f, 0.0f}, {0, 0, 0, 1}};
  std::vector<uint32_t> labels = {10u | (3u << 16), 40, 252u | (9u << 16)};
  write_bin(dir / "a.bin", pts);
  write_labels(dir / "a.label", labels);
  EXPECT_EQ(fs::file_size(dir / "a.bin"), 48u);
  const Scan s = read_scan(dir / "a.bin", dir / "a.label");
  ASSERT_EQ(s.points.size(), 3u);
  for (size_t i = 0; i < 3; ++i) {
    EXPECT_EQ(s.points[i].x, pts[i].x);
    EXPECT_EQ(s.points[i].y, pts[i].y);
    EXPECT_EQ(s.points[i].z, pts[i].z);
    EXPECT_EQ(s.points[i].r, pts[i].r);
  }
  EXPECT_EQ(s.labels, labels);
  EXPECT_EQ(s.dropped_nonfinite, 0u);
}

TEST(SemanticKitti, PosesAndCalibRoundTripAndLidarFrame) {
  const auto dir = test::temp_dir();
  write_text(dir / "calib.txt", kCalibText);
  const Calib calib = read_calib(dir / "calib.txt");
  EXPECT_NEAR(calib.Tr(0, 1), -9.999672484946e-01, 1e-15);
  EXPECT_NEAR(calib.Tr(2, 3), -2.921968648686e-01, 1e-15);
  EXPECT_EQ(calib.Tr(3, 3), 1.0);
  EXPECT_NEAR(calib.P[0](0, 0), 718.856, 1e-9);

  std::vector<Pose> poses(3, Pose::Identity());
  poses[1](2, 3) = 0.8;  // cam0 moves forward along its z axis
  poses[2](2, 3) = 1.7;
  poses[2].topLeftCorner<3, 3>() = Eigen::AngleAxisd(0.1, Eigen::Vector3d::UnitY()).toRotationMatrix();
  write_poses(dir / "poses.txt", poses);
  write_calib(dir / "calib2.txt", calib);
  const auto back = read_poses(dir / "poses.txt");
  ASSERT_EQ(back.size(), 3u);
  for (size_t i = 0; i < 3; ++i) EXPECT_TRUE(back[i].isApprox(poses[i], 1e-12));
  EXPECT_TRUE(read_calib(dir / "calib2.txt").Tr.isApprox(calib.Tr, 1e-12));

  // LiDAR frame: cam0 forward (z) is LiDAR forward (x) for KITTI's Tr, so moving 0.8 m along
  // cam0 z is about 0.8 m along LiDAR x.
  const auto lidar = lidar_poses(back, calib);
  EXPECT_TRUE(lidar[0].isApprox(Pose::Identity(), 1e-12));
  EXPECT_NEAR(lidar[1](0, 3), 0.8, 2e-3);
  EXPECT_NEAR(lidar[1](1, 3), 0.0, 2e-3);
  const Pose expected = calib.Tr.inverse() * back[2] * calib.Tr;
  EXPECT_TRUE(lidar[2].isApprox(expected, 1e-12));
}

TEST(SemanticKitti, SequenceLayoutPosesAndRelative) {
  const auto root = test::temp_dir();
  const fs::path seq = root / "sequences" / "03";
  for (int f = 0; f < 3; ++f) {
    write_bin(seq / "velodyne" / fmt::format("{:06}.bin", f), {{float(f), 0, 0, 0}});
    if (f != 1) write_labels(seq / "labels" / fmt::format("{:06}.label", f), {40});
  }
  write_text(seq / "calib.txt", "Tr: 1 0 0 0 0 1 0 0 0 0 1 0\n");
  write_text(seq / "poses.txt", "1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 2 0 1 0 0 0 0 1 0\n1 0 0 5 0 1 0 1 0 0 1 0\n");
  EXPECT_EQ(list_sequences(root), std::vector<int>{3});
  Sequence s(root, 3);
  ASSERT_EQ(s.size(), 3u);
  EXPECT_TRUE(s.has_labels(0));
  EXPECT_FALSE(s.has_labels(1));
  EXPECT_TRUE(s.load(1).labels.empty());
  EXPECT_EQ(s.load(2).labels.size(), 1u);
  // Scan 2 seen from scan 1: translation (5, 1, 0) - (2, 0, 0).
  const Pose rel = s.relative(1, 2);
  EXPECT_NEAR(rel(0, 3), 3.0, 1e-12);
  EXPECT_NEAR(rel(1, 3), 1.0, 1e-12);
  EXPECT_EQ(split_sequences("val"), std::vector<int>{8});
  EXPECT_EQ(split_sequences("train").size(), 10u);
  EXPECT_THROW(split_sequences("test"), Error);
}

TEST(SemanticKitti, RealScanCountAndClassHistogram) {
  const fs::path seq = test::shared_data_dir() / "semantickitti" / "sequences" / "99";
  if (!fs::exists(seq / "velodyne" / "000000.bin")) GTEST_SKIP() << "shared data not found at " << seq;
  const Scan s = read_scan(seq / "velodyne" / "000000.bin", seq / "labels" / "000000.label");
  EXPECT_EQ(s.points.size(), 123389u);
  EXPECT_EQ(s.labels.size(), 123389u);
  EXPECT_EQ(s.dropped_nonfinite, 0u);
  const ClassTable t = ClassTable::defaults();
  std::array<int64_t, kNumClassIds> hist{};
  for (uint32_t l : s.labels) hist[t.class_of(l)]++;
  // Computed independently (numpy) from the raw files and DESIGN.md's table.
  const std::array<int64_t, kNumClassIds> expected = {6924,  1534, 161,  20,   0,    20975, 30092,
                                                      84,    2126, 2056, 24514, 3978, 30925};
  EXPECT_EQ(hist, expected);
  int64_t in_range = 0;
  const GridSpec grid;
  for (const Point& p : s.points) in_range += grid.contains(p.x, p.y, p.z);
  EXPECT_EQ(in_range, 108527);
}

TEST(SemanticKitti, BadInputGivesClearErrors) {
  const auto dir = test::temp_dir();
  // Truncated .bin (not a multiple of 16 bytes).
  write_file_atomic(dir / "trunc.bin", "0123456789abcdefXYZ", 19);
  std::string msg = error_of([&] { read_scan(dir / "trunc.bin"); });
  EXPECT_NE(msg.find("trunc.bin"), std::string::npos) << msg;
  EXPECT_NE(msg.find("multiple of 16"), std::string::npos) << msg;

  // Label count mismatch.
  write_bin(dir / "two.bin", {{1, 2, 3, 0}, {4, 5, 6, 0}});
  write_labels(dir / "three.label", {1, 2, 3});
  msg = error_of([&] { read_scan(dir / "two.bin", dir / "three.label"); });
  EXPECT_NE(msg.find("three.label"), std::string::npos) << msg;
  EXPECT_NE(msg.find("3 labels"), std::string::npos) << msg;
  write_file_atomic(dir / "odd.label", "abcde", 5);
  msg = error_of([&] { read_labels(dir / "odd.label"); });
  EXPECT_NE(msg.find("multiple of 4"), std::string::npos) << msg;

  // Malformed pose lines.
  write_text(dir / "poses_short.txt", "1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n");
  msg = error_of([&] { read_poses(dir / "poses_short.txt"); });
  EXPECT_NE(msg.find("poses_short.txt:2"), std::string::npos) << msg;
  EXPECT_NE(msg.find("11 numbers"), std::string::npos) << msg;
  write_text(dir / "poses_word.txt", "1 0 0 x 0 1 0 0 0 0 1 0\n");
  msg = error_of([&] { read_poses(dir / "poses_word.txt"); });
  EXPECT_NE(msg.find("poses_word.txt:1"), std::string::npos) << msg;
  write_text(dir / "poses_nan.txt", "1 0 0 nan 0 1 0 0 0 0 1 0\n");
  EXPECT_NE(error_of([&] { read_poses(dir / "poses_nan.txt"); }), "");

  // Missing Tr:, and a Tr line with too few numbers.
  write_text(dir / "calib_notr.txt", "P0: 1 0 0 0 0 1 0 0 0 0 1 0\n");
  msg = error_of([&] { read_calib(dir / "calib_notr.txt"); });
  EXPECT_NE(msg.find("Tr:"), std::string::npos) << msg;
  EXPECT_NE(msg.find("calib_notr.txt"), std::string::npos) << msg;
  write_text(dir / "calib_short.txt", "Tr: 1 0 0\n");
  EXPECT_NE(error_of([&] { read_calib(dir / "calib_short.txt"); }).find("3 numbers"), std::string::npos);

  // Missing file.
  msg = error_of([&] { read_scan(dir / "nope.bin"); });
  EXPECT_NE(msg.find("nope.bin"), std::string::npos) << msg;
  // Missing sequence directory.
  EXPECT_NE(error_of([&] { Sequence(dir, 5); }).find("velodyne"), std::string::npos);
}

TEST(SemanticKitti, NonFinitePointsAreDroppedWithTheirLabels) {
  const auto dir = test::temp_dir();
  const float nan = std::numeric_limits<float>::quiet_NaN(), inf = std::numeric_limits<float>::infinity();
  write_bin(dir / "nan.bin", {{1, 1, 1, 0}, {nan, 0, 0, 0}, {2, 2, 2, 0}, {0, inf, 0, 0}, {3, 3, 3, nan}});
  write_labels(dir / "nan.label", {10, 11, 12, 13, 14});
  const Scan s = read_scan(dir / "nan.bin", dir / "nan.label");
  ASSERT_EQ(s.points.size(), 2u);
  EXPECT_EQ(s.dropped_nonfinite, 3u);
  EXPECT_EQ(s.labels, (std::vector<uint32_t>{10, 12}));
  EXPECT_EQ(s.points[1].x, 2.0f);
}

TEST(SemanticKitti, EmptyScanIsValid) {
  const auto dir = test::temp_dir();
  write_bin(dir / "empty.bin", {});
  write_labels(dir / "empty.label", {});
  const Scan s = read_scan(dir / "empty.bin", dir / "empty.label");
  EXPECT_TRUE(s.points.empty());
  EXPECT_TRUE(s.labels.empty());
}
