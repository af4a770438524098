// The data-pipeline and evaluation kernels on the CUDA emulation, against the CPU reference ops of
// host/ on the same inputs: the pillar gather (kernels/pillar_gather.cu, inference mode), the
// point decoration (point_decoration.cu), the 2D observability and 3D occupancy ray walks
// (raywalk.cu) and the confusion matrix (confusion.cu). Cases: point counts that are not
// multiples of the block size, odd grids, 0 and 1 point, 0 and 1 pillar, more pillars than P and
// more points than N, points outside the grid and non-finite ones, rays along the axes and
// through cell corners, origins on corners and outside the grid, guard words around every output,
// the same bits for every emulated thread count. Everything is integer or data movement and must
// match bit for bit, except the decorated offsets and the occupancy probability (see there).
#include <gtest/gtest.h>
#include <omp.h>

#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <utility>
#include <vector>

#include "core/classes.hpp"
#include "core/eigen.hpp"
#include "core/grid.hpp"
#include "core/point.hpp"
#include "core/rng.hpp"
#include "host/confusion.hpp"
#include "host/pillar_gather.hpp"
#include "host/point_decoration.hpp"
#include "host/raywalk.hpp"
#include "kernels/confusion.cuh"
#include "kernels/pillar_gather.cuh"
#include "kernels/point_decoration.cuh"
#include "kernels/raywalk.cuh"
#include "tests/kernel_test_helpers.hpp"
#include "tests/support/raywalk_grids.hpp"
#include "tests/support/scans.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
using kernel_test::error_message;
using kernel_test::GuardedArray;
using kernel_test::same_bits;

namespace {

constexpr float kNan = std::numeric_limits<float>::quiet_NaN();
constexpr float kInf = std::numeric_limits<float>::infinity();

using test::dyadic_grid;
using test::random_scan;
using test::small_grid;

// points as (M, 4) floats in device memory, between guard words.
GuardedArray<float> device_points(const std::vector<Point>& points) {
  std::vector<float> values;
  values.reserve(points.size() * 4);
  for (const Point& p : points) values.insert(values.end(), {p.x, p.y, p.z, p.r});
  return GuardedArray<float>(values);
}

template <class T>
std::vector<T> to_vector(const Tensor<T>& t) {
  return std::vector<T>(t.begin(), t.end());
}

// The outputs of cuda::pillar_gather, downloaded.
struct DevicePillars {
  std::int32_t num_pillars = 0;
  std::int64_t rows = 0;
  std::vector<std::int32_t> cell, point_index, count;
};

// Runs cuda::pillar_gather on `points`, checks the guards, returns the outputs.
DevicePillars gather_on_device(const std::vector<Point>& points, const GridSpec& grid, int slots,
                               int max_pillars) {
  const auto m = static_cast<std::int64_t>(points.size());
  const std::int64_t rows = cuda::pillar_gather_capacity(m, grid, max_pillars);
  GuardedArray<float> device_input = device_points(points);
  GuardedArray<std::int32_t> cell(2 * rows), point_index(rows * slots), count(rows), total(1);
  GuardedArray<std::int32_t> workspace(cuda::pillar_gather_workspace_size(m, grid));
  cuda::pillar_gather(device_input.data(), m, grid, slots, max_pillars, cell.data(),
                      point_index.data(), count.data(), total.data(), workspace.data(),
                      workspace.size(), nullptr);
  EXPECT_TRUE(cell.guards_intact());
  EXPECT_TRUE(point_index.guards_intact());
  EXPECT_TRUE(count.guards_intact());
  EXPECT_TRUE(total.guards_intact());
  EXPECT_TRUE(workspace.guards_intact());
  return DevicePillars{total.download()[0], rows, cell.download(), point_index.download(),
                       count.download()};
}

// The device pillars equal the host's rows, and the rows after them are unused rows.
::testing::AssertionResult same_pillars(const DevicePillars& actual, const host::Pillars& expected,
                                        int slots) {
  const std::int64_t kept = expected.num_pillars();
  if (actual.num_pillars != kept) {
    return ::testing::AssertionFailure()
           << "num_pillars " << actual.num_pillars << " != expected " << kept;
  }
  const auto head = [](const std::vector<std::int32_t>& v, std::int64_t n) {
    return std::vector<std::int32_t>(v.begin(), v.begin() + n);
  };
  if (auto r = same_bits(head(actual.cell, 2 * kept), to_vector(expected.cell)); !r) {
    return r << " (cell)";
  }
  if (auto r = same_bits(head(actual.point_index, kept * slots), to_vector(expected.point_index));
      !r) {
    return r << " (point_index)";
  }
  if (auto r = same_bits(head(actual.count, kept), to_vector(expected.count)); !r) {
    return r << " (count)";
  }
  for (std::int64_t q = kept; q < actual.rows; ++q) {
    bool unused = actual.cell[2 * q] == -1 && actual.cell[2 * q + 1] == -1 && actual.count[q] == 0;
    for (std::int64_t k = 0; k < slots; ++k)
      unused = unused && actual.point_index[q * slots + k] == -1;
    if (!unused) return ::testing::AssertionFailure() << "row " << q << " >= P' is not unused";
  }
  return ::testing::AssertionSuccess();
}

host::Pillars gather_on_host(const std::vector<Point>& points, const GridSpec& grid, int slots,
                             int max_pillars) {
  return host::pillar_gather(points, grid, {slots, max_pillars}, host::SampleMode::Inference,
                             nullptr);
}

// Restores the OpenMP thread count (the emulation's blocks run on OpenMP threads).
class OmpThreads {
 public:
  explicit OmpThreads(int threads) : saved_(omp_get_max_threads()) { omp_set_num_threads(threads); }
  ~OmpThreads() { omp_set_num_threads(saved_); }
  OmpThreads(const OmpThreads&) = delete;
  OmpThreads& operator=(const OmpThreads&) = delete;

 private:
  int saved_;
};

}  // namespace

// ---------------------------------------------------------------------------------------------
// Pillar gather

namespace {

struct GatherCase {
  std::int64_t points;
  int slots, max_pillars;
  bool dyadic;
};

const std::vector<GatherCase> kGatherCases = {
    {0, 20, 0, false},      // empty scan, P = 0: no rows at all
    {0, 4, 7, false},       // empty scan: 7 unused rows
    {1, 20, 0, false},      // one point
    {1, 3, 1, true},        // one point, P = 1
    {300, 20, 0, false},    // every pillar kept, not a multiple of any block
    {1500, 3, 0, false},    // crowded pillars: far more than N = 3 points
    {1500, 1, 5, false},    // N = 1, fewer kept pillars than non-empty: evenly spaced subset
    {2047, 20, 1, true},    // P = 1, dyadic grid (points on cell borders)
    {2600, 7, 2000, true},  // P above the non-empty count: unused rows after P'
    {5000, 32, 61, false},  // several scan tiles
};

}  // namespace

TEST(PillarGatherKernel, MatchesTheHostBitForBit) {
  std::uint64_t seed = 4000;
  for (const GatherCase& c : kGatherCases) {
    SCOPED_TRACE(::testing::Message() << "M " << c.points << ", N " << c.slots << ", P "
                                      << c.max_pillars << (c.dyadic ? ", dyadic" : ""));
    const GridSpec grid = c.dyadic ? dyadic_grid() : small_grid();
    const std::vector<Point> points = random_scan(c.points, grid, seed++);
    const host::Pillars expected = gather_on_host(points, grid, c.slots, c.max_pillars);
    EXPECT_TRUE(
        same_pillars(gather_on_device(points, grid, c.slots, c.max_pillars), expected, c.slots));
  }
}

TEST(PillarGatherKernel, CoversTheSubsamplingAndCropping) {
  // The cases above must reach what they are meant to: crowded pillars, more pillars than P,
  // points outside the volume.
  const GridSpec grid = small_grid();
  const std::vector<Point> points = random_scan(1500, grid, 4003);
  const host::Pillars all = gather_on_host(points, grid, 3, 0);
  std::int64_t outside = static_cast<std::int64_t>(points.size()), crowded = 0;
  for (std::int64_t p = 0; p < all.num_pillars(); ++p) crowded += all.count[p] == 3;
  for (const Point& p : points) outside -= grid.contains(p.x, p.y, p.z);
  EXPECT_GT(all.num_pillars(), 5);
  EXPECT_GE(crowded, 5);
  EXPECT_GT(outside, 100);
}

TEST(PillarGatherKernel, HandComputedOrderAndSelection) {
  // Cells (iy, ix) of the small grid: A = (1, 2), B = (3, 4). Input: B A A B A A A, one point
  // outside, then A. Pillars in order of first appearance: B (points 0, 3), A (1, 2, 4, 5, 6, 8).
  const GridSpec grid = small_grid();
  const auto at = [&](int iy, int ix, float z) {
    return Point{static_cast<float>(grid.x_min + (ix + 0.5) * grid.cell),
                 static_cast<float>(grid.y_min + (iy + 0.5) * grid.cell), z, 0.5f};
  };
  const std::vector<Point> points = {at(3, 4, 0),    at(1, 2, 0),    at(1, 2, 0.1f),
                                     at(3, 4, 0.2f), at(1, 2, 0),    at(1, 2, 0),
                                     at(1, 2, 0),    at(1, 2, 0.9f), at(1, 2, 0)};
  const DevicePillars pillars = gather_on_device(points, grid, 4, 0);
  ASSERT_EQ(pillars.num_pillars, 2);
  EXPECT_EQ(pillars.cell[0], 3);
  EXPECT_EQ(pillars.cell[1], 4);
  EXPECT_EQ(pillars.cell[2], 1);
  EXPECT_EQ(pillars.cell[3], 2);
  EXPECT_EQ(pillars.count[0], 2);
  EXPECT_EQ(pillars.count[1], 4);
  EXPECT_EQ(
      (std::vector<std::int32_t>(pillars.point_index.begin(), pillars.point_index.begin() + 8)),
      (std::vector<std::int32_t>{0, 3, -1, -1, /**/ 1, 2, 5, 6}))
      << "A has 6 points, N = 4: ranks floor(k 6 / 4) = 0, 1, 3, 4";
  // P = 1 of 2 pillars keeps position floor(0 * 2 / 1) = 0: B.
  const DevicePillars first = gather_on_device(points, grid, 4, 1);
  ASSERT_EQ(first.num_pillars, 1);
  EXPECT_EQ(first.cell[0], 3);
}

TEST(PillarGatherKernel, SameBitsForEveryThreadCount) {
  // The emulation runs blocks on OpenMP threads, so atomics land in a different order.
  const GridSpec grid = small_grid();
  const std::vector<Point> points = random_scan(3000, grid, 4100);
  DevicePillars one;
  {
    const OmpThreads threads(1);
    one = gather_on_device(points, grid, 5, 0);
  }
  const OmpThreads threads(4);
  for (int run = 0; run < 2; ++run) {
    const DevicePillars again = gather_on_device(points, grid, 5, 0);
    EXPECT_EQ(again.num_pillars, one.num_pillars);
    EXPECT_TRUE(same_bits(again.point_index, one.point_index));
    EXPECT_TRUE(same_bits(again.cell, one.cell));
  }
}

TEST(PillarGatherKernel, LauncherChecksItsArguments) {
  const GridSpec grid = small_grid();
  GuardedArray<std::int32_t> outputs(64), workspace(4);
  const std::string small_workspace = error_message([&] {
    cuda::pillar_gather(nullptr, 0, grid, 4, 2, outputs.data(), outputs.data(), outputs.data(),
                        outputs.data(), workspace.data(), workspace.size(), nullptr);
  });
  EXPECT_NE(small_workspace.find("the workspace must hold pillar_gather_workspace_size(M, grid)"),
            std::string::npos)
      << small_workspace;
  const std::string no_slots = error_message([&] {
    cuda::pillar_gather(nullptr, 0, grid, 0, 2, outputs.data(), outputs.data(), outputs.data(),
                        outputs.data(), workspace.data(), workspace.size(), nullptr);
  });
  EXPECT_NE(no_slots.find("max_points_per_pillar (N) must be >= 1, given 0"), std::string::npos)
      << no_slots;
}

// ---------------------------------------------------------------------------------------------
// Point decoration

namespace {

// The host's decoration and the kernel's on the host's pillars: x, y, z, r and the zero padding
// bit for bit; the offsets within one float rounding (the centre x_min + (ix + 0.5) cell may be
// contracted into an fma by one compiler and not by the other).
void expect_decoration_matches(const std::vector<Point>& points, const host::Pillars& pillars,
                               const GridSpec& grid) {
  const Tensor<float> expected = host::decorate_points(points, pillars, grid);
  const std::int64_t p = pillars.num_pillars();
  const std::int64_t slots = pillars.max_points_per_pillar();
  GuardedArray<float> device_input = device_points(points);
  GuardedArray<std::int32_t> cell(to_vector(pillars.cell)),
      point_index(to_vector(pillars.point_index)), count(to_vector(pillars.count));
  // The output starts as other data: every element must be written.
  GuardedArray<float> out(kernel_test::normal_values(p * slots * 10, 77));
  cuda::decorate_points(device_input.data(), static_cast<std::int64_t>(points.size()), cell.data(),
                        point_index.data(), count.data(), p, slots, grid, out.data(), nullptr);
  EXPECT_TRUE(out.guards_intact());
  const std::vector<float> actual = out.download();
  for (std::int64_t e = 0; e < expected.numel(); ++e) {
    const float want = expected.data()[e];
    const float got = actual[static_cast<std::size_t>(e)];
    if (e % 10 < 4 || want == 0.0f) {
      ASSERT_EQ(std::bit_cast<std::uint32_t>(got), std::bit_cast<std::uint32_t>(want))
          << "element " << e << " (pillar " << e / (slots * 10) << ", slot " << e / 10 % slots
          << ", feature " << e % 10 << ")";
    } else {
      ASSERT_NEAR(got, want, 1e-6 + 1.2e-7 * std::abs(want)) << "element " << e;
    }
  }
}

}  // namespace

TEST(PointDecorationKernel, MatchesTheHost) {
  struct Case {
    std::int64_t points;
    int slots, max_pillars;
  };
  const std::vector<Case> cases = {
      {0, 20, 0},     // no pillar
      {1, 20, 0},     // one pillar of one point
      {300, 20, 0},   // partial blocks of 32 pillars
      {1500, 3, 0},   // full pillars
      {1500, 1, 33},  // N = 1, P = 33: one block and one pillar
      {5000, 32, 0},  // many pillars, N = 32
  };
  std::uint64_t seed = 4200;
  for (const Case& c : cases) {
    SCOPED_TRACE(::testing::Message()
                 << "M " << c.points << ", N " << c.slots << ", P " << c.max_pillars);
    const GridSpec grid = small_grid();
    const std::vector<Point> points = random_scan(c.points, grid, seed++);
    expect_decoration_matches(points, gather_on_host(points, grid, c.slots, c.max_pillars), grid);
  }
}

TEST(PointDecorationKernel, HandComputedPillar) {
  // One pillar at (iy 2, ix 3) of the dyadic grid (centre (-1.125, -0.875, -0.25)) holding two
  // points; N = 3, so the third row is padding.
  const GridSpec grid = dyadic_grid();
  const std::vector<Point> points = {{-1.25f, -1.0f, 0.25f, 0.5f}, {-1.0f, -0.75f, -0.25f, 1.0f}};
  GuardedArray<float> device_input = device_points(points), out(30);
  GuardedArray<std::int32_t> cell(std::vector<std::int32_t>{2, 3}),
      point_index(std::vector<std::int32_t>{0, 1, -1}), count(std::vector<std::int32_t>{2});
  cuda::decorate_points(device_input.data(), 2, cell.data(), point_index.data(), count.data(), 1, 3,
                        grid, out.data(), nullptr);
  const std::vector<float> expected = {
      -1.25f, -1.0f,  0.25f,  0.5f, -0.125f, -0.125f, 0.25f,  -0.125f, -0.125f, 0.5f,  //
      -1.0f,  -0.75f, -0.25f, 1.0f, 0.125f,  0.125f,  -0.25f, 0.125f,  0.125f,  0.0f,  //
      0,      0,      0,      0,    0,       0,       0,      0,       0,       0};
  EXPECT_TRUE(same_bits(out.download(), expected));
  EXPECT_TRUE(out.guards_intact());
}

TEST(PointDecorationKernel, PillarsTheHostWouldRefuseAreZero) {
  // A kernel cannot throw: a count above N, or an index outside the points, zeroes the pillar
  // instead of reading outside memory; the valid pillar beside them is decorated.
  const GridSpec grid = dyadic_grid();
  const std::vector<Point> points = {{-1.25f, -1.0f, 0.25f, 0.5f}};
  GuardedArray<float> device_input = device_points(points), out(3 * 2 * 10);
  GuardedArray<std::int32_t> cell(std::vector<std::int32_t>{2, 3, 2, 3, 2, 3}),
      point_index(std::vector<std::int32_t>{0, 0, 0, 5, 0, -1}),
      count(std::vector<std::int32_t>{3, 2, 1});
  cuda::decorate_points(device_input.data(), 1, cell.data(), point_index.data(), count.data(), 3, 2,
                        grid, out.data(), nullptr);
  const std::vector<float> values = out.download();
  for (int e = 0; e < 40; ++e) EXPECT_EQ(values[static_cast<std::size_t>(e)], 0.0f) << e;
  EXPECT_EQ(values[40], -1.25f);
  EXPECT_EQ(values[49], 0.5f);
  for (int e = 50; e < 60; ++e) EXPECT_EQ(values[static_cast<std::size_t>(e)], 0.0f) << e;
}

TEST(PointDecorationKernel, GatherThenDecorateOnTheDeviceEqualsTheHost) {
  // The two kernels chained as the engine runs them, on the gather's unused rows too.
  const GridSpec grid = small_grid();
  const std::vector<Point> points = random_scan(400, grid, 4300);
  const int slots = 6, max_pillars = 250;
  const auto m = static_cast<std::int64_t>(points.size());
  const std::int64_t rows = cuda::pillar_gather_capacity(m, grid, max_pillars);
  GuardedArray<float> device_input = device_points(points), out(rows * slots * 10);
  GuardedArray<std::int32_t> cell(2 * rows), point_index(rows * slots), count(rows), total(1);
  GuardedArray<std::int32_t> workspace(cuda::pillar_gather_workspace_size(m, grid));
  cuda::pillar_gather(device_input.data(), m, grid, slots, max_pillars, cell.data(),
                      point_index.data(), count.data(), total.data(), workspace.data(),
                      workspace.size(), nullptr);
  cuda::decorate_points(device_input.data(), m, cell.data(), point_index.data(), count.data(), rows,
                        slots, grid, out.data(), nullptr);
  const host::Pillars pillars = gather_on_host(points, grid, slots, max_pillars);
  ASSERT_LT(pillars.num_pillars(), rows) << "the case needs unused rows";
  const Tensor<float> expected = host::decorate_points(points, pillars, grid);
  const std::vector<float> actual = out.download();
  EXPECT_TRUE(test::all_close(actual.data(), expected.data(), expected.numel(), 1e-6, 1.2e-7));
  for (std::int64_t e = expected.numel(); e < rows * slots * 10; ++e) {
    ASSERT_EQ(actual[static_cast<std::size_t>(e)], 0.0f) << "unused row element " << e;
  }
  EXPECT_TRUE(out.guards_intact());

  // With the gather's P' as the live pillars (read on the device): the same pillar rows, and the
  // rows past P' left as they were (-5). The live count is the device's, so one past it or 0
  // moves where the kernel stops.
  for (const std::int32_t shift : {0, -1}) {
    const std::int32_t live = static_cast<std::int32_t>(pillars.num_pillars()) + shift;
    GuardedArray<std::int32_t> live_rows(std::vector<std::int32_t>{live});
    out.upload(std::vector<float>(static_cast<std::size_t>(rows * slots * 10), -5.0f));
    cuda::decorate_points(device_input.data(), m, cell.data(), point_index.data(), count.data(),
                          rows, slots, grid, out.data(), nullptr, live_rows.data());
    const std::vector<float> cut = out.download();
    const std::int64_t live_floats = std::int64_t{live} * slots * 10;
    EXPECT_TRUE(test::all_close(cut.data(), expected.data(), live_floats, 1e-6, 1.2e-7));
    for (std::int64_t e = live_floats; e < rows * slots * 10; ++e) {
      ASSERT_EQ(cut[static_cast<std::size_t>(e)], -5.0f) << "live " << live << ", element " << e;
    }
    EXPECT_TRUE(out.guards_intact());
  }
}

// ---------------------------------------------------------------------------------------------
// Ray walks

namespace {

struct RayCase {
  const char* name;
  GridSpec grid;
  Eigen::Vector3d origin;
  std::vector<Point> points;
};

// Rays for `grid` from `origin`: random ones, ones along x and y (through the origin's row and
// column), ones of zero length, far ones, and non-finite ones.
std::vector<Point> random_rays(std::int64_t count, const GridSpec& grid,
                               const Eigen::Vector3d& origin, std::uint64_t seed) {
  std::vector<Point> points = random_scan(count, grid, seed);
  for (std::size_t i = 0; i < points.size(); ++i) {
    Point& p = points[i];
    switch (i % 12) {
      case 1:
        p.y = static_cast<float>(origin.y());
        break;  // along x
      case 2:
        p.x = static_cast<float>(origin.x());
        break;  // along y
      case 3:
        p = Point{static_cast<float>(origin.x()), static_cast<float>(origin.y()),
                  static_cast<float>(origin.z()), 0.0f};
        break;
      case 4:
        p.x *= 1e6f;
        p.y *= -3e5f;
        break;
      default:
        break;
    }
  }
  return points;
}

// Points on the 1/8 m lattice of the dyadic grid: with an origin on a cell corner, most rays pass
// exactly through cell corners or voxel edges.
std::vector<Point> lattice_rays(std::int64_t count, std::uint64_t seed) {
  Rng rng(seed);
  const auto lattice = [&](double lo, double hi) {
    return static_cast<float>(lo + 0.125 * static_cast<double>(rng.uniform_int(
                                               static_cast<std::uint64_t>((hi - lo) * 8) + 1)));
  };
  std::vector<Point> points(static_cast<std::size_t>(count));
  for (Point& p : points) p = Point{lattice(-3.0, 3.5), lattice(-2.0, 2.0), lattice(-1.5, 1.0), 0};
  return points;
}

std::vector<RayCase> ray_cases() {
  std::vector<RayCase> cases;
  const GridSpec small = small_grid();
  const GridSpec dyadic = dyadic_grid();
  cases.push_back({"no point", small, {0.0, 0.0, 0.0}, {}});
  cases.push_back({"one point", small, {0.0, 0.0, 0.0}, {Point{1.23f, -0.4f, 0.1f, 0.0f}}});
  cases.push_back({"origin on a corner",
                   small,
                   {0.0, 0.0, 0.0},
                   random_rays(1000, small, {0.0, 0.0, 0.0}, 5000)});
  cases.push_back({"origin inside a cell",
                   small,
                   {0.37, -0.21, 0.05},
                   random_rays(777, small, {0.37, -0.21, 0.05}, 5100)});
  cases.push_back({"origin outside the grid",
                   small,
                   {-3.0, 2.5, 0.7},
                   random_rays(500, small, {-3.0, 2.5, 0.7}, 5200)});
  cases.push_back(
      {"lattice, origin on a corner", dyadic, {0.0, 0.0, 0.0}, lattice_rays(1500, 5300)});
  cases.push_back(
      {"lattice, origin on an edge", dyadic, {0.125, -0.25, 0.0}, lattice_rays(1200, 5400)});
  cases.push_back({"near ties", test::near_tie_grid(), {0.0, 0.0, 0.0}, test::near_tie_rays()});
  return cases;
}

}  // namespace

TEST(RayWalkKernels, ObservabilityMatchesTheHostExactly) {
  for (const RayCase& c : ray_cases()) {
    SCOPED_TRACE(c.name);
    const host::ObservabilityCounts expected = host::observability_2d(c.points, c.origin, c.grid);
    const Tensor<std::uint32_t> expected_map = host::observability_map(expected);
    const std::int64_t cells = c.grid.cells();
    GuardedArray<float> device_input = device_points(c.points);
    GuardedArray<std::uint32_t> transmissions(cells), detections(cells), map(cells),
        workspace(cuda::observability_2d_workspace_size(c.grid));
    const cuda::SensorOrigin origin{c.origin.x(), c.origin.y(), c.origin.z()};
    cuda::observability_2d(device_input.data(), static_cast<std::int64_t>(c.points.size()), origin,
                           c.grid, transmissions.data(), detections.data(), workspace.data(),
                           workspace.size(), nullptr);
    cuda::observability_map(transmissions.data(), detections.data(), cells, map.data(), nullptr);
    EXPECT_TRUE(same_bits(transmissions.download(), expected.transmissions));
    EXPECT_TRUE(same_bits(detections.download(), expected.detections));
    EXPECT_TRUE(same_bits(map.download(), expected_map));
    EXPECT_TRUE(transmissions.guards_intact());
    EXPECT_TRUE(detections.guards_intact());
    EXPECT_TRUE(map.guards_intact());
    EXPECT_TRUE(workspace.guards_intact());
  }
}

TEST(RayWalkKernels, OccupancyMatchesTheHost) {
  // Counts exactly; the probability within one float ulp (exp on a GPU may differ from glibc's
  // by an ulp of the double).
  for (const RayCase& c : ray_cases()) {
    SCOPED_TRACE(c.name);
    const host::OccupancyCounts expected = host::occupancy_counts_3d(c.points, c.origin, c.grid);
    const Tensor<float> expected_probability = host::occupancy_probability(expected);
    const std::int64_t voxels = expected.hits.numel();
    GuardedArray<float> device_input = device_points(c.points), probability(voxels);
    GuardedArray<std::uint32_t> hits(voxels), passes(voxels);
    const cuda::SensorOrigin origin{c.origin.x(), c.origin.y(), c.origin.z()};
    cuda::occupancy_counts_3d(device_input.data(), static_cast<std::int64_t>(c.points.size()),
                              origin, c.grid, hits.data(), passes.data(), nullptr);
    cuda::occupancy_probability(hits.data(), passes.data(), voxels, probability.data(), nullptr);
    EXPECT_TRUE(same_bits(hits.download(), expected.hits));
    EXPECT_TRUE(same_bits(passes.download(), expected.passes));
    const std::vector<float> actual = probability.download();
    EXPECT_TRUE(test::all_close(actual.data(), expected_probability.data(), voxels, 0.0, 1.2e-7));
    EXPECT_TRUE(hits.guards_intact());
    EXPECT_TRUE(passes.guards_intact());
    EXPECT_TRUE(probability.guards_intact());
  }
}

TEST(RayWalkKernels, RaysThroughCornersVisitTheSpecifiedCells) {
  // From the corner (0, 0) of the dyadic grid (cell coordinates (8, 6)) to (0.5, 0.5): the ray
  // passes the corners (9, 7) and (10, 8) exactly; x steps first at each, so it visits
  // (8, 6) (9, 6) (9, 7) (10, 7) and ends in (10, 8).
  const GridSpec grid = dyadic_grid();
  GuardedArray<float> device_input = device_points({Point{0.5f, 0.5f, 0.0f, 0.0f}});
  const std::int64_t cells = grid.cells();
  GuardedArray<std::uint32_t> transmissions(cells), detections(cells), workspace(cells);
  cuda::observability_2d(device_input.data(), 1, {}, grid, transmissions.data(), detections.data(),
                         workspace.data(), workspace.size(), nullptr);
  std::vector<std::uint32_t> expected_transmissions(static_cast<std::size_t>(cells), 0);
  for (const auto& [iy, ix] : std::vector<std::pair<int, int>>{{6, 8}, {6, 9}, {7, 9}, {7, 10}}) {
    expected_transmissions[static_cast<std::size_t>(iy * grid.width() + ix)] = 1;
  }
  std::vector<std::uint32_t> expected_detections(static_cast<std::size_t>(cells), 0);
  expected_detections[static_cast<std::size_t>(8 * grid.width() + 10)] = 1;
  EXPECT_TRUE(same_bits(transmissions.download(), expected_transmissions));
  EXPECT_TRUE(same_bits(detections.download(), expected_detections));
}

TEST(RayWalkKernels, SameCountsForEveryThreadCount) {
  const GridSpec grid = small_grid();
  const std::vector<Point> points = random_rays(2000, grid, {0.0, 0.0, 0.0}, 5500);
  GuardedArray<float> device_input = device_points(points);
  const std::int64_t voxels = std::int64_t{grid.layers()} * grid.cells();
  std::vector<std::uint32_t> first;
  for (const int threads : {1, 4}) {
    const OmpThreads scope(threads);
    GuardedArray<std::uint32_t> hits(voxels), passes(voxels);
    cuda::occupancy_counts_3d(device_input.data(), static_cast<std::int64_t>(points.size()), {},
                              grid, hits.data(), passes.data(), nullptr);
    if (first.empty()) {
      first = passes.download();
    } else {
      EXPECT_TRUE(same_bits(passes.download(), first));
    }
  }
}

TEST(RayWalkKernels, LaunchersCheckTheirArguments) {
  GridSpec grid = small_grid();
  GuardedArray<std::uint32_t> counts(grid.cells());
  const std::string origin = error_message([&] {
    cuda::observability_2d(nullptr, 0, {kNan, 0.0, 0.0}, grid, counts.data(), counts.data(),
                           counts.data(), counts.size(), nullptr);
  });
  EXPECT_NE(origin.find("the sensor origin must be finite"), std::string::npos) << origin;
  const std::string workspace = error_message([&] {
    cuda::observability_2d(nullptr, 0, {}, grid, counts.data(), counts.data(), counts.data(), 10,
                           nullptr);
  });
  EXPECT_NE(workspace.find("observability_2d_workspace_size(grid) = 693 uint32, given 10"),
            std::string::npos)
      << workspace;
  grid.voxel_z = 0.0;
  const std::string voxel = error_message([&] {
    cuda::occupancy_counts_3d(nullptr, 0, {}, grid, counts.data(), counts.data(), nullptr);
  });
  EXPECT_NE(voxel.find("voxel_z must be a positive size"), std::string::npos) << voxel;
}

// ---------------------------------------------------------------------------------------------
// Confusion matrix

namespace {

// n cells of ids 0..12, predictions 1..12, mask 0/1 (one cell in 4 masked out).
struct Labels {
  Tensor<std::uint8_t> truth, predicted, mask;
};
Labels random_labels(std::int64_t n, std::uint64_t seed) {
  Rng rng(seed);
  Labels labels{Tensor<std::uint8_t>({n}), Tensor<std::uint8_t>({n}), Tensor<std::uint8_t>({n})};
  for (std::int64_t i = 0; i < n; ++i) {
    labels.truth[i] = static_cast<std::uint8_t>(rng.uniform_int(kNumClasses + 1));
    labels.predicted[i] = static_cast<std::uint8_t>(1 + rng.uniform_int(kNumClasses));
    labels.mask[i] = rng.uniform_int(4) == 0 ? 0 : 1;
  }
  return labels;
}

}  // namespace

TEST(ConfusionKernel, AccumulatesLikeTheHost) {
  std::uint64_t seed = 6000;
  for (const std::int64_t n : {0, 1, 255, 4097, 100003}) {
    for (const bool masked : {false, true}) {
      SCOPED_TRACE(::testing::Message() << "n " << n << (masked ? ", masked" : ""));
      const Labels labels = random_labels(n, seed++);
      // The matrix starts with counts of an earlier batch: both add to it.
      Tensor<std::int64_t> expected({kNumClasses, kNumClasses});
      for (std::int64_t i = 0; i < expected.numel(); ++i) expected.data()[i] = 3 * i + 1;
      GuardedArray<std::int64_t> confusion(to_vector(expected));
      GuardedArray<std::uint64_t> invalid(std::vector<std::uint64_t>{0});
      host::confusion_accumulate(labels.truth, labels.predicted, masked ? &labels.mask : nullptr,
                                 expected);
      GuardedArray<std::uint8_t> truth(labels.truth), predicted(labels.predicted),
          mask(labels.mask);
      cuda::confusion_accumulate(truth.data(), predicted.data(), masked ? mask.data() : nullptr, n,
                                 confusion.data(), invalid.data(), nullptr);
      EXPECT_TRUE(same_bits(confusion.download(), expected));
      EXPECT_EQ(invalid.download()[0], 0u);
      EXPECT_TRUE(confusion.guards_intact());
      EXPECT_TRUE(invalid.guards_intact());
    }
  }
}

TEST(ConfusionKernel, CountsInvalidIdsInsteadOfThrowing) {
  // Where the host throws, the kernel leaves the cell out and counts it: a true id above 12, a
  // predicted 0 or 13 on a counted cell. Unlabeled or masked cells never count, whatever their
  // prediction.
  const std::vector<std::uint8_t> truth = {13, 1, 1, 0, 2, 5, 12, 200};
  const std::vector<std::uint8_t> predicted = {1, 0, 13, 99, 99, 5, 12, 3};
  const std::vector<std::uint8_t> mask = {1, 1, 1, 1, 0, 1, 1, 1};
  GuardedArray<std::uint8_t> device_truth(truth), device_predicted(predicted), device_mask(mask);
  GuardedArray<std::int64_t> confusion(std::vector<std::int64_t>(kNumClasses * kNumClasses, 0));
  GuardedArray<std::uint64_t> invalid(std::vector<std::uint64_t>{2});
  cuda::confusion_accumulate(device_truth.data(), device_predicted.data(), device_mask.data(), 8,
                             confusion.data(), invalid.data(), nullptr);
  std::vector<std::int64_t> expected(kNumClasses * kNumClasses, 0);
  expected[4 * kNumClasses + 4] = 1;    // (5, 5)
  expected[11 * kNumClasses + 11] = 1;  // (12, 12)
  EXPECT_TRUE(same_bits(confusion.download(), expected));
  EXPECT_EQ(invalid.download()[0], 2u + 4u) << "cells 0, 1, 2 and 7, added to the 2 it held";
}
