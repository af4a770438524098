// Pillar gather and point decoration: checked against a std::map based reference written here
// (obviously correct, slow), hand-computed cases (evenly spaced subsampling, range borders, a
// 3-point pillar), training-mode sampling properties, and thread-count independence.
#include <fmt/format.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <ostream>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "core/error.hpp"
#include "core/parallel.hpp"
#include "host/pillar_gather.hpp"
#include "host/point_decoration.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
using namespace pillarseg::host;

namespace {

// ---- reference -------------------------------------------------------------------------------

struct ReferencePillar {
  int64_t iy = 0, ix = 0;
  std::vector<int32_t> kept;  // input indices of the kept points, file order
};

// Inference-mode pillars by the letter of DESIGN.md: group the points inside the volume by
// cell, order the cells by first appearance, keep floor(k * n / P) of them and floor(k * n / N)
// of each one's points.
std::vector<ReferencePillar> reference_gather(const std::vector<Point>& points,
                                              const GridSpec& grid, int max_points,
                                              int max_pillars) {
  std::map<std::pair<int64_t, int64_t>, std::vector<int32_t>> points_of_cell;
  std::vector<std::pair<int64_t, int64_t>> cells_in_order;
  for (size_t i = 0; i < points.size(); ++i) {
    const Point& p = points[i];
    if (!grid.contains(p.x, p.y, p.z)) continue;
    const std::pair<int64_t, int64_t> cell{grid.iy(p.y), grid.ix(p.x)};
    if (!points_of_cell.count(cell)) cells_in_order.push_back(cell);
    points_of_cell[cell].push_back(static_cast<int32_t>(i));
  }
  const int64_t n = static_cast<int64_t>(cells_in_order.size());
  std::vector<std::pair<int64_t, int64_t>> kept_cells;
  if (max_pillars > 0 && n > max_pillars) {
    for (int64_t k = 0; k < max_pillars; ++k)
      kept_cells.push_back(cells_in_order[k * n / max_pillars]);
  } else {
    kept_cells = cells_in_order;
  }
  std::vector<ReferencePillar> out;
  for (const auto& cell : kept_cells) {
    const std::vector<int32_t>& all = points_of_cell[cell];
    ReferencePillar pillar{cell.first, cell.second, {}};
    const int64_t size = static_cast<int64_t>(all.size());
    if (size > max_points) {
      for (int64_t k = 0; k < max_points; ++k) pillar.kept.push_back(all[k * size / max_points]);
    } else {
      pillar.kept = all;
    }
    out.push_back(pillar);
  }
  return out;
}

// Decorated features of reference pillars, one point at a time; padding rows stay zero.
Tensor<float> reference_decorate(const std::vector<Point>& points,
                                 const std::vector<ReferencePillar>& pillars, const GridSpec& grid,
                                 int max_points) {
  Tensor<float> out({static_cast<int64_t>(pillars.size()), max_points, kDecoratedFeatures});
  for (size_t p = 0; p < pillars.size(); ++p) {
    const std::vector<int32_t>& kept = pillars[p].kept;
    double mean[3] = {0, 0, 0};
    for (int32_t i : kept) {
      mean[0] += points[i].x / static_cast<double>(kept.size());
      mean[1] += points[i].y / static_cast<double>(kept.size());
      mean[2] += points[i].z / static_cast<double>(kept.size());
    }
    const double centre[3] = {grid.x_min + (pillars[p].ix + 0.5) * grid.cell,
                              grid.y_min + (pillars[p].iy + 0.5) * grid.cell,
                              (grid.z_min + grid.z_max) / 2};
    for (size_t k = 0; k < kept.size(); ++k) {
      const Point& pt = points[kept[k]];
      const double xyz[3] = {pt.x, pt.y, pt.z};
      const auto slot = static_cast<int64_t>(k);
      for (int a = 0; a < 3; ++a) {
        out(p, slot, a) = static_cast<float>(xyz[a]);
        out(p, slot, 4 + a) = static_cast<float>(xyz[a] - mean[a]);
        out(p, slot, 7 + a) = static_cast<float>(xyz[a] - centre[a]);
      }
      out(p, slot, 3) = pt.r;
    }
  }
  return out;
}

// ---- scans -----------------------------------------------------------------------------------

// `count` points: 70% uniform in a box that overhangs the grid volume by `margin` on every side
// (so some fall outside), 30% packed into 5 random cells (so some pillars hold more than N
// points on any grid).
std::vector<Point> random_scan(const GridSpec& grid, int count, double margin, uint64_t seed) {
  Rng rng(seed);
  double cluster_x[5], cluster_y[5];
  for (int c = 0; c < 5; ++c) {
    cluster_x[c] = grid.x_min + static_cast<double>(rng.uniform_int(grid.width())) * grid.cell;
    cluster_y[c] = grid.y_min + static_cast<double>(rng.uniform_int(grid.height())) * grid.cell;
  }
  std::vector<Point> points(static_cast<size_t>(count));
  for (Point& p : points) {
    if (rng.bernoulli(0.3)) {
      const auto c = rng.uniform_int(5);
      p.x = static_cast<float>(cluster_x[c] + rng.uniform(0.01, 0.99) * grid.cell);
      p.y = static_cast<float>(cluster_y[c] + rng.uniform(0.01, 0.99) * grid.cell);
    } else {
      p.x = static_cast<float>(rng.uniform(grid.x_min - margin, grid.x_max + margin));
      p.y = static_cast<float>(rng.uniform(grid.y_min - margin, grid.y_max + margin));
    }
    p.z = static_cast<float>(rng.uniform(grid.z_min - margin, grid.z_max + margin));
    p.r = static_cast<float>(rng.uniform());
  }
  return points;
}

GridSpec small_grid() {  // 16 x 8 cells
  GridSpec g;
  g.x_min = -2.0, g.x_max = 2.0, g.y_min = -1.0, g.y_max = 1.0, g.z_min = -1.0, g.z_max = 1.0;
  g.cell = 0.25;
  return g;
}

GridSpec odd_grid() {  // 13 x 7 cells, cell 0.3, off-centre
  GridSpec g;
  g.x_min = -1.5, g.x_max = 2.4, g.y_min = 0.3, g.y_max = 2.4, g.z_min = -2.0, g.z_max = 0.5;
  g.cell = 0.3;
  return g;
}

GridSpec wide_grid() {  // 7919 x 3 cells: a prime row length for the cell = iy * W + ix split
  GridSpec g;
  g.x_min = -1979.75, g.x_max = 1979.75, g.y_min = -0.75, g.y_max = 0.75, g.z_min = -1.0;
  g.z_max = 1.0, g.cell = 0.5;
  return g;
}

// A point in the middle of cell (iy, ix).
Point point_in_cell(const GridSpec& g, int64_t iy, int64_t ix, float r = 0.5f) {
  return Point{static_cast<float>(g.x_min + (ix + 0.5) * g.cell),
               static_cast<float>(g.y_min + (iy + 0.5) * g.cell),
               static_cast<float>((g.z_min + g.z_max) / 2), r};
}

// Kept indices of pillar p.
std::vector<int32_t> kept_of(const Pillars& pillars, int64_t p) {
  const int32_t* slots = &pillars.point_index(p, 0);
  return {slots, slots + pillars.count[p]};
}

void expect_matches_reference(const Pillars& actual, const std::vector<ReferencePillar>& expected,
                              int max_points) {
  ASSERT_EQ(actual.num_pillars(), static_cast<int64_t>(expected.size()));
  ASSERT_EQ(actual.cell.shape(), Shape({actual.num_pillars(), 2}));
  ASSERT_EQ(actual.point_index.shape(), Shape({actual.num_pillars(), max_points}));
  for (size_t p = 0; p < expected.size(); ++p) {
    const auto q = static_cast<int64_t>(p);
    ASSERT_EQ(actual.cell(q, 0), expected[p].iy) << "pillar " << p;
    ASSERT_EQ(actual.cell(q, 1), expected[p].ix) << "pillar " << p;
    ASSERT_EQ(kept_of(actual, q), expected[p].kept) << "pillar " << p;
    for (int64_t k = actual.count[q]; k < max_points; ++k) {
      ASSERT_EQ(actual.point_index(q, k), -1) << "padding of pillar " << p << " slot " << k;
    }
  }
}

// Restores the thread count a test changed.
struct ThreadCountGuard {
  ~ThreadCountGuard() { set_num_threads(0); }
};

}  // namespace

// ---- against the reference -------------------------------------------------------------------

struct GatherCase {
  const char* name;
  GridSpec grid;
  int num_points;
  int max_points;   // N
  int max_pillars;  // P
};

void PrintTo(const GatherCase& c, std::ostream* os) {
  *os << c.name;
}

class PillarsVsReference : public ::testing::TestWithParam<GatherCase> {};

TEST_P(PillarsVsReference, InferenceGatherAndDecorationMatch) {
  const GatherCase& c = GetParam();
  for (uint64_t seed = 1; seed <= 3; ++seed) {
    const std::vector<Point> points = random_scan(c.grid, c.num_points, 0.4, seed);
    const PillarConfig cfg{c.max_points, c.max_pillars};
    const Pillars pillars = pillar_gather(points, c.grid, cfg, SampleMode::Inference, nullptr);
    const std::vector<ReferencePillar> expected =
        reference_gather(points, c.grid, c.max_points, c.max_pillars);
    expect_matches_reference(pillars, expected, c.max_points);

    const Tensor<float> features = decorate_points(points, pillars, c.grid);
    EXPECT_TRUE(test::all_close(
        features, reference_decorate(points, expected, c.grid, c.max_points), 1e-6, 1e-6));
  }
}

// The cases make sure each path is exercised: pillars over N, more pillars than P, N = 1.
TEST_P(PillarsVsReference, CaseExercisesTheLimits) {
  const GatherCase& c = GetParam();
  const std::vector<Point> points = random_scan(c.grid, c.num_points, 0.4, 1);
  const std::vector<ReferencePillar> all = reference_gather(points, c.grid, 1 << 30, 0);
  size_t largest = 0;
  for (const ReferencePillar& p : all) largest = std::max(largest, p.kept.size());
  EXPECT_GT(largest, static_cast<size_t>(c.max_points)) << "no pillar needs subsampling";
  if (c.max_pillars > 0) {
    EXPECT_GT(all.size(), static_cast<size_t>(c.max_pillars));
  }
}

INSTANTIATE_TEST_SUITE_P(Cases, PillarsVsReference,
                         ::testing::Values(GatherCase{"small_N20_all", small_grid(), 4000, 20, 0},
                                           GatherCase{"small_N20_P50", small_grid(), 4000, 20, 50},
                                           GatherCase{"small_N3_P7", small_grid(), 1000, 3, 7},
                                           GatherCase{"odd_N1_all", odd_grid(), 500, 1, 0},
                                           GatherCase{"odd_N5_P80", odd_grid(), 900, 5, 80},
                                           GatherCase{"default_N20_P3000", GridSpec{}, 30000, 20,
                                                      3000},
                                           GatherCase{"wide_N20_all", wide_grid(), 20000, 20, 0}),
                         [](const ::testing::TestParamInfo<GatherCase>& param_info) {
                           return std::string(param_info.param.name);
                         });

// ---- hand-computed cases ---------------------------------------------------------------------

TEST(PillarGather, KeepsEvenlySpacedPointsOfAFullPillar) {
  // 47 points of one pillar at the odd file positions, interleaved with 47 points spread over
  // other cells; N = 20 keeps pillar positions floor(k * 47 / 20).
  const GridSpec grid = small_grid();
  std::vector<Point> points;
  for (int j = 0; j < 47; ++j) {
    points.push_back(point_in_cell(grid, 1 + j % 6, 2 + j % 13));
    Point in_pillar = point_in_cell(grid, 0, 0);
    in_pillar.z = static_cast<float>(-0.9 + 0.01 * j);
    points.push_back(in_pillar);
  }
  const Pillars pillars = pillar_gather(points, grid, {20, 0}, SampleMode::Inference, nullptr);
  const std::vector<int32_t> positions = {0,  2,  4,  7,  9,  11, 14, 16, 18, 21,
                                          23, 25, 28, 30, 32, 35, 37, 39, 42, 44};
  int64_t found = -1;
  for (int64_t p = 0; p < pillars.num_pillars(); ++p) {
    if (pillars.cell(p, 0) == 0 && pillars.cell(p, 1) == 0) found = p;
  }
  ASSERT_EQ(found, 1) << "the (0, 0) pillar appears second in the file";
  ASSERT_EQ(pillars.count[found], 20);
  for (int k = 0; k < 20; ++k) EXPECT_EQ(pillars.point_index(found, k), 2 * positions[k] + 1);
}

TEST(PillarGather, KeepsEvenlySpacedPillarsBeyondP) {
  // Ten pillars appear in file order along row 3; P = 4 keeps positions 0, 2, 5, 7.
  const GridSpec grid = small_grid();
  std::vector<Point> points;
  for (int ix = 0; ix < 10; ++ix) points.push_back(point_in_cell(grid, 3, 15 - ix));
  const Pillars pillars = pillar_gather(points, grid, {20, 4}, SampleMode::Inference, nullptr);
  ASSERT_EQ(pillars.num_pillars(), 4);
  const int expected_first_point[4] = {0, 2, 5, 7};
  for (int p = 0; p < 4; ++p) {
    EXPECT_EQ(pillars.cell(p, 0), 3);
    EXPECT_EQ(pillars.cell(p, 1), 15 - expected_first_point[p]);
    EXPECT_EQ(pillars.count[p], 1);
    EXPECT_EQ(pillars.point_index(p, 0), expected_first_point[p]);
  }
}

TEST(PillarGather, NumbersPillarsByFirstAppearance) {
  // Cells C, A, B, A, C, B, A -> pillars C, A, B with points {0, 4}, {1, 3, 6}, {2, 5}.
  const GridSpec grid = small_grid();
  const Point a = point_in_cell(grid, 0, 0), b = point_in_cell(grid, 7, 15),
              c = point_in_cell(grid, 4, 8);
  const std::vector<Point> points = {c, a, b, a, c, b, a};
  const Pillars pillars = pillar_gather(points, grid, {4, 0}, SampleMode::Inference, nullptr);
  ASSERT_EQ(pillars.num_pillars(), 3);
  EXPECT_EQ(pillars.cell(0, 0), 4);
  EXPECT_EQ(pillars.cell(0, 1), 8);
  EXPECT_EQ(pillars.cell(1, 0), 0);
  EXPECT_EQ(pillars.cell(1, 1), 0);
  EXPECT_EQ(pillars.cell(2, 0), 7);
  EXPECT_EQ(pillars.cell(2, 1), 15);
  EXPECT_EQ(kept_of(pillars, 0), (std::vector<int32_t>{0, 4}));
  EXPECT_EQ(kept_of(pillars, 1), (std::vector<int32_t>{1, 3, 6}));
  EXPECT_EQ(kept_of(pillars, 2), (std::vector<int32_t>{2, 5}));
  EXPECT_EQ(pillars.point_index(1, 3), -1);
}

TEST(PillarGather, EmptyInputGivesZeroPillarsWithShapes) {
  const GridSpec grid;
  const std::vector<Point> empty;
  const std::vector<Point> all_outside = {{60.f, 0.f, 0.f, 1.f}, {0.f, 0.f, 2.0f, 1.f}};
  Rng rng(5);
  for (const std::vector<Point>* points : {&empty, &all_outside}) {
    for (SampleMode mode : {SampleMode::Inference, SampleMode::Training}) {
      const Pillars pillars = pillar_gather(*points, grid, {20, 0}, mode, &rng);
      EXPECT_EQ(pillars.num_pillars(), 0);
      EXPECT_EQ(pillars.cell.shape(), Shape({0, 2}));
      EXPECT_EQ(pillars.point_index.shape(), Shape({0, 20}));
      EXPECT_EQ(pillars.count.shape(), Shape({0}));
      EXPECT_EQ(decorate_points(*points, pillars, grid).shape(), Shape({0, 20, 10}));
    }
  }
}

TEST(PillarGather, SinglePoint) {
  const GridSpec grid;
  const std::vector<Point> points = {{1.23f, -4.56f, 0.25f, 0.75f}};
  const Pillars pillars = pillar_gather(points, grid, {20, 0}, SampleMode::Inference, nullptr);
  ASSERT_EQ(pillars.num_pillars(), 1);
  EXPECT_EQ(pillars.cell(0, 0), 204);  // floor((-4.56 + 25) / 0.1)
  EXPECT_EQ(pillars.cell(0, 1), 512);  // floor((1.23 + 50) / 0.1)
  EXPECT_EQ(pillars.count[0], 1);
  EXPECT_EQ(pillars.point_index(0, 0), 0);
  for (int k = 1; k < 20; ++k) EXPECT_EQ(pillars.point_index(0, k), -1);

  const Tensor<float> f = decorate_points(points, pillars, grid);
  ASSERT_EQ(f.shape(), Shape({1, 20, 10}));
  const float expected[10] = {1.23f,
                              -4.56f,
                              0.25f,
                              0.75f,
                              0.f,
                              0.f,
                              0.f,
                              static_cast<float>(double{1.23f} - 1.25),
                              static_cast<float>(double{-4.56f} - -4.55),
                              static_cast<float>(double{0.25f} - -0.5)};
  for (int d = 0; d < 10; ++d) EXPECT_NEAR(f(0, 0, d), expected[d], 1e-6) << "feature " << d;
  for (int64_t i = 10; i < f.numel(); ++i) ASSERT_EQ(f[i], 0.0f) << "padding element " << i;
}

TEST(PillarGather, RangeBordersLowerIncludedUpperExcluded) {
  const GridSpec grid;
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const float below_x_max = std::nextafter(50.0f, 0.0f);
  const std::vector<Point> points = {
      {-50.0f, 0.f, 0.f, 0.f},       // 0: x = x_min, in, ix 0
      {50.0f, 0.f, 0.f, 0.f},        // 1: x = x_max, out
      {0.f, -25.0f, 0.f, 0.f},       // 2: y = y_min, in, iy 0
      {0.f, 25.0f, 0.f, 0.f},        // 3: y = y_max, out
      {0.f, 0.f, -2.5f, 0.f},        // 4: z = z_min, in
      {0.f, 0.f, 1.5f, 0.f},         // 5: z = z_max, out
      {below_x_max, 0.f, 0.f, 0.f},  // 6: just below x_max, in, ix 999
      {-50.01f, 0.f, 0.f, 0.f},      // 7: below x_min, out
      {0.f, 0.f, -2.51f, 0.f},       // 8: below z_min, out
      {nan, 0.f, 0.f, 0.f},          // 9: not finite, out
      {0.f, 24.95f, 1.49f, 0.f},     // 10: in, iy 499
      {1.f, 1.f, 0.f, nan},          // 11: reflectance not finite, out
      {1.f, 1.f, 0.f, std::numeric_limits<float>::infinity()},  // 12: likewise
      {1.f, 1.f, 0.f, 1e6f},         // 13: reflectance beyond kMaxAbsReflectance, out
  };
  const Pillars pillars = pillar_gather(points, grid, {20, 0}, SampleMode::Inference, nullptr);
  // Points 0, 2, 4, 6, 10 are inside, each in its own cell, so they are pillars 0..4.
  const int32_t expected_point[5] = {0, 2, 4, 6, 10};
  const int32_t expected_cell[5][2] = {{250, 0}, {0, 500}, {250, 500}, {250, 999}, {499, 500}};
  ASSERT_EQ(pillars.num_pillars(), 5);
  for (int p = 0; p < 5; ++p) {
    EXPECT_EQ(kept_of(pillars, p), std::vector<int32_t>{expected_point[p]}) << "pillar " << p;
    EXPECT_EQ(pillars.cell(p, 0), expected_cell[p][0]) << "pillar " << p;
    EXPECT_EQ(pillars.cell(p, 1), expected_cell[p][1]) << "pillar " << p;
  }
}

TEST(PointDecoration, HandComputedThreePointPillar) {
  // Cell (iy 250, ix 500) of the default grid: centre (0.05, 0.05, -0.5).
  const GridSpec grid;
  const std::vector<Point> points = {{0.01f, 0.02f, 0.0f, 0.5f},
                                     {7.0f, 7.0f, 0.0f, 0.9f},  // another pillar
                                     {0.05f, 0.08f, -1.0f, 0.1f},
                                     {0.09f, 0.03f, 1.0f, 0.2f}};
  const Pillars pillars = pillar_gather(points, grid, {5, 0}, SampleMode::Inference, nullptr);
  ASSERT_EQ(pillars.num_pillars(), 2);
  ASSERT_EQ(pillars.cell(0, 0), 250);
  ASSERT_EQ(pillars.cell(0, 1), 500);
  ASSERT_EQ(kept_of(pillars, 0), (std::vector<int32_t>{0, 2, 3}));
  const Tensor<float> f = decorate_points(points, pillars, grid);
  ASSERT_EQ(f.shape(), Shape({2, 5, 10}));
  // mean = (0.05, 0.13 / 3, 0); offsets by hand.
  const double expected[3][10] = {
      {0.01, 0.02, 0.0, 0.5, -0.04, 0.02 - 0.13 / 3, 0.0, -0.04, -0.03, 0.5},
      {0.05, 0.08, -1.0, 0.1, 0.0, 0.08 - 0.13 / 3, -1.0, 0.0, 0.03, -0.5},
      {0.09, 0.03, 1.0, 0.2, 0.04, 0.03 - 0.13 / 3, 1.0, 0.04, -0.02, 1.5}};
  for (int k = 0; k < 3; ++k) {
    for (int d = 0; d < 10; ++d) {
      EXPECT_NEAR(f(0, k, d), expected[k][d], 2e-6) << "slot " << k << " feature " << d;
    }
  }
  for (int k = 3; k < 5; ++k) {
    for (int d = 0; d < 10; ++d) EXPECT_EQ(f(0, k, d), 0.0f) << "padding slot " << k;
  }
  // The lone point of the second pillar is its own mean.
  for (int d = 4; d < 7; ++d) EXPECT_EQ(f(1, 0, d), 0.0f);
}

TEST(PointDecoration, ReusedOutputEqualsFreshAndAnyThreadCount) {
  ThreadCountGuard guard;
  const GridSpec grid = small_grid();
  const std::vector<Point> points = random_scan(grid, 3000, 0.3, 11);
  const Pillars pillars = pillar_gather(points, grid, {20, 0}, SampleMode::Inference, nullptr);
  set_num_threads(1);
  const Tensor<float> one_thread = decorate_points(points, pillars, grid);
  for (int threads : {2, 3, 7}) {
    set_num_threads(threads);
    const Tensor<float> many = decorate_points(points, pillars, grid);
    ASSERT_EQ(many.shape(), one_thread.shape());
    EXPECT_EQ(many.values(), one_thread.values()) << threads << " threads";
  }
  // A bigger and a smaller previous output are reused and fully overwritten.
  Tensor<float> reused({pillars.num_pillars() + 5, 20, 10}, 7.0f);
  decorate_points(points, pillars, grid, reused);
  EXPECT_EQ(reused.shape(), one_thread.shape());
  EXPECT_EQ(reused.values(), one_thread.values());
  Tensor<float> small({1, 2, 10}, -3.0f);
  decorate_points(points, pillars, grid, small);
  EXPECT_EQ(small.values(), one_thread.values());
}

TEST(PillarGather, ReusedWorkspaceAndOutputGiveTheSameResult) {
  // One workspace over scans of two grids and both modes, and one whose cell map was left
  // dirty (as after an interrupted call), against fresh calls.
  PillarWorkspace workspace;
  Pillars reused;
  const PillarConfig cfg{6, 40};
  for (int round = 0; round < 4; ++round) {
    const GridSpec grid = round % 2 == 0 ? small_grid() : odd_grid();
    const SampleMode mode = round < 2 ? SampleMode::Inference : SampleMode::Training;
    const std::vector<Point> points = random_scan(grid, 800 + 100 * round, 0.3, 20 + round);
    if (round == 3) {
      std::fill(workspace.pillar_of_cell.begin(), workspace.pillar_of_cell.end(), 5);
      workspace.cell_map_clean = false;
    }
    Rng rng_fresh(round), rng_reused(round);
    const Pillars fresh = pillar_gather(points, grid, cfg, mode, &rng_fresh);
    pillar_gather(points, grid, cfg, mode, &rng_reused, workspace, reused);
    EXPECT_EQ(reused.cell.shape(), fresh.cell.shape()) << "round " << round;
    EXPECT_EQ(reused.cell.values(), fresh.cell.values()) << "round " << round;
    EXPECT_EQ(reused.point_index.shape(), fresh.point_index.shape()) << "round " << round;
    EXPECT_EQ(reused.point_index.values(), fresh.point_index.values()) << "round " << round;
    EXPECT_EQ(reused.count.values(), fresh.count.values()) << "round " << round;
    EXPECT_TRUE(workspace.cell_map_clean);
    EXPECT_TRUE(std::all_of(workspace.pillar_of_cell.begin(), workspace.pillar_of_cell.end(),
                            [](int32_t pillar) { return pillar == -1; }))
        << "the cell map must be left all -1";
  }
}

// ---- training mode ---------------------------------------------------------------------------

TEST(PillarGatherTraining, SameSeedSameResultDifferentSeedDifferentSubset) {
  const GridSpec grid = small_grid();
  const std::vector<Point> points = random_scan(grid, 4000, 0.2, 3);
  const PillarConfig cfg{20, 60};
  Rng a(99), b(99), c(100);
  const Pillars first = pillar_gather(points, grid, cfg, SampleMode::Training, &a);
  const Pillars again = pillar_gather(points, grid, cfg, SampleMode::Training, &b);
  const Pillars other = pillar_gather(points, grid, cfg, SampleMode::Training, &c);
  EXPECT_EQ(first.cell.values(), again.cell.values());
  EXPECT_EQ(first.point_index.values(), again.point_index.values());
  EXPECT_EQ(first.count.values(), again.count.values());
  EXPECT_NE(first.cell.values(), other.cell.values());
  EXPECT_NE(first.point_index.values(), other.point_index.values());
}

TEST(PillarGatherTraining, KeptSetsAreOrderedSubsetsOfTheRightSize) {
  const GridSpec grid = small_grid();
  const std::vector<Point> points = random_scan(grid, 4000, 0.2, 4);
  const std::vector<ReferencePillar> all = reference_gather(points, grid, 1 << 30, 0);
  std::map<std::pair<int64_t, int64_t>, size_t> rank_of_cell;
  for (size_t r = 0; r < all.size(); ++r) rank_of_cell[{all[r].iy, all[r].ix}] = r;

  for (const int max_pillars : {0, 50}) {
    Rng rng(7);
    const Pillars pillars =
        pillar_gather(points, grid, {20, max_pillars}, SampleMode::Training, &rng);
    const size_t expected_pillars = max_pillars > 0 ? 50 : all.size();
    ASSERT_EQ(pillars.num_pillars(), static_cast<int64_t>(expected_pillars));
    int64_t previous_rank = -1;
    for (int64_t p = 0; p < pillars.num_pillars(); ++p) {
      const auto it = rank_of_cell.find({pillars.cell(p, 0), pillars.cell(p, 1)});
      ASSERT_NE(it, rank_of_cell.end()) << "pillar " << p << " is not a non-empty cell";
      const auto rank = static_cast<int64_t>(it->second);
      ASSERT_GT(rank, previous_rank) << "pillars out of first-appearance order";
      previous_rank = rank;
      const std::vector<int32_t>& in_cell = all[it->second].kept;
      const std::vector<int32_t> kept = kept_of(pillars, p);
      ASSERT_EQ(kept.size(), std::min<size_t>(in_cell.size(), 20));
      ASSERT_TRUE(std::is_sorted(kept.begin(), kept.end()));
      ASSERT_EQ(std::set<int32_t>(kept.begin(), kept.end()).size(), kept.size());
      ASSERT_TRUE(std::includes(in_cell.begin(), in_cell.end(), kept.begin(), kept.end()));
    }
  }
}

TEST(PillarGatherTraining, EveryPointOfAFullPillarIsEquallyLikely) {
  // One pillar of 40 points, N = 10: each point is kept with probability 1/4.
  const GridSpec grid = small_grid();
  const std::vector<Point> points(40, point_in_cell(grid, 2, 3));
  std::vector<int> kept_times(40, 0);
  const int trials = 4000;
  for (int t = 0; t < trials; ++t) {
    Rng rng = Rng::derive(1234, static_cast<uint64_t>(t));
    const Pillars pillars = pillar_gather(points, grid, {10, 0}, SampleMode::Training, &rng);
    ASSERT_EQ(pillars.count[0], 10);
    for (int32_t i : kept_of(pillars, 0)) ++kept_times[i];
  }
  // Binomial(4000, 0.25): sd = 27.4; 5 sd.
  for (int i = 0; i < 40; ++i) EXPECT_NEAR(kept_times[i], trials / 4, 137) << "point " << i;
}

TEST(SelectPositions, EvenlySpacedOrAllOrRandomAscending) {
  std::vector<int32_t> out(5);
  select_positions(12, 5, SampleMode::Inference, nullptr, out.data());
  EXPECT_EQ(out, (std::vector<int32_t>{0, 2, 4, 7, 9}));
  Rng rng(1);
  const Rng::State before = rng.state();
  select_positions(5, 5, SampleMode::Training, &rng, out.data());
  EXPECT_EQ(out, (std::vector<int32_t>{0, 1, 2, 3, 4}));
  EXPECT_EQ(rng.state(), before) << "keeping everything draws no random numbers";
  select_positions(1000, 5, SampleMode::Training, &rng, out.data());
  EXPECT_TRUE(std::is_sorted(out.begin(), out.end()));
  EXPECT_EQ(std::set<int32_t>(out.begin(), out.end()).size(), 5u);
  EXPECT_LT(out.back(), 1000);
  EXPECT_THROW(select_positions(3, 4, SampleMode::Inference, nullptr, out.data()), Error);
}

// ---- errors ----------------------------------------------------------------------------------

TEST(PillarGather, RejectsBadArguments) {
  const GridSpec grid;
  const std::vector<Point> points = {{0.f, 0.f, 0.f, 0.f}};
  EXPECT_THROW(pillar_gather(points, grid, {0, 0}, SampleMode::Inference, nullptr), Error);
  EXPECT_THROW(pillar_gather(points, grid, {20, -1}, SampleMode::Inference, nullptr), Error);
  EXPECT_THROW(pillar_gather(points, grid, {20, 0}, SampleMode::Training, nullptr), Error);

  Pillars pillars = pillar_gather(points, grid, {20, 0}, SampleMode::Inference, nullptr);
  const std::vector<Point> fewer;
  EXPECT_THROW(decorate_points(fewer, pillars, grid), Error);  // index 0 outside an empty scan
  Pillars wrong_count = pillars;
  wrong_count.count[0] = 21;
  EXPECT_THROW(decorate_points(points, wrong_count, grid), Error);
  Pillars wrong_cell = pillars;
  wrong_cell.cell(0, 1) = 1000;
  EXPECT_THROW(decorate_points(points, wrong_cell, grid), Error);
  Pillars wrong_shape = pillars;
  wrong_shape.cell = Tensor<int32_t>({2, 2});
  EXPECT_THROW(decorate_points(points, wrong_shape, grid), Error);
}

// The values are checked while the pillars are decorated, on every thread, for N = 20 (the
// compiled-in case) and any other N: the error names the first pillar at fault.
TEST(PointDecoration, NamesTheFirstPillarAtFault) {
  ThreadCountGuard guard;
  const GridSpec grid = small_grid();
  const std::vector<Point> points = random_scan(grid, 3000, 0.0, 5);
  for (const int slots : {20, 7}) {
    const Pillars pillars = pillar_gather(points, grid, {slots, 0}, SampleMode::Inference, nullptr);
    const int64_t last = pillars.num_pillars() - 1;
    ASSERT_GT(last, 10);
    const auto message = [&](const Pillars& bad) {
      try {
        decorate_points(points, bad, grid);
      } catch (const Error& e) {
        return std::string(e.what());
      }
      return std::string("no error");
    };
    for (const int threads : {1, 2}) {
      set_num_threads(threads);
      Pillars negative_index = pillars;
      negative_index.point_index(last, 0) = -3;
      EXPECT_NE(message(negative_index).find(fmt::format("pillar {} slot 0 points at -3", last)),
                std::string::npos)
          << message(negative_index);
      Pillars far_index = pillars;
      far_index.point_index(last, 0) = 3000;
      far_index.point_index(last - 1, 0) = 5000;
      EXPECT_NE(message(far_index).find(fmt::format("pillar {} slot 0 points at 5000", last - 1)),
                std::string::npos)
          << message(far_index);
      Pillars negative_count = pillars;
      negative_count.count[last] = -1;
      EXPECT_NE(message(negative_count).find(fmt::format("pillar {} has count -1", last)),
                std::string::npos)
          << message(negative_count);
      Pillars outside = pillars;
      outside.cell(last, 0) = -1;
      EXPECT_NE(message(outside).find(fmt::format("pillar {} has cell (iy -1", last)),
                std::string::npos)
          << message(outside);
    }
  }
}
