// Pillar gather and point decoration on a realistic synthetic scan: a 64-beam spinning LiDAR
// (elevations +2 .. -24.9 degrees, 1900 azimuth steps, 121,600 rays) ray-cast against a ground
// plane at z = -1.73 m, two street facades, two far walls beyond the grid and parked cars;
// seeded. Times pillar_gather (inference) and decorate_points, each with fresh and with reused
// memory, and both together in steady state (memory reused) at the default grid (1000 x 500 cells
// of 0.1 m, N = 20, P = 0) for 1 and 2 threads; reports ms per scan and input points/s.
#include <benchmark/benchmark.h>

#include <cmath>
#include <limits>
#include <numbers>
#include <vector>

#include "core/eigen.hpp"
#include "core/grid.hpp"
#include "core/parallel.hpp"
#include "core/point.hpp"
#include "core/rng.hpp"
#include "host/pillar_gather.hpp"
#include "host/point_decoration.hpp"

using namespace pillarseg;
using namespace pillarseg::host;

namespace {

struct Box {
  Eigen::Vector3d lo, hi;
};

// Distance along the unit ray `dir` from the origin to the box, or +inf (slab method).
double hit_box(const Eigen::Vector3d& dir, const Box& box) {
  double enter = 0.0, leave = std::numeric_limits<double>::infinity();
  for (int a = 0; a < 3; ++a) {
    const double t0 = box.lo[a] / dir[a], t1 = box.hi[a] / dir[a];
    enter = std::max(enter, std::min(t0, t1));
    leave = std::min(leave, std::max(t0, t1));
  }
  return enter <= leave && enter > 0.0 ? enter : std::numeric_limits<double>::infinity();
}

// Distance to the plane {p[axis] = at} along `dir` when ahead of the sensor, else +inf.
double hit_plane(const Eigen::Vector3d& dir, int axis, double at) {
  const double t = at / dir[axis];
  return t > 0.0 ? t : std::numeric_limits<double>::infinity();
}

std::vector<Point> synthetic_scan(uint64_t seed) {
  constexpr int kBeams = 64, kAzimuthSteps = 1900;
  constexpr double kGround = -1.73, kFacadeLeft = 9.0, kFacadeRight = -11.0, kFarWall = 70.0;
  Rng rng(seed);
  std::vector<Box> cars;
  for (int i = 0; i < 12; ++i) {
    const double x = -45.0 + 8.0 * i + rng.uniform(-1.0, 1.0);
    const double y = (i % 2 == 0) ? 6.0 : -7.5;
    cars.push_back({{x, y - 0.9, kGround}, {x + 4.5, y + 0.9, kGround + 1.5}});
  }
  std::vector<Point> points;
  points.reserve(kBeams * kAzimuthSteps);
  for (int step = 0; step < kAzimuthSteps; ++step) {
    for (int beam = 0; beam < kBeams; ++beam) {
      const double elevation = (2.0 - (2.0 + 24.9) * beam / (kBeams - 1)) * std::numbers::pi / 180;
      const double azimuth = 2 * std::numbers::pi * (step + rng.uniform(-0.1, 0.1)) / kAzimuthSteps;
      const Eigen::Vector3d dir(std::cos(elevation) * std::cos(azimuth),
                                std::cos(elevation) * std::sin(azimuth), std::sin(elevation));
      double range = std::numeric_limits<double>::infinity();
      float reflectance = 0.2f;  // asphalt
      const double walls =
          std::min({hit_plane(dir, 1, kFacadeLeft), hit_plane(dir, 1, kFacadeRight),
                    hit_plane(dir, 0, kFarWall), hit_plane(dir, 0, -kFarWall)});
      if (walls < range) range = walls, reflectance = 0.5f;
      const double ground = hit_plane(dir, 2, kGround);
      if (ground < range) range = ground, reflectance = 0.2f;
      for (const Box& car : cars) {
        const double t = hit_box(dir, car);
        if (t < range) range = t, reflectance = 0.8f;
      }
      if (!std::isfinite(range) || range > 120.0) continue;
      const Eigen::Vector3d p = dir * (range + rng.normal(0.0, 0.02));
      points.push_back({static_cast<float>(p.x()), static_cast<float>(p.y()),
                        static_cast<float>(p.z()),
                        static_cast<float>(reflectance + rng.uniform(-0.1, 0.1))});
    }
  }
  return points;
}

const std::vector<Point>& scan() {
  static const std::vector<Point> points = synthetic_scan(42);
  return points;
}

void report(benchmark::State& state, const Pillars& pillars) {
  state.counters["points/s"] = benchmark::Counter(static_cast<double>(scan().size()),
                                                  benchmark::Counter::kIsIterationInvariantRate);
  state.counters["points"] = static_cast<double>(scan().size());
  state.counters["pillars"] = static_cast<double>(pillars.num_pillars());
  state.counters["threads"] = static_cast<double>(num_threads());
}

// Pillar gather is sequential; the thread count is swept only to show it does not matter.
void BM_PillarGatherFresh(benchmark::State& state) {  // allocates its scratch and output
  set_num_threads(static_cast<int>(state.range(0)));
  const GridSpec grid;
  Pillars pillars;
  for (auto _ : state) {
    pillars = pillar_gather(scan(), grid, PillarConfig{}, SampleMode::Inference, nullptr);
    benchmark::DoNotOptimize(pillars.count.data());
  }
  report(state, pillars);
}

void BM_PillarGatherReused(benchmark::State& state) {  // steady state: workspace and output kept
  set_num_threads(static_cast<int>(state.range(0)));
  const GridSpec grid;
  PillarWorkspace workspace;
  Pillars pillars;
  for (auto _ : state) {
    pillar_gather(scan(), grid, PillarConfig{}, SampleMode::Inference, nullptr, workspace, pillars);
    benchmark::DoNotOptimize(pillars.count.data());
  }
  report(state, pillars);
}

void BM_DecoratePointsFresh(benchmark::State& state) {  // allocates the (P', N, 10) output
  set_num_threads(static_cast<int>(state.range(0)));
  const GridSpec grid;
  const Pillars pillars =
      pillar_gather(scan(), grid, PillarConfig{}, SampleMode::Inference, nullptr);
  for (auto _ : state) {
    Tensor<float> features = decorate_points(scan(), pillars, grid);
    benchmark::DoNotOptimize(features.data());
  }
  report(state, pillars);
}

void BM_DecoratePointsReused(benchmark::State& state) {  // steady state: output kept
  set_num_threads(static_cast<int>(state.range(0)));
  const GridSpec grid;
  const Pillars pillars =
      pillar_gather(scan(), grid, PillarConfig{}, SampleMode::Inference, nullptr);
  Tensor<float> features;
  for (auto _ : state) {
    decorate_points(scan(), pillars, grid, features);
    benchmark::DoNotOptimize(features.data());
  }
  report(state, pillars);
}

void BM_GatherAndDecorate(benchmark::State& state) {  // one inference step in steady state
  set_num_threads(static_cast<int>(state.range(0)));
  const GridSpec grid;
  PillarWorkspace workspace;
  Pillars pillars;
  Tensor<float> features;
  for (auto _ : state) {
    pillar_gather(scan(), grid, PillarConfig{}, SampleMode::Inference, nullptr, workspace, pillars);
    decorate_points(scan(), pillars, grid, features);
    benchmark::DoNotOptimize(features.data());
  }
  report(state, pillars);
}

// 1 and 2 threads; 5 repetitions, reported as mean, median, stddev and cv.
void sweep_threads(benchmark::internal::Benchmark* b) {
  b->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond)->UseRealTime()->Repetitions(5);
  b->ReportAggregatesOnly(true);
}

BENCHMARK(BM_PillarGatherFresh)->Apply(sweep_threads);
BENCHMARK(BM_PillarGatherReused)->Apply(sweep_threads);
BENCHMARK(BM_DecoratePointsFresh)->Apply(sweep_threads);
BENCHMARK(BM_DecoratePointsReused)->Apply(sweep_threads);
BENCHMARK(BM_GatherAndDecorate)->Apply(sweep_threads);

}  // namespace

BENCHMARK_MAIN();
