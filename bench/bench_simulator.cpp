// Simulator timings: generating a city (streets, objects, routes, the static scene grid) for
// 100 and 1000 scans; one LiDAR revolution (64 x ~2100 pulses cast against ground, static
// scene and moving agents) on one thread and on all; the ground layout query; and a ray
// through the SceneGrid against the brute-force reference over the same primitives.
// Reports ms per iteration and points/s, pulses/s, queries/s or rays/s.
#include <benchmark/benchmark.h>

#include <cmath>

#include "core/parallel.hpp"
#include "core/rng.hpp"
#include "engine/sim/simulate.hpp"

namespace {

using pillarseg::Rng;
using namespace pillarseg::sim;

constexpr uint64_t kSeed = 7;
constexpr int kScans = 100;

const SequenceSimulator& simulator() {
  static const SequenceSimulator sim(kSeed, kScans);
  return sim;
}

// Rays from the ego's sensor positions in random directions below +2 deg, as the LiDAR casts.
std::vector<Ray> sensor_rays(int n) {
  Rng rng(3);
  std::vector<Ray> rays;
  for (int i = 0; i < n; ++i) {
    const auto pose = simulator().lidar_pose_world(static_cast<int>(rng.uniform_int(kScans)));
    const double az = rng.uniform(-M_PI, M_PI), el = rng.uniform(-0.43, 0.035);
    rays.push_back(
        {pose.topRightCorner<3, 1>(),
         Eigen::Vector3d(std::cos(el) * std::cos(az), std::cos(el) * std::sin(az), std::sin(el))});
  }
  return rays;
}

void BM_GenerateCity(benchmark::State& state) {
  size_t primitives = 0;
  for (auto _ : state) {
    const City city = City::generate(kSeed, static_cast<int>(state.range(0)));
    primitives = city.static_scene().size();
    benchmark::DoNotOptimize(primitives);
  }
  state.counters["primitives"] = static_cast<double>(primitives);
}
BENCHMARK(BM_GenerateCity)->ArgName("scans")->Arg(100)->Arg(1000)->Unit(benchmark::kMillisecond);

// threads = 0: all hardware threads.
void BM_CastScan(benchmark::State& state) {
  const SequenceSimulator& sim = simulator();
  pillarseg::set_num_threads(static_cast<int>(state.range(0)));
  int64_t points = 0, pulses = 0;
  int i = 0;
  for (auto _ : state) {
    const SimScan scan = sim.scan(i++ % kScans);
    points += static_cast<int64_t>(scan.points.size());
    pulses += static_cast<int64_t>(sim.lidar().beams()) * sim.lidar().azimuth_steps;
  }
  pillarseg::set_num_threads(0);
  state.counters["points/s"] =
      benchmark::Counter(static_cast<double>(points), benchmark::Counter::kIsRate);
  state.counters["pulses/s"] =
      benchmark::Counter(static_cast<double>(pulses), benchmark::Counter::kIsRate);
  state.counters["points/scan"] = static_cast<double>(points) / static_cast<double>(std::max(i, 1));
}
BENCHMARK(BM_CastScan)
    ->ArgName("threads")
    ->Arg(1)
    ->Arg(0)
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

void BM_GroundAt(benchmark::State& state) {
  const City& city = simulator().city();
  Rng rng(9);
  std::vector<Eigen::Vector2d> queries;
  for (int i = 0; i < 4096; ++i) {
    const auto pose = simulator().lidar_pose_world(static_cast<int>(rng.uniform_int(kScans)));
    const double dx = rng.uniform(-50, 50), dy = rng.uniform(-50, 50);
    queries.emplace_back(pose(0, 3) + dx, pose(1, 3) + dy);
  }
  for (auto _ : state)
    for (const auto& q : queries) benchmark::DoNotOptimize(city.ground_at(q.x(), q.y()));
  state.counters["queries/s"] = benchmark::Counter(
      static_cast<double>(state.iterations() * queries.size()), benchmark::Counter::kIsRate);
}
BENCHMARK(BM_GroundAt)->Unit(benchmark::kMicrosecond);

void BM_TraceGrid(benchmark::State& state) {
  const SceneGrid& scene = simulator().city().static_scene();
  const std::vector<Ray> rays = sensor_rays(256);
  for (auto _ : state)
    for (const Ray& r : rays) {
      Hit hit;
      benchmark::DoNotOptimize(scene.trace(r, 0.9, 100.0, &hit));
    }
  state.counters["rays/s"] = benchmark::Counter(
      static_cast<double>(state.iterations() * rays.size()), benchmark::Counter::kIsRate);
}
BENCHMARK(BM_TraceGrid)->Unit(benchmark::kMicrosecond);

void BM_TraceBruteForce(benchmark::State& state) {
  const auto& primitives = simulator().city().static_scene().primitives();
  const std::vector<Ray> rays = sensor_rays(256);
  for (auto _ : state)
    for (const Ray& r : rays) {
      Hit hit;
      benchmark::DoNotOptimize(trace_brute_force(primitives, r, 0.9, 100.0, &hit));
    }
  state.counters["rays/s"] = benchmark::Counter(
      static_cast<double>(state.iterations() * rays.size()), benchmark::Counter::kIsRate);
}
BENCHMARK(BM_TraceBruteForce)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
