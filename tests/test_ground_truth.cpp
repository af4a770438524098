// Ground truth: the sparse rule on hand-built point sets (ties, weights, borders, ranges)
// and against a std::map reference; dense aggregation on small synthetic sequences written in
// SemanticKITTI layout (poses through a KITTI-like Tr): static, moving and parked points,
// neighbour selection, augmentation consistency, cropping; the builder's cache keys; and the
// `pillarseg gt` command end to end.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <fstream>
#include <map>
#include <numbers>

#include "core/classes.hpp"
#include "core/eigen.hpp"
#include "core/grid.hpp"
#include "core/io.hpp"
#include "core/parallel.hpp"
#include "core/rng.hpp"
#include "engine/cli/gt_command.hpp"
#include "engine/data/cache.hpp"
#include "engine/data/class_table_yaml.hpp"
#include "engine/data/ground_truth.hpp"
#include "engine/data/semantickitti.hpp"
#include "engine/util/image.hpp"
#include "host/rasterize_labels.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
namespace fs = std::filesystem;

using pillarseg::test::error_of;

namespace {

// Raw SemanticKITTI ids used below and their classes.
constexpr uint32_t kCar = 10;          // vehicle (1)
constexpr uint32_t kPerson = 30;       // person (2)
constexpr uint32_t kRoad = 40;         // road (5)
constexpr uint32_t kSidewalk = 48;     // sidewalk (6)
constexpr uint32_t kBuilding = 50;     // building (8)
constexpr uint32_t kMovingCar = 252;   // vehicle (1), moving
constexpr uint32_t kUnlabeledRaw = 0;  // unlabeled (0)
constexpr uint8_t kVehicle = 1, kPersonClass = 2, kRoadClass = 5, kSidewalkClass = 6,
                  kBuildingClass = 8, kVegetationClass = 10, kTerrainClass = 12;

// A small grid: x [-2, 2), y [-1, 1.5), cell 0.5 -> W = 8, H = 5.
GridSpec small_grid() {
  GridSpec g;
  g.x_min = -2, g.x_max = 2, g.y_min = -1, g.y_max = 1.5, g.cell = 0.5;
  return g;
}

// Centre of cell (ix, iy) of `grid` at height z.
Point centre(const GridSpec& grid, int ix, int iy, float z = -1.0f) {
  return {static_cast<float>(grid.x_min + (ix + 0.5) * grid.cell),
          static_cast<float>(grid.y_min + (iy + 0.5) * grid.cell), z, 0.5f};
}

// Labelled points built up by repetition: add(n, point, label).
struct PointSet {
  std::vector<Point> points;
  std::vector<uint32_t> labels;
  void add(int n, const Point& p, uint32_t label) {
    for (int i = 0; i < n; ++i) points.push_back(p), labels.push_back(label);
  }
};

// Cells of a map that are not unlabeled: (iy, ix) -> class.
std::map<std::pair<int64_t, int64_t>, int> labelled_cells(const Tensor<uint8_t>& map) {
  std::map<std::pair<int64_t, int64_t>, int> cells;
  for (int64_t iy = 0; iy < map.dim(0); ++iy)
    for (int64_t ix = 0; ix < map.dim(1); ++ix)
      if (map(iy, ix) != 0) cells[{iy, ix}] = map(iy, ix);
  return cells;
}

// The sparse rule written the plain way: std::map of per-cell counts, explicit range tests.
Tensor<uint8_t> reference_rasterize(const std::vector<Point>& points,
                                    const std::vector<uint8_t>& classes, const ClassTable& table,
                                    const GridSpec& grid) {
  std::map<int64_t, std::array<int64_t, kNumClassIds>> counts;
  for (size_t i = 0; i < points.size(); ++i) {
    const double x = points[i].x, y = points[i].y, z = points[i].z;
    if (x < grid.x_min || x >= grid.x_max || y < grid.y_min || y >= grid.y_max || z < grid.z_min ||
        z >= grid.z_max)
      continue;
    const auto ix = static_cast<int64_t>(std::floor((x - grid.x_min) / grid.cell));
    const auto iy = static_cast<int64_t>(std::floor((y - grid.y_min) / grid.cell));
    counts[iy * grid.width() + ix][classes[i]] += 1;
  }
  Tensor<uint8_t> map({grid.height(), grid.width()});
  for (const auto& [cell, n] : counts) {
    int best = 0;
    int64_t best_score = 0;
    for (int k = 1; k < kNumClassIds; ++k) {
      if (table.gt_weight(k) * n[k] > best_score) best_score = table.gt_weight(k) * n[k], best = k;
    }
    map[cell] = static_cast<uint8_t>(best);
  }
  return map;
}

std::vector<uint8_t> classes_of(const std::vector<uint32_t>& labels, const ClassTable& table) {
  std::vector<uint8_t> classes;
  for (uint32_t label : labels) classes.push_back(table.class_of(label));
  return classes;
}

// KITTI's LiDAR -> cam0 transform (sequence 00), so that poses go through a real calibration.
Pose kitti_tr() {
  Pose tr = Pose::Identity();
  tr.topRows<3>() << 4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03,
      -1.198459927713e-02, -7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01,
      -5.403984729748e-02, 9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03,
      -2.921968648686e-01;
  return tr;
}

// LiDAR-frame pose: rotation by `yaw` about z, then translation (x, y, z).
Pose lidar_pose(double yaw, double x, double y, double z = 0.0) {
  Pose p = Pose::Identity();
  p.topLeftCorner<3, 3>() = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  p.topRightCorner<3, 1>() = Eigen::Vector3d(x, y, z);
  return p;
}

struct SyntheticScan {
  Pose pose = Pose::Identity();  // LiDAR frame, as Sequence::pose returns it
  PointSet points;               // in the scan's own LiDAR frame
};

// Writes ROOT/sequences/SS in SemanticKITTI layout: cam0 poses Tr * T * inv(Tr) so that
// Sequence::pose gives back T.
void write_sequence(const fs::path& root, int id, const std::vector<SyntheticScan>& scans) {
  const fs::path dir = root / "sequences" / sequence_name(id);
  Calib calib;
  for (auto& P : calib.P) P = Eigen::Matrix<double, 3, 4>::Identity();
  calib.Tr = kitti_tr();
  write_calib(dir / "calib.txt", calib);
  std::vector<Pose> cam0;
  for (const SyntheticScan& s : scans) cam0.push_back(calib.Tr * s.pose * calib.Tr.inverse());
  write_poses(dir / "poses.txt", cam0);
  for (size_t i = 0; i < scans.size(); ++i) {
    write_bin(dir / "velodyne" / fmt::format("{:06}.bin", i), scans[i].points.points);
    write_labels(dir / "labels" / fmt::format("{:06}.label", i), scans[i].points.labels);
  }
}

// Moves a map rotated by +90 degrees about z on a square grid centred on the sensor:
// (x, y) -> (-y, x) takes cell (ix, iy) to (N-1-iy, ix).
Tensor<uint8_t> rotate_map_90(const Tensor<uint8_t>& map) {
  const int64_t n = map.dim(0);
  Tensor<uint8_t> out({n, n});
  for (int64_t iy = 0; iy < n; ++iy)
    for (int64_t ix = 0; ix < n; ++ix) out(ix, n - 1 - iy) = map(iy, ix);
  return out;
}

}  // namespace

// ---- sparse rule ----

TEST(SparseRule, TieGoesToLowerClassId) {
  const GridSpec grid = small_grid();
  const ClassTable table = ClassTable::defaults();
  PointSet s;
  s.add(2, centre(grid, 1, 1), kSidewalk);  // sidewalk first in file order: order must not matter
  s.add(2, centre(grid, 1, 1), kRoad);
  s.add(2, centre(grid, 2, 1), kRoad);
  s.add(2, centre(grid, 2, 1), kSidewalk);
  s.add(2, centre(grid, 3, 1), kRoad);  // no tie: the larger count wins
  s.add(3, centre(grid, 3, 1), kSidewalk);
  const Tensor<uint8_t> map = rasterize_labels(s.points, s.labels, table, grid);
  EXPECT_EQ(map(1, 1), kRoadClass);
  EXPECT_EQ(map(1, 2), kRoadClass);
  EXPECT_EQ(map(1, 3), kSidewalkClass);
}

TEST(SparseRule, TrafficParticipantsWeighFive) {
  const GridSpec grid = small_grid();
  const ClassTable table = ClassTable::defaults();
  PointSet s;
  s.add(1, centre(grid, 0, 0), kCar);  // 5 * 1 > 1 * 4
  s.add(4, centre(grid, 0, 0), kRoad);
  s.add(1, centre(grid, 1, 0), kCar);  // 5 = 5: tie, vehicle (1) < road (5)
  s.add(5, centre(grid, 1, 0), kRoad);
  s.add(1, centre(grid, 2, 0), kCar);  // 5 < 6
  s.add(6, centre(grid, 2, 0), kRoad);
  s.add(1, centre(grid, 3, 0), kPerson);  // 5 = 5 between two weight-5 classes: vehicle
  s.add(1, centre(grid, 3, 0), kMovingCar);
  s.add(2, centre(grid, 4, 0), kPerson);  // 10 > 5
  s.add(1, centre(grid, 4, 0), kCar);
  const Tensor<uint8_t> map = rasterize_labels(s.points, s.labels, table, grid);
  EXPECT_EQ(map(0, 0), kVehicle);
  EXPECT_EQ(map(0, 1), kVehicle);
  EXPECT_EQ(map(0, 2), kRoadClass);
  EXPECT_EQ(map(0, 3), kVehicle);
  EXPECT_EQ(map(0, 4), kPersonClass);
}

TEST(SparseRule, UnlabeledPointsNeverWinAndEmptyCellsStayUnlabeled) {
  const GridSpec grid = small_grid();
  const ClassTable table = ClassTable::defaults();
  PointSet s;
  for (uint32_t raw : {kUnlabeledRaw, 1u, 52u, 99u, 12345u, 0xABCD0000u})
    s.add(3, centre(grid, 5, 2), raw);
  s.add(50, centre(grid, 6, 2), kUnlabeledRaw);
  s.add(1, centre(grid, 6, 2), kBuilding);  // one building point beats 50 unlabeled ones
  const Tensor<uint8_t> map = rasterize_labels(s.points, s.labels, table, grid);
  ASSERT_EQ(map.shape(), (Shape{5, 8}));
  const auto cells = labelled_cells(map);
  ASSERT_EQ(cells.size(), 1u);
  EXPECT_EQ(cells.begin()->first, std::make_pair(int64_t{2}, int64_t{6}));
  EXPECT_EQ(cells.begin()->second, kBuildingClass);
}

TEST(SparseRule, InstanceBitsAreIgnored) {
  const GridSpec grid = small_grid();
  PointSet s;
  s.add(1, centre(grid, 3, 3), kCar | (77u << 16));
  s.add(4, centre(grid, 3, 3), kRoad | (5u << 16));
  EXPECT_EQ(rasterize_labels(s.points, s.labels, ClassTable::defaults(), grid)(3, 3), kVehicle);
}

TEST(SparseRule, CellBordersAndRangesAtTheDefaultGrid) {
  const GridSpec grid;  // x [-50, 50), y [-25, 25), z [-2.5, 1.5), 0.1 m
  const ClassTable table = ClassTable::defaults();
  // Each point its own class-bearing probe; expected (iy, ix) from floor((p - min) / 0.1) in
  // double on the float coordinate: -49.9f is -49.9000015..., so it lies in cell 0, not 1;
  // -0.1f is -0.10000000149 -> 498.99999998 -> 498; 0.1f -> 501.0000000149 -> 501.
  struct Probe {
    Point p;
    bool inside;
    int64_t iy, ix;
  };
  const std::vector<Probe> probes = {
      {{-50.0f, -25.0f, -1.0f, 0}, true, 0, 0},   // lower corners are inside
      {{-49.9f, 0.0f, -1.0f, 0}, true, 250, 0},   // float -49.9 is below the 0.1 border
      {{-49.8f, 0.05f, -1.0f, 0}, true, 250, 2},  // -49.79999924 -> 2.0000076 -> 2
      {{-0.1f, -24.9f, -1.0f, 0}, true, 1, 498},  // y -24.8999996 -> 1.0000038 -> 1
      {{0.1f, 24.9f, -1.0f, 0}, true, 498, 501},  // y 24.8999996 -> 498.99999 -> 498
      {{0.0f, 0.1f, -1.0f, 0}, true, 251, 500},
      {{49.95f, 24.95f, -1.0f, 0}, true, 499, 999},  // last cell
      {{10.0f, 10.0f, -2.5f, 0}, true, 350, 600},    // z_min is inside
      {{20.0f, 10.0f, 1.49f, 0}, true, 350, 700},
      {{30.0f, 10.0f, 1.5f, 0}, false, 0, 0},  // z_max is outside
      {{30.0f, 12.0f, -2.51f, 0}, false, 0, 0},
      {{50.0f, 0.0f, -1.0f, 0}, false, 0, 0},  // x_max is outside
      {{0.0f, 25.0f, -1.0f, 0}, false, 0, 0},  // y_max is outside
      {{-50.01f, 0.0f, -1.0f, 0}, false, 0, 0},
      {{0.0f, -25.01f, -1.0f, 0}, false, 0, 0},
  };
  // Probes along x 10 m apart could share cells with nothing else: check one at a time.
  for (size_t i = 0; i < probes.size(); ++i) {
    SCOPED_TRACE(testing::Message() << "probe " << i << " at (" << probes[i].p.x << ", "
                                    << probes[i].p.y << ", " << probes[i].p.z << ")");
    const std::vector<Point> pts = {probes[i].p};
    const std::vector<uint32_t> labels = {kBuilding};
    const auto cells = labelled_cells(rasterize_labels(pts, labels, table, grid));
    if (!probes[i].inside) {
      EXPECT_TRUE(cells.empty());
      continue;
    }
    ASSERT_EQ(cells.size(), 1u);
    EXPECT_EQ(cells.begin()->first, std::make_pair(probes[i].iy, probes[i].ix));
  }
}

TEST(SparseRule, EmptyScanGivesAllUnlabeled) {
  const GridSpec grid;
  const Tensor<uint8_t> map = rasterize_labels({}, {}, ClassTable::defaults(), grid);
  ASSERT_EQ(map.shape(), (Shape{500, 1000}));
  EXPECT_TRUE(labelled_cells(map).empty());
  EXPECT_TRUE(labelled_cells(sparse_ground_truth(Scan{}, ClassTable::defaults(), grid)).empty());
}

TEST(SparseRule, MatchesMapReferenceOnRandomPoints) {
  const ClassTable table = ClassTable::defaults();
  // An odd grid (W = 13, H = 7) so that many points share cells and every rule path is taken.
  GridSpec grid;
  grid.x_min = -3.25, grid.x_max = 3.25, grid.y_min = -1.0, grid.y_max = 2.5, grid.cell = 0.5;
  ASSERT_EQ(grid.width(), 13);
  ASSERT_EQ(grid.height(), 7);
  const std::vector<uint32_t> pool = {0,  1,  10, 11,  13,  15,  18,  30,  31,  40,
                                      44, 48, 49, 50,  51,  52,  60,  70,  71,  72,
                                      80, 81, 99, 252, 253, 254, 255, 256, 259, 500};
  Rng rng(7);
  for (int trial = 0; trial < 20; ++trial) {
    PointSet s;
    const int n = static_cast<int>(rng.uniform_int(800));
    for (int i = 0; i < n; ++i) {
      const Point p{static_cast<float>(rng.uniform(-4.0, 4.0)),
                    static_cast<float>(rng.uniform(-1.5, 3.0)),
                    static_cast<float>(rng.uniform(-3.0, 2.0)), 0.0f};
      s.add(1, p, pool[rng.uniform_int(pool.size())]);
    }
    const std::vector<uint8_t> classes = classes_of(s.labels, table);
    const Tensor<uint8_t> expected = reference_rasterize(s.points, classes, table, grid);
    const Tensor<uint8_t> from_labels = rasterize_labels(s.points, s.labels, table, grid);
    const Tensor<uint8_t> from_classes = rasterize_classes(s.points, classes, table, grid);
    ASSERT_EQ(from_labels.values(), expected.values()) << "trial " << trial;
    ASSERT_EQ(from_classes.values(), expected.values()) << "trial " << trial;
  }
}

TEST(SparseRule, IndependentOfPointOrder) {
  const GridSpec grid = small_grid();
  const ClassTable table = ClassTable::defaults();
  Rng rng(3);
  PointSet s;
  for (int i = 0; i < 500; ++i)
    s.add(1,
          centre(grid, static_cast<int>(rng.uniform_int(8)), static_cast<int>(rng.uniform_int(5))),
          std::array<uint32_t, 5>{kCar, kRoad, kSidewalk, kBuilding, kPerson}[rng.uniform_int(5)]);
  const Tensor<uint8_t> map = rasterize_labels(s.points, s.labels, table, grid);
  std::vector<size_t> order(s.points.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  rng.shuffle(order.begin(), order.end());
  PointSet shuffled;
  for (size_t i : order) shuffled.add(1, s.points[i], s.labels[i]);
  EXPECT_EQ(rasterize_labels(shuffled.points, shuffled.labels, table, grid).values(),
            map.values());
}

TEST(SparseRule, UsesTheTableWeights) {
  const fs::path dir = test::temp_dir();
  // A table where road weighs 10: 1 vehicle (5) now loses to 1 road (10).
  {
    std::ofstream yaml(dir / "classes.yaml");
    yaml << "classes:\n  - id: 5\n    gt_weight: 10\n";
  }
  const ClassTable table = load_class_table((dir / "classes.yaml").string());
  const GridSpec grid = small_grid();
  PointSet s;
  s.add(1, centre(grid, 0, 0), kCar);
  s.add(1, centre(grid, 0, 0), kRoad);
  EXPECT_EQ(rasterize_labels(s.points, s.labels, table, grid)(0, 0), kRoadClass);
  EXPECT_EQ(rasterize_labels(s.points, s.labels, ClassTable::defaults(), grid)(0, 0), kVehicle);
}

TEST(SparseRule, RealScanMatchesReference) {
  const fs::path bin = test::shared_data_dir() / "semantickitti/sequences/99/velodyne/000000.bin";
  if (!fs::exists(bin)) GTEST_SKIP() << "no real scan at " << bin;
  const Scan scan =
      read_scan(bin, test::shared_data_dir() / "semantickitti/sequences/99/labels/000000.label");
  const ClassTable table = ClassTable::defaults();
  const GridSpec grid;
  const Tensor<uint8_t> map = sparse_ground_truth(scan, table, grid);
  const Tensor<uint8_t> expected =
      reference_rasterize(scan.points, classes_of(scan.labels, table), table, grid);
  EXPECT_EQ(map.values(), expected.values());
  // A real street scene fills tens of thousands of cells with road, terrain, vegetation,
  // buildings and cars.
  const auto cells = labelled_cells(map);
  EXPECT_GT(cells.size(), 20000u);
  std::array<int, kNumClassIds> per_class{};
  for (const auto& [cell, k] : cells) ++per_class[k];
  for (int k : {kVehicle, kRoadClass, kBuildingClass, kVegetationClass, kTerrainClass})
    EXPECT_GT(per_class[k], 100) << table.name(k);
}

TEST(SparseRule, RejectsMismatchedInput) {
  const GridSpec grid = small_grid();
  const ClassTable table = ClassTable::defaults();
  const std::vector<Point> pts = {centre(grid, 0, 0), centre(grid, 1, 0)};
  EXPECT_NE(error_of([&] {
              rasterize_labels(pts, std::vector<uint32_t>{kRoad}, table, grid);
            }).find("expected one label per point (2 points), got 1"),
            std::string::npos);
  EXPECT_NE(error_of([&] {
              rasterize_classes(pts, std::vector<uint8_t>{1, 13}, table, grid);
            }).find("point 1 has class id 13"),
            std::string::npos);
  Scan unlabelled;
  unlabelled.points = pts;
  EXPECT_NE(error_of([&] { sparse_ground_truth(unlabelled, table, grid); }).find("no labels"),
            std::string::npos);
}

// ---- dense: neighbour selection ----

TEST(DenseNeighbours, DistanceIsStrictAndThreeDimensional) {
  const std::vector<Eigen::Vector3d> positions = {
      {0, 0, 0},      // t
      {3.0, 0, 0},    // exactly 2 d: out
      {2.999, 0, 0},  // in
      {0, 0, 2.9},    // in, through z alone
      {2, 2, 1},      // |.| = 3: out
      {0, -1, 0},     // in
  };
  EXPECT_EQ(select_dense_neighbours(positions, 0, 1.5), (std::vector<size_t>{0, 5, 3, 2}));
}

TEST(DenseNeighbours, NearestFirstTiesToLowerIndexCurrentScanFirst) {
  std::vector<Eigen::Vector3d> positions;
  for (int j = 0; j < 9; ++j) positions.emplace_back(0.5 * j, 0, 0);
  positions.emplace_back(2.0, 0, 0);  // index 9 shares scan 4's position
  positions.emplace_back(2.0, 0, 0);  // index 10 too
  EXPECT_EQ(select_dense_neighbours(positions, 4, 10.0),
            (std::vector<size_t>{4, 9, 10, 3, 5, 2, 6, 1, 7, 0, 8}));
  EXPECT_EQ(select_dense_neighbours(positions, 9, 10.0, 3), (std::vector<size_t>{9, 4, 10}));
  EXPECT_EQ(select_dense_neighbours(positions, 9, 10.0, 1), (std::vector<size_t>{9}));
  EXPECT_EQ(select_dense_neighbours(positions, 0, 0.0), (std::vector<size_t>{0}));  // empty scan
  EXPECT_EQ(select_dense_neighbours(positions, 0, 0.5), (std::vector<size_t>{0, 1}));
}

TEST(DenseNeighbours, KeepsAtMostFortyCountingTheCurrentScan) {
  std::vector<Eigen::Vector3d> positions;
  for (int j = 0; j < 60; ++j) positions.emplace_back(0.0, 0.25 * j, 0.0);
  const std::vector<size_t> scans = select_dense_neighbours(positions, 30, 100.0);
  ASSERT_EQ(scans.size(), kDenseMaxScans);
  // 30, then the pairs 30 -+ k for k = 1..19 (lower index first), then 10 at 20 steps (beats 50).
  std::vector<size_t> expected = {30};
  for (size_t k = 1; k <= 19; ++k) expected.push_back(30 - k), expected.push_back(30 + k);
  expected.push_back(10);
  EXPECT_EQ(scans, expected);
}

TEST(DenseNeighbours, RejectsBadArguments) {
  const std::vector<Eigen::Vector3d> positions = {{0, 0, 0}, {1, 0, 0}};
  EXPECT_NE(error_of([&] { select_dense_neighbours(positions, 2, 1.0); }).find("out of range"),
            std::string::npos);
  EXPECT_NE(error_of([&] { select_dense_neighbours(positions, 0, -1.0); }).find("d >= 0"),
            std::string::npos);
  EXPECT_NE(error_of([&] { select_dense_neighbours(positions, 0, NAN); }).find("d >= 0"),
            std::string::npos);
  EXPECT_NE(error_of([&] { select_dense_neighbours(positions, 0, 1.0, 0); }).find("max_scans >= 1"),
            std::string::npos);
}

TEST(DenseNeighbours, MaxHorizontalRangeIgnoresZ) {
  const std::vector<Point> pts = {{3, 4, 100, 0}, {-1, 0, 0, 0}, {0, -4.5f, -50, 0}};
  EXPECT_DOUBLE_EQ(max_horizontal_range(pts), 5.0);
  EXPECT_EQ(max_horizontal_range({}), 0.0);
}

// ---- dense: aggregation ----

// Scan 0 at the origin; scan 1 rotated by 90 degrees and moved to (2, 1). Expected cells
// worked through the pose: a point p of scan 1 lands at R p + (2, 1) in scan 0's frame.
class DenseTwoScans : public testing::Test {
 protected:
  void SetUp() override {
    root_ = test::temp_dir();
    SyntheticScan s0, s1;
    s0.points.add(1, {30.05f, 0.05f, -1.0f, 0}, kRoad);       // d = 30.05: 2 d covers scan 1
    s0.points.add(2, {5.05f, -3.05f, -1.0f, 0}, kMovingCar);  // scan 0's own moving car
    s0.points.add(1, {-3.05f, 2.05f, -1.0f, 0}, kRoad);
    s1.pose = lidar_pose(std::numbers::pi / 2, 2.0, 1.0);
    s1.points.add(1, {1.25f, 0.35f, -1.0f, 0}, kBuilding);      // -> (1.65, 2.25)
    s1.points.add(3, {3.05f, 0.45f, -1.0f, 0}, kMovingCar);     // -> (1.55, 4.05): dropped
    s1.points.add(1, {0.25f, -4.15f, -1.0f, 0}, kCar);          // -> (6.15, 1.25): parked, kept
    s1.points.add(2, {0.35f, 1.05f, -1.0f, 0}, kUnlabeledRaw);  // weight 0: dropped
    write_sequence(root_, 3, {s0, s1});
  }
  fs::path root_;
};

TEST_F(DenseTwoScans, StaticAndParkedFromNeighboursMovingFromCurrentScanOnly) {
  const Sequence seq(root_, 3);
  const ClassTable table = ClassTable::defaults();
  const GridSpec grid;
  EXPECT_EQ(dense_neighbours(seq, 0), (std::vector<size_t>{0, 1}));
  const Tensor<uint8_t> map = dense_ground_truth(seq, 0, table, grid);
  // Cell (iy, ix) = (floor((y + 25) / 0.1), floor((x + 50) / 0.1)) of each kept point.
  const std::map<std::pair<int64_t, int64_t>, int> expected = {
      {{250, 800}, kRoadClass},      // (30.05, 0.05)
      {{219, 550}, kVehicle},        // scan 0's moving car (5.05, -3.05)
      {{270, 469}, kRoadClass},      // (-3.05, 2.05)
      {{272, 516}, kBuildingClass},  // scan 1's building at (1.65, 2.25)
      {{262, 561}, kVehicle},        // scan 1's parked car at (6.15, 1.25)
  };
  EXPECT_EQ(labelled_cells(map), expected);
  // The sparse map of scan 0 has only its own points.
  const auto sparse = labelled_cells(sparse_ground_truth(seq.load(0), table, grid));
  EXPECT_EQ(sparse.size(), 3u);
  EXPECT_EQ(sparse.count({272, 516}), 0u);
}

TEST_F(DenseTwoScans, CurrentScanKeepsItsMovingPointsInItsOwnFrame) {
  const Sequence seq(root_, 3);
  const ClassTable table = ClassTable::defaults();
  const GridSpec grid;
  // Scan 1: d = |(0.25, -4.15)| = 4.16, scan 0 is 2.24 m away, so it is aggregated. Scan 0's
  // points in scan 1's frame: q = R^T (p - (2, 1)), R^T (x, y) = (y, -x).
  EXPECT_EQ(dense_neighbours(seq, 1), (std::vector<size_t>{1, 0}));
  const auto cells = labelled_cells(dense_ground_truth(seq, 1, table, grid));
  const std::map<std::pair<int64_t, int64_t>, int> expected = {
      {{253, 512}, kBuildingClass},  // (1.25, 0.35)
      {{254, 530}, kVehicle},        // own moving car (3.05, 0.45)
      {{208, 502}, kVehicle},        // parked car (0.25, -4.15)
      {{300, 510}, kRoadClass},      // scan 0's road (-3.05, 2.05) -> (1.05, 5.05)
      // scan 0's moving car (5.05, -3.05) -> (-4.05, -3.05): not aggregated
      // scan 0's far road (30.05, 0.05) -> (-0.95, -28.05): outside the grid
  };
  EXPECT_EQ(cells, expected);
}

TEST_F(DenseTwoScans, FarNeighboursAreNotAggregated) {
  const fs::path root = root_ / "far";
  SyntheticScan s0, s1;
  s0.points.add(1, {1.05f, 1.05f, -1.0f, 0}, kRoad);  // d = 1.48: 2 d < 3
  s1.pose = lidar_pose(0, 3.0, 0.0);
  s1.points.add(1, {-3.0f + 1.05f, 2.05f, -1.0f, 0}, kBuilding);
  write_sequence(root, 0, {s0, s1});
  const Sequence seq(root, 0);
  EXPECT_EQ(dense_neighbours(seq, 0), (std::vector<size_t>{0}));
  EXPECT_EQ(dense_ground_truth(seq, 0, ClassTable::defaults(), GridSpec{}).values(),
            sparse_ground_truth(seq.load(0), ClassTable::defaults(), GridSpec{}).values());
}

TEST_F(DenseTwoScans, EmptyCurrentScanGivesAllUnlabeled) {
  const fs::path root = root_ / "empty";
  SyntheticScan s0, s1;
  s1.pose = lidar_pose(0, 0.5, 0.0);
  s1.points.add(5, {1.05f, 1.05f, -1.0f, 0}, kRoad);
  write_sequence(root, 0, {s0, s1});
  const Sequence seq(root, 0);
  EXPECT_EQ(dense_neighbours(seq, 0), (std::vector<size_t>{0}));
  EXPECT_TRUE(
      labelled_cells(dense_ground_truth(seq, 0, ClassTable::defaults(), GridSpec{})).empty());
}

TEST_F(DenseTwoScans, MissingNeighbourLabelsNameTheFile) {
  const Sequence seq(root_, 3);
  fs::remove(seq.label_path(1));
  const std::string error =
      error_of([&] { dense_ground_truth(seq, 0, ClassTable::defaults(), GridSpec{}); });
  EXPECT_NE(error.find("000001.label is missing"), std::string::npos) << error;
}

TEST_F(DenseTwoScans, SameResultForAnyThreadCount) {
  const Sequence seq(root_, 3);
  const ClassTable table = ClassTable::defaults();
  const int saved = num_threads();
  set_num_threads(1);
  const LabelledPoints one = dense_points(seq, 0, table, GridSpec{}, AugmentationBounds{});
  set_num_threads(4);
  const LabelledPoints four = dense_points(seq, 0, table, GridSpec{}, AugmentationBounds{});
  set_num_threads(saved);
  ASSERT_EQ(one.size(), four.size());
  EXPECT_EQ(one.classes, four.classes);
  for (size_t i = 0; i < one.size(); ++i) {
    EXPECT_EQ(one.points[i].x, four.points[i].x);
    EXPECT_EQ(one.points[i].y, four.points[i].y);
    EXPECT_EQ(one.points[i].z, four.points[i].z);
  }
  // Scan t's points come first, in file order: its three labelled points, 4 with the moving car.
  ASSERT_GE(one.size(), 4u);
  EXPECT_EQ(one.classes[0], kRoadClass);
  EXPECT_EQ(one.classes[1], kVehicle);
}

// 45 scans 0.5 m apart along x, each with one building point at its own place in the world:
// for scan 22 all others lie within 2 d, and only the 39 nearest (2..41) are kept.
TEST(DenseSequence, FortyNearestScansContribute) {
  const fs::path root = test::temp_dir();
  std::vector<SyntheticScan> scans(45);
  for (int j = 0; j < 45; ++j) {
    scans[j].pose = lidar_pose(0, 0.5 * j, 0);
    scans[j].points.add(1, {20.05f, 0.05f, -1.0f, 0}, kRoad);  // d = 20.05
    // World (-20.05 + j, 10.05): in scan 22's frame x = -31.05 + j, a cell centre.
    scans[j].points.add(1, {static_cast<float>(-20.05 + j - 0.5 * j), 10.05f, -1.0f, 0}, kBuilding);
  }
  write_sequence(root, 5, scans);
  const Sequence seq(root, 5);
  const std::vector<size_t> neighbours = dense_neighbours(seq, 22);
  ASSERT_EQ(neighbours.size(), 40u);
  std::vector<size_t> expected = {22};
  for (size_t k = 1; k <= 19; ++k) expected.push_back(22 - k), expected.push_back(22 + k);
  expected.push_back(2);  // distance 10 on both sides: 2 beats 42
  EXPECT_EQ(neighbours, expected);

  const Tensor<uint8_t> map = dense_ground_truth(seq, 22, ClassTable::defaults(), GridSpec{});
  const int64_t iy = 350;  // floor((10.05 + 25) / 0.1) = floor(350.5)
  for (int j = 0; j < 45; ++j) {
    const int64_t ix = 189 + 10 * j;  // floor((-31.05 + j + 50) / 0.1)
    const bool kept = j >= 2 && j <= 41;
    EXPECT_EQ(map(iy, ix), kept ? kBuildingClass : 0) << "scan " << j;
  }
}

// ---- dense: augmentation ----

// Scans whose points sit at cell centres of a square 0.5 m grid centred on the sensor, with
// poses that are multiples of 90 degrees and of 0.5 m, so a 90-degree rotation maps cells
// onto cells exactly.
class DenseAugmented : public testing::Test {
 protected:
  void SetUp() override {
    root_ = test::temp_dir();
    grid_.x_min = -10, grid_.x_max = 10, grid_.y_min = -10, grid_.y_max = 10, grid_.cell = 0.5;
    Rng rng(11);
    const std::array<uint32_t, 6> labels = {kCar, kRoad, kSidewalk, kBuilding, kPerson, kMovingCar};
    std::vector<SyntheticScan> scans(4);
    for (int j = 0; j < 4; ++j) {
      scans[j].pose = lidar_pose(std::numbers::pi / 2 * j, 0.5 * j, -0.5 * j);
      for (int i = 0; i < 300; ++i) {
        const int ix = static_cast<int>(rng.uniform_int(40)),
                  iy = static_cast<int>(rng.uniform_int(40));
        scans[j].points.add(1, centre(grid_, ix, iy), labels[rng.uniform_int(labels.size())]);
      }
      // Beyond the grid's corner radius 14.14 m: only a shrinking augmentation brings it in.
      scans[j].points.add(1, {14.8f, 0.0f, -1.0f, 0}, kBuilding);
      scans[j].points.add(1, {30.0f, 0.0f, -1.0f, 0}, kRoad);  // beyond any augmentation's reach
    }
    write_sequence(root_, 1, scans);
  }
  fs::path root_;
  GridSpec grid_;
};

TEST_F(DenseAugmented, RotatingTheAggregatedSetRotatesTheMap) {
  const Sequence seq(root_, 1);
  const ClassTable table = ClassTable::defaults();
  const Pose rotation = lidar_pose(std::numbers::pi / 2, 0, 0);
  for (size_t t = 0; t < seq.size(); ++t) {
    const Tensor<uint8_t> plain = dense_ground_truth(seq, t, table, grid_);
    const Tensor<uint8_t> rotated =
        dense_ground_truth(seq, t, table, grid_, kDenseMaxScans, rotation);
    EXPECT_GT(labelled_cells(plain).size(), 300u);
    EXPECT_EQ(rotated.values(), rotate_map_90(plain).values()) << "scan " << t;
    // The same through the exposed set: aggregate, move, rasterise.
    LabelledPoints set = dense_points(seq, t, table, grid_, AugmentationBounds::none());
    set.transform(rotation);
    EXPECT_EQ(rasterize_classes(set.points, set.classes, table, grid_).values(),
              rotated.values());
  }
}

TEST_F(DenseAugmented, CropKeepsEveryPointTheWorstAugmentationCanBringIn) {
  const Sequence seq(root_, 1);
  const ClassTable table = ClassTable::defaults();
  const std::vector<size_t> scans = dense_neighbours(seq, 0);
  ASSERT_EQ(scans.size(), 4u);
  AugmentationBounds wide;
  wide.scale_min = 0.01;  // a crop that keeps everything
  const LabelledPoints all = aggregate_scans(seq, scans, table, crop_region(grid_, wide));
  const LabelledPoints cropped =
      aggregate_scans(seq, scans, table, crop_region(grid_, AugmentationBounds{}));
  const LabelledPoints exact =
      aggregate_scans(seq, scans, table, crop_region(grid_, AugmentationBounds::none()));
  EXPECT_LT(cropped.size(), all.size());
  // Flip along x, rotation by 45 degrees, the smallest scale: the 14.8 m point moves to
  // 14.06 m along the diagonal, inside the grid.
  Pose augmentation = Pose::Identity();
  augmentation.topLeftCorner<3, 3>() =
      0.95 * Eigen::AngleAxisd(std::numbers::pi / 4, Eigen::Vector3d::UnitZ()).toRotationMatrix() *
      Eigen::Vector3d(1, -1, 1).asDiagonal();
  const auto rasterized = [&](LabelledPoints set) {
    set.transform(augmentation);
    return rasterize_classes(set.points, set.classes, table, grid_);
  };
  const Tensor<uint8_t> reference = rasterized(all);
  EXPECT_EQ(rasterized(cropped).values(), reference.values());
  EXPECT_NE(rasterized(exact).values(), reference.values());  // the tight crop loses that point
}

TEST(CropRegion, BoundsFollowTheGridAndTheAugmentation) {
  const GridSpec grid;  // corner radius sqrt(50^2 + 25^2) = 55.9017
  const CropRegion none = crop_region(grid, AugmentationBounds::none());
  EXPECT_NEAR(none.radius_xy, std::hypot(50.0, 25.0) + 0.1, 1e-12);
  EXPECT_NEAR(none.z_min, -2.6, 1e-12);
  EXPECT_NEAR(none.z_max, 1.6, 1e-12);
  AugmentationBounds bounds;
  bounds.translation_xy = 20, bounds.translation_z = 0.2;
  const CropRegion wide = crop_region(grid, bounds);
  EXPECT_NEAR(wide.radius_xy, (std::hypot(50.0, 25.0) + 20) / 0.95 + 0.1, 1e-12);
  EXPECT_NEAR(wide.z_min, -2.7 / 0.95 - 0.1, 1e-12);
  EXPECT_NEAR(wide.z_max, 1.7 / 0.95 + 0.1, 1e-12);
  bounds.scale_min = 0;
  EXPECT_NE(error_of([&] { crop_region(grid, bounds); }).find("scale_min"), std::string::npos);
}

TEST(LabelledPoints, EncodeDecodeRoundTripAndRejectsBadBytes) {
  LabelledPoints set;
  set.points = {{1.5f, -2.0f, 0.25f, 0.5f}, {3, 4, 5, 6}};
  set.classes = {kVehicle, 12};
  const std::vector<char> bytes = encode_labelled_points(set);
  EXPECT_EQ(bytes.size(), 8u + 2 * 17);
  const std::optional<LabelledPoints> back = decode_labelled_points(bytes);
  ASSERT_TRUE(back);
  EXPECT_EQ(back->classes, set.classes);
  EXPECT_EQ(back->points[1].z, 5.0f);
  EXPECT_FALSE(decode_labelled_points(std::span<const char>(bytes.data(), bytes.size() - 1)));
  std::vector<char> bad_class = bytes;
  bad_class.at(bytes.size() - 1) = 13;  // the last class id
  EXPECT_FALSE(decode_labelled_points(bad_class));
  EXPECT_TRUE(decode_labelled_points(encode_labelled_points(LabelledPoints{})));
  EXPECT_FALSE(decode_labelled_points({}));
}

// ---- the builder and its cache keys ----

TEST_F(DenseTwoScans, BuilderReadsBackWhatItStored) {
  const Cache cache(root_ / "cache");
  GroundTruthBuilder builder(Sequence(root_, 3), ClassTable::defaults(), {}, cache);
  for (GroundTruthKind kind : {GroundTruthKind::sparse, GroundTruthKind::dense}) {
    bool from_cache = true;
    const Tensor<uint8_t> first = builder.map(0, kind, &from_cache);
    EXPECT_FALSE(from_cache);
    const Tensor<uint8_t> second = builder.map(0, kind, &from_cache);
    EXPECT_TRUE(from_cache);
    EXPECT_EQ(first.values(), second.values());
  }
  EXPECT_EQ(builder.map(0, GroundTruthKind::dense).values(),
            dense_ground_truth(builder.sequence(), 0, builder.table(), GridSpec{}).values());
  EXPECT_EQ(builder.neighbours(0), (std::vector<size_t>{0, 1}));
  const auto counts = builder.build_all(GroundTruthKind::dense, false);
  EXPECT_EQ(counts.cached, 1u);
  EXPECT_EQ(counts.computed, 1u);
  const GroundTruthBuilder no_cache(Sequence(root_, 3), ClassTable::defaults(), {}, std::nullopt);
  EXPECT_NE(
      error_of([&] { no_cache.build_all(GroundTruthKind::sparse, false); }).find("needs a cache"),
      std::string::npos);
}

TEST_F(DenseTwoScans, KeysChangeWithEverythingTheMapDependsOn) {
  const Cache cache(root_ / "cache");
  const GroundTruthBuilder base(Sequence(root_, 3), ClassTable::defaults(), {}, cache);
  const CacheKey sparse = base.key(0, GroundTruthKind::sparse),
                 dense = base.key(0, GroundTruthKind::dense);
  EXPECT_NE(sparse.settings, dense.settings);
  EXPECT_EQ(sparse.frame, 0);
  EXPECT_EQ(sparse.sequence, fs::canonical(root_ / "sequences" / "03").string());

  GroundTruthSettings finer;
  finer.grid.cell = 0.2;
  const GroundTruthBuilder other_grid(Sequence(root_, 3), ClassTable::defaults(), finer, cache);
  EXPECT_NE(other_grid.key(0, GroundTruthKind::sparse).settings, sparse.settings);
  GroundTruthSettings fewer;
  fewer.max_scans = 1;
  const GroundTruthBuilder other_max(Sequence(root_, 3), ClassTable::defaults(), fewer, cache);
  EXPECT_EQ(other_max.key(0, GroundTruthKind::sparse), sparse);
  EXPECT_NE(other_max.key(0, GroundTruthKind::dense).settings, dense.settings);

  {
    std::ofstream yaml(root_ / "classes.yaml");
    yaml << "classes:\n  - id: 8\n    gt_weight: 2\n";
  }
  const GroundTruthBuilder other_table(
      Sequence(root_, 3), load_class_table((root_ / "classes.yaml").string()), {}, cache);
  EXPECT_NE(other_table.key(0, GroundTruthKind::sparse).settings, sparse.settings);

  // Rewriting a neighbour's labels changes scan 0's dense key but not its sparse key.
  const Sequence seq(root_, 3);
  write_labels(seq.label_path(1), read_labels(seq.label_path(1)));
  fs::last_write_time(seq.label_path(1),
                      fs::last_write_time(seq.label_path(1)) + std::chrono::seconds(5));
  EXPECT_EQ(base.key(0, GroundTruthKind::sparse), sparse);
  const CacheKey dense_after = base.key(0, GroundTruthKind::dense);
  EXPECT_EQ(dense_after.settings, dense.settings);
  EXPECT_NE(dense_after.inputs, dense.inputs);
  // So does rewriting poses.txt.
  fs::last_write_time(seq.dir() / "poses.txt",
                      fs::last_write_time(seq.dir() / "poses.txt") + std::chrono::seconds(5));
  EXPECT_NE(base.key(0, GroundTruthKind::dense).inputs, dense_after.inputs);
}

TEST_F(DenseTwoScans, TouchingTheScanIsACacheMissAndTheEntryIsRewritten) {
  const Cache cache(root_ / "cache");
  const GroundTruthBuilder builder(Sequence(root_, 3), ClassTable::defaults(), {}, cache);
  bool from_cache = false;
  const Tensor<uint8_t> before = builder.map(0, GroundTruthKind::sparse, &from_cache);
  const fs::path stored = cache.path_of(builder.key(0, GroundTruthKind::sparse));
  ASSERT_TRUE(fs::exists(stored));

  // Scan 0 gains a building point: a stale entry would hide it.
  Scan scan = builder.sequence().load(0);
  scan.points.push_back({-1.05f, -1.05f, -1.0f, 0});
  scan.labels.push_back(kBuilding);
  write_bin(builder.sequence().scan_path(0), scan.points);
  write_labels(builder.sequence().label_path(0), scan.labels);
  const Tensor<uint8_t> after = builder.map(0, GroundTruthKind::sparse, &from_cache);
  EXPECT_FALSE(from_cache);
  EXPECT_EQ(before(239, 489), 0);
  EXPECT_EQ(after(239, 489), kBuildingClass);
  EXPECT_EQ(cache.path_of(builder.key(0, GroundTruthKind::sparse)),
            stored);  // same file, rewritten
  builder.map(0, GroundTruthKind::sparse, &from_cache);
  EXPECT_TRUE(from_cache);
}

TEST_F(DenseTwoScans, CachedDensePointsMatchComputed) {
  GroundTruthSettings settings;
  settings.cache_dense_points = true;
  const GroundTruthBuilder builder(Sequence(root_, 3), ClassTable::defaults(), settings,
                                   Cache(root_ / "cache"));
  const LabelledPoints computed = builder.dense_points(0);
  const LabelledPoints read = builder.dense_points(0);
  EXPECT_EQ(computed.classes, read.classes);
  ASSERT_EQ(computed.size(),
            6u);  // scan 0: 2 roads + 2 moving car points; scan 1: building, parked car
  for (size_t i = 0; i < computed.size(); ++i) EXPECT_EQ(computed.points[i].x, read.points[i].x);
}

// ---- the gt command ----

TEST_F(DenseTwoScans, GtCommandWritesPngAndRawMaps) {
  GtCommandOptions options;
  options.data_root = root_;
  options.sequence = 3;
  options.scan = 1;
  options.kind = GroundTruthKind::dense;
  options.cache_dir = root_ / "cache";
  options.show_progress = false;
  options.out = root_ / "out" / "map.u8";
  const std::string report = run_gt_command(options);
  EXPECT_NE(report.find("dense ground truth of sequence 03 scan 000001"), std::string::npos)
      << report;
  const std::vector<char> raw = read_file_bytes(options.out);
  ASSERT_EQ(raw.size(), 500u * 1000u);
  const Tensor<uint8_t> expected =
      dense_ground_truth(Sequence(root_, 3), 1, ClassTable::defaults(), GridSpec{});
  EXPECT_TRUE(std::equal(raw.begin(), raw.end(), expected.data(),
                         [](char a, uint8_t b) { return static_cast<uint8_t>(a) == b; }));

  options.out = root_ / "out" / "map.PNG";
  EXPECT_NE(run_gt_command(options).find("from the cache"), std::string::npos);
  const ImageRgb image = read_png_rgb(options.out);
  ASSERT_EQ(image.width, 1000);
  ASSERT_EQ(image.height, 500);
  // The building at (iy 253, ix 512) is drawn at row H-1-iy = 246: +y up, +x right.
  const ImageRgb& img = image;
  const uint8_t* pixel = &img.pixels[(246u * 1000u + 512u) * 3u];
  const Rgb building = ClassTable::defaults().color(kBuildingClass);
  EXPECT_EQ((Rgb{pixel[0], pixel[1], pixel[2]}), building);
  const uint8_t* empty = &img.pixels[(253u * 1000u + 512u) * 3u];
  EXPECT_EQ((Rgb{empty[0], empty[1], empty[2]}), (Rgb{0, 0, 0}));
}

TEST_F(DenseTwoScans, GtCommandBuildsTheWholeSequence) {
  GtCommandOptions options;
  options.data_root = root_;
  options.sequence = 3;
  options.kind = GroundTruthKind::sparse;
  options.cache_dir = root_ / "cache";
  options.show_progress = false;
  EXPECT_NE(run_gt_command(options).find("of 2 scans in"), std::string::npos);
  const std::string again = run_gt_command(options);
  EXPECT_NE(again.find("(computed 0, already cached 2)"), std::string::npos) << again;
  // Atomic writes leave no temporary files behind.
  for (const auto& entry : fs::recursive_directory_iterator(options.cache_dir))
    EXPECT_EQ(entry.path().string().find(".tmp"), std::string::npos) << entry.path();
}

TEST_F(DenseTwoScans, GtCommandErrorsNameTheArgument) {
  GtCommandOptions options;
  options.data_root = root_;
  options.sequence = 3;
  options.scan = 0;
  options.cache_dir = root_ / "cache";
  options.show_progress = false;
  options.out = root_ / "map.jpg";
  EXPECT_NE(error_of([&] { run_gt_command(options); }).find("--out"), std::string::npos);
  EXPECT_NE(error_of([&] { run_gt_command(options); }).find("unknown extension '.jpg'"),
            std::string::npos);
  options.out = root_ / "map.png";
  options.scan = 7;
  EXPECT_NE(error_of([&] {
              run_gt_command(options);
            }).find("--scan 7: out of range, sequence 03 has scans 000000..000001"),
            std::string::npos);
  options.scan = 0;
  options.sequence = 4;
  EXPECT_NE(error_of([&] { run_gt_command(options); }).find("--sequence 04: no directory"),
            std::string::npos);
  options.sequence = 3;
  options.data_root = root_ / "nowhere";
  EXPECT_NE(error_of([&] { run_gt_command(options); }).find("--data"), std::string::npos);
  options.data_root = root_;
  options.out.clear();
  EXPECT_NE(error_of([&] { run_gt_command(options); }).find("--out: required with --scan"),
            std::string::npos);
  options.scan.reset();
  options.out = root_ / "map.png";
  EXPECT_NE(error_of([&] { run_gt_command(options); }).find("needs --scan"), std::string::npos);
}
