// The data-pipeline and evaluation kernels on the GPU, on one simulated street scan (the embedded
// data set's HDL-64E-like LiDAR, about 120k points) and the default grid (1000 x 500 cells of
// 0.1 m, Z = 20 layers, N = 20 points per pillar, P = 12000 pillars): pillar gather
// (kernels/pillar_gather.cu), point decoration (point_decoration.cu), 2D observability counts,
// 3D occupancy counts and probability (raywalk.cu), and the confusion matrix over the grid's
// 500k cells (confusion.cu). Each pass is timed with CUDA events on its own stream after one
// warm-up run and reported in ms with its rate (points/s, cells/s, GB/s of the bytes it must
// move at least), and host_ms/gpu_ms, the time of the host/ reference on this machine (all its
// threads, the median of 3 runs) over the kernel's. The scan's pillar statistics are printed
// first: sum_size2 is the work of the gather's rank pass (the sum over pillars of size^2).
//
// Without a CUDA device, and in the emulated build (whose times say nothing about a GPU), it
// prints "skipped: no CUDA device" and runs nothing.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <functional>
#include <string>
#include <unordered_map>
#include <vector>

#include "bench/support/cuda_bench.hpp"
#include "core/classes.hpp"
#include "core/eigen.hpp"
#include "core/grid.hpp"
#include "core/point.hpp"
#include "core/rng.hpp"
#include "core/tensor.hpp"
#include "engine/sim/simulate.hpp"
#include "host/confusion.hpp"
#include "host/pillar_gather.hpp"
#include "host/point_decoration.hpp"
#include "host/raywalk.hpp"
#include "kernels/common.cuh"
#include "kernels/confusion.cuh"
#include "kernels/device_buffer.hpp"
#include "kernels/pillar_gather.cuh"
#include "kernels/point_decoration.cuh"
#include "kernels/raywalk.cuh"

using namespace pillarseg;
using cuda::DeviceBuffer;

namespace {

constexpr int kSlots = 20;          // N
constexpr int kMaxPillars = 12000;  // P

// The scan, the grid and the host's results on them.
struct Scene {
  GridSpec grid;
  std::vector<Point> points;
  host::Pillars pillars;                        // inference mode
  Tensor<std::uint8_t> truth, predicted, mask;  // (H, W) labels for the confusion matrix
};

const Scene& scene() {
  static const Scene s = [] {
    Scene built;
    built.points = sim::SequenceSimulator(7, 1).scan(0).points;
    built.pillars = host::pillar_gather(built.points, built.grid, {kSlots, kMaxPillars},
                                        host::SampleMode::Inference, nullptr);
    const Shape plane{built.grid.height(), built.grid.width()};
    built.truth = Tensor<std::uint8_t>(plane);
    built.predicted = Tensor<std::uint8_t>(plane);
    built.mask = Tensor<std::uint8_t>(plane);
    Rng rng(11);
    for (std::int64_t i = 0; i < built.truth.numel(); ++i) {
      built.truth[i] = static_cast<std::uint8_t>(rng.uniform_int(kNumClasses + 1));
      built.predicted[i] = static_cast<std::uint8_t>(1 + rng.uniform_int(kNumClasses));
      built.mask[i] = rng.uniform_int(3) == 0 ? 0 : 1;
    }
    return built;
  }();
  return s;
}

std::int64_t num_points() {
  return static_cast<std::int64_t>(scene().points.size());
}

// Median wall time of 3 runs of `run`, in ms.
double host_ms(const std::function<void()>& run) {
  std::vector<double> times;
  for (int i = 0; i < 3; ++i) {
    const auto start = std::chrono::steady_clock::now();
    run();
    times.push_back(
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
            .count());
  }
  std::sort(times.begin(), times.end());
  return times[1];
}

// What one pass processes per run, for its rates.
struct Work {
  double items = 0.0;  // points or cells
  const char* item_name = "points/s";
  double bytes = 0.0;  // the bytes it must read and write at least
  double reference_ms = 0.0;
};

// bench::time_iterations, and the rate counters.
void time_pass(benchmark::State& state, const Work& work,
               const std::function<void(cudaStream_t)>& run) {
  const double mean_ms = bench::time_iterations(state, run);
  state.counters[work.item_name] =
      benchmark::Counter(work.items, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["GB/s"] =
      benchmark::Counter(work.bytes * 1e-9, benchmark::Counter::kIsIterationInvariantRate);
  if (mean_ms > 0.0) state.counters["host_ms/gpu_ms"] = work.reference_ms / mean_ms;
}

DeviceBuffer<float> device_points() {
  std::vector<float> values;
  values.reserve(scene().points.size() * 4);
  for (const Point& p : scene().points) values.insert(values.end(), {p.x, p.y, p.z, p.r});
  return DeviceBuffer<float>::from_host(values);
}

// The gather's outputs and workspace on the device.
struct GatherBuffers {
  GatherBuffers()
      : rows(cuda::pillar_gather_capacity(num_points(), scene().grid, kMaxPillars)),
        points(device_points()),
        cell(static_cast<std::size_t>(2 * rows)),
        point_index(static_cast<std::size_t>(rows * kSlots)),
        count(static_cast<std::size_t>(rows)),
        num_pillars(1),
        workspace(static_cast<std::size_t>(
            cuda::pillar_gather_workspace_size(num_points(), scene().grid))) {}

  void gather(cudaStream_t stream) {
    cuda::pillar_gather(points.data(), num_points(), scene().grid, kSlots, kMaxPillars, cell.data(),
                        point_index.data(), count.data(), num_pillars.data(), workspace.data(),
                        static_cast<std::int64_t>(workspace.size()), stream);
  }

  std::int64_t rows;
  DeviceBuffer<float> points;
  DeviceBuffer<std::int32_t> cell, point_index, count, num_pillars, workspace;
};

void BM_PillarGather(benchmark::State& state) {
  GatherBuffers b;
  Work work{static_cast<double>(num_points()), "points/s",
            // points in; cells, indices and counts out
            static_cast<double>(num_points() * 16 + b.rows * (kSlots + 3) * 4)};
  work.reference_ms = host_ms([] {
    static_cast<void>(host::pillar_gather(scene().points, scene().grid, {kSlots, kMaxPillars},
                                          host::SampleMode::Inference, nullptr));
  });
  time_pass(state, work, [&](cudaStream_t stream) { b.gather(stream); });
}

void BM_PointDecoration(benchmark::State& state) {
  GatherBuffers b;
  b.gather(nullptr);
  DeviceBuffer<float> out(static_cast<std::size_t>(b.rows * kSlots * cuda::kDecoratedFeatures));
  // The decorated tensor out, and each kept point and its index in.
  Work work{static_cast<double>(num_points()), "points/s",
            static_cast<double>(out.bytes()) + static_cast<double>(b.rows * (kSlots + 3) * 4) +
                static_cast<double>(num_points() * 16)};
  work.reference_ms = host_ms([] {
    static_cast<void>(host::decorate_points(scene().points, scene().pillars, scene().grid));
  });
  time_pass(state, work, [&](cudaStream_t stream) {
    cuda::decorate_points(b.points.data(), num_points(), b.cell.data(), b.point_index.data(),
                          b.count.data(), b.rows, kSlots, scene().grid, out.data(), stream);
  });
}

void BM_Observability2d(benchmark::State& state) {
  const GridSpec& grid = scene().grid;
  DeviceBuffer<float> points = device_points();
  DeviceBuffer<std::uint32_t> transmissions(static_cast<std::size_t>(grid.cells())),
      detections(transmissions.size()),
      workspace(static_cast<std::size_t>(cuda::observability_2d_workspace_size(grid)));
  Work work{
      static_cast<double>(num_points()), "points/s",
      static_cast<double>(num_points() * 16) + 3.0 * static_cast<double>(transmissions.bytes())};
  work.reference_ms = host_ms([&] {
    static_cast<void>(host::observability_2d(scene().points, Eigen::Vector3d::Zero(), grid));
  });
  time_pass(state, work, [&](cudaStream_t stream) {
    cuda::observability_2d(points.data(), num_points(), {}, grid, transmissions.data(),
                           detections.data(), workspace.data(),
                           static_cast<std::int64_t>(workspace.size()), stream);
  });
}

// Occupancy counts on the (Z, H, W) voxels; with probability: the counts and the probability.
void BM_Occupancy3d(benchmark::State& state, bool with_probability) {
  const GridSpec& grid = scene().grid;
  const std::int64_t voxels = std::int64_t{grid.layers()} * grid.cells();
  DeviceBuffer<float> points = device_points();
  DeviceBuffer<std::uint32_t> hits(static_cast<std::size_t>(voxels)), passes(hits.size());
  DeviceBuffer<float> probability(with_probability ? hits.size() : 0);
  Work work{static_cast<double>(num_points()), "points/s",
            static_cast<double>(num_points() * 16) + 2.0 * static_cast<double>(hits.bytes()) +
                static_cast<double>(probability.bytes())};
  work.reference_ms = host_ms([&] {
    const host::OccupancyCounts counts =
        host::occupancy_counts_3d(scene().points, Eigen::Vector3d::Zero(), grid);
    if (with_probability) static_cast<void>(host::occupancy_probability(counts));
  });
  time_pass(state, work, [&](cudaStream_t stream) {
    cuda::occupancy_counts_3d(points.data(), num_points(), {}, grid, hits.data(), passes.data(),
                              stream);
    if (with_probability) {
      cuda::occupancy_probability(hits.data(), passes.data(), voxels, probability.data(), stream);
    }
  });
}

void BM_Confusion(benchmark::State& state) {
  const Scene& s = scene();
  const std::int64_t cells = s.truth.numel();
  const auto upload = [](const Tensor<std::uint8_t>& t) {
    return DeviceBuffer<std::uint8_t>::from_host(std::vector<std::uint8_t>(t.begin(), t.end()));
  };
  DeviceBuffer<std::uint8_t> truth = upload(s.truth), predicted = upload(s.predicted),
                             mask = upload(s.mask);
  DeviceBuffer<std::int64_t> confusion(kNumClasses * kNumClasses);
  DeviceBuffer<std::uint64_t> invalid(1);
  confusion.fill_zero();
  invalid.fill_zero();
  Work work{static_cast<double>(cells), "cells/s", 3.0 * static_cast<double>(cells)};
  work.reference_ms = host_ms([&] {
    Tensor<std::int64_t> matrix({kNumClasses, kNumClasses});
    host::confusion_accumulate(s.truth, s.predicted, &s.mask, matrix);
  });
  time_pass(state, work, [&](cudaStream_t stream) {
    cuda::confusion_accumulate(truth.data(), predicted.data(), mask.data(), cells, confusion.data(),
                               invalid.data(), stream);
  });
}

// The pillar statistics of the scan: points, points in the volume, non-empty pillars, kept
// pillars, the largest pillar and the sum of squared pillar sizes.
void print_scan_statistics() {
  const Scene& s = scene();
  std::unordered_map<std::int64_t, std::int64_t> sizes;
  for (const Point& p : s.points) {
    if (s.grid.contains(p.x, p.y, p.z)) ++sizes[s.grid.cell_index(p.x, p.y)];
  }
  std::int64_t inside = 0, largest = 0, sum_size2 = 0;
  for (const auto& [cell, size] : sizes) {
    inside += size;
    largest = std::max(largest, size);
    sum_size2 += size * size;
  }
  std::printf(
      "scan: %zu points, %lld in the volume, %zu non-empty pillars (%lld kept, P = %d, N = %d), "
      "largest pillar %lld points, sum_size2 %lld\n",
      s.points.size(), static_cast<long long>(inside), sizes.size(),
      static_cast<long long>(s.pillars.num_pillars()), kMaxPillars, kSlots,
      static_cast<long long>(largest), static_cast<long long>(sum_size2));
}

void register_benchmarks() {
  const auto pass = [](const char* name, auto function, auto... args) {
    benchmark::RegisterBenchmark(name, function, args...)
        ->Unit(benchmark::kMillisecond)
        ->UseManualTime();
  };
  pass("PillarGather", BM_PillarGather);
  pass("PointDecoration", BM_PointDecoration);
  pass("Observability2d", BM_Observability2d);
  pass("OccupancyCounts3d", BM_Occupancy3d, false);
  pass("OccupancyCounts3dWithProbability", BM_Occupancy3d, true);
  pass("Confusion", BM_Confusion);
}

}  // namespace

int main(int argc, char** argv) {
  const std::string missing = pillarseg::bench::missing_cuda_device();
  if (!missing.empty()) {
    std::printf("bench_kernels_pipeline skipped: no CUDA device (%s)\n", missing.c_str());
    return 0;
  }
  print_scan_statistics();
  register_benchmarks();
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
