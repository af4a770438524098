// Benchmarks of the ray walks (host/raywalk) on a realistic scan built here: a 64-beam spinning
// LiDAR (elevations -24.9 .. +2 degrees, 1900 azimuth steps, about 120k points, ranges up to
// 80 m) ray-cast against a ground plane at z = -1.73 m, building facades, far walls, parked cars
// and poles, with seeded range noise. Times observability_2d (fresh, and in steady state with its
// workspace and output kept), and occupancy_counts_3d with occupancy_probability, on 1 and 2
// threads on the default grid; reports ms, points/s and walked cells/s.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <vector>

#include "core/grid.hpp"
#include "core/parallel.hpp"
#include "core/rng.hpp"
#include "host/raywalk.hpp"

namespace pillarseg::host {
namespace {

struct Box {
  Eigen::Vector3d lo, hi;
};

// Distance along the unit direction to the first face of the box the ray hits, or +inf
// (slab method).
double ray_box(const Eigen::Vector3d& direction, const Box& box) {
  double t_near = 0.0, t_far = std::numeric_limits<double>::infinity();
  for (int k = 0; k < 3; ++k) {
    if (direction[k] == 0.0) {
      if (box.lo[k] > 0.0 || box.hi[k] < 0.0) return std::numeric_limits<double>::infinity();
      continue;
    }
    double ta = box.lo[k] / direction[k], tb = box.hi[k] / direction[k];
    if (ta > tb) std::swap(ta, tb);
    t_near = std::max(t_near, ta);
    t_far = std::min(t_far, tb);
  }
  return t_near <= t_far && t_near > 0.0 ? t_near : std::numeric_limits<double>::infinity();
}

std::vector<Point> simulated_scan() {
  constexpr int kBeams = 64, kAzimuthSteps = 1900;
  constexpr double kGroundZ = -1.73, kMaxRange = 80.0;
  const auto box = [](double x0, double y0, double z0, double x1, double y1, double z1) {
    return Box{Eigen::Vector3d(x0, y0, z0), Eigen::Vector3d(x1, y1, z1)};
  };
  std::vector<Box> boxes = {
      // facades left and right of the street, with an alley on each side
      box(-75.0, 9.0, kGroundZ, -6.0, 10.0, 18.0), box(-2.0, 9.0, kGroundZ, 70.0, 10.0, 18.0),
      box(-75.0, -14.0, kGroundZ, 12.0, -13.0, 14.0), box(17.0, -14.0, kGroundZ, 70.0, -13.0, 14.0),
      // far walls ahead and behind
      box(62.0, -13.0, kGroundZ, 63.0, 9.0, 12.0), box(-71.0, -13.0, kGroundZ, -70.0, 9.0, 12.0)};
  // parked cars along both curbs and poles on the sidewalks
  for (int k = 0; k < 8; ++k) {
    const double x = -30.0 + 8.5 * k;
    boxes.push_back(box(x, 6.0, kGroundZ, x + 4.4, 7.8, kGroundZ + 1.5));
    boxes.push_back(box(x + 3.0, -10.8, kGroundZ, x + 7.4, -9.0, kGroundZ + 1.5));
    boxes.push_back(box(x + 1.0, 8.3, kGroundZ, x + 1.25, 8.55, kGroundZ + 5.0));
  }
  Rng rng(2021);
  std::vector<Point> points;
  points.reserve(kBeams * kAzimuthSteps);
  for (int beam = 0; beam < kBeams; ++beam) {
    const double elevation =
        (-24.9 + (2.0 + 24.9) * beam / (kBeams - 1)) * std::numbers::pi / 180.0;
    for (int step = 0; step < kAzimuthSteps; ++step) {
      const double azimuth = 2.0 * std::numbers::pi * step / kAzimuthSteps;
      const Eigen::Vector3d direction(std::cos(elevation) * std::cos(azimuth),
                                      std::cos(elevation) * std::sin(azimuth), std::sin(elevation));
      double range =
          direction.z() < 0.0 ? kGroundZ / direction.z() : std::numeric_limits<double>::infinity();
      for (const Box& b : boxes) range = std::min(range, ray_box(direction, b));
      if (range > kMaxRange) continue;
      const Eigen::Vector3d p = (range + rng.normal(0.0, 0.02)) * direction;
      points.push_back({static_cast<float>(p.x()), static_cast<float>(p.y()),
                        static_cast<float>(p.z()), static_cast<float>(rng.uniform())});
    }
  }
  return points;
}

const std::vector<Point>& scan() {
  static const std::vector<Point> points = simulated_scan();
  return points;
}

void set_rates(benchmark::State& state, uint64_t cells_per_run) {
  const double runs = static_cast<double>(state.iterations());
  state.counters["points"] = static_cast<double>(scan().size());
  state.counters["points/s"] =
      benchmark::Counter(runs * static_cast<double>(scan().size()), benchmark::Counter::kIsRate);
  state.counters["cells/s"] =
      benchmark::Counter(runs * static_cast<double>(cells_per_run), benchmark::Counter::kIsRate);
}

uint64_t sum(const Tensor<uint32_t>& t) {
  uint64_t total = 0;
  for (int64_t i = 0; i < t.numel(); ++i) total += t[i];
  return total;
}

// Voxels the scan's rays walk inside the volume (passes + hits).
uint64_t walked_voxels(const Eigen::Vector3d& origin, const GridSpec& grid) {
  const OccupancyCounts counts = occupancy_counts_3d(scan(), origin, grid);
  return sum(counts.hits) + sum(counts.passes);
}

void BM_Observability2D(benchmark::State& state) {
  const int saved = num_threads();
  set_num_threads(static_cast<int>(state.range(0)));
  const GridSpec grid;
  const Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  const ObservabilityCounts once = observability_2d(scan(), origin, grid);
  const uint64_t cells = sum(once.transmissions) + sum(once.detections);
  for (auto _ : state) {
    ObservabilityCounts counts = observability_2d(scan(), origin, grid);
    benchmark::DoNotOptimize(counts.transmissions.data());
  }
  set_rates(state, cells);
  set_num_threads(saved);
}

void BM_Observability2DReused(benchmark::State& state) {  // steady state: workspace and output kept
  const int saved = num_threads();
  set_num_threads(static_cast<int>(state.range(0)));
  const GridSpec grid;
  const Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  ObservabilityWorkspace workspace;
  ObservabilityCounts counts;
  observability_2d(scan(), origin, grid, workspace, counts);
  const uint64_t cells = sum(counts.transmissions) + sum(counts.detections);
  for (auto _ : state) {
    observability_2d(scan(), origin, grid, workspace, counts);
    benchmark::DoNotOptimize(counts.transmissions.data());
  }
  set_rates(state, cells);
  set_num_threads(saved);
}

void BM_Occupancy3D(benchmark::State& state) {
  const int saved = num_threads();
  set_num_threads(static_cast<int>(state.range(0)));
  const GridSpec grid;
  const Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  const uint64_t cells = walked_voxels(origin, grid);
  for (auto _ : state) {
    const OccupancyCounts counts = occupancy_counts_3d(scan(), origin, grid);
    Tensor<float> probability = occupancy_probability(counts);
    benchmark::DoNotOptimize(probability.data());
  }
  set_rates(state, cells);
  set_num_threads(saved);
}

void BM_OccupancyCounts3D(benchmark::State& state) {
  const int saved = num_threads();
  set_num_threads(static_cast<int>(state.range(0)));
  const GridSpec grid;
  const Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  const uint64_t cells = walked_voxels(origin, grid);
  for (auto _ : state) {
    OccupancyCounts counts = occupancy_counts_3d(scan(), origin, grid);
    benchmark::DoNotOptimize(counts.passes.data());
  }
  set_rates(state, cells);
  set_num_threads(saved);
}

void BM_OccupancyProbability(benchmark::State& state) {
  const int saved = num_threads();
  set_num_threads(static_cast<int>(state.range(0)));
  const OccupancyCounts counts = occupancy_counts_3d(scan(), Eigen::Vector3d::Zero(), GridSpec());
  for (auto _ : state) {
    Tensor<float> probability = occupancy_probability(counts);
    benchmark::DoNotOptimize(probability.data());
  }
  state.counters["voxels/s"] = benchmark::Counter(
      static_cast<double>(state.iterations() * counts.hits.numel()), benchmark::Counter::kIsRate);
  set_num_threads(saved);
}

// 1 and 2 threads, 5 repetitions each, reported as median and min (the machine may be shared);
// wall-clock times and rates, as the work runs on OpenMP threads.
void thread_counts(benchmark::internal::Benchmark* b) {
  b->ArgName("threads")->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond)->UseRealTime();
  b->Repetitions(5)->DisplayAggregatesOnly(true);
  b->ComputeStatistics(
      "min", [](const std::vector<double>& v) { return *std::min_element(v.begin(), v.end()); });
}

BENCHMARK(BM_Observability2D)->Apply(thread_counts);
BENCHMARK(BM_Observability2DReused)->Apply(thread_counts);
BENCHMARK(BM_Occupancy3D)->Apply(thread_counts);
BENCHMARK(BM_OccupancyCounts3D)->Apply(thread_counts);
BENCHMARK(BM_OccupancyProbability)->Apply(thread_counts);

}  // namespace
}  // namespace pillarseg::host

BENCHMARK_MAIN();
