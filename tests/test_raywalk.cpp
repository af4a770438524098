// Tests of the ray walks (host/raywalk): single rays against a brute-force reference (dense
// sampling of the segment, jumps between samples resolved by exact crossing times), hand-computed
// cells and voxels, the bulk 2D / 3D counts against the sum of single-ray walks for every thread
// count, the occupancy probability formula, and input checks.
#include "host/raywalk.hpp"

#include <fmt/format.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <initializer_list>
#include <limits>
#include <ostream>
#include <string>
#include <vector>

#include "core/error.hpp"
#include "core/parallel.hpp"
#include "core/rng.hpp"
#include "tests/support/raywalk_grids.hpp"

namespace pillarseg::host {

// Prints cells readably in failure messages.
void PrintTo(const WalkCell& cell, std::ostream* os) {
  *os << "(" << cell.ix << "," << cell.iy << "," << cell.iz << ")";
}

namespace {

using Vec3 = Eigen::Vector3d;

// Restores the thread count a test changes.
class ThreadCountGuard {
 public:
  ThreadCountGuard() : saved_(num_threads()) {}
  ~ThreadCountGuard() { set_num_threads(saved_); }
  ThreadCountGuard(const ThreadCountGuard&) = delete;
  ThreadCountGuard& operator=(const ThreadCountGuard&) = delete;

 private:
  int saved_;
};

using test::dyadic_grid;
using test::small_grid;

std::string cells_str(const std::vector<WalkCell>& cells) {
  std::string s;
  for (const WalkCell& c : cells) s += fmt::format("({},{},{}) ", c.ix, c.iy, c.iz);
  return s;
}

// ---- brute-force reference ----

// The in-grid cells of the segment from origin to point, in walk order: the segment is sampled
// densely (within the grid box and a margin), the first cell follows the direction rule and the
// last is floor(point); where two consecutive samples differ on several axes, the crossings in
// between are ordered by their exact times (long double), x before y before z at equal times.
std::vector<WalkCell> reference_walk(const Vec3& origin, const Vec3& point, const GridSpec& grid,
                                     int dims) {
  const std::array<double, 3> scale = {grid.cell, grid.cell, grid.voxel_z};
  const std::array<double, 3> minimum = {grid.x_min, grid.y_min, grid.z_min};
  const std::array<int64_t, 3> cells = {grid.width(), grid.height(), dims == 3 ? grid.layers() : 1};
  std::array<long double, 3> o{}, p{}, d{};
  for (int k = 0; k < dims; ++k) {
    o[k] = (origin[k] - minimum[k]) / scale[k];  // the walk's cell coordinates, in double
    p[k] = (point[k] - minimum[k]) / scale[k];
    d[k] = p[k] - o[k];
  }
  // Parameter range inside the box grown by two cells.
  long double t_in = 0.0L, t_out = 1.0L;
  for (int k = 0; k < dims; ++k) {
    const long double lo = -2.0L, hi = static_cast<long double>(cells[k]) + 2.0L;
    if (d[k] == 0.0L) {
      if (o[k] < lo || o[k] > hi) return {};
      continue;
    }
    long double ta = (lo - o[k]) / d[k], tb = (hi - o[k]) / d[k];
    if (ta > tb) std::swap(ta, tb);
    t_in = std::max(t_in, ta);
    t_out = std::min(t_out, tb);
  }
  if (t_in > t_out) return {};
  using Cell = std::array<int64_t, 3>;
  const auto cell_at = [&](long double t) {
    Cell c{0, 0, 0};
    for (int k = 0; k < dims; ++k) c[k] = static_cast<int64_t>(std::floor(o[k] + t * d[k]));
    return c;
  };
  std::vector<Cell> samples;
  if (t_in == 0.0L) {
    Cell first{0, 0, 0};
    for (int k = 0; k < dims; ++k)
      first[k] = static_cast<int64_t>(d[k] < 0.0L ? std::ceil(o[k]) - 1.0L : std::floor(o[k]));
    samples.push_back(first);
  }
  long double span = 0.0L;
  for (int k = 0; k < dims; ++k) span += std::abs(d[k]) * (t_out - t_in);
  const int64_t count = std::max<int64_t>(100000, static_cast<int64_t>(8.0L * span));
  // An irrational offset keeps samples off the crossing points of lattice rays.
  const long double offset = 0.41421356237309504880L;
  for (int64_t s = 0; s < count; ++s) {
    const Cell c = cell_at(t_in + (t_out - t_in) * (static_cast<long double>(s) + offset) / count);
    if (samples.empty() || samples.back() != c) samples.push_back(c);
  }
  if (t_out == 1.0L) {
    Cell last{0, 0, 0};
    for (int k = 0; k < dims; ++k) last[k] = static_cast<int64_t>(std::floor(p[k]));
    if (samples.back() != last) samples.push_back(last);
  }
  std::vector<Cell> walk = {samples.front()};
  for (size_t i = 1; i < samples.size(); ++i) {
    Cell current = walk.back();
    const Cell& next = samples[i];
    std::vector<std::pair<long double, int>> crossings;  // (time, axis)
    for (int k = 0; k < dims; ++k) {
      if (next[k] == current[k]) continue;
      EXPECT_EQ(std::abs(next[k] - current[k]), 1) << "reference sampling too sparse";
      const long double boundary = static_cast<long double>(std::max(next[k], current[k]));
      crossings.emplace_back((boundary - o[k]) / d[k], k);
    }
    std::sort(crossings.begin(), crossings.end());
    for (const auto& crossing : crossings) {
      const int k = crossing.second;
      current[k] = next[k];
      walk.push_back(current);
    }
  }
  std::vector<WalkCell> in_grid;
  for (const Cell& c : walk) {
    bool inside = true;
    for (int k = 0; k < dims; ++k) inside = inside && c[k] >= 0 && c[k] < cells[k];
    if (inside) in_grid.push_back({c[0], c[1], c[2]});
  }
  return in_grid;
}

void expect_walk_matches_reference(const Vec3& origin, const Vec3& point, const GridSpec& grid) {
  const std::vector<WalkCell> expected_2d = reference_walk(origin, point, grid, 2);
  const std::vector<WalkCell> actual_2d = ray_cells_2d(origin, point, grid);
  EXPECT_EQ(actual_2d, expected_2d)
      << "2D ray from " << origin.transpose() << " to " << point.transpose()
      << "\n  walk:      " << cells_str(actual_2d) << "\n  reference: " << cells_str(expected_2d);
  const std::vector<WalkCell> expected_3d = reference_walk(origin, point, grid, 3);
  const std::vector<WalkCell> actual_3d = ray_voxels_3d(origin, point, grid);
  EXPECT_EQ(actual_3d, expected_3d)
      << "3D ray from " << origin.transpose() << " to " << point.transpose()
      << "\n  walk:      " << cells_str(actual_3d) << "\n  reference: " << cells_str(expected_3d);
}

// A float position, as points are stored.
Vec3 float_point(double x, double y, double z) {
  return Vec3(static_cast<float>(x), static_cast<float>(y), static_cast<float>(z));
}

// ---- single rays: reference ----

TEST(RayWalkReference, CraftedRaysOnDefaultGrid) {
  const GridSpec grid;
  const Vec3 zero(0.0, 0.0, 0.0);
  const std::vector<Vec3> points = {
      // along the axes, both ways
      {3.0, 0.0, 0.0},
      {-3.0, 0.0, 0.0},
      {0.0, 2.0, 0.0},
      {0.0, -2.0, 0.0},
      // diagonals through every corner on the way, the four quadrants
      {2.5, 2.5, 0.0},
      {-2.5, 2.5, 0.0},
      {2.5, -2.5, 0.0},
      {-2.5, -2.5, 0.0},
      // slopes 1/2, -1/3, 3 through corners; ending on a vertical line, a horizontal line, a corner
      {0.5, 0.25, 0.0},
      {-1.5, 0.5, 0.0},
      {0.5, 1.5, 0.0},
      {0.75, 0.3, 0.0},
      {0.3, -0.5, 0.0},
      {-0.5, -0.5, 0.0},
      // zero length, one cell, leaving the grid, far away
      {0.0, 0.0, 0.0},
      {0.05, 0.05, 0.05},
      {70.0, 10.0, -1.0},
      {-80.0, -40.0, 3.0},
      {1e30, 2.7e29, -1.3e29},
      // through voxel edges: z crossings at the times of x crossings
      {0.25, 0.05, -0.25},
      {0.5, 0.5, -0.5},
      {-0.5, 0.2, 0.4}};
  for (const Vec3& point : points)
    expect_walk_matches_reference(zero, float_point(point.x(), point.y(), point.z()), grid);
}

TEST(RayWalkReference, RandomRaysOnSmallGrid) {
  const GridSpec grid = small_grid();
  Rng rng(7);
  for (int i = 0; i < 120; ++i) {
    Vec3 origin;
    switch (i % 3) {
      case 0:  // on a cell corner (cell coordinates nearly integer: 0.1 m is not a binary fraction)
        origin = Vec3(grid.x_min + 0.1 * static_cast<double>(rng.uniform_int(34)),
                      grid.y_min + 0.1 * static_cast<double>(rng.uniform_int(22)), 0.0);
        break;
      case 1:  // anywhere near the grid
        origin = Vec3(rng.uniform(-2.0, 3.0), rng.uniform(-2.0, 2.0), rng.uniform(-1.0, 1.0));
        break;
      default:  // outside the grid
        origin = Vec3(rng.uniform(-6.0, -2.0), rng.uniform(1.5, 4.0), rng.uniform(-2.0, 2.0));
        break;
    }
    Vec3 point =
        float_point(rng.uniform(-3.0, 4.0), rng.uniform(-3.0, 3.0), rng.uniform(-1.0, 1.0));
    if (i % 10 == 1) point.y() = origin.y();  // parallel to x
    if (i % 10 == 2) point.x() = origin.x();  // parallel to y
    if (i % 10 == 3) point = origin;          // zero length
    expect_walk_matches_reference(origin, point, grid);
  }
}

TEST(RayWalkReference, LatticeRaysThroughCornersAndEdges) {
  // On the 1/8 m lattice of the dyadic grid, cell coordinates are exact halves and integers:
  // origins on corners, points on borders, rays through corners and voxel edges everywhere.
  const GridSpec grid = dyadic_grid();
  Rng rng(11);
  const auto lattice = [&](double lo, double hi, double step) {
    return lo +
           step * static_cast<double>(rng.uniform_int(static_cast<uint64_t>((hi - lo) / step) + 1));
  };
  for (int i = 0; i < 160; ++i) {
    const double origin_step = i % 2 == 0 ? 0.25 : 0.125;
    const Vec3 origin(lattice(-3.0, 3.5, origin_step), lattice(-2.0, 2.0, origin_step),
                      lattice(-1.5, 1.0, 0.25));
    const Vec3 point(lattice(-3.0, 3.5, 0.125), lattice(-2.0, 2.0, 0.125),
                     lattice(-1.5, 1.0, 0.125));
    expect_walk_matches_reference(origin, point, grid);
  }
}

TEST(RayWalkReference, RaysPassingJustBesideCorners) {
  // Rays that miss a cell corner by 1e-13 cells, on either side, and rays through it: the double
  // evaluation alone cannot tell these apart, the exact decision must.
  const GridSpec grid;
  const Vec3 zero(0.0, 0.0, 0.0);
  for (const double offset : {-1e-12, -1e-14, 0.0, 1e-14, 1e-12}) {
    expect_walk_matches_reference(zero, Vec3(2.5, 2.5 + offset, 0.0), grid);
    expect_walk_matches_reference(zero, Vec3(-1.5 + offset, 0.5, 0.0), grid);
    expect_walk_matches_reference(zero, Vec3(0.5, -1.0 - offset, 0.0), grid);
    // Beside voxel edges: z crossings (w = 12 at t = 0.4) next to x crossings.
    expect_walk_matches_reference(zero, Vec3(0.25, 0.05, -0.25 + offset), grid);
    expect_walk_matches_reference(Vec3(0.0, 0.0, 0.1), Vec3(-0.5 + offset, 0.25, -0.9), grid);
  }
  // Beyond long double: the ray to the float point (1e30, 3e29, -1e29) passes within 1e-28 of
  // the voxel corner (510, 253, 12) (cell coordinates); computed exactly with rationals from the
  // double cell coordinates, it crosses w = 12 first (at t * (1 - 7.5e-29)), then u = 510, then
  // v = 253 (at t * (1 + 3.3e-29)), so the walk steps z, x, y there.
  const std::vector<WalkCell> far = ray_voxels_3d(zero, float_point(1e30, 3e29, -1e29), grid);
  const std::vector<WalkCell> z_first = {
      {509, 252, 12}, {509, 252, 11}, {510, 252, 11}, {510, 253, 11}};
  EXPECT_NE(std::search(far.begin(), far.end(), z_first.begin(), z_first.end()), far.end())
      << cells_str(far);
  // Just above the diagonal the walk steps y first at every corner, just below x first.
  const std::vector<WalkCell> above = ray_cells_2d(zero, Vec3(0.25, 0.25 + 1e-13, 0.0), grid);
  const std::vector<WalkCell> below = ray_cells_2d(zero, Vec3(0.25 + 1e-13, 0.25, 0.0), grid);
  EXPECT_EQ(above,
            (std::vector<WalkCell>{{500, 250}, {500, 251}, {501, 251}, {501, 252}, {502, 252}}));
  EXPECT_EQ(below,
            (std::vector<WalkCell>{{500, 250}, {501, 250}, {501, 251}, {502, 251}, {502, 252}}));
}

TEST(RayWalkReference, WalksAreConnectedAndComplete) {
  // A ray inside the grid visits |dix| + |diy| (+ |diz|) + 1 cells, each a unit step from the last.
  const GridSpec grid;
  Rng rng(3);
  for (int i = 0; i < 200; ++i) {
    const Vec3 origin(rng.uniform(-20.0, 20.0), rng.uniform(-10.0, 10.0), rng.uniform(-2.0, 1.0));
    const Vec3 point =
        float_point(rng.uniform(-45.0, 45.0), rng.uniform(-20.0, 20.0), rng.uniform(-2.4, 1.4));
    const std::vector<WalkCell> cells = ray_voxels_3d(origin, point, grid);
    const WalkCell last{grid.ix(point.x()), grid.iy(point.y()), grid.iz(point.z())};
    const double du = point.x() - origin.x(), dv = point.y() - origin.y(),
                 dw = point.z() - origin.z();
    const WalkCell first{du < 0 ? grid.ix(origin.x() - 1e-9) : grid.ix(origin.x()),
                         dv < 0 ? grid.iy(origin.y() - 1e-9) : grid.iy(origin.y()),
                         dw < 0 ? grid.iz(origin.z() - 1e-9) : grid.iz(origin.z())};
    ASSERT_FALSE(cells.empty());
    EXPECT_EQ(cells.front(), first);
    EXPECT_EQ(cells.back(), last);
    EXPECT_EQ(static_cast<int64_t>(cells.size()), std::abs(last.ix - first.ix) +
                                                      std::abs(last.iy - first.iy) +
                                                      std::abs(last.iz - first.iz) + 1);
    for (size_t k = 1; k < cells.size(); ++k) {
      const int64_t step = std::abs(cells[k].ix - cells[k - 1].ix) +
                           std::abs(cells[k].iy - cells[k - 1].iy) +
                           std::abs(cells[k].iz - cells[k - 1].iz);
      ASSERT_EQ(step, 1) << cells_str(cells);
    }
  }
}

// ---- single rays: hand-computed ----

TEST(RayWalkCells, HandComputed2D) {
  const GridSpec grid;  // origin (0, 0) is the corner of cells (499..500, 249..250)
  const Vec3 zero(0.0, 0.0, 0.0);
  EXPECT_EQ(ray_cells_2d(zero, float_point(0.25, 0.05, 0.0), grid),
            (std::vector<WalkCell>{{500, 250}, {501, 250}, {502, 250}}));
  // Negative dx from the corner: starts in the cell to the left.
  EXPECT_EQ(ray_cells_2d(zero, float_point(-0.25, 0.05, 0.0), grid),
            (std::vector<WalkCell>{{499, 250}, {498, 250}, {497, 250}}));
  EXPECT_EQ(ray_cells_2d(zero, float_point(-0.05, -0.15, 0.0), grid),
            (std::vector<WalkCell>{{499, 249}, {499, 248}}));
  // Through the corners of a diagonal: x steps first.
  EXPECT_EQ(ray_cells_2d(zero, float_point(0.25, 0.25, 0.0), grid),
            (std::vector<WalkCell>{{500, 250}, {501, 250}, {501, 251}, {502, 251}, {502, 252}}));
  EXPECT_EQ(ray_cells_2d(zero, float_point(-0.25, 0.25, 0.0), grid),
            (std::vector<WalkCell>{{499, 250}, {498, 250}, {498, 251}, {497, 251}, {497, 252}}));
  EXPECT_EQ(ray_cells_2d(zero, float_point(0.25, -0.25, 0.0), grid),
            (std::vector<WalkCell>{{500, 249}, {501, 249}, {501, 248}, {502, 248}, {502, 247}}));
  // Slope 1/2 through a corner at every second column, ending on a vertical cell border.
  EXPECT_EQ(ray_cells_2d(zero, float_point(0.5, 0.25, 0.0), grid),
            (std::vector<WalkCell>{{500, 250},
                                   {501, 250},
                                   {502, 250},
                                   {502, 251},
                                   {503, 251},
                                   {504, 251},
                                   {504, 252},
                                   {505, 252}}));
  // Ending exactly on a corner: the end cell is floor, reached x first when coming from below
  // left, and the last cell of the diagonal when coming from above right.
  EXPECT_EQ(ray_cells_2d(zero, float_point(0.5, 0.5, 0.0), grid),
            (std::vector<WalkCell>{{500, 250},
                                   {501, 250},
                                   {501, 251},
                                   {502, 251},
                                   {502, 252},
                                   {503, 252},
                                   {503, 253},
                                   {504, 253},
                                   {504, 254},
                                   {505, 254},
                                   {505, 255}}));
  EXPECT_EQ(ray_cells_2d(zero, float_point(-0.5, -0.5, 0.0), grid),
            (std::vector<WalkCell>{{499, 249},
                                   {498, 249},
                                   {498, 248},
                                   {497, 248},
                                   {497, 247},
                                   {496, 247},
                                   {496, 246},
                                   {495, 246},
                                   {495, 245}}));
  // A point in the origin's corner cell: only the end cell.
  EXPECT_EQ(ray_cells_2d(zero, float_point(0.05, 0.05, 0.0), grid),
            (std::vector<WalkCell>{{500, 250}}));
  EXPECT_EQ(ray_cells_2d(zero, zero, grid), (std::vector<WalkCell>{{500, 250}}));
  // From outside the grid: only the in-grid cells, starting where the ray enters.
  EXPECT_EQ(ray_cells_2d(Vec3(-50.25, -24.95, 0.0), float_point(-49.75, -24.95, 0.0), grid),
            (std::vector<WalkCell>{{0, 0}, {1, 0}, {2, 0}}));
  EXPECT_TRUE(ray_cells_2d(Vec3(-51.0, 0.0, 0.0), Vec3(-51.0, 5.0, 0.0), grid).empty());
  // Leaving the grid: the in-grid cells only, the last one at the border.
  const std::vector<WalkCell> leaving =
      ray_cells_2d(Vec3(49.75, 0.05, 0.0), float_point(60.0, 0.05, 0.0), grid);
  EXPECT_EQ(leaving, (std::vector<WalkCell>{{997, 250}, {998, 250}, {999, 250}}));
}

TEST(RayWalkCells, HandComputed3D) {
  const GridSpec grid;  // the origin is at w = 12.5, mid-layer
  const Vec3 zero(0.0, 0.0, 0.0);
  // x crossings at t = 0.4, 0.8; the z crossing (w = 12) also at t = 0.4: x steps first.
  EXPECT_EQ(
      ray_voxels_3d(zero, float_point(0.25, 0.05, -0.25), grid),
      (std::vector<WalkCell>{{500, 250, 12}, {501, 250, 12}, {501, 250, 11}, {502, 250, 11}}));
  // Straight down, leaving the volume at z = -2.5: layers 12 .. 0 only.
  std::vector<WalkCell> down;
  for (int64_t iz = 12; iz >= 0; --iz) down.push_back({500, 250, iz});
  EXPECT_EQ(ray_voxels_3d(zero, float_point(0.05, 0.05, -4.0), grid), down);
  // Coming from above the volume: enters at the top layer.
  EXPECT_EQ(ray_voxels_3d(Vec3(0.05, 0.05, 2.0), float_point(0.05, 0.05, 1.1), grid),
            (std::vector<WalkCell>{{500, 250, 19}, {500, 250, 18}}));
  // Entirely above the volume: nothing.
  EXPECT_TRUE(ray_voxels_3d(Vec3(0.0, 0.0, 2.0), float_point(5.0, 1.0, 1.6), grid).empty());
}

// ---- bulk counts ----

// A scan of random points around a sensor, some outside the grid and the z range, some on
// lattice positions (cell borders and corners), a few non-finite.
std::vector<Point> random_scan(int count, uint64_t seed) {
  Rng rng(seed);
  std::vector<Point> points;
  for (int i = 0; i < count; ++i) {
    Point p;
    if (i % 4 == 0) {
      p.x = static_cast<float>(0.125 * std::round(rng.uniform(-3.0, 3.5) * 8.0));
      p.y = static_cast<float>(0.125 * std::round(rng.uniform(-2.0, 2.0) * 8.0));
      p.z = static_cast<float>(0.125 * std::round(rng.uniform(-1.5, 1.0) * 8.0));
    } else {
      p.x = static_cast<float>(rng.uniform(-3.0, 3.5));
      p.y = static_cast<float>(rng.uniform(-2.0, 2.0));
      p.z = static_cast<float>(rng.uniform(-1.5, 1.0));
    }
    p.r = static_cast<float>(rng.uniform());
    points.push_back(p);
  }
  points[3].x = std::numeric_limits<float>::quiet_NaN();
  points[5].z = std::numeric_limits<float>::infinity();
  // Far away: the walk costs only the in-grid cells and no index overflows.
  points[7] = {1e30f, -3e29f, 2e29f, 0.0f};
  points[11] = {-7e5f, 2e5f, -1e3f, 0.0f};
  points[13] = {3.0e38f, 3.0e38f, -3.0e38f, 0.0f};
  return points;
}

// The bulk counts rebuilt from single-ray walks: every walked cell but the end cell counts a
// transmission (pass); the end cell counts a detection (hit) when the point lies in the grid.
void expected_counts(const std::vector<Point>& points, const Vec3& origin, const GridSpec& grid,
                     bool three_d, Tensor<uint32_t>& passed, Tensor<uint32_t>& ended) {
  const int64_t width = grid.width(), height = grid.height(), layers = three_d ? grid.layers() : 1;
  passed = Tensor<uint32_t>::zeros(three_d ? Shape{layers, height, width} : Shape{height, width});
  ended = Tensor<uint32_t>::zeros(passed.shape());
  for (const Point& p : points) {
    if (!std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z)) continue;
    const Vec3 point(p.x, p.y, p.z);
    const std::vector<WalkCell> cells =
        three_d ? ray_voxels_3d(origin, point, grid) : ray_cells_2d(origin, point, grid);
    const WalkCell end{grid.ix(p.x), grid.iy(p.y), three_d ? grid.iz(p.z) : 0};
    const bool ends_inside = three_d ? grid.contains(p.x, p.y, p.z) : grid.contains_xy(p.x, p.y);
    for (size_t k = 0; k < cells.size(); ++k) {
      const WalkCell& c = cells[k];
      const int64_t index = (c.iz * height + c.iy) * width + c.ix;
      if (k + 1 == cells.size() && c == end) {
        if (ends_inside) ++ended[index];
      } else {
        ++passed[index];
      }
    }
  }
}

::testing::AssertionResult same_counts(const Tensor<uint32_t>& actual,
                                       const Tensor<uint32_t>& expected) {
  if (actual.shape() != expected.shape())
    return ::testing::AssertionFailure()
           << "shape " << shape_str(actual.shape()) << " != " << shape_str(expected.shape());
  for (int64_t i = 0; i < actual.numel(); ++i)
    if (actual[i] != expected[i])
      return ::testing::AssertionFailure() << "first difference at flat index " << i << ": "
                                           << actual[i] << " != expected " << expected[i];
  return ::testing::AssertionSuccess();
}

// observability_2d against the sum of single-ray walks, for each thread count (the caller
// restores the thread count).
void expect_observability_matches_walks(const std::vector<Point>& points, const Vec3& origin,
                                        const GridSpec& grid, std::initializer_list<int> threads) {
  Tensor<uint32_t> transmissions, detections;
  expected_counts(points, origin, grid, false, transmissions, detections);
  for (int t : threads) {
    set_num_threads(t);
    const ObservabilityCounts counts = observability_2d(points, origin, grid);
    EXPECT_TRUE(same_counts(counts.transmissions, transmissions))
        << "origin (" << origin.x() << ", " << origin.y() << "), " << t << " threads";
    EXPECT_TRUE(same_counts(counts.detections, detections))
        << "origin (" << origin.x() << ", " << origin.y() << "), " << t << " threads";
  }
}

TEST(Observability2D, MatchesSingleRayWalksForEveryThreadCount) {
  ThreadCountGuard guard;
  for (const GridSpec& grid : {small_grid(), dyadic_grid()}) {
    for (const Vec3& origin : {Vec3(0.0, 0.0, 0.0), Vec3(0.37, -0.21, 0.1), Vec3(-2.6, 1.9, 0.0)}) {
      // 24: more threads than rows or columns
      expect_observability_matches_walks(random_scan(3000, 5), origin, grid, {1, 2, 3, 5, 24});
    }
  }
}

// Rays the 2D counts treat specially (observability_2d sorts rays into row and column sweeps by
// direction): a point at the origin, rays along the origin's row and column, exact diagonals
// through cell corners, rays ending on a cell border, rays that leave the grid; from origins on
// a cell corner, inside a cell, on a cell border, and outside the grid on each side (so that a
// sweep starts beyond the grid).
TEST(Observability2D, MatchesSingleRayWalksForCraftedRaysAndOrigins) {
  ThreadCountGuard guard;
  const GridSpec grid = test::dyadic_grid();  // x in [-2, 2.75), y in [-1.5, 1.25), 0.25 m cells
  for (const Vec3& origin :
       {Vec3(0.0, 0.0, 0.0), Vec3(0.1, -0.3, 0.0), Vec3(0.25, 0.6, 0.0), Vec3(-3.0, 0.1, 0.0),
        Vec3(4.0, -0.2, 0.0), Vec3(0.3, -2.5, 0.0), Vec3(-0.4, 2.0, 0.0), Vec3(-3.0, -2.5, 0.0)}) {
    std::vector<Point> points;
    const auto add = [&](double x, double y) {
      points.push_back({static_cast<float>(x), static_cast<float>(y), 0.0f, 0.0f});
    };
    add(origin.x(), origin.y());
    for (double d : {-5.0, -1.0, -0.25, 0.125, 0.5, 2.0, 6.0}) {
      add(origin.x() + d, origin.y());  // along the origin's row
      add(origin.x(), origin.y() + d);  // along its column
      add(origin.x() + d, origin.y() + d);
      add(origin.x() + d, origin.y() - d);
    }
    for (double x = -2.5; x <= 3.0; x += 0.25)  // every cell border, and beyond the grid
      for (double y : {-1.75, -1.5, -0.5, 0.0, 0.625, 1.25, 1.5}) add(x, y);
    expect_observability_matches_walks(points, origin, grid, {1, 2, 4});
  }
}

// Rays passing within about 1e-7 cells of cell corners (inside the tie window, rarely exactly
// through): crossings decided by the exact orientation sign, in the sweeps' fallback path.
TEST(Observability2D, MatchesSingleRayWalksForRaysNearCorners) {
  ThreadCountGuard guard;
  const GridSpec grid = test::near_tie_grid();
  expect_observability_matches_walks(test::near_tie_rays(), Vec3(0.0, 0.0, 0.0), grid, {1, 2});
}

// The default grid (origin on a cell corner) against single-ray walks, for a spread of ranges.
TEST(Observability2D, MatchesSingleRayWalksOnDefaultGrid) {
  ThreadCountGuard guard;
  const GridSpec grid;
  Rng rng(8);
  std::vector<Point> points;
  for (int i = 0; i < 1500; ++i) {
    const double range = rng.uniform(0.0, 70.0), angle = rng.uniform(0.0, 6.283185307179586);
    points.push_back({static_cast<float>(range * std::cos(angle)),
                      static_cast<float>(range * std::sin(angle)), 0.0f, 0.0f});
  }
  expect_observability_matches_walks(points, Vec3(0.0, 0.0, 0.0), grid, {1, 2});
}

// Degenerate grids (one row, one column, one cell) and far origins: sweeps that start beyond
// the grid, slabs of one cell, rays that only graze the grid.
TEST(Observability2D, MatchesSingleRayWalksOnThinGridsAndFarOrigins) {
  ThreadCountGuard guard;
  const auto thin = [](double x_max, double y_max) {
    GridSpec grid = test::dyadic_grid();  // cells of 0.25 m from (-2, -1.5)
    grid.x_max = x_max;
    grid.y_max = y_max;
    return grid;
  };
  const std::vector<Point> points = random_scan(1500, 9);
  for (const GridSpec& grid : {thin(2.75, -1.25), thin(-1.75, 1.25), thin(-1.75, -1.25)}) {
    for (const Vec3& origin : {Vec3(0.0, 0.0, 0.0), Vec3(-1.9, -1.4, 0.0), Vec3(40.0, -3.0, 0.0),
                               Vec3(-2.5, 1e6, 0.0)}) {
      expect_observability_matches_walks(points, origin, grid, {1, 2, 3});
    }
  }
}

TEST(Observability2D, IdenticalForOneAndTwoThreadsOnDefaultGrid) {
  ThreadCountGuard guard;
  const GridSpec grid;
  Rng rng(21);
  std::vector<Point> points;
  for (int i = 0; i < 20000; ++i)
    points.push_back({static_cast<float>(rng.normal(0.0, 20.0)),
                      static_cast<float>(rng.normal(0.0, 15.0)),
                      static_cast<float>(rng.uniform(-3.0, 2.0)), 0.0f});
  const Vec3 origin(0.0, 0.0, 0.0);
  set_num_threads(1);
  const ObservabilityCounts one = observability_2d(points, origin, grid);
  set_num_threads(2);
  const ObservabilityCounts two = observability_2d(points, origin, grid);
  EXPECT_TRUE(same_counts(two.transmissions, one.transmissions));
  EXPECT_TRUE(same_counts(two.detections, one.detections));
  // Every finite point inside the grid is detected once.
  uint64_t detected = 0, inside = 0;
  for (int64_t i = 0; i < one.detections.numel(); ++i) detected += one.detections[i];
  for (const Point& p : points) inside += grid.contains_xy(p.x, p.y);
  EXPECT_EQ(detected, inside);
}

// One workspace and one output kept across calls that change the scan size, the grid (so the
// run axes change length), the origin and the thread count (so the bands change): every call
// gives the counts of a fresh one.
TEST(Observability2D, ReusedWorkspaceAndOutputGiveTheFreshCounts) {
  ThreadCountGuard guard;
  GridSpec wide = test::dyadic_grid();
  wide.x_max = 3.5;
  const std::vector<GridSpec> grids = {test::dyadic_grid(), wide, GridSpec{}};
  ObservabilityWorkspace workspace;
  ObservabilityCounts reused;
  int round = 0;
  for (const int threads : {1, 3, 2}) {
    for (const int count : {1500, 40, 3000}) {
      const GridSpec& grid = grids[static_cast<size_t>(round % 3)];
      const Vec3 origin = round % 2 == 0 ? Vec3(0.0, 0.0, 0.0) : Vec3(-1.9, 0.7, 0.0);
      const std::vector<Point> points = random_scan(count, 100 + static_cast<uint64_t>(round));
      set_num_threads(threads);
      observability_2d(points, origin, grid, workspace, reused);
      const ObservabilityCounts fresh = observability_2d(points, origin, grid);
      EXPECT_TRUE(same_counts(reused.transmissions, fresh.transmissions)) << "round " << round;
      EXPECT_TRUE(same_counts(reused.detections, fresh.detections)) << "round " << round;
      ++round;
    }
  }
  // A moved-to workspace goes on; a moved-from one makes its buffers again.
  const std::vector<Point> points = random_scan(500, 7);
  const ObservabilityCounts fresh = observability_2d(points, Vec3(0.0, 0.0, 0.0), grids[0]);
  ObservabilityWorkspace moved = std::move(workspace);
  for (ObservabilityWorkspace* kept : {&moved, &workspace}) {
    observability_2d(points, Vec3(0.0, 0.0, 0.0), grids[0], *kept, reused);
    EXPECT_TRUE(same_counts(reused.transmissions, fresh.transmissions));
    EXPECT_TRUE(same_counts(reused.detections, fresh.detections));
  }
}

TEST(Observability2D, HandComputedCounts) {
  const GridSpec grid;
  const Vec3 zero(0.0, 0.0, 0.0);
  const ObservabilityCounts counts = observability_2d(std::vector<Point>{{0.25f, 0.05f, 0.0f, 0.0f}}, zero, grid);
  EXPECT_EQ(counts.transmissions(250, 500), 1u);
  EXPECT_EQ(counts.transmissions(250, 501), 1u);
  EXPECT_EQ(counts.transmissions(250, 502), 0u);
  EXPECT_EQ(counts.detections(250, 502), 1u);
  uint64_t total = 0;
  for (int64_t i = 0; i < counts.transmissions.numel(); ++i)
    total += counts.transmissions[i] + counts.detections[i];
  EXPECT_EQ(total, 3u);
  const Tensor<uint32_t> map = observability_map(counts);
  EXPECT_EQ(map.shape(), (Shape{500, 1000}));
  EXPECT_EQ(map(250, 500), 1u);
  EXPECT_EQ(map(250, 502), 1u);
  EXPECT_EQ(map(250, 503), 0u);

  // A point outside the grid: transmissions up to the border, no detection.
  const ObservabilityCounts outside = observability_2d(std::vector<Point>{{60.0f, 0.05f, 0.0f, 0.0f}}, zero, grid);
  for (int64_t ix = 500; ix < 1000; ++ix) EXPECT_EQ(outside.transmissions(250, ix), 1u) << ix;
  EXPECT_EQ(outside.transmissions(250, 499), 0u);
  for (int64_t i = 0; i < outside.detections.numel(); ++i) ASSERT_EQ(outside.detections[i], 0u);

  // Points outside the z range count in 2D as any other point.
  const ObservabilityCounts high =
      observability_2d(std::vector<Point>{{-0.25f, 0.05f, 5.0f, 0.0f}, {-0.25f, 0.05f, -9.0f, 0.0f}}, zero, grid);
  EXPECT_EQ(high.transmissions(250, 499), 2u);
  EXPECT_EQ(high.transmissions(250, 498), 2u);
  EXPECT_EQ(high.detections(250, 497), 2u);

  // Non-finite points are skipped.
  const ObservabilityCounts with_nan = observability_2d(
      std::vector<Point>{{std::numeric_limits<float>::quiet_NaN(), 1.0f, 0.0f, 0.0f}, {0.25f, 0.05f, 0.0f, 0.0f}},
      zero, grid);
  EXPECT_TRUE(same_counts(with_nan.transmissions, counts.transmissions));
  EXPECT_TRUE(same_counts(with_nan.detections, counts.detections));
}

TEST(Observability2D, EmptyScanGivesZeros) {
  const GridSpec grid = small_grid();
  const ObservabilityCounts counts = observability_2d({}, Vec3(0.0, 0.0, 0.0), grid);
  EXPECT_EQ(counts.transmissions.shape(), (Shape{21, 33}));
  EXPECT_EQ(counts.detections.shape(), (Shape{21, 33}));
  for (int64_t i = 0; i < counts.transmissions.numel(); ++i) {
    ASSERT_EQ(counts.transmissions[i], 0u);
    ASSERT_EQ(counts.detections[i], 0u);
  }
  const OccupancyCounts occupancy = occupancy_counts_3d({}, Vec3(0.0, 0.0, 0.0), grid);
  EXPECT_EQ(occupancy.hits.shape(), (Shape{5, 21, 33}));
  const Tensor<float> probability = occupancy_probability(occupancy);
  for (int64_t i = 0; i < probability.numel(); ++i) ASSERT_EQ(probability[i], 0.5f);
}

TEST(Occupancy3D, MatchesSingleRayWalksForEveryThreadCount) {
  ThreadCountGuard guard;
  for (const GridSpec& grid : {small_grid(), dyadic_grid()}) {
    for (const Vec3& origin : {Vec3(0.0, 0.0, 0.0), Vec3(0.37, -0.21, 0.1), Vec3(-2.6, 1.9, 0.8)}) {
      const std::vector<Point> points = random_scan(3000, 9);
      Tensor<uint32_t> passes, hits;
      expected_counts(points, origin, grid, true, passes, hits);
      for (int threads : {1, 2, 3, 5}) {
        set_num_threads(threads);
        const OccupancyCounts counts = occupancy_counts_3d(points, origin, grid);
        EXPECT_TRUE(same_counts(counts.passes, passes)) << threads << " threads";
        EXPECT_TRUE(same_counts(counts.hits, hits)) << threads << " threads";
      }
    }
  }
}

TEST(Occupancy3D, IdenticalForOneAndTwoThreadsOnDefaultGrid) {
  ThreadCountGuard guard;
  const GridSpec grid;
  Rng rng(22);
  std::vector<Point> points;
  for (int i = 0; i < 20000; ++i)
    points.push_back({static_cast<float>(rng.normal(0.0, 20.0)),
                      static_cast<float>(rng.normal(0.0, 15.0)),
                      static_cast<float>(rng.uniform(-3.0, 2.0)), 0.0f});
  const Vec3 origin(0.3, -0.2, 0.05);
  set_num_threads(1);
  const OccupancyCounts one = occupancy_counts_3d(points, origin, grid);
  set_num_threads(2);
  const OccupancyCounts two = occupancy_counts_3d(points, origin, grid);
  EXPECT_TRUE(same_counts(two.passes, one.passes));
  EXPECT_TRUE(same_counts(two.hits, one.hits));
  uint64_t hit = 0, inside = 0;
  for (int64_t i = 0; i < one.hits.numel(); ++i) hit += one.hits[i];
  for (const Point& p : points) inside += grid.contains(p.x, p.y, p.z);
  EXPECT_EQ(hit, inside);
}

TEST(Occupancy3D, HandComputedCountsAndZClipping) {
  const GridSpec grid;
  const Vec3 zero(0.0, 0.0, 0.0);
  const OccupancyCounts counts = occupancy_counts_3d(std::vector<Point>{{0.25f, 0.05f, -0.25f, 0.0f}}, zero, grid);
  EXPECT_EQ(counts.hits.shape(), (Shape{20, 500, 1000}));
  EXPECT_EQ(counts.passes(12, 250, 500), 1u);
  EXPECT_EQ(counts.passes(12, 250, 501), 1u);
  EXPECT_EQ(counts.passes(11, 250, 501), 1u);
  EXPECT_EQ(counts.hits(11, 250, 502), 1u);
  uint64_t total = 0;
  for (int64_t i = 0; i < counts.hits.numel(); ++i) total += counts.hits[i] + counts.passes[i];
  EXPECT_EQ(total, 4u);

  // Below the z range: passes down to layer 0, no hit; the 2D walk still detects it.
  const std::vector<Point> below = {{0.05f, 0.05f, -4.0f, 0.0f}};
  const OccupancyCounts clipped = occupancy_counts_3d(below, zero, grid);
  uint64_t passes = 0, hits = 0;
  for (int64_t i = 0; i < clipped.hits.numel(); ++i) {
    passes += clipped.passes[i];
    hits += clipped.hits[i];
  }
  EXPECT_EQ(passes, 13u);
  EXPECT_EQ(hits, 0u);
  for (int64_t iz = 0; iz <= 12; ++iz) EXPECT_EQ(clipped.passes(iz, 250, 500), 1u) << iz;
  EXPECT_EQ(observability_2d(below, zero, grid).detections(250, 500), 1u);
}

TEST(Occupancy3D, ProbabilityFormula) {
  OccupancyCounts counts{Tensor<uint32_t>::zeros({1, 2, 3}), Tensor<uint32_t>::zeros({1, 2, 3})};
  counts.hits[1] = 1;    // one hit: 0.7
  counts.passes[2] = 1;  // one pass: 0.4
  counts.hits[3] = 1;    // with one pass: 7/3 * 2/3 = 14/9 odds, 14/23
  counts.passes[3] = 1;
  counts.hits[4] = 2;         // 49/9 odds: 49/58
  counts.passes[5] = 100000;  // certainly free
  const Tensor<float> p = occupancy_probability(counts);
  EXPECT_EQ(p.shape(), (Shape{1, 2, 3}));
  EXPECT_EQ(p[0], 0.5f);
  EXPECT_FLOAT_EQ(p[1], 0.7f);
  EXPECT_FLOAT_EQ(p[2], 0.4f);
  EXPECT_FLOAT_EQ(p[3], 14.0f / 23.0f);
  EXPECT_FLOAT_EQ(p[4], 49.0f / 58.0f);
  EXPECT_EQ(p[5], 0.0f);
}

TEST(RayWalkInputs, BadInputsThrowActionableErrors) {
  const GridSpec grid = small_grid();
  const Vec3 nan_origin(std::numeric_limits<double>::quiet_NaN(), 0.0, 0.0);
  EXPECT_THROW(observability_2d({}, nan_origin, grid), Error);
  EXPECT_THROW(occupancy_counts_3d({}, nan_origin, grid), Error);
  EXPECT_THROW(
      ray_cells_2d(Vec3::Zero(), Vec3(0.0, std::numeric_limits<double>::infinity(), 0.0), grid),
      Error);
  GridSpec bad = grid;
  bad.cell = 0.0;
  EXPECT_THROW(observability_2d({}, Vec3::Zero(), bad), Error);
  bad = grid;
  bad.voxel_z = -0.2;
  EXPECT_THROW(occupancy_counts_3d({}, Vec3::Zero(), bad), Error);
  try {
    observability_2d({}, nan_origin, grid);
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("origin must be finite"), std::string::npos) << e.what();
  }
  OccupancyCounts mismatched{Tensor<uint32_t>::zeros({1, 2, 3}),
                             Tensor<uint32_t>::zeros({1, 3, 2})};
  EXPECT_THROW(occupancy_probability(mismatched), Error);
  ObservabilityCounts flat{Tensor<uint32_t>::zeros({6}), Tensor<uint32_t>::zeros({6})};
  EXPECT_THROW(observability_map(flat), Error);
}

}  // namespace
}  // namespace pillarseg::host
