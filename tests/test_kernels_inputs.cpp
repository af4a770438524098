// The input-preparation kernels of the device pipeline on the CUDA emulation (and, as *_gpu, on a
// GPU), against the host ops on the same inputs: point padding (kernels/pad_points.cu), batch
// cells (scatter.cu), the 2D occupancy input (observability_input.cu), the masking of unobserved
// cells (mask_unobserved.cu) and the grid-map layers (grid_map_features.cu, on the gather's grouping).
// Cases: odd grids, empty scans, points outside the grid and non-finite ones, padding rows,
// guard words around every output. Everything is exact except log1p on a GPU (one float ulp at
// most in rare cells; the emulation uses the host's log1p, so there it is exact too).
#include <gtest/gtest.h>

#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "core/eigen.hpp"
#include "core/grid.hpp"
#include "core/point.hpp"
#include "host/grid_map_features.hpp"
#include "host/mask_unobserved.hpp"
#include "host/observability_input.hpp"
#include "host/pillar_gather.hpp"
#include "host/pad_points.hpp"
#include "host/raywalk.hpp"
#include "host/scatter.hpp"
#include "kernels/grid_map_features.cuh"
#include "kernels/mask_unobserved.cuh"
#include "kernels/observability_input.cuh"
#include "kernels/pillar_gather.cuh"
#include "kernels/pad_points.cuh"
#include "kernels/raywalk.cuh"
#include "kernels/scatter.cuh"
#include "tests/kernel_test_helpers.hpp"
#include "tests/support/raywalk_grids.hpp"
#include "tests/support/scans.hpp"

using namespace pillarseg;
using kernel_test::error_message;
using kernel_test::GuardedArray;
using kernel_test::same_bits;

namespace {

#if defined(PILLARSEG_CUDA_EMULATION)
constexpr std::uint32_t kLog1pUlps = 0;  // the host's log1p
#else
constexpr std::uint32_t kLog1pUlps = 1;  // the GPU's double log1p is within an ulp of it
#endif

// Within `ulps` units in the last place (both finite and of one sign, or equal).
::testing::AssertionResult within_ulps(const std::vector<float>& actual,
                                       const std::vector<float>& expected, std::uint32_t ulps) {
  if (actual.size() != expected.size())
    return ::testing::AssertionFailure() << "size " << actual.size() << " != " << expected.size();
  for (std::size_t i = 0; i < actual.size(); ++i) {
    const auto a = std::bit_cast<std::int32_t>(actual[i]);
    const auto e = std::bit_cast<std::int32_t>(expected[i]);
    const std::int64_t apart = std::abs(std::int64_t{a} - std::int64_t{e});
    if (apart > ulps || (apart > 0 && (a < 0) != (e < 0))) {
      return ::testing::AssertionFailure() << "element " << i << ": " << actual[i]
                                           << " != expected " << expected[i] << " (" << apart
                                           << " ulps apart)";
    }
  }
  return ::testing::AssertionSuccess();
}

GuardedArray<float> device_points(const std::vector<Point>& points) {
  std::vector<float> values;
  for (const Point& p : points) values.insert(values.end(), {p.x, p.y, p.z, p.r});
  return GuardedArray<float>(values);
}

// An odd grid: 37 x 23 cells of 0.3 m over a z range that crops some points.
GridSpec odd_grid() {
  GridSpec g;
  g.x_min = -4.0, g.x_max = -4.0 + 37 * 0.3;
  g.y_min = -3.1, g.y_max = -3.1 + 23 * 0.3;
  g.z_min = -1.0, g.z_max = 1.0;
  g.cell = 0.3;
  return g;
}

}  // namespace

TEST(PointPaddingKernel, MatchesTheHost) {
  for (const auto& [capacity, count] : std::vector<std::pair<std::int64_t, std::int32_t>>{
           {0, 0}, {1, 0}, {1, 1}, {257, 100}, {1000, 1000}, {513, 0}}) {
    SCOPED_TRACE(::testing::Message() << "capacity " << capacity << ", points " << count);
    const std::vector<Point> scan = test::random_scan(capacity, odd_grid(), 71);
    GuardedArray<float> points = device_points(scan);
    GuardedArray<std::int32_t> num_points(std::vector<std::int32_t>{count});
    cuda::pad_points(num_points.data(), capacity, points.data(), nullptr);
    EXPECT_TRUE(points.guards_intact());
    Tensor<float> expected({capacity, 4});
    for (std::int64_t i = 0; i < capacity; ++i)
      for (int k = 0; k < 4; ++k) expected(i, k) = (&scan[static_cast<size_t>(i)].x)[k];
    host::pad_points(count, expected);
    EXPECT_TRUE(same_bits(points.download(), expected));
  }
  // A count past the capacity keeps every row; a negative one pads all (a kernel cannot throw).
  const std::vector<Point> scan = test::random_scan(8, odd_grid(), 72);
  GuardedArray<float> points = device_points(scan);
  GuardedArray<std::int32_t> too_many(std::vector<std::int32_t>{9}), negative(std::vector<std::int32_t>{-3});
  const std::vector<float> before = points.download();
  cuda::pad_points(too_many.data(), 8, points.data(), nullptr);
  EXPECT_TRUE(same_bits(points.download(), before));
  cuda::pad_points(negative.data(), 8, points.data(), nullptr);
  for (float v : points.download()) EXPECT_TRUE(std::isnan(v));
  EXPECT_NE(error_message([&] { cuda::pad_points(negative.data(), -1, points.data(), nullptr); })
                .find("capacity must be >= 0"),
            std::string::npos);
}

TEST(BatchCellsKernel, MatchesTheHostOnGatheredPillars) {
  const GridSpec grid = odd_grid();
  const std::vector<Point> scan = test::random_scan(900, grid, 73);
  const std::int64_t rows = cuda::pillar_gather_capacity(900, grid, 0);
  GuardedArray<float> points = device_points(scan);
  GuardedArray<std::int32_t> cell(2 * rows), index(rows * 5), count(rows), total(1), cells(3 * rows);
  GuardedArray<std::int32_t> workspace(cuda::pillar_gather_workspace_size(900, grid));
  cuda::pillar_gather(points.data(), 900, grid, 5, 0, cell.data(), index.data(), count.data(),
                      total.data(), workspace.data(), workspace.size(), nullptr);
  cuda::batch_cells(cell.data(), rows, 3, cells.data(), nullptr);
  EXPECT_TRUE(cells.guards_intact());
  Tensor<std::int32_t> expected({rows, 3});
  host::batch_cells(cell.download({rows, 2}), 3, expected);
  EXPECT_TRUE(same_bits(cells.download(), expected));
  // The gather left unused rows (-1, -1) past P': they stay inert.
  ASSERT_LT(total.download()[0], rows);
  EXPECT_EQ(cells.download()[3 * static_cast<std::size_t>(rows - 1)], -1);
}

TEST(ObservabilityInputKernel, MatchesTheHost) {
  const GridSpec grid = odd_grid();
  const std::vector<Point> scan = test::random_scan(2000, grid, 74);
  const host::ObservabilityCounts counts = host::observability_2d(scan, {0.3, -0.2, 0.0}, grid);
  GuardedArray<std::uint32_t> t(counts.transmissions), d(counts.detections);
  GuardedArray<float> out(grid.cells(), 1);
  cuda::observability_input(t.data(), d.data(), grid.cells(), out.data(), nullptr);
  EXPECT_TRUE(out.guards_intact());
  Tensor<float> expected({1, grid.height(), grid.width()});
  host::observability_input(counts.transmissions, counts.detections, expected);
  EXPECT_TRUE(within_ulps(out.download(), std::vector<float>(expected.begin(), expected.end()),
                          kLog1pUlps));
}

TEST(MaskUnobservedKernel, MatchesTheHost) {
  const GridSpec grid = odd_grid();
  const std::vector<Point> scan = test::random_scan(300, grid, 75);
  const host::ObservabilityCounts counts = host::observability_2d(scan, {0.0, 0.0, 0.0}, grid);
  const std::int64_t n = grid.cells();
  Tensor<std::uint8_t> labels({grid.height(), grid.width()});
  for (std::int64_t i = 0; i < n; ++i) labels[i] = static_cast<std::uint8_t>(1 + i % 12);
  Tensor<float> probs = kernel_test::normal_tensor({3, grid.height(), grid.width()}, 76);
  GuardedArray<std::uint32_t> t(counts.transmissions), d(counts.detections);
  GuardedArray<std::uint8_t> device_labels(labels, 3);
  GuardedArray<float> device_probs(probs, 1);
  cuda::mask_unobserved(t.data(), d.data(), n, device_labels.data(), device_probs.data(), 3,
                        nullptr);
  EXPECT_TRUE(device_labels.guards_intact());
  EXPECT_TRUE(device_probs.guards_intact());
  host::mask_unobserved(counts.transmissions, counts.detections, labels, &probs);
  EXPECT_TRUE(same_bits(device_labels.download(), labels));
  EXPECT_TRUE(same_bits(device_probs.download(), probs));
  std::int64_t masked = 0;
  for (std::int64_t i = 0; i < n; ++i) masked += labels[i] == 0;
  EXPECT_GT(masked, 0);       // some cells no ray reached
  EXPECT_LT(masked, n / 2);   // and most were observed
}

TEST(GridMapFeaturesKernel, MatchesTheHost) {
  struct Case {
    std::int64_t points;
    GridSpec grid;
    Eigen::Vector3d origin;
  };
  const std::vector<Case> cases = {
      {0, odd_grid(), {0.0, 0.0, 0.0}},
      {1, odd_grid(), {0.0, 0.0, 0.0}},
      {1500, odd_grid(), {0.4, -0.7, 0.2}},
      {3000, test::small_grid(), {0.0, 0.0, 0.0}},
      {2047, test::dyadic_grid(), {-1.0, 2.0, 0.0}},
  };
  std::uint64_t seed = 80;
  for (const Case& c : cases) {
    SCOPED_TRACE(::testing::Message() << c.points << " points on " << c.grid.width() << " x "
                                      << c.grid.height());
    const std::vector<Point> scan = test::random_scan(c.points, c.grid, seed++);
    const host::ObservabilityCounts counts = host::observability_2d(scan, c.origin, c.grid);
    const Tensor<float> expected =
        host::grid_map_features(scan, counts.detections, counts.transmissions, c.grid);
    GuardedArray<float> points = device_points(scan);
    GuardedArray<std::uint32_t> t(counts.transmissions), d(counts.detections);
    GuardedArray<float> out(6 * c.grid.cells(), 3);
    GuardedArray<std::int32_t> workspace(cuda::pillar_gather_workspace_size(c.points, c.grid));
    cuda::grid_map_features(points.data(), c.points, c.grid, d.data(), t.data(), out.data(),
                            workspace.data(), workspace.size(), nullptr);
    EXPECT_TRUE(out.guards_intact());
    const std::vector<float> got = out.download();
    const std::int64_t plane = c.grid.cells();
    // Layers 0 and 1 (log1p) within kLog1pUlps; 2..5 exact.
    for (int layer = 0; layer < 6; ++layer) {
      SCOPED_TRACE(::testing::Message() << "layer " << layer);
      const std::vector<float> a(got.begin() + layer * plane, got.begin() + (layer + 1) * plane);
      const std::vector<float> e(expected.begin() + layer * plane,
                                 expected.begin() + (layer + 1) * plane);
      EXPECT_TRUE(layer < 2 ? within_ulps(a, e, kLog1pUlps) : same_bits(a, e));
    }
  }
}

TEST(GridMapFeaturesKernel, LauncherChecksItsArguments) {
  const GridSpec grid = odd_grid();
  GuardedArray<std::int32_t> small(4);
  GuardedArray<float> out(6 * grid.cells());
  GuardedArray<std::uint32_t> counts(grid.cells());
  EXPECT_NE(error_message([&] {
              cuda::grid_map_features(nullptr, 0, grid, counts.data(), counts.data(), out.data(),
                                      small.data(), small.size(), nullptr);
            }).find("pillar_gather_workspace_size"),
            std::string::npos);
  EXPECT_NE(error_message([&] {
              cuda::grid_map_features(nullptr, 0, grid, nullptr, counts.data(), out.data(),
                                      small.data(), small.size(), nullptr);
            }).find("must be device memory"),
            std::string::npos);
}
